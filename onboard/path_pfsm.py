"""A drone on more than one path: a PFSM per path, which sets the flow that path's traffic takes and
what the path asks its own site's agent (so its own operator) for. Pure (docs/supervisor.md, "Two paths").

The drone's own PFSM (onboard/supervisor.py) judges the Commands the drone applies, the first answer of
either path, and so decides what the drone does: the camera's rate and the fallback. The fallback
flies only when neither path answers, since the watchdog runs on the applied Commands and no Command
covers now only when neither path delivered one within T_wd. What the drone's PFSM cannot tell is which
path is loaded: while one path answers in time the winner's windows stay LL, and the loaded path would
get no priority until the other failed too. So each path has its own PFSM, the same machine with the
same configuration, fed by:

- its own command RTTs (the first answer to each State copy it carried, down either path: its uplink,
  onboard/paths.py) and the age of the oldest State whose copy by it is unanswered;
- the camera's latencies while the camera rides it (none otherwise: its P_lat is then its C&C term);
- the drone's depth: risk is the space around the drone, the same on both paths;
- its own site's grant: priority_denied when that site's agent refuses what this path asked for;
- its own watchdog: no answer to a copy it carried within T_wd (its cell out, or its site's router,
  the one it dials, gone) sends it to qA.

The path's State, status and QoS requests take its PFSM's flow, and the camera, on the path it rides,
that path's camera flow. A path PFSM's rate and control source are not used (one camera, one fallback:
the drone's PFSM's), and neither the modem's SINR nor the core's delay reports reach it (they are the
drone's, and feed the drone's PFSM).
"""

from __future__ import annotations

import logging
from dataclasses import replace

from dynqos.common.config import SupervisorConfig
from dynqos.common.modes import Flow, Grant, SupervisorState
from dynqos.onboard.asking import Need, QosAsking
from dynqos.onboard.commands import CommandTracker
from dynqos.onboard.grants import SiteGrants
from dynqos.onboard.paths import Paths
from dynqos.onboard.supervisor import Decision, Inputs, Supervisor
from dynqos.onboard.tick import LogEvent


class PathSupervisors:
    """One PFSM per path; `sites`: each path's site, in configured order."""

    def __init__(
        self, config: SupervisorConfig, sites: dict[str, str], watchdog_ns: int, start_ns: int
    ) -> None:
        self.config = config
        self.sites = sites
        self.watchdog_ns = watchdog_ns
        self.supervisors: dict[str, Supervisor] = {}
        self.decisions: dict[str, Decision] = {}
        self.restart(start_ns)

    def restart(self, start_ns: int) -> None:
        """Every path in q1 on fresh windows (the drone starts to fly)."""
        self.supervisors = {path: Supervisor(self.config, start_ns=start_ns) for path in self.sites}
        self.decisions = {}

    def step(
        self,
        now: int,
        drone: Inputs,
        paths: Paths,
        tracker: CommandTracker,
        asked: tuple[QosAsking, SiteGrants],
        *,
        judge: bool,
    ) -> list[LogEvent]:
        """Each path's PFSM steps on its own evidence (`drone`: what the drone's PFSM got this step;
        `judge` False: on the ground, observed only); what the log should say."""
        asking, grants = asked
        events = []
        refused = {
            path: asking.requested(path) and grants.of(site, now) is Grant.UNAVAILABLE
            for path, site in self.sites.items()
        }
        for path, supervisor in self.supervisors.items():
            record = paths.records[path]
            rtts = tuple(record.unjudged_rtts)
            record.unjudged_rtts.clear()
            carries_camera = path == paths.camera
            inputs = replace(
                drone,
                camera_latencies_ms=drone.camera_latencies_ms if carries_camera else (),
                camera_outstanding_ms=drone.camera_outstanding_ms if carries_camera else None,
                cc_rtts_ms=rtts,
                cc_outstanding_ms=tracker.oldest_unanswered_ms(now, record.answered_seq),
                watchdog_expired=not record.answering(now, self.watchdog_ns),
                priority_denied=refused[path],
                sinr_db=None,
                network_rtt_ms=None,
            )
            decision = (supervisor.step if judge else supervisor.observe)(inputs, now)
            if (t := decision.transition) is not None:
                p_lat = "NA" if t.p_lat is None else f"{t.p_lat:.2f}"
                move = f"{t.source.value} -> {t.target.value} ({t.cause}) P_lat={p_lat}"
                events.append(LogEvent(logging.INFO, f"supervisor, path {path}: {move}"))
            if decision.note:
                events.append(LogEvent(logging.INFO, f"supervisor, path {path}: {decision.note}"))
            self.decisions[path] = decision
        return events

    def flow(self, path: str) -> Flow:
        """The flow `path`'s State, status and QoS requests take (default before its first step)."""
        decision = self.decisions.get(path)
        return Flow.DEFAULT if decision is None else decision.actions.flow

    def camera_flow(self, path: str) -> Flow:
        """The camera's flow while it rides `path` (it differs from `flow` while it probes the default)."""
        decision = self.decisions.get(path)
        return Flow.DEFAULT if decision is None else decision.actions.camera_flow

    def flows(self) -> tuple[tuple[str, Flow], ...]:
        return tuple((path, self.flow(path)) for path in self.supervisors)

    def states(self) -> tuple[tuple[str, SupervisorState, Flow], ...]:
        """Each stepped path's PFSM state and flow, for the status."""
        return tuple((path, d.state, d.actions.flow) for path, d in self.decisions.items())

    def needs(self) -> list[Need]:
        """What each path's PFSM says about asking its site's agent."""
        out = []
        for path in self.supervisors:
            decision = self.decisions.get(path)
            if decision is None:
                out.append(Need(path, Flow.DEFAULT, None, "NA", None))
            else:
                s = decision.signals
                out.append(Need(path, decision.actions.flow, decision.state, s.risk.value, s.p_lat))
        return out

    def health(self) -> dict[str, object]:
        """Each path's PFSM state and flow, for the health line."""
        return {
            f"pfsm_{path}": f"{d.state.value}/{d.actions.flow.value}" for path, d in self.decisions.items()
        }
