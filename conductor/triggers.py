"""Triggers (the paper's §3.3): when an action annotation, an output's new value, a model's event or a client's
service call (``conductor/trigger/<name>``) arrives, the scene's triggers that listen to it bind their variables
(``let``; a service call's arguments), check their precondition (``when``) and run their effects: transfer a
responsibility, or call a service on a model (its result bound with ``as`` for the effects after it).

Expressions are evaluated with the built-ins of :mod:`conductor.builtins` bound to the run's state, plus the
scene's evaluators, which query models (``model/<id>/eval/<name>``). Every firing, fired or not, is recorded
in the trigger log and raised as a ``trigger`` event; a problem is a ``trigger_error`` and never stops the run.
"""
from __future__ import annotations

import difflib
import functools
import logging
from collections.abc import Callable
from typing import Any

from protocol import codec
from protocol.errors import AgentError, ExprError, ProtocolError, RunAborted

from .builtins import bind
from .handover import Handovers
from .link import AgentLink, ServiceCall
from .record import RunRecord, plain
from .responsibility import Responsibilities
from .scene import Effect, EvaluatorSpec, Scene, TriggerSpec
from .scene.load import fmt_path

log = logging.getLogger("twin.triggers")


class TriggerEngine:
    """The scene's triggers for one run. ``clock`` is read for the current tick and time."""

    def __init__(self, scene: Scene, rmap: Responsibilities, link: AgentLink, handovers: Handovers,
                 record: RunRecord, clock: Any) -> None:
        self.scene, self.map, self.link, self.handovers, self.record = scene, rmap, link, handovers, record
        self.clock = clock
        self._fired_once: set[str] = set()
        self._warned: set[tuple[str, str]] = set()  # (trigger, text) of the warn effects said (once a run each)
        # "model.name" of the outputs and events some trigger listens to (most outputs change every tick unheard)
        self._heard = {kind: {str(t.on[kind]) for t in scene.triggers if kind in t.on} for kind in ("topic", "event")}
        # the functions every expression may call: built-ins bound to this run, then the scene's evaluators
        self.functions: dict[str, Callable[..., Any]] = bind(rmap)
        for ev in scene.evaluators.values():
            self.functions[ev.name] = self._evaluator(ev)

    # ------------------------------------------------------------------------------ sources
    def on_action(self, msg: dict[str, Any]) -> None:
        """An action annotation arrived (``{operation, phase, params}``)."""
        op, phase = msg["operation"], msg["phase"]
        self._fire("action", lambda on: on["action"] == op and on.get("phase", "start") in (phase, "any"),
                   {"action": msg})

    def on_output(self, model: str, name: str, value: Any) -> None:
        """An output took a new value."""
        ref = f"{model}.{name}"
        if ref in self._heard["topic"]:
            self._fire("topic", lambda on: on["topic"] == ref, {"value": value})

    def on_event(self, model: str, name: str, data: dict[str, Any]) -> None:
        """A model raised an event."""
        if self.map.count_event(model, name):
            self._on_counted(model, name, data)

    def _on_counted(self, model: str, name: str, data: dict[str, Any]) -> None:
        """An event already counted, to the triggers that listen to it."""
        ref = f"{model}.{name}"
        if ref in self._heard["event"]:
            self._fire("event", lambda on: on["event"] == ref, {"event": {"model": model, "name": name, "data": data}})

    def on_service(self, call: ServiceCall) -> None:
        """A client called ``conductor/trigger/<name>``: fire the triggers on ``{service: name}`` with the call's
        arguments bound, and answer with what each did; refuse (with the reasons) when none fired."""
        if call.expired():  # its caller was told that nothing answered: firing it now would be a surprise
            log.warning("service call %s not fired: its caller stopped waiting before the run could take it", call.name)
            call.refuse("not fired: the run took the call after its caller's timeout")
            return
        try:
            self._serve_call(call)
        except Exception as e:  # whatever a client sends, the run goes on and the client hears why not
            log.exception("service call %s", call.name)
            call.refuse(f"the call failed: {type(e).__name__}: {e}")

    def _serve_call(self, call: ServiceCall) -> None:
        listening = [t for t in self.scene.triggers if t.on.get("service") == call.name]
        if not listening:
            have = sorted({str(t.on["service"]) for t in self.scene.triggers if "service" in t.on})
            call.refuse(f"no trigger of scene {self.scene.name} listens to service {call.name!r} "
                        f"(it has: {', '.join(have) or 'none'})")
            return
        done: list[dict[str, Any]] = []
        for trig in listening:
            names = list(trig.on.get("args") or [])
            missing, unknown = [a for a in names if a not in call.args], sorted(set(call.args) - set(names))
            if missing or unknown:
                why = (f"missing arguments: {', '.join(missing)}" if missing else
                       f"unknown arguments: {', '.join(unknown)} (it takes: {', '.join(names) or 'none'})")
                done.append({"trigger": trig.name, "fired": False, "reason": why})
            elif trig.once and trig.name in self._fired_once:
                done.append({"trigger": trig.name, "fired": False, "reason": "it fires once, and it has fired"})
            else:
                done.append(self._run(trig, "service", {a: call.args[a] for a in names}))
        if any(d["fired"] for d in done):
            call.answer(plain(done))
        else:
            call.refuse("; ".join(f"{d['trigger']}: {d.get('reason') or d.get('error')}" for d in done))

    def absorb_tick(self, replies: list[tuple[str, dict[str, Any]]]) -> None:
        """Take in every model's step reply of one tick: first every state, then every output and event, and only
        then fire the triggers they fire, in the order given (the scene's). A trigger so fires after the tick, on
        its whole state: one fired by a model before the owner in that order no longer hands the attribute over
        before the owner's value of the same tick is in (that value was dropped and counted as an unauthorized
        write), and its condition reads every model's outputs and event counts of that tick, whichever comes first
        in the scene (one after the firing model's was read a tick old)."""
        for model, rep in replies:
            if rep["state"]:
                self.map.absorb_state(model, rep["state"])
        fire = [f for model, rep in replies for f in self._record_signals(model, rep)]
        for f in fire:
            f()

    def absorb(self, model: str, msg: dict[str, Any]) -> None:
        """Take in what a model reported (a step reply, or a clock/free model's publication): its state into the
        map, its outputs and events to the triggers that listen to them."""
        mtype = msg.get("type")
        if mtype in ("step_reply", "state"):
            self.map.absorb_state(model, msg["state"] if mtype == "step_reply" else msg["values"], stepped=False)
        if mtype == "step_reply":
            for f in self._record_signals(model, msg):
                f()
        elif mtype == "out":
            self._output(model, msg["name"], msg["value"])
        elif mtype == "event":
            self.on_event(model, msg["name"], msg["data"])

    def _record_signals(self, model: str, reply: dict[str, Any]) -> list[Callable[[], None]]:
        """Record a step reply's outputs and events (the map's values, its event counts); the firing of the
        triggers that listen to the changed outputs and the events, to call once they are all in."""
        fire: list[Callable[[], None]] = []
        for n, v in reply["outputs"].items():
            if self.map.set_output(model, n, v):
                fire.append(functools.partial(self.on_output, model, n, v))
        for ev in reply["events"]:
            if isinstance(ev, dict) and "name" in ev and self.map.count_event(model, str(ev["name"])):
                fire.append(functools.partial(self._on_counted, model, str(ev["name"]), ev.get("data") or {}))
        return fire

    def _output(self, model: str, name: str, value: Any) -> None:
        if self.map.set_output(model, name, value):
            self.on_output(model, name, value)

    def semantics(self) -> dict[str, Any]:
        """The scene's semantic predicates, evaluated on the state now (None where one fails)."""
        out: dict[str, Any] = {}
        resolve = self._resolver({})
        for label, ex in self.scene.semantics.items():
            try:
                out[label] = plain(ex.evaluate(resolve, self.functions))
            except Exception as e:  # (any: an array's truth value, an int of inf...): that predicate alone is lost
                out[label] = None
                self.record.error(f"semantics {label}: {e if isinstance(e, ExprError) else _named_error(e)}")
        return out

    # ------------------------------------------------------------------------------ firing
    def _fire(self, kind: str, match: Callable[[dict[str, Any]], bool], context: dict[str, Any]) -> None:
        for trig in self.scene.triggers:
            if kind in trig.on and match(trig.on) and not (trig.once and trig.name in self._fired_once):
                self._run(trig, kind, context)

    def _run(self, trig: TriggerSpec, kind: str, context: dict[str, Any]) -> dict[str, Any]:
        c = self.clock
        scope = dict(context, tick=c.tick, t=c.t, trigger=trig.name)
        resolve = self._resolver(scope)
        fns = self.functions
        record: dict[str, Any] = {"trigger": trig.name, "tick": c.tick, "t": c.t, "on": kind, "fired": False}
        part: tuple[Any, ...] = ()  # the key of the trigger being evaluated: an error names its line
        try:
            for var, ex in trig.let:
                part = ("let", var)
                scope[var] = ex.evaluate(resolve, fns)
            bound = list(trig.on.get("args") or []) if kind == "service" else []  # a call's arguments
            variables = plain({v: scope[v] for v in [*bound, *(v for v, _ in trig.let)]})
            part = ("when",)
            if trig.when is not None and not trig.when.evaluate(resolve, fns):
                record["variables"] = variables
                record["reason"] = f"precondition false: {trig.when.source}" + _given(variables, bound, self.scene)
                self._log(record)
                return record
            known: dict[int, tuple[int, Any, Any, Any]] = {}  # effect -> (map version, entity, attribute, model)
            unfit = self._unfit_transfer(trig, resolve, known) if kind == "service" else None
            if unfit:  # a client's argument names nothing of the scene: refused, the run not made worse by it
                record.update(variables=variables, reason=unfit)
                self._log(record)
                return record
            record.update(fired=True, variables=dict(variables))  # (as they were when it fired: logged now)
            self._log(record)
            if trig.once:
                self._fired_once.add(trig.name)
            record = dict(record, effects=[], variables=variables)  # (what it did: the calls' results bound too)
            for i, eff in enumerate(trig.do):
                part = ("do", i)
                record["effects"].append(self._effect(trig, eff, resolve, variables, scope, known.get(i)))
        except RunAborted:  # (the main model lost meanwhile: the run cannot go on)
            raise
        except Exception as e:  # (an ExprError, or what Python raised on values it cannot compare): the run goes on
            why = str(e) if isinstance(e, ExprError) else _named_error(e)
            if kind == "service" and not record["fired"]:  # the call's arguments do not fit: refused, not a fault
                record["reason"] = f"cannot be evaluated with the arguments given: {why}"
                self._log(record)
                return record
            self.handovers.problem(trig.name, f"{self._where(trig, part)}: {why}")
            record["error"] = why
        return record

    def _unfit_transfer(self, trig: TriggerSpec, resolve: Callable[[str], Any],
                        known: dict[int, tuple[int, Any, Any, Any]]) -> str | None:
        """What a service trigger's transfers would be asked to move that the scene does not have (an entity, an
        attribute of it, a model, a model that cannot own it), from the call's arguments; None if all fit. A transfer
        that needs what an earlier effect binds is left to the run. What each transfer's fields evaluated to goes
        into ``known`` (with the map's version): the effect uses it while no handover has changed the map, rather
        than asking the evaluators in them a second time."""
        for i, eff in enumerate(trig.do):
            if eff.kind != "transfer":
                continue
            try:
                e, a, dst = (eff.fields[f].evaluate(resolve, self.functions) for f in ("entity", "attribute", "to"))
            except Exception:
                continue
            known[i] = (self.map.version, e, a, dst)
            for one in e if isinstance(e, list) else [e]:
                if (str(one), str(a)) not in self.map.owners:
                    near = difflib.get_close_matches(str(one), list(self.scene.entities), n=1)
                    return (f"no responsibility {one}.{a} in scene {self.scene.name}"
                            + (f" (did you mean {near[0]!r}?)" if near else ""))
            if str(dst) not in self.scene.models:
                return f"no model {dst!r} in scene {self.scene.name} (it has: {', '.join(self.scene.models)})"
            if str(a) not in self.handovers.registry.declares(str(dst), "attributes"):
                return f"model {dst} cannot own attribute {a!r}"
        return None

    def _where(self, trig: TriggerSpec, part: tuple[Any, ...]) -> str:
        """``file:line: key`` of ``part`` of a trigger (its ``when``, a ``let`` variable, an effect), else of the
        trigger itself."""
        at = next((i for i, t in enumerate(self.scene.triggers) if t is trig), None)
        line = (self.scene.line("triggers", at, *part) if at is not None else None) or trig.line
        key = fmt_path(("triggers", at, *part)) if at is not None else f"trigger {trig.name}"
        return f"{self.scene.file}:{line}: {key}"

    def _effect(self, trig: TriggerSpec, eff: Effect, resolve: Callable[[str], Any], variables: dict[str, Any],
                scope: dict[str, Any], known: tuple[int, Any, Any, Any] | None = None) -> dict[str, Any]:
        """Do one effect; what it did. A ``call`` effect's result is bound to its ``as`` variable in ``scope``
        for the effects after it."""
        fns = self.functions
        if eff.kind == "warn":  # (said once a run: the first time its trigger fires, with the variables then)
            shown = "; ".join(f"{k} = {_rounded(v)!r}" for k, v in variables.items())[:300]
            said = f"trigger {trig.name} at t={self.clock.t:.2f} s: {eff.fields['text']}"
            said += f" ({shown})" if shown else ""
            if (trig.name, eff.fields["text"]) not in self._warned:
                self._warned.add((trig.name, eff.fields["text"]))
                self.record.degraded.append(said)
            return {"warn": eff.fields["text"]}
        if eff.kind == "transfer":
            if known is not None and known[0] == self.map.version:  # (evaluated by the service's check, the same map)
                e, a, dst = known[1:]
            else:
                e = eff.fields["entity"].evaluate(resolve, fns)
                a = eff.fields["attribute"].evaluate(resolve, fns)
                dst = eff.fields["to"].evaluate(resolve, fns)
            if e is None:
                self.handovers.problem(trig.name, f"{eff.path}: entity evaluated to null")
                return {"transfer": None, "problem": "entity evaluated to null"}
            moved = [str(one) for one in (e if isinstance(e, list) else [e])  # a list transfers each entity
                     if self.handovers.transfer(str(one), str(a), str(dst), trig.name, dict(variables))]
            named = ", ".join(map(str, e if isinstance(e, list) else [e])) or "nothing (the list is empty)"
            return {"transfer": f"{a} of {named} to {dst}", "moved": moved}
        args = [x.evaluate(resolve, fns) for x in eff.fields["args"]]
        c = self.clock
        done: dict[str, Any] = {"call": f"{eff.fields['model']}.{eff.fields['service']}"}
        try:
            payload = codec.encode("call", args=args, kwargs={}, tick=c.tick, t=c.t)
            value = self.link.ask(eff.fields["model"], f"call/{eff.fields['service']}", payload, "value_reply").value
        except (AgentError, ProtocolError) as ex:
            self.handovers.problem(trig.name, f"{eff.path}: {ex}")
            value, done["problem"] = None, str(ex)
        if eff.fields.get("as"):  # (a handover before it keeps the variables as they were then: a copy)
            scope[eff.fields["as"]] = value  # null when the call failed: the effects after it see that
            variables[eff.fields["as"]] = plain(value)
        done["value"] = plain(value)
        return done

    def _log(self, record: dict[str, Any]) -> None:
        self.record.trigger_log.append(record)
        self.link.event("trigger", record, self.clock.tick, self.clock.t)

    def _evaluator(self, ev: EvaluatorSpec) -> Callable[..., Any]:
        def call(*args: Any) -> Any:
            c = self.clock
            payload = codec.encode("eval", args=list(ev.args) + list(args), tick=c.tick, t=c.t)
            try:
                return self.link.ask(ev.model, f"eval/{ev.remote}", payload, "value_reply").value
            except (AgentError, ProtocolError) as e:  # (no answer, an error, or an answer that is no value_reply)
                raise ExprError(f"evaluator {ev.name} failed: {e}") from None

        return call

    def _resolver(self, scope: dict[str, Any]) -> Callable[[str], Any]:
        def resolve(name: str) -> Any:
            if name in scope:
                return scope[name]
            if name in self.scene.entities or name in self.scene.models:
                return name
            raise ExprError(f"undefined variable {name!r}")

        return resolve


def _rounded(v: Any) -> Any:
    """``v`` with its floats to 4 significant digits (for a warning a person reads)."""
    if isinstance(v, float):
        return float(f"{v:.4g}")
    if isinstance(v, dict):
        return {k: _rounded(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_rounded(x) for x in v]
    return v


def _given(variables: dict[str, Any], args: list[str], scene: Scene) -> str:
    """The call's arguments a refused precondition was evaluated with, each string that names neither an entity nor
    a model of the scene marked as such (a misspelt entity makes a precondition false, not an error)."""
    if not args:
        return ""
    parts = []
    for a in args:
        v = variables.get(a)
        unknown = isinstance(v, str) and v not in scene.entities and v not in scene.models
        parts.append(f"{a}={v!r}" + (", which is no entity or model of the scene" if unknown else ""))
    return f" (with {'; '.join(parts)})"


def _named_error(e: Exception) -> str:
    """An exception an expression raised that is no :class:`ExprError`, as a line: its type and message."""
    return f"{type(e).__name__}: {e}"
