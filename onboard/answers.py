"""The edge's answers as the onboard core takes them in: each Command offered to the tracker (which
decides whether it flies), what the log says about who controls the drone, and on a drone with more
than one path, each path's share of the answers (onboard/paths.py). Pure."""

from __future__ import annotations

import logging
from typing import Any

from dynqos.common.floods import worth_logging
from dynqos.common.messages import Command
from dynqos.onboard.commands import CommandTracker
from dynqos.onboard.paths import Paths
from dynqos.onboard.tick import LogEvent


class Answers:
    def __init__(
        self,
        uav: str,
        watchdog_ns: int,
        rtt_window: int,
        path_names: tuple[str, ...],
        start_ns: int,
        *,
        site_step_max_mps2: float = 0.0,
        setpoint_period_ns: int = 20_000_000,
    ) -> None:
        self.uav = uav
        self.tracker = CommandTracker(
            uav,
            watchdog_ns,
            rtt_window,
            site_step_max_mps2=site_step_max_mps2,
            setpoint_period_ns=setpoint_period_ns,
        )
        # one path: nothing to compare, and the wire and the status stay as they were
        self.paths = Paths(path_names, watchdog_ns, start_ns) if len(path_names) > 1 else None

    def offer(self, command: Command, arrival_ns: int, path: str) -> list[LogEvent]:
        """Offer one Command that arrived by `path`; what the log should say about it."""
        tracker, counters = self.tracker, self.tracker.counters
        changes, fenced, last_ns = counters.controller_changes, counters.fenced, tracker.last_valid_ns
        duplicates, new_site = counters.duplicates, command.site not in tracker.sites
        accepted = tracker.offer(command, arrival_ns)
        if self.paths is not None and (accepted or counters.duplicates > duplicates):
            rtt_ms = (arrival_ns - command.state_stamp_ns - command.edge_hold_ns) / 1e6
            by = command.state_path or path  # the copy's path: its uplink is what this answer timed
            self.paths.heard(by, rtt_ms, arrival_ns, won=accepted, state_seq=command.state_seq)
        at = f" at site {command.site}" if command.site else ""
        sender = f"MPC replica {command.replica or '(unnamed)'}{at}"
        if accepted and command.site and new_site:
            text = f"{self.uav}: first command from site {command.site}: {sender} (term {command.term})"
            return [LogEvent(logging.INFO, text)]
        if accepted and counters.controller_changes > changes:
            gap = "" if last_ns is None else f", {(arrival_ns - last_ns) / 1e6:.0f} ms after the last command"
            return [
                LogEvent(logging.INFO, f"{self.uav}: controller is now {sender} (term {command.term}{gap})")
            ]
        if counters.fenced > fenced and worth_logging(counters.fenced):
            term, replica = tracker.sites.get(command.site, (tracker.term, tracker.replica))
            return [
                LogEvent(
                    logging.WARNING,
                    f"{self.uav}: refused a command from {sender} term {command.term}: "
                    f"the drone follows {replica or '(unnamed)'} term {term}{at} ({counters.fenced} so far)",
                )
            ]
        return []

    def camera_path(self, now_ns: int) -> str:
        return "" if self.paths is None else self.paths.camera_path(now_ns)

    def status_fields(self) -> dict[str, Any]:
        """SupervisorStatus's per-path fields (their defaults with one path)."""
        if self.paths is None:
            return {}
        return {
            "path_rtt_samples_ms": self.paths.take_new_rtts(),
            "camera_path": self.paths.camera,
            "duplicates": self.tracker.counters.duplicates,
            "site": self.tracker.site,
            "site_wins": tuple(sorted(self.tracker.wins.items())),
        }

    def health(self) -> dict[str, object]:
        """The health line's fields for the paths and the sites (none with one path)."""
        if self.paths is None:
            return {}
        c, steps = self.tracker.counters, self.tracker.steps
        fields: dict[str, object] = {
            "duplicates": c.duplicates,
            "site": self.tracker.site or "-",
            "site_changes": c.site_changes,
            "site_step_mean": f"{steps.site_change_mean:.2f}",
            "site_step_max": f"{steps.site_change_max:.2f}",
            "site_steps_bounded": c.site_steps_bounded,
            "replan_step_mean": f"{steps.same_site_mean:.2f}",
            "replan_step_max": f"{steps.same_site_max:.2f}",
            "camera_path": self.paths.camera,
        }
        for name, record in self.paths.records.items():
            median = record.rtts.percentile(50)
            fields[f"path_{name}"] = (
                f"{record.wins}/{record.answers}@{'-' if median is None else f'{median:.0f}'}ms"
            )
        return fields
