"""Benchmark: what watching the loop costs it (docs/observability.md).

Path measured: the control loop of `control_loop` (a drone session publishes a State on the priority
flow; `dynqos edge mpc` answers with a Command), paced at 100 states a second (five times a drone's
rate: a watcher's work per state must fit between states, as it does in flight), first bare, then
with what watches it attached: the MPC serving Prometheus metrics that a scraper reads every second;
`dynqos view` subscribed to the drone's keys with a Foxglove WebSocket client (its own process)
subscribed to every channel it advertises, so that each state is also converted and sent; both. The
floor of any watcher is also measured: a bare zenoh subscriber of the states that does nothing (the
router then sends each state to two sessions). Each mode runs once per round, four rounds, the order
rotated each round and the MPC restarted each phase, so that drift in the machine's load hits all.
Target: the watched p50 at most 5% above the bare p50.

Run: dynqos bench observability (suite settings), or with its own options:
  python -m dynqos.bench.observability [--round-trips 2000] [--pace-hz 100] [--quick] [--out FILE]
"""

from __future__ import annotations

import contextlib
import statistics
import sys
import threading
import time
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from dynqos.bench.control_loop import BLOCK, Loop, _summary
from dynqos.bench.report import bench_parser, emit, judged, provenance
from dynqos.bench.rig import router_rig
from dynqos.common import keys
from dynqos.common.keys import Stream
from dynqos.common.transport import Role, open_bus
from dynqos.experiment.processes import Processes, free_port

MODES = ("bare", "metrics", "subscriber", "viewer", "watched")  # watched: metrics and viewer at once
ROUNDS = 4  # each mode once per round, the order rotated each round: drift in the machine hits all
SCRAPE_EVERY_S = 1.0


class Scraper:
    """Prometheus's part: GET /metrics every second on its own thread (a light load on this process)."""

    def __init__(self, port: int) -> None:
        self.url = f"http://127.0.0.1:{port}/metrics"
        self.stop = threading.Event()
        self.scrapes = 0
        self.thread = threading.Thread(target=self._run, name="scraper", daemon=True)

    def __enter__(self) -> Scraper:
        self.thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self.stop.set()
        self.thread.join(timeout=5)

    def _run(self) -> None:
        while not self.stop.wait(SCRAPE_EVERY_S):
            with contextlib.suppress(OSError), urllib.request.urlopen(self.url, timeout=2) as response:
                response.read()
                self.scrapes += 1


@dataclass
class Seen:
    scrapes: int = 0
    frames: int = 0


@contextlib.contextmanager
def _phase(procs: Processes, index: int, mode: str, seen: Seen) -> Iterator[None]:
    """The MPC (with metrics and a scraper, or not) and the viewer with its client (or not)."""
    metrics = mode in ("metrics", "watched")
    viewer = mode in ("viewer", "watched")
    mpc, view, client = f"mpc-{index}", f"view-{index}", f"foxglove-client-{index}"
    metrics_port, view_port = free_port(), free_port()
    procs.start(mpc, ["edge", "mpc", *(["--metrics-port", str(metrics_port)] if metrics else [])])
    listener = f"listener-{index}"
    if mode == "subscriber":  # the floor of any watcher: zenoh's fan-out of each state to a second session
        procs.start(
            listener,
            ["--listen", keys.uplink_all_drones(Stream.STATE)],
            program=[sys.executable, "-m", "dynqos.bench.zenoh_echo"],
        )
    count_file = procs.logs / f"{client}.count"
    if viewer:
        procs.start(view, ["view", "--port", str(view_port), "--no-camera"])
        procs.start(
            client,
            ["--port", str(view_port), "--count-file", str(count_file)],
            program=[sys.executable, "-m", "dynqos.bench.foxglove_client"],
        )
    try:
        with Scraper(metrics_port) if metrics else contextlib.nullcontext() as scraper:
            yield
        if isinstance(scraper, Scraper) and mode == "watched":
            seen.scrapes += scraper.scrapes
    finally:
        if mode == "subscriber":
            procs.stop(listener)
        if viewer:
            procs.stop(client)
            procs.stop(view)
            if mode == "watched" and count_file.exists():
                seen.frames += int(count_file.read_text())
        procs.stop(mpc)


def _paced(loop: Loop, count: int, pace_hz: float) -> list[float]:
    """`count` round trips, one every 1/pace_hz s (a drone sends states at a rate, not back to back;
    the wait is the pacing, not synchronisation)."""
    period = 1.0 / pace_hz
    seconds = []
    next_at = time.monotonic()
    for _ in range(count):
        delay = next_at - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        next_at += period
        seconds.append(loop.ours())
    return seconds


