"""The onboard core on two paths, tick by tick on a fake clock: both sites answer every State by both
paths; the drone flies the first answer, moves the camera to the better path, and falls back only when
neither path answers within the watchdog."""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field, replace

import pytest

from dynqos.common.bus import Received
from dynqos.common.config import Config, OnboardConfig, OnboardPathConfig
from dynqos.common.messages import Command, State, SupervisorStatus, decode, encode
from dynqos.common.modes import ControlSource
from dynqos.onboard.core import SETPOINT_PERIOD_NS, OnboardCore
from dynqos.onboard.fc import FcState
from dynqos.onboard.paths import DWELL_NS, Paths
from dynqos.onboard.tick import TickInput, TickOutput

MS = 1_000_000
PATHS = ("a", "b")


def two_paths(qos: str) -> Config:
    paths = tuple(
        OnboardPathConfig(name=n, connect_default=f"127.0.0.1:{p}", connect_priority=f"127.0.0.1:{p + 1}")
        for n, p in (("a", 17447), ("b", 18447))
    )
    return replace(Config(), onboard=replace(OnboardConfig(), qos=qos, paths=paths))  # type: ignore[arg-type]


@dataclass
class TwoPaths:
    """Each State reaches both sites; site s answers it by path p after `rtt_ms[p]` (None: path p
    carries nothing), plus `site_lag_ms[s]` (the site's own delay, e.g. its link to the other's path)."""

    core: OnboardCore
    rtt_ms: dict[str, float | None] = field(default_factory=lambda: {"a": 10.0, "b": 18.0})
    site_lag_ms: dict[str, float] = field(default_factory=lambda: {"a": 0.0, "b": 3.0})
    site_accel: dict[str, float] = field(default_factory=lambda: {"a": 0.50, "b": 0.52})
    site_up: dict[str, bool] = field(default_factory=lambda: {"a": True, "b": True})
    space_m: float = 8.0  # the depth camera's spaciousness: LR
    now: int = 1_000 * MS
    pending: list[tuple[int, Received]] = field(default_factory=list)
    outputs: list[TickOutput] = field(default_factory=list)

    def tick(self) -> TickOutput:
        self.now += SETPOINT_PERIOD_NS
        fc = FcState(self.now, (1.0, 2.0, -1.5), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0))
        due = sorted((r for t, r in self.pending if t <= self.now), key=lambda r: r.arrival_ns)
        self.pending = [(t, r) for t, r in self.pending if t > self.now]
        out = self.core.tick(
            TickInput(now_ns=self.now, fc=fc, downlink=due, offboard=True, spaciousness_m=self.space_m)
        )
        for item in out.publish:
            assert decode(encode(item.message)) == item.message
            if isinstance(item.message, State):
                self._answer(item.message)
        self.outputs.append(out)
        return out

    def _answer(self, state: State) -> None:
        for site in [s for s, up in self.site_up.items() if up]:
            command = Command(uav="uav1", seq=state.seq, state_seq=state.seq, state_stamp_ns=state.stamp_ns,
                              edge_hold_ns=0, dt_s=0.05, accel_mps2=[(self.site_accel[site], 0.0, 0.0)] * 10,
                              yaw_rad=[0.0] * 10, term=1, replica=f"mpc-{site}", site=site)  # fmt: skip
            for path, rtt in self.rtt_ms.items():
                if rtt is not None:
                    arrival = self.now + round((rtt + self.site_lag_ms[site]) * MS)
                    self.pending.append((arrival, Received("cmd", command, arrival, path)))

    def run(self, seconds: float) -> list[TickOutput]:
        return [self.tick() for _ in range(round(seconds * 1e9 / SETPOINT_PERIOD_NS))]

    def statuses(self, outs: list[TickOutput]) -> list[SupervisorStatus]:
        return [p.message for o in outs for p in o.publish if isinstance(p.message, SupervisorStatus)]


