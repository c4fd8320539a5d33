"""The emulated operator's notifications, posted to each client's sink in the background: CloudEvents
over HTTP (CAMARA's) or the NEF's JSON, bounded (a flood of them waits for no one), each counted as
delivered or failed.
The cell (a session the network ended) and the control API (a session created or deleted) both send."""

from __future__ import annotations

import asyncio
import json
import logging

from aiohttp import ClientSession, ClientTimeout

from dynqos.sim.network.operator import Notification

log = logging.getLogger(__name__)

MAX_PENDING_NOTIFICATIONS = 64
NOTIFY_TIMEOUT_S = 2.0


class Notifier:
    def __init__(self) -> None:
        self.pending: set[asyncio.Task[None]] = set()
        self.notified = 0
        self.notify_failures = 0
        self.http: ClientSession | None = None

    async def start(self) -> None:
        self.http = ClientSession(timeout=ClientTimeout(total=NOTIFY_TIMEOUT_S))

    async def stop(self) -> None:
        for task in list(self.pending):
            task.cancel()
        if self.http is not None:
            await self.http.close()

    def send(self, notes: list[Notification]) -> None:
        """Post each notification to its sink in the background (bounded; the oldest work is not waited)."""
        for note in notes:
            if len(self.pending) >= MAX_PENDING_NOTIFICATIONS:
                self.notify_failures += 1
                log.warning("qod: too many notifications pending; dropping one for %s", note.sink)
                continue
            task = asyncio.get_running_loop().create_task(self._post(note))
            self.pending.add(task)
            task.add_done_callback(self.pending.discard)

    async def _post(self, note: Notification) -> None:
        assert self.http is not None, "start() first"
        headers = {"Content-Type": note.content_type}
        credential = note.credential or {}
        if credential.get("credentialType") == "ACCESSTOKEN" and credential.get("accessToken"):
            headers["Authorization"] = f"Bearer {credential['accessToken']}"
        try:
            async with self.http.post(note.sink, data=json.dumps(note.event), headers=headers) as response:
                ok = response.status in (200, 202, 204)
        except Exception as exc:  # any failure of a sink (refused, timed out, bad TLS) is the sink's
            ok = False
            log.warning("qod: notification to %s failed (%s)", note.sink, type(exc).__name__)
        self.notified += ok
        self.notify_failures += not ok
