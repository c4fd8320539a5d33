"""The floor for the control-loop benchmark: a bare zenoh-python responder, in its own process.

It answers every sample on `bench/ping` with `--reply-bytes` bytes on `bench/pong`, at the same
priority and express setting as the MPC's Command, through the same router: what a round trip costs
with zenoh alone, without our messages, queues or the MPC. Started by `bench/control_loop.py`.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading

import zenoh

from dynqos.common.config import load_config
from dynqos.common.transport import Role, open_session

PING, PONG = "bench/ping", "bench/pong"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--reply-bytes", type=int, default=0, help="payload size of each answer")
    parser.add_argument(
        "--listen",
        metavar="KEY",
        help="only subscribe to KEY and do nothing with it (the observability floor)",
    )
    parser.add_argument("--config", required=True, help="dynqos config (its [zenoh] section: the router)")
    args = parser.parse_args(argv)
    session = open_session(load_config(args.config).zenoh, Role.EDGE)
    if args.listen:  # a second subscriber of the drone's states, as cheap as zenoh makes one
        subscriber = session.declare_subscriber(args.listen, lambda _sample: None)
    else:
        if args.reply_bytes <= 0:
            parser.error("--reply-bytes is required (or --listen KEY)")
        reply = bytes(args.reply_bytes)
        pong = session.declare_publisher(PONG, priority=zenoh.Priority.REAL_TIME, express=True)
        subscriber = session.declare_subscriber(PING, lambda _sample: pong.put(reply))
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    print(json.dumps({"ready": True, "service": "zenoh_echo"}), flush=True)
    stop.wait()
    subscriber.undeclare()  # type: ignore[no-untyped-call]
    session.close()  # type: ignore[no-untyped-call]
    return 0


if __name__ == "__main__":
    sys.exit(main())
