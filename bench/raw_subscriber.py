"""Raw Zenoh pub/sub baseline: a process that answers every message on bench/ps/step with a put on
bench/ps/done/<i> (no framework)."""
import signal
import sys
import threading

import zenoh


def main():
    endpoint, i = sys.argv[1], sys.argv[2]
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("connect/endpoints", f'["{endpoint}"]')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    s = zenoh.open(cfg)
    pub = s.declare_publisher(f"bench/ps/done/{i}")
    reply = b"\x85" + b"x" * 40
    sub = s.declare_subscriber("bench/ps/step", lambda sample: pub.put(reply))
    tok = s.liveliness().declare_token(f"bench/ps/alive/{i}")
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    stop.wait()
    del sub, tok
    s.close()


if __name__ == "__main__":
    main()
