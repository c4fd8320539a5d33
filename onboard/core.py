"""The drone's decisions as pure logic: one `tick` per control period, time passed in.

The daemon (onboard/daemon.py) is a shell around this core: it reads the flight controller and the
bus, calls `tick`, and writes what comes back. Everything that decides lives here, each in one place:

- commands: which edge command is valid and which of its setpoints applies now (CommandTracker);
- the State the drone publishes every T_mpc, and the supervisor's step after it;
- who flies the drone, decided once per tick: the edge while the supervisor wants it and a valid
  command covers now, else the fallback PID; and a position hold when the flight controller itself
  has gone silent (its state is stale, so neither the edge nor the PID can fly on it);
- the flow each stream takes and the camera's rate: the supervisor's actions in `qos = "dynamic"`, the
  configured flow otherwise (the supervisor then only reports, and the watchdog still hands control to
  the fallback);
- the SupervisorStatus, with what the drone does (not what it was asked to do) and what was measured;
- the request for priority to the QoS agent (onboard/asking.py) and the grant it answers
  (docs/qos.md). The drone never waits for it: it switches its link at once; a refusal is an input
  to the supervisor;
- on a drone with two paths, each path's flow and request from its own PFSM (onboard/path_pfsm.py).

No zenoh, MAVLink, OpenCV, threads or wall clock here: tests drive it tick by tick on a fake clock.
"""

from __future__ import annotations

import logging

import numpy as np

from dynqos.common import builtin_tasks
from dynqos.common.clock import NS_PER_S, to_ns
from dynqos.common.config import Config
from dynqos.common.keys import Stream
from dynqos.common.messages import (
    CameraAck,
    Command,
    Detections,
    QosGrant,
    QosMonitoring,
    Reference,
    State,
    SupervisorStatus,
    TaskAnswer,
)
from dynqos.common.modes import ControlSource, Flow, Grant
from dynqos.common.reference import ReferenceTrack
from dynqos.common.tasks import Task
from dynqos.onboard.answers import Answers
from dynqos.onboard.asking import Need, QosAsking
from dynqos.onboard.commands import SetpointSteps
from dynqos.onboard.fc import AccelSetpoint, FcSaid, FcState, Hold, PositionSetpoint, Setpoint, triple
from dynqos.onboard.grants import SiteGrants
from dynqos.onboard.modem import ModemReading
from dynqos.onboard.monitors import CameraLatencyMonitor, LatencySamples, NetworkDelays
from dynqos.onboard.path_pfsm import PathSupervisors
from dynqos.onboard.pid import CascadedPid
from dynqos.onboard.supervisor import Decision, Inputs, Supervisor
from dynqos.onboard.supervisor_status import decision_fields
from dynqos.onboard.tasks import OnboardTasks, TaskJobs
from dynqos.onboard.tick import Counters, LogEvent, Outgoing, TickInput, TickOutput

# The setpoint period at [control] setpoint_hz's default; the daemon ticks at `setpoint_period_ns(config)`.
SETPOINT_PERIOD_NS = NS_PER_S // 50
STALE_STATE_NS = 500_000_000  # no position from the FC for this long: it is lost, stop using its state


