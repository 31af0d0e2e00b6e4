"""Queries to agents over a real router: an answer, an agent that is gone, and one that does not answer in time
are three different outcomes (:meth:`conductor.link.AgentLink.ask`)."""
from __future__ import annotations

import threading
import time

import pytest

from conductor.link import AgentLink
from protocol import codec
from protocol.errors import AgentLost, AgentTimeout
from protocol.keys import Keys

KEYS = Keys("queries")


def _eval() -> bytes:
    return codec.encode("eval", args=[], tick=0, t=0.0)


def test_an_agent_that_is_gone_is_told_apart_from_one_that_is_slow(router, client):
    session, _ = router
    link = AgentLink(session, KEYS, step_timeout=5.0)
    # nothing serves the key: Zenoh ends the query at once, and the link says the agent is gone
    with pytest.raises(AgentLost, match="agent is gone") as lost:
        link.ask("nobody", "eval/x", _eval(), "value_reply", timeout=5.0)
    assert lost.value.agent == "nobody"
    # an agent that holds the query without answering: the query waits out its timeout
    held: list = []
    mute = client.declare_queryable(KEYS.model("mute", "eval/x"), held.append)
    answering = client.declare_queryable(KEYS.model("fine", "eval/x"), lambda q: q.reply(
        q.key_expr, codec.encode("value_reply", value=42)))
    try:
        # (lost_wait: until the router has learnt of the queryables just declared, the queries find nobody)
        with pytest.raises(AgentTimeout, match="no answer within 0.5 s"):
            link.ask("mute", "eval/x", _eval(), "value_reply", timeout=0.5, lost_wait=10.0)
        assert held and link.malformed == 0  # it did get the query; Zenoh's timeout reply is not malformed
        assert link.ask("fine", "eval/x", _eval(), "value_reply", timeout=5.0, lost_wait=10.0).value == 42
    finally:
        held.clear()
        mute.undeclare()
        answering.undeclare()


def test_an_agent_whose_link_comes_back_is_asked_again_within_lost_wait(router, client):
    """Before a run (init, start) the conductor waits for an agent whose link lapsed: asked while nothing serves
    the key, then again until the agent's queryable is back, the query gets the agent's answer."""
    session, _ = router
    link = AgentLink(session, KEYS, step_timeout=5.0)
    later: list = []
    back = threading.Timer(1.5, lambda: later.append(client.declare_queryable(
        KEYS.model("late", "eval/x"), lambda q: q.reply(q.key_expr, codec.encode("value_reply", value=7)))))
    back.start()
    try:
        with pytest.raises(AgentLost):  # without lost_wait, the first query ends at once
            link.ask("late", "eval/x", _eval(), "value_reply", timeout=5.0)
        t0 = time.monotonic()
        assert link.ask("late", "eval/x", _eval(), "value_reply", timeout=5.0, lost_wait=10.0).value == 7
        assert time.monotonic() - t0 < 10.0
        with pytest.raises(AgentLost):  # gone for longer than lost_wait: still gone
            link.ask("never", "eval/x", _eval(), "value_reply", timeout=5.0, lost_wait=0.5)
    finally:
        back.cancel()
        back.join()
        for q in later:
            q.undeclare()


def test_a_service_call_the_run_never_took_is_refused_when_it_closes(router):
    """A client's conductor/trigger/<name> call that came after the run's last look at its inbox was left open: its
    caller waited for its own timeout and heard that nothing answered. Closing the link now refuses it, saying so."""
    from conductor.link import ServiceCall

    class Query:
        key_expr = KEYS.conductor("trigger/hold")
        said: list = []

        def reply_err(self, payload):
            self.said.append(codec.unpack(payload))

        def drop(self):
            self.said.append("dropped")

    session, _ = router
    link = AgentLink(session, KEYS, step_timeout=5.0)
    q = Query()
    link.inbox.put(ServiceCall("hold", {}, q))
    link.close()
    assert [m if isinstance(m, str) else m["message"] for m in q.said] == [
        "not fired: the run ended before it could take the call", "dropped"]
