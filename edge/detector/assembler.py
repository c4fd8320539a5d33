"""Joins the parts of paced camera frames (onboard/pacing.py) back into whole images. Pure.

Parts of one image arrive in order over one flow, but a part can be lost (the camera publishers drop
under congestion) and a drone can switch flows between images. So an image in progress is given up
when a newer image of the same drone and kind completes, and the whole table is bounded in images
and bytes: a sender cannot make the detector hold more than `max_bytes`, whatever it sends.

`add_timed` also says when each part of a completed image arrived: the drone's camera rate controller
reads the one-way delay's growth from those times (onboard/camera_rate.py).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field, replace

from dynqos.common.messages import CameraFrame

Key = tuple[str, str, int]  # uav, kind, frame seq


@dataclass(slots=True)
class _Partial:
    first: CameraFrame
    payloads: dict[int, bytes] = field(default_factory=dict)
    arrivals_ns: dict[int, int] = field(default_factory=dict)
    nbytes: int = 0


class FrameAssembler:
    def __init__(self, max_frames: int = 64, max_bytes: int = 64 * 1024 * 1024) -> None:
        self.max_frames = max_frames
        self.max_bytes = max_bytes
        self._partials: OrderedDict[Key, _Partial] = OrderedDict()
        self._bytes = 0
        self.incomplete = 0  # images given up with parts missing
        self.inconsistent = 0  # parts that contradict the first part of their image

    @property
    def pending_bytes(self) -> int:
        return self._bytes

    def __len__(self) -> int:
        return len(self._partials)

    def add(self, frame: CameraFrame) -> CameraFrame | None:
        """The whole image once `frame` completes it, else None."""
        done = self.add_timed(frame, 0)
        return None if done is None else done[0]

    def add_timed(self, frame: CameraFrame, arrival_ns: int) -> tuple[CameraFrame, tuple[int, ...]] | None:
        """The whole image once `frame` (arrived at `arrival_ns`) completes it, with when each of its
        parts arrived, in part order; else None."""
        if frame.parts == 1:
            return frame, (arrival_ns,)
        key = (frame.uav, frame.kind, frame.seq)
        partial = self._partials.get(key)
        if partial is None:
            partial = self._partials[key] = _Partial(frame)
        elif not _same_image(partial.first, frame):
            self.inconsistent += 1
            return None
        if frame.part not in partial.payloads:
            partial.payloads[frame.part] = frame.payload
            partial.arrivals_ns[frame.part] = arrival_ns
            partial.nbytes += len(frame.payload)
            self._bytes += len(frame.payload)
        if len(partial.payloads) == frame.parts:
            self._drop(key)
            self._give_up_older(frame)
            payload = b"".join(partial.payloads[i] for i in range(frame.parts))
            arrivals = tuple(partial.arrivals_ns[i] for i in range(frame.parts))
            return replace(partial.first, payload=payload, part=0, parts=1), arrivals
        while len(self._partials) > self.max_frames or self._bytes > self.max_bytes:
            self._drop(next(iter(self._partials)))
            self.incomplete += 1
        return None

    def _drop(self, key: Key) -> None:
        self._bytes -= self._partials.pop(key).nbytes

    def _give_up_older(self, done: CameraFrame) -> None:
        stale = [k for k in self._partials if k[0] == done.uav and k[1] == done.kind and k[2] < done.seq]
        for key in stale:
            self._drop(key)
        self.incomplete += len(stale)


def _same_image(a: CameraFrame, b: CameraFrame) -> bool:
    def shape(f: CameraFrame) -> tuple[int, int, str, int, int]:
        return (f.parts, f.stamp_ns, f.encoding, f.width, f.height)

    return shape(a) == shape(b)