def phases(rounds: int = ROUNDS) -> list[str]:
    """Every mode once per round, each round's order rotated by one."""
    return [MODES[(i + r) % len(MODES)] for r in range(rounds) for i in range(len(MODES))]


def run(round_trips: int, pace_hz: float = 100.0, rounds: int = ROUNDS) -> dict[str, Any]:
    per_phase = max(BLOCK, round_trips // rounds)
    samples: dict[str, list[float]] = {mode: [] for mode in MODES}
    phase_p50: dict[str, list[float]] = {mode: [] for mode in MODES}
    seen = Seen()
    with router_rig() as (zcfg, procs):
        bus = open_bus(zcfg, Role.DRONE)
        try:
            loop = Loop(bus)
            for index, mode in enumerate(phases(rounds)):
                with _phase(procs, index, mode, seen):
                    loop.wait_served()  # this phase's MPC (the listener matches the states too)
                    for _ in range(BLOCK):  # warm-up: the new MPC's first solves and routes
                        loop.ours()
                    measured = _paced(loop, per_phase, pace_hz)
                    samples[mode].extend(measured)
                    phase_p50[mode].append(statistics.median(measured) * 1000)
        finally:
            bus.close()
    figures: dict[str, dict[str, Any]] = {
        mode: {**_summary(samples[mode]), "phase_p50_ms": phase_p50[mode]} for mode in MODES
    }
    bare = figures["bare"]["p50_ms"]
    return {
        "benchmark": "observability",
        **provenance(),
        "round_trips_per_path": len(samples["bare"]),
        "pace_hz": pace_hz,
        "rounds": rounds,
        **figures,
        "overhead_p50": {mode: figures[mode]["p50_ms"] / bare - 1 for mode in MODES[1:]},
        "scrapes": seen.scrapes,
        "foxglove_messages": seen.frames,
        "target_overhead_p50": 0.05,
    }


def verdict(result: dict[str, Any]) -> str:
    overhead = result["overhead_p50"]["watched"]
    return judged(
        overhead <= result["target_overhead_p50"],
        f"state -> MPC -> command p50 {result['watched']['p50_ms']:.2f} ms watched (metrics scraped "
        f"{result['scrapes']} times, {result['foxglove_messages']} messages to a Foxglove client) against "
        f"{result['bare']['p50_ms']:.2f} ms bare: {overhead * 100:+.1f}% (target <= +5%)",
    )


LABELS = {
    "bare": "bare",
    "metrics": f"MPC metrics, scraped every {SCRAPE_EVERY_S:.0f} s",
    "subscriber": "floor: a bare zenoh subscriber of the states (does nothing with them)",
    "viewer": "`dynqos view` with a Foxglove client subscribed to every channel",
    "watched": "both",
}


def markdown(result: dict[str, Any]) -> str:
    rows = [
        "| control loop on loopback via a router | p50 (ms) | p99 (ms) | mean (ms) | p50 vs bare "
        "| each phase's p50 (ms) |",
        "|---|---|---|---|---|---|",
    ]
    for mode in MODES:
        f = result[mode]
        change = f"{result['overhead_p50'][mode] * 100:+.1f}%" if mode != "bare" else "-"
        phases_text = ", ".join(f"{p:.2f}" for p in f["phase_p50_ms"])
        rows.append(
            f"| {LABELS[mode]} | {f['p50_ms']:.3f} | {f['p99_ms']:.3f} | {f['mean_ms']:.3f} | {change} | "
            f"{phases_text} |"
        )
    rows += [
        "",
        f"{result['round_trips_per_path']} round trips per path at {result['pace_hz']:.0f} Hz, in "
        f"{result['rounds']} phases each (the order rotated each round); "
        f"while watched: {result['scrapes']} scrapes, {result['foxglove_messages']} Foxglove messages",
    ]
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument("--round-trips", type=int, default=2000, help="per path (default 2000)")
    parser.add_argument(
        "--pace-hz", type=float, default=100.0, help="states per second (default 100, 5x a drone's 20 Hz)"
    )
    parser.add_argument(
        "--quick", action="store_true", help="smoke mode: 200 round trips per path, in 1 round rather than 4"
    )
    args = parser.parse_args(argv)
    if args.round_trips < 2 * BLOCK:
        parser.error(f"--round-trips must be at least {2 * BLOCK}")
    if not 1 <= args.pace_hz <= 1000:
        parser.error("--pace-hz must be in 1..1000")
    # each phase starts its own MPC (and viewer): the smoke's one round starts 5 rather than 20
    result = run(200 if args.quick else args.round_trips, args.pace_hz, 1 if args.quick else ROUNDS)
    return emit(result, markdown(result), args.out, verdict(result))


if __name__ == "__main__":
    sys.exit(main())
