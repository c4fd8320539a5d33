"""`dynqos edge router`: a zenoh router in a Python process, listening on the two flow ports.

The default flow's port (7447) and the priority flow's port (7448) are two listeners of one router;
`transport/unicast/max_links` is raised so a drone's two priority-range links can both open.

It is the one edge process outside edge/runtime.py: it is zenoh's router itself, not a client of it,
and has no core (nothing arrives for it to handle); its health line is its links.
"""

from __future__ import annotations

import logging
import os
import threading
from pathlib import Path

from dynqos.common.config import Config
from dynqos.common.lifecycle import ready_line, serving_metrics, stop_on_signals
from dynqos.common.metrics import gauge
from dynqos.common.transport import Role, close_session, open_session, router_endpoints
from dynqos.edge.health import Health

log = logging.getLogger(__name__)


def run(config: Config, *, health_file: Path | None = None) -> int:
    """Serve until SIGTERM: its metrics, its health file, one ready line, the session closed after."""
    stop = threading.Event()
    stop_on_signals("router", stop.set)
    with serving_metrics("router", config) as metrics:
        session = open_session(config.zenoh, Role.ROUTER)
        health = Health("router", 5.0, file=health_file, beat=metrics.health.beat)
        metrics.add(
            lambda: [
                gauge("dynqos_router_links", "Transport links open to the router", len(session.info.links()))
            ]
        )
        try:
            log.info("router: listening on %s", ", ".join(router_endpoints(config.zenoh)))
            health.write("ready")
            ready_line("router")
            while not stop.is_set():
                health.maybe(lambda: f"links={len(session.info.links())}")
                stop.wait(0.5)
        finally:
            closed = close_session(session, "router")
            log.info("router: stopped")
    if not closed:
        logging.shutdown()
        os._exit(0)  # zenoh's runtime may hang the interpreter's exit as well; it has stopped serving
    return 0
