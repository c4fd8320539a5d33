"""A router on free loopback ports in a temporary folder, for the benchmarks that start edge services."""

from __future__ import annotations

import contextlib
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from dynqos.common.config import ZenohConfig
from dynqos.common.messages import State
from dynqos.experiment.processes import Processes, flow_ports


@contextlib.contextmanager
def router_rig(extra_toml: str = "") -> Iterator[tuple[ZenohConfig, Processes]]:
    """Yields the zenoh config to reach a running `dynqos edge router` and the Processes to start more
    services with (same config file, [zenoh] ports plus `extra_toml`); stops them all on exit."""
    with tempfile.TemporaryDirectory(prefix="dynqos-bench-") as tmp:
        folder = Path(tmp)
        zcfg = ZenohConfig(**flow_ports())
        config = folder / "bench.toml"
        config.write_text(
            f"[zenoh]\ndefault_port = {zcfg.default_port}\npriority_port = {zcfg.priority_port}\n"
            + extra_toml
        )
        procs = Processes(config, folder)
        try:
            procs.start("router", ["edge", "router"])
            yield zcfg, procs
        finally:
            procs.stop_all()


def hovering_state(uav: str, seq: int, index: int, term: int = 0, replica: str = "") -> State:
    """A load drone's State: the `index`-th drone of a fleet hovering in a row, following `replica`."""
    return State(
        uav=uav,
        seq=seq,
        stamp_ns=time.monotonic_ns(),
        pos_m=(0.01 * index, 0.0, -1.5),
        vel_mps=(0.0, 0.0, 0.0),
        quat=(1.0, 0.0, 0.0, 0.0),
        command_term=term,
        command_replica=replica,
    )
