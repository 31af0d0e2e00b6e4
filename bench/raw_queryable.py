"""Raw Zenoh baseline: a queryable process with no framework (answers every query with a small reply)."""
import signal
import sys
import threading

import zenoh


def main():
    endpoint, key = sys.argv[1], sys.argv[2]
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("connect/endpoints", f'["{endpoint}"]')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    s = zenoh.open(cfg)
    reply = b"\x85" + b"x" * 40

    def on_query(q):
        q.reply(q.key_expr, reply)
        q.drop()

    qb = s.declare_queryable(key, on_query)
    tok = s.liveliness().declare_token(key.replace("/step", "/alive"))
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    stop.wait()
    del qb, tok
    s.close()


if __name__ == "__main__":
    main()
