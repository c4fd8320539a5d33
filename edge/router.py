"""`dynqos edge router`: a zenoh router in a Python process, listening on the two flow ports.

The default flow's port (7447) and the priority flow's port (7448) are two listeners of one router;
`transport/unicast/max_links` is raised so a drone's two priority-range links can both open.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

from dynqos.common.config import Config
from dynqos.common.lifecycle import ready_line, serving_metrics
from dynqos.common.metrics import gauge
from dynqos.common.transport import Role, close_session, open_session, router_endpoints
from dynqos.edge.service import Service

log = logging.getLogger(__name__)


def run(config: Config, *, health_file: Path | None = None) -> int:
    """Serve until SIGTERM: its metrics, its health file, one ready line, the session closed after."""
    service = Service("router", 5.0)
    service.health_file = health_file
    service.install_signal_handlers()
    with serving_metrics("router", config) as metrics:
        session = open_session(config.zenoh, Role.ROUTER)
        service.beat = metrics.health.beat
        metrics.add(
            lambda: [
                gauge("dynqos_router_links", "Transport links open to the router", len(session.info.links()))
            ]
        )
        try:
            log.info("router: listening on %s", ", ".join(router_endpoints(config.zenoh)))
            service.write_health("ready")
            ready_line("router")
            while not service.stop.is_set():
                service.maybe_health(lambda: f"links={len(session.info.links())}")
                service.stop.wait(0.5)
        finally:
            closed = close_session(session, "router")
            log.info("router: stopped")
    if not closed:
        logging.shutdown()
        os._exit(0)  # zenoh's runtime may hang the interpreter's exit as well; it has stopped serving
    return 0