class OnboardCore:
    """The onboard decisions; `tick` once per setpoint period (50 Hz) with what the shell read."""

    def __init__(self, config: Config, start_ns: int, tasks: tuple[Task[object, object], ...] = ()) -> None:
        """`tasks`: the user's offloaded tasks ([onboard] tasks, loaded by the shell; docs/offload.md)."""
        self.config = config
        self.uav = config.drone.id
        self.qos = config.onboard.qos
        paths = tuple(p.name for p in config.onboard.paths) or ("",)
        self.mpc = builtin_tasks.mpc(config)  # the MPC's rate and deadline, as its edge side declares them
        watchdog_ns = self.mpc.deadline_ns
        self.answers = Answers(
            self.uav,
            watchdog_ns,
            config.supervisor.window[1],
            paths,
            start_ns,
            site_step_max_mps2=config.onboard.site_step_max_mps2,
            setpoint_period_ns=round(1e9 / config.control.setpoint_hz),
        )
        self.tracker = self.answers.tracker
        self.camera_monitor = CameraLatencyMonitor()
        self.network = NetworkDelays()  # the 5G core's own delay reports, when the agent forwards them
        self.supervisor = Supervisor(config.supervisor, start_ns=start_ns)
        sites = {p.name: p.site or p.name for p in config.onboard.paths}
        self.path_pfsms = (
            PathSupervisors(config.supervisor, sites, watchdog_ns, start_ns) if len(sites) > 1 else None
        )
        self.pid = CascadedPid()
        self.reference = ReferenceTrack()
        self.samples = LatencySamples()
        self.counters = Counters()
        self.decision: Decision | None = None
        self.control = ControlSource.NONE
        self.offloading = False
        self.control_changed_ns = 0
        self.command_age_ms: float | None = None
        self.max_setpoint_gap_ms = 0.0
        self._hold = Hold()
        self._last_accel = np.zeros(3)
        self._space: float | None = None  # the newest spaciousness not yet given to the supervisor
        self._state_seq = 0
        self._status_seq = 0
        self._t_mpc_ns = self.mpc.period_ns
        self._status_period_ns = round(NS_PER_S / config.onboard.status_hz)
        self.modem: ModemReading | None = None
        self.fc_said: FcSaid | None = None
        self._modem_stale_ns = to_ns(3 * config.onboard.modem_interval_s)
        self._next_state_ns: int | None = None
        self._next_status_ns = start_ns
        self._last_setpoint_ns: int | None = None
        self._status_gap_ms = 0.0  # the longest setpoint gap since the last status
        self._events: list[LogEvent] = []
        self.grants = SiteGrants(to_ns(config.qos.agent_timeout_s))  # each site's agent's last word
        period_ns, th_lat = to_ns(config.qos.request_interval_s), config.supervisor.th_lat
        self.asking = QosAsking(self.uav, paths if self.path_pfsms else ("",), period_ns, th_lat, start_ns)
        self.tasks = OnboardTasks(tasks, start_ns)
        self._task_answers: list[tuple[TaskAnswer, int]] = []
        self._now_ns = start_ns

    # ---- the one entry point ------------------------------------------------------------------------

    def tick(self, inp: TickInput) -> TickOutput:
        now = self._now_ns = inp.now_ns
        self._events = []
        publish: list[Outgoing] = []
        grant_before = self.reported_grant(now)  # before this tick's grants are taken in
        self._take_in(inp)
        if inp.offboard and not self.offloading and inp.fc is not None:
            self._engage(inp.fc, now)
        fresh = inp.fc is not None and now - inp.fc.stamp_ns <= STALE_STATE_NS
        watchdog = self.tracker.watchdog_expired(now)
        if fresh and inp.fc is not None and self._state_due(now):
            publish.append(self._state(inp.fc, now))
            self._supervise(now, watchdog)
        elif watchdog and self.control is ControlSource.EDGE:
            self._supervise(now, watchdog)  # the watchdog acts at once, not at the next supervisor tick
        before = self.control
        setpoint = self._control(inp.fc, now, watchdog, self.tasks.steer(inp.task_steers, now))
        self._measure_gap(setpoint, now)
        flow, camera_flow, rate = self._flows()
        jobs = self._task_jobs(inp, flow, camera_flow, rate)
        if self.qos != "default" and self.offloading:  # never asks; and nobody asks on the ground
            publish.extend(self.asking.requests(now, self.qos, self._needs(flow), self.counters.camera_bytes))
        changed = self.control is not before or self.reported_grant(now) is not grant_before
        if self.decision is not None and (now >= self._next_status_ns or changed):
            self._next_status_ns = now + self._status_period_ns
            status = self._status(now, flow, camera_flow, rate)
            publish.append(Outgoing(Stream.STATUS, flow, status, path_flows=self._path_flows()))
        return TickOutput(
            setpoint,
            tuple(publish),
            camera_flow,
            rate,
            tuple(self._events),
            self.answers.camera_path(now),
            jobs,
        )

    # ---- inputs ---------------------------------------------------------------------------------------

    def _take_in(self, inp: TickInput) -> None:
        # Frames first: an ack in this batch may answer a frame reported in the same tick.
        for frame in inp.frames_sent:
            self.camera_monitor.frame_sent(frame.seq, frame.kind, frame.stamp_ns)
            self.counters.camera_bytes += frame.nbytes
            self.counters.frames += frame.kind == "rgb"
        if inp.uplink_bytes is not None:
            self.counters.uplink_bytes = max(self.counters.uplink_bytes, inp.uplink_bytes)
        if inp.spaciousness_m is not None:
            self._space = inp.spaciousness_m
        if inp.modem is not None:
            self.modem = inp.modem
        self.fc_said = inp.fc_said or self.fc_said
        for item in inp.downlink:
            message = item.message
            if isinstance(message, Command):
                self._events.extend(self.answers.offer(message, item.arrival_ns, item.path))
            elif isinstance(message, CameraAck):
                self.camera_monitor.on_ack(message, item.arrival_ns)
            elif isinstance(message, Detections):
                self.counters.detections += 1
            elif isinstance(message, Reference):
                self.reference.update(message, item.arrival_ns)
            elif isinstance(message, QosGrant | QosMonitoring) and message.uav == self.uav:
                self._take_qos(message, item.arrival_ns)
            elif isinstance(message, TaskAnswer) and message.uav == self.uav:
                self._task_answers.append((message, item.arrival_ns))

    def _task_jobs(self, inp: TickInput, flow: Flow, camera_flow: Flow, rate: float) -> TaskJobs:
        """The tasks' tick: what the shell's task threads do next (onboard/tasks.py)."""
        answers, self._task_answers = self._task_answers, []
        flows = {"control": flow, "bulk": camera_flow}
        jobs, said = self.tasks.tick(inp.now_ns, self.offloading, answers, inp.task_sent, flows, rate)
        self._events.extend(LogEvent(level, text) for level, text in said)
        return jobs

    def _take_qos(self, message: QosGrant | QosMonitoring, arrival_ns: int) -> None:
        if isinstance(message, QosMonitoring):
            if not self.network.reports:
                self._log(logging.INFO, f"qos: the core's delay reports arrive, every {message.period_s} s")
            self.network.offer(message, arrival_ns)
            return
        if (event := self.grants.take(message, arrival_ns)) is not None:
            self._events.append(event)

    def agent_heard(self, now: int) -> bool:
        """A QoS agent answered within [qos] agent_timeout_s (else: links only, nobody asks the network)."""
        return self.grants.agent_heard(now)

    def reported_grant(self, now: int) -> Grant:
        return self.grants.reported(now)

    def _needs(self, flow: Flow) -> list[Need]:
        """What each path says about asking for priority: its own PFSM's, or the drone's (one path, or
        a fixed flow)."""
        if self.path_pfsms is not None and self.qos == "dynamic":
            return self.path_pfsms.needs()
        d = self.decision
        state, risk, p_lat = (d.state, d.signals.risk.value, d.signals.p_lat) if d else (None, "NA", None)
        return [Need(path, flow, state, risk, p_lat) for path in self.asking.asked]

    def _path_flows(self) -> tuple[tuple[str, Flow], ...]:
        """Each path's own flow while its PFSM sets it (two paths, qos dynamic); () otherwise."""
        return self.path_pfsms.flows() if self.path_pfsms is not None and self.qos == "dynamic" else ()

    def _engage(self, fc: FcState, now: int) -> None:
        """The FC flies offboard: from now on every tick sends a setpoint, starting from a hold here.

        The supervisor judges the flight from here, in q1, on fresh windows: on the ground it only
        observes (`Supervisor.observe`), since nothing is flown from the edge there."""
        self.offloading = True
        # the steps between Commands for the flight's states: not the climb's, nor the change from them
        self.tracker.steps, self.tracker.steps_from_seq = SetpointSteps(), self._state_seq + 1
        self._hold.set(fc)
        self.pid.reset()
        self.supervisor = Supervisor(self.config.supervisor, start_ns=now)
        if self.path_pfsms is not None:
            self.path_pfsms.restart(now)
        self._log(logging.INFO, "supervisor: judging the flight from q1 (offloading)")

    def _state_due(self, now: int) -> bool:
        if self._next_state_ns is None:
            self._next_state_ns = now
        if now < self._next_state_ns:
            return False
        self._next_state_ns += self._t_mpc_ns
        if self._next_state_ns < now:
            self._next_state_ns = now + self._t_mpc_ns
        return True

    def _state(self, fc: FcState, now: int) -> Outgoing:
        self._state_seq += 1
        message = State(
            uav=self.uav,
            seq=self._state_seq,
            stamp_ns=now,
            pos_m=fc.pos_m,
            vel_mps=fc.vel_mps,
            quat=fc.quat,
            rtt_est_ms=self.tracker.rtt_estimate_ms(),
            mode="offboard" if self.offloading else "standby",
            command_term=self.tracker.term,
            command_replica=self.tracker.replica,
            controllers=self.tracker.controllers(),
        )
        self.tracker.state_sent(self._state_seq, now)
        self.counters.states += 1
        return Outgoing(Stream.STATE, self._flows()[0], message, path_flows=self._path_flows())

    def _supervise(self, now: int, watchdog: bool) -> None:
        cams, rtts = self.camera_monitor.take_new(), self.tracker.take_new_rtts()
        self.samples.extend(cams, rtts)
        tasks = self.tasks.take_samples(now)  # a control task's calls count as the MPC's, bulk as frames
        inputs = Inputs(
            camera_latencies_ms=cams + tasks.bulk_rtts_ms,
            cc_rtts_ms=rtts + tasks.control_rtts_ms,
            camera_outstanding_ms=_most(
                self.camera_monitor.oldest_outstanding_ms(now), tasks.bulk_outstanding_ms
            ),
            cc_outstanding_ms=_most(self.tracker.oldest_unanswered_ms(now), tasks.control_outstanding_ms),
            spaciousness_m=self._space,
            watchdog_expired=watchdog,
            priority_denied=self.asking.requested() and self.reported_grant(now) is Grant.UNAVAILABLE,
            sinr_db=modem.sinr_db if (modem := self._fresh_modem(now)) else None,
            network_rtt_ms=self.network.round_trip_ms(now),
        )
        self._space = None
        # on the ground: observed, not judged (see _engage)
        step = self.supervisor.step if self.offloading else self.supervisor.observe
        decision = step(inputs, now)
        if self.path_pfsms is not None and self.answers.paths is not None:
            asked = (self.asking, self.grants)
            paths = self.answers.paths
            self._events.extend(
                self.path_pfsms.step(now, inputs, paths, self.tracker, asked, judge=self.offloading)
            )
        if decision.transition is not None:
            t = decision.transition
            p_lat = "NA" if t.p_lat is None else f"{t.p_lat:.2f}"
            self._log(
                logging.INFO, f"supervisor: {t.source.value} -> {t.target.value} ({t.cause}) P_lat={p_lat}"
            )
        if decision.note:
            self._log(logging.INFO, f"supervisor: {decision.state.value}: {decision.note}")
        was_lost = self.decision is not None and self.decision.signals.depth_lost
        if decision.signals.depth_lost and not was_lost:
            stale_s = self.config.supervisor.risk_stale_s
            self._log(logging.WARNING, f"onboard: no depth for {stale_s:g} s: risk unknown, read as high")
        elif was_lost and not decision.signals.depth_lost:
            self._log(logging.INFO, "onboard: depth is back: risk from the camera again")
        self.decision = decision

    def _flows(self) -> tuple[Flow, Flow, float]:
        """(the state's flow, the camera's flow, the camera's rate factor). With two paths each path's
        PFSM sets its flow: the state's flow is then the priority flow if any path takes it, and the
        camera's is that of the path it rides."""
        if self.qos != "dynamic":
            return Flow(self.qos), self.supervisor.camera_flow(Flow(self.qos)), 1.0
        if self.decision is None:
            return Flow.DEFAULT, Flow.DEFAULT, 1.0
        a = self.decision.actions
        if self.path_pfsms is not None and self.answers.paths is not None:
            flows = self.path_pfsms.flows()
            flow = Flow.PRIORITY if any(f is Flow.PRIORITY for _, f in flows) else Flow.DEFAULT
            return flow, self.path_pfsms.camera_flow(self.answers.paths.camera), a.camera_rate_factor
        return a.flow, a.camera_flow, a.camera_rate_factor

    # ---- who flies --------------------------------------------------------------------------------------

    def _source(self, watchdog: bool) -> ControlSource:
        """The one edge-or-fallback decision: the edge while it is wanted and a valid command covers now."""
        wanted = (
            self.qos != "dynamic"  # fixed flow: the supervisor only reports
            or self.decision is None
            or self.decision.actions.control_source is ControlSource.EDGE
        )
        return ControlSource.EDGE if wanted and not watchdog else ControlSource.FALLBACK

    def _control(self, fc: FcState | None, now: int, watchdog: bool, steer: float | None) -> Setpoint | None:
        """The setpoint of whoever flies; a task's Steer (docs/offload.md) sets its heading."""
        if not self.offloading or fc is None:
            return None
        if now - fc.stamp_ns > STALE_STATE_NS:
            if self.control is not ControlSource.HOLD:
                silent_s = (now - fc.stamp_ns) / NS_PER_S
                why = f"no state from the flight controller for {silent_s:.1f} s"
                self._log(logging.ERROR, f"onboard: {why}: holding position")
                self._hold.set(fc)
                self._switch(ControlSource.HOLD, now)
            return PositionSetpoint(triple(self._hold.pos_m), self._hold.yaw_rad)
        if self.control is ControlSource.HOLD:
            self._log(logging.INFO, "onboard: the flight controller's state is back")
        source = self._source(watchdog)
        if source is ControlSource.EDGE:
            setpoint = self.tracker.setpoint(now)
            assert setpoint is not None  # the watchdog expires when no setpoint covers now
            if self.control is not ControlSource.EDGE:
                seq = self.tracker.active.seq if self.tracker.active else -1
                self._log(logging.INFO, f"onboard: control from the edge (seq {seq})")
                self._switch(ControlSource.EDGE, now)
            accel, yaw = np.array(setpoint.accel_mps2), setpoint.yaw_rad
            self.counters.edge_ticks += 1
        else:
            if self.control is not ControlSource.FALLBACK:
                self._log(
                    logging.WARNING,
                    f"onboard: fallback PID holding position ({self._why_fallback(now, watchdog)})",
                )
                self.counters.switches_to_fallback += 1
                self._hold.set(fc)
                self.pid.reset(self._last_accel)  # bumpless
                self._switch(ControlSource.FALLBACK, now)
            target, target_vel, yaw = self._fallback_target(now)
            dt_s = 1 / self.config.control.setpoint_hz
            accel = self.pid.step(np.array(fc.pos_m), np.array(fc.vel_mps), target, dt_s, target_vel)
            self.counters.fallback_ticks += 1
        self._last_accel = accel
        return AccelSetpoint(triple(accel), yaw if steer is None else steer)

    def _why_fallback(self, now: int, watchdog: bool) -> str:
        if watchdog:
            last = self.tracker.last_valid_ns
            age = "never" if last is None else f"{(now - last) / 1e6:.0f} ms ago"
            return f"watchdog: last valid command {age}"
        return f"supervisor state {self.decision.state.value if self.decision else '-'}"

    def _switch(self, source: ControlSource, now: int) -> None:
        self.control = source
        self.control_changed_ns = now
        last = self.tracker.last_valid_ns
        self.command_age_ms = None if last is None else (now - last) / 1e6

    def _fallback_target(self, now: int) -> tuple[np.ndarray, np.ndarray | None, float]:
        """Hold where the fallback took over, or (fallback = continue) follow the last reference while it
        lasts; past its end the reference holds its last sample."""
        if self.config.onboard.fallback == "continue":
            window = self.reference.window(now, 1, self.config.control.t_mpc_s)
            if window is not None:
                states, yaws = window
                return states[0, :3], states[0, 3:], float(yaws[0])
        return self._hold.pos_m, None, self._hold.yaw_rad

    # ---- what is measured and reported ----------------------------------------------------------------

    def _measure_gap(self, setpoint: Setpoint | None, now: int) -> None:
        if setpoint is None:
            return
        self.counters.setpoints += 1
        if self._last_setpoint_ns is not None:
            gap_ms = (now - self._last_setpoint_ns) / 1e6
            self._status_gap_ms = max(self._status_gap_ms, gap_ms)
            self.max_setpoint_gap_ms = max(self.max_setpoint_gap_ms, gap_ms)
        self._last_setpoint_ns = now

    def _status(self, now: int, flow: Flow, camera_flow: Flow, rate: float) -> SupervisorStatus:
        assert self.decision is not None
        self._status_seq += 1
        cams, rtts = self.samples.take()
        gap, self._status_gap_ms = self._status_gap_ms, 0.0
        modem = self._fresh_modem(now)
        said = self.fc_said if self.fc_said and self.fc_said.fresh(now) else None
        return SupervisorStatus(
            uav=self.uav,
            seq=self._status_seq,
            stamp_ns=now,
            flow=flow,
            camera_flow=camera_flow,
            camera_rate_factor=rate,
            control_source=self.control,
            rtt_ms=self.tracker.last_rtt_ms,
            camera_latency_ms=self.camera_monitor.last_ms,
            setpoint_gap_ms=gap if self.offloading else None,
            rtt_samples_ms=rtts,
            camera_latency_samples_ms=cams,
            fallbacks=self.counters.switches_to_fallback,
            fallback_s=self.counters.fallback_ticks / self.config.control.setpoint_hz,
            camera_bytes=self.counters.camera_bytes,
            uplink_bytes=self.counters.uplink_bytes,
            control_changed_ns=self.control_changed_ns,
            command_age_ms=self.command_age_ms,
            qos_grant=self.reported_grant(now),
            qos_agent=self.agent_heard(now),
            rsrp_dbm=modem.rsrp_dbm if modem else None,
            sinr_db=modem.sinr_db if modem else None,
            fc_text=said.text if said else "",
            fc_severity=said.severity if said else None,
            **self.answers.status_fields(),
            path_states=self.path_pfsms.states() if self.path_pfsms is not None else (),
            tasks=self.tasks.status(now),
            **decision_fields(self.decision, self.supervisor.log[-1] if self.supervisor.log else None),
        )

    def _fresh_modem(self, now: int) -> ModemReading | None:
        """The modem's reading while it is fresh (three of its intervals), else None."""
        m = self.modem
        return m if m is not None and now - m.stamp_ns <= self._modem_stale_ns else None

    def _log(self, level: int, text: str) -> None:
        self._events.append(LogEvent(level, text))

    def health(self, bus_rejected: int = 0) -> dict[str, object]:
        """The health line's fields; `bus_rejected`: commands the bus refused before they reached us."""
        t = self.tracker.counters
        return {
            "state": self.decision.state.value if self.decision else "-",
            "flow": self._flows()[0].value,
            "control": self.control.value,
            "rtt_ms": f"{self.tracker.rtt_estimate_ms():.1f}",
            "commands_ok": t.accepted,
            "rejected": t.rejected + bus_rejected,
            "stale": t.stale,
            "unknown": t.unknown_state,
            "expired": t.expired,
            "future": t.future,
            "wrong_drone": t.wrong_drone,
            "fenced": t.fenced,
            "controller_changes": t.controller_changes,
            "controller": f"{self.tracker.replica or '-'}@{self.tracker.term}",
            **vars(self.counters),
            "max_setpoint_gap_ms": f"{self.max_setpoint_gap_ms:.1f}",
            "max_command_gap_ms": f"{self.tracker.longest_gap_ns / 1e6:.1f}",
            **self.answers.health(),
            **(self.path_pfsms.health() if self.path_pfsms is not None else {}),
            **self.tasks.health(self._now_ns),
        }


def _most(a: float | None, b: float | None) -> float | None:
    return b if a is None else a if b is None else max(a, b)


def setpoint_period_ns(config: Config) -> int:
    """The period of the setpoint stream to the FC, the daemon's tick: [control] setpoint_hz."""
    return round(NS_PER_S / config.control.setpoint_hz)