@pytest.mark.parametrize("qos", ["dynamic", "default", "priority"])
def test_the_drone_flies_the_first_answer_and_survives_the_loss_of_a_path_and_of_a_site(qos: str) -> None:
    rig = TwoPaths(OnboardCore(two_paths(qos), start_ns=1_000 * MS))
    outs = rig.run(3.0)
    tracker = rig.core.tracker
    assert rig.core.control is ControlSource.EDGE
    assert tracker.site == "a"  # path a is faster and site a answers first on it
    assert tracker.counters.duplicates >= 3 * tracker.counters.accepted - 3  # 4 answers per state, 1 flies
    assert outs[-1].camera_path == "a"
    status = rig.statuses(outs)[-1]
    assert (status.camera_path, status.site) == ("a", "a")
    assert {name for name, _ in status.path_rtt_samples_ms} == {"a", "b"}
    assert dict(status.site_wins).keys() == {"a"}  # every Command applied so far was site a's
    states = [p.message for o in outs for p in o.publish if isinstance(p.message, State)]
    assert states[-1].controllers == (("a", 1, "mpc-a"),)  # site b never won yet: not followed
    # path a goes dark: both sites' answers by path b fly the drone (site a's first, across the
    # sites' link), and the camera moves to path b at once
    fallbacks, edge_ticks = rig.core.counters.switches_to_fallback, rig.core.counters.edge_ticks
    rig.rtt_ms["a"] = None
    outs = rig.run(1.0)
    assert tracker.site == "a"
    assert outs[-1].camera_path == "b"
    assert tracker.steps.site_change_count == 0
    # and site a goes too: site b flies
    rig.site_up["a"] = False
    outs += rig.run(1.0)
    assert rig.core.counters.switches_to_fallback == fallbacks  # (one at the start: no command yet)
    assert rig.core.counters.edge_ticks - edge_ticks == len(outs)  # the edge flew every tick
    assert rig.core.tracker.longest_gap_ns < 150 * MS
    assert tracker.site == "b"
    assert tracker.steps.site_change_count == 1
    assert dict(rig.statuses(outs)[-1].site_wins).keys() == {"a", "b"}
    assert tracker.steps.site_change_max == pytest.approx(0.02, abs=1e-6)  # the two sites' setpoints differ
    # both paths dark: now, and only now, the fallback flies
    rig.rtt_ms["b"] = None
    rig.run(1.0)
    assert rig.core.control is ControlSource.FALLBACK


def test_one_path_keeps_its_status_and_state_as_they_were() -> None:
    core = OnboardCore(Config(), start_ns=0)
    assert core.answers.paths is None
    assert core.answers.status_fields() == {}
    assert core.answers.health() == {}


def test_the_camera_moves_to_a_clearly_better_path_after_its_dwell_not_for_a_small_gain() -> None:
    paths = Paths(PATHS, watchdog_ns=150 * MS, start_ns=0)
    now = 0
    for _ in range(30):
        now += 50 * MS
        paths.heard("a", 40.0, now, won=False)
        paths.heard("b", 34.0, now, won=True)  # 15% better: inside the hysteresis
    assert paths.camera_path(now) == "a"
    for _ in range(30):
        now += 50 * MS
        paths.heard("a", 40.0, now, won=False)
        paths.heard("b", 20.0, now, won=True)
    assert paths.camera_path(now) == "b"
    assert paths.camera_moves == 1
    moved = now
    for _ in range(5):  # a is better again at once, but the camera stays out its dwell
        now += 50 * MS
        paths.heard("a", 5.0, now, won=True)
        paths.heard("b", 20.0, now, won=False)
    assert now - moved < DWELL_NS
    assert paths.camera_path(now) == "b"
    assert paths.camera_path(moved + DWELL_NS + 1) == "a" or not paths.answering(moved + DWELL_NS + 1)


def test_when_the_sites_disagree_the_setpoint_moves_to_the_new_site_by_the_bound_per_tick() -> None:
    rig = TwoPaths(OnboardCore(two_paths("priority"), start_ns=1_000 * MS))
    rig.site_accel = {"a": 0.5, "b": 6.0}  # e.g. a site that solved against another reference
    rig.run(2.0)
    assert rig.core.tracker.site == "a"
    rig.site_up["a"] = False
    outs = rig.run(1.0)
    accels = [o.setpoint.accel_mps2[0] for o in outs if o.setpoint is not None]
    assert accels[-1] == pytest.approx(6.0)  # site b's plan, reached
    steps = [abs(b - a) for a, b in itertools.pairwise(accels)]
    bound = rig.core.config.onboard.site_step_max_mps2
    assert max(steps) <= bound + 1e-9 < 5.5  # never the whole 5.5 at once
    # 5.5 in steps of 2 per period, from an arrival between two ticks: four ticks to the new plan
    assert sum(step > 0.1 for step in steps) == 4
    assert rig.core.counters.switches_to_fallback == 1  # (the start's, before any command)
