"""Where the emulated operator computes its predictions: a process of its own, below the cell's priority.

An answer at geohash level 10 for a hall takes some 0.4 s of CPU and is megabytes of JSON. The cell's
loop forwards every drone's packets; stalled that long (or slowed by a thread of its own through the
GIL) it would send the whole fleet to its fallbacks, and an operator's prediction service does not run
in its radio's data path. The process is spawned (not forked from a process with an event loop and
threads) and sends back only the answer's bytes.
"""

from __future__ import annotations

import asyncio
import json
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from typing import Any

from dynqos.sim.network.prediction import Predictor

NICE = 10


def answer_json(predictor: Predictor, body: dict[str, Any], now_unix: float) -> bytes:
    """A retrieve's answer as the JSON it is sent as; Refused (picklable) when the API refuses it."""
    return json.dumps(predictor.retrieve(body, now_unix)).encode()


class PredictionProcess:
    def __init__(self) -> None:
        self._pool: ProcessPoolExecutor | None = None

    def start(self) -> None:
        """Spawn it now (a second or so), so that the first request does not wait for it."""
        if self._pool is None:
            context = multiprocessing.get_context("spawn")
            self._pool = ProcessPoolExecutor(1, mp_context=context, initializer=os.nice, initargs=(NICE,))
            self._pool.submit(os.getpid)

    async def answer(self, predictor: Predictor, body: dict[str, Any], now_unix: float) -> bytes:
        self.start()
        assert self._pool is not None
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self._pool, answer_json, predictor, body, now_unix)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
