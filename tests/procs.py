"""Start `dynqos` subcommands as real processes, wait for their ready line, stop them by pid.

A child's stderr is read all the time by a thread of ours: a pipe nobody reads holds 64 KiB, and a
service that logs a health line a second fills it within a few minutes and then blocks in its next log
call, which stops the service mid-flight (a long flight on a loaded machine went silent that way).
"""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import json
import os
import queue
import selectors
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

DYNQOS = shutil.which("dynqos") or str(Path(sys.executable).parent / "dynqos")
KEPT_STDERR_LINES = 20_000  # what stop() returns: the log's tail, bounded
LIVE_STDERR_LINES = 10_000  # what lines() can still hand out; older ones are dropped when nobody reads
STOP_WAIT_S = 15.0  # how long stop() waits after SIGTERM before it kills the child


class DynqosProcess:
    def __init__(
        self,
        args: list[str],
        config: Path,
        ready_timeout_s: float = 30.0,
        env: dict[str, str] | None = None,
        executable: str | Path = DYNQOS,
    ) -> None:
        self.args = args
        self.killed = False  # stop() had to kill it: it did not end within STOP_WAIT_S of SIGTERM
        self.proc = subprocess.Popen(
            [str(executable), *args, "--config", str(config)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, **env} if env else None,
        )
        self._stderr_tail: collections.deque[str] = collections.deque(maxlen=KEPT_STDERR_LINES)
        self._stderr_live: queue.Queue[str | None] = queue.Queue(maxsize=LIVE_STDERR_LINES)
        self._drains = [threading.Thread(target=self._drain_stderr, daemon=True)]
        self._drains[0].start()
        assert self.proc.stdout is not None
        with selectors.DefaultSelector() as selector:
            selector.register(self.proc.stdout, selectors.EVENT_READ)
            ready = selector.select(timeout=ready_timeout_s)
        line = self.proc.stdout.readline() if ready else ""
        if not line:
            err = self.stop()
            raise AssertionError(f"dynqos {' '.join(args)} did not become ready: {err[-2000:]}")
        self.info: dict[str, Any] = json.loads(line)
        self._drains.append(threading.Thread(target=self._drain_stdout, daemon=True))
        self._drains[-1].start()

    def _drain_stderr(self) -> None:
        assert self.proc.stderr is not None
        for text in self.proc.stderr:
            self._stderr_tail.append(text)
            self._offer(text)
        self._offer(None)

    def _offer(self, text: str | None) -> None:
        while True:
            try:
                self._stderr_live.put_nowait(text)
                return
            except queue.Full:
                with contextlib.suppress(queue.Empty):
                    self._stderr_live.get_nowait()  # nobody is reading live: keep the newest

    def _drain_stdout(self) -> None:
        assert self.proc.stdout is not None
        for _ in self.proc.stdout:
            pass

    def lines(self, timeout_s: float) -> Iterator[str]:
        """The child's stderr as it comes, until it ends or `timeout_s` passes with nothing new."""
        while True:
            try:
                text = self._stderr_live.get(timeout=timeout_s)
            except queue.Empty:
                return
            if text is None:
                return
            yield text

    @property
    def returncode(self) -> int | None:
        """How the child ended (negative: the signal that ended it), None while it runs."""
        return self.proc.poll()

    def ended(self) -> str:
        """How it ended, for an assertion's message."""
        how = "killed after not stopping" if self.killed else "stopped"
        return f"dynqos {' '.join(self.args)}: {how}, exit code {self.returncode}"

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self) -> str:
        """SIGTERM our own child by its pid; kill it if it does not stop (`killed` says so, `returncode`
        how it ended). Returns its stderr."""
        if self.proc.poll() is None:
            self.proc.terminate()
        try:
            self.proc.wait(timeout=STOP_WAIT_S)
        except subprocess.TimeoutExpired:
            self.killed = True
            self.proc.kill()
            self.proc.wait(timeout=5)
        deadline = time.monotonic() + 5
        for drain in self._drains:
            drain.join(timeout=max(0.0, deadline - time.monotonic()))  # the pipes end when it exits
        if not any(drain.is_alive() for drain in self._drains):  # a grandchild may still hold a pipe
            for pipe in (self.proc.stdout, self.proc.stderr):
                if pipe is not None:
                    pipe.close()
        return "".join(self._stderr_tail)


def start_together(config: Path, *commands: list[str]) -> list[DynqosProcess]:
    """Each command started at once and waited for until ready, in the order given: processes that need
    only what is already up need not wait for one another to load. If one does not become ready, those
    that did are stopped and its error is raised."""
    with concurrent.futures.ThreadPoolExecutor(max_workers=len(commands)) as pool:
        futures = [pool.submit(DynqosProcess, command, config) for command in commands]
    started, error = [], None
    for future in futures:
        try:
            started.append(future.result())
        except Exception as exc:  # not ready, or could not start at all: the others are stopped either way
            error = error or exc
    if error is not None:
        for proc in reversed(started):
            proc.stop()
        raise error
    return started
