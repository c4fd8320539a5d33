"""A Foxglove WebSocket client for the benchmarks: connects to `dynqos view`, subscribes to every channel
it advertises, counts what arrives, prints a ready line, and on SIGTERM writes its count to the file
given. In its own process, so that receiving does not share the measuring process's interpreter.

  python -m dynqos.bench.foxglove_client --port PORT --count-file FILE [--config FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import signal
import sys
from pathlib import Path

import aiohttp

SUBPROTOCOL = "foxglove.sdk.v1"


async def watch(port: int, count_file: Path) -> None:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    frames = 0
    async with (
        aiohttp.ClientSession() as session,
        session.ws_connect(f"ws://127.0.0.1:{port}", protocols=(SUBPROTOCOL,)) as ws,
    ):
        print(json.dumps({"ready": True, "service": "foxglove-client"}), flush=True)
        subscribed: set[int] = set()
        while not stop.is_set():
            try:
                frame = await ws.receive(timeout=0.5)
            except TimeoutError:
                continue
            if frame.type == aiohttp.WSMsgType.TEXT:
                body = json.loads(frame.data)
                if body.get("op") == "advertise":
                    new = [c["id"] for c in body["channels"] if c["id"] not in subscribed]
                    subscribed.update(new)
                    subs = [{"id": cid, "channelId": cid} for cid in new]
                    await ws.send_str(json.dumps({"op": "subscribe", "subscriptions": subs}))
            elif frame.type == aiohttp.WSMsgType.BINARY:
                frames += 1
            else:
                break
    count_file.write_text(str(frames))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--count-file", type=Path, required=True)
    parser.add_argument("--config", help="ignored (the benchmarks' process runner passes one to all)")
    args = parser.parse_args(argv)
    asyncio.run(watch(args.port, args.count_file))
    return 0


if __name__ == "__main__":
    sys.exit(main())
