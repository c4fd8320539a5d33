"""`dynqos record --ros2`: the flight as a ROS 2 bag in one MCAP file (edge/ros2/bag.py), with the
topics, types and frames `dynqos edge ros2` publishes (edge/ros2/translate.py), so that `ros2 bag
info/play` and Foxglove open it as ROS 2 data. It watches the drones as `dynqos record` does (an edge
client, a bounded queue, niced, the last messages kept on stop: dynqos/observers/observer.py).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

from dynqos import __version__
from dynqos.common import keys
from dynqos.common.config import Config
from dynqos.common.errors import DecodeError
from dynqos.common.lifecycle import ready_line, stop_on_signals
from dynqos.common.messages import decode
from dynqos.observers.observer import BATCH_S, OBSERVER_NICE, Observer
from dynqos.sim.vehicle.world import default_world

log = logging.getLogger(__name__)


class Ros2Recorder(Observer):
    """The observer's zenoh side and queue; each message translated to ROS 2 samples and written."""

    def __init__(self, config: Config, out: Path, *, uav: str | None, camera: bool) -> None:
        from dynqos.edge.ros2.bag import Ros2Mcap  # the ros2 extra (rosbags, mcap)
        from dynqos.edge.ros2.translate import Translator

        super().__init__(config, default_world(), uav=uav, camera=camera)
        self.translator = Translator(config.ros2.prefix, config.ros2.frame_id)
        self.bag = Ros2Mcap(out, library=f"dynqos {__version__}")

    def run(self) -> None:
        while not self.stop.wait(BATCH_S):
            for key, payload in self.queue.drain():
                self.take(key, payload)
        self._flush()

    def take(self, key: str, payload: bytes) -> None:
        try:
            message = decode(payload)
            uav = keys.parse(key).uav
        except (DecodeError, ValueError) as exc:
            self.counts.rejected += 1
            if self.counts.rejected == 1:
                log.warning("record: undecodable message on %s: %s", key, exc)
            return
        self.counts.received += 1
        now = self.now_ns()
        for sample in self.translator.translate(uav, message, now):
            self.bag.write(sample, now)
            self.counts.logged[sample.topic] = self.counts.logged.get(sample.topic, 0) + 1


def run(config: Config, out: Path, *, uav: str | None = None, camera: bool = True) -> int:
    """Until SIGTERM or Ctrl-C; the MCAP closed whole."""
    os.nice(OBSERVER_NICE)
    recorder = Ros2Recorder(config, out, uav=uav, camera=camera)
    stop_on_signals("record", recorder.stop.set)
    try:
        recorder.open()
        info: dict[str, Any] = {"keys": recorder.keys, "out": str(out), "encoding": "ros2"}
        ready_line("record", **info)
        recorder.run()
    finally:
        recorder.close()
        recorder.bag.close()
        log.info("record: stopped; %d ROS 2 messages written; %s", recorder.bag.written, recorder.summary())
    return 0
