"""`dynqos edge qos` with `policy = "arbiter"` as a real process: three test drones (zenoh sessions on
127.0.0.1) ask the emulated operator's QoD API for priority through it, with room for one. Who holds a
session, what each drone is told, and what the decision key says."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from dynqos.common import keys
from dynqos.common.config import ZenohConfig
from dynqos.common.keys import Downlink, Flow, Stream
from dynqos.common.messages import QosDecision, QosGrant, QosRequest
from dynqos.common.modes import Grant
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Bus, Priority, Received, Role, open_bus
from tests.conftest import flow_ports, free_tcp_port
from tests.test_qos_agent import Rig, running

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]

UAVS = ("uav1", "uav2", "uav3")


def write_config(path: Path, zcfg: ZenohConfig, cell_port: int) -> None:
    bearers = "".join(
        f'[[cell.bearers]]\nname = "{uav}-{flow}"\ntarget = "127.0.0.1:{port}"\nue = "{uav}"\n'
        f"weight = {4.0 if flow == 'priority' else 1.0}\n"
        for uav in UAVS
        for flow, port in (("default", zcfg.default_port), ("priority", zcfg.priority_port))
    )
    devices = "".join(f'{uav} = {{ phoneNumber = "+4670000000{i + 1}" }}\n' for i, uav in enumerate(UAVS))
    path.write_text(
        f"[zenoh]\ndefault_port = {zcfg.default_port}\npriority_port = {zcfg.priority_port}\n"
        f"[cell]\nqod = true\ncontrol_port = {cell_port}\nqod_setup_s = 0.1\n{bearers}"
        '[qos]\nbackend = "camara"\npolicy = "arbiter"\nhold_down_s = 5\ngrant_interval_s = 0.2\n'
        "agent_timeout_s = 1.0\ndrone_timeout_s = 2.0\nrequest_interval_s = 0.2\nhealth_interval_s = 1.0\n"
        "[qos.arbiter]\nmax_grants = 1\nmin_hold_s = 0.5\nrotate_after_s = 60\n"
        f'[qos.camara]\napi_root = "http://127.0.0.1:{cell_port}/quality-on-demand/v1"\nduration_s = 30\n'
        f"extend_before_s = 5\npoll_interval_s = 0.05\nretry_after_denied_s = 0.5\n"
        f"[qos.camara.devices]\n{devices}"
    )


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Rig]:
    zcfg = ZenohConfig(**flow_ports())
    cell_port = free_tcp_port()
    config = tmp_path / "qos.toml"
    write_config(config, zcfg, cell_port)
    with running(config, zcfg, cell_port) as started:
        yield started


class Fleet:
    """What each drone's onboard daemon does for QoS, by hand, in one zenoh session; and a tool that
    watches every decision."""

    def __init__(self, zcfg: ZenohConfig) -> None:
        self.bus: Bus = open_bus(zcfg, Role.EDGE)
        self.grants: BoundedQueue[Received] = BoundedQueue(5000)
        self.decisions: BoundedQueue[Received] = BoundedQueue(1000)
        self.bus.subscribe(keys.downlink_all_drones(Downlink.QOS_GRANT), self.grants, expect=(QosGrant,))
        self.bus.subscribe(
            keys.downlink_all_drones(Downlink.QOS_DECISION), self.decisions, expect=(QosDecision,)
        )
        self.pubs = {
            u: self.bus.publisher(keys.uplink(u, Flow.PRIORITY, Stream.QOS), Priority.DATA_HIGH) for u in UAVS
        }
        assert all(p.wait_matched(20) for p in self.pubs.values()), "the agent never subscribed"
        self.wants: dict[str, tuple[bool, str]] = {}
        self.last: dict[str, QosGrant] = {}
        self.seq = 0
        self.seen: list[QosDecision] = []

    def ask(self, uav: str, want: bool, risk: str = "LR") -> None:
        self.wants[uav] = (want, risk)
        self._send(uav)

    def _send(self, uav: str) -> None:
        want, risk = self.wants[uav]
        self.seq += 1
        self.pubs[uav].put(
            QosRequest(
                uav=uav, seq=self.seq, stamp_ns=time.monotonic_ns(), want=want, risk=risk, offered_mbps=1.0
            )
        )

    def until(self, what: Callable[[], bool], timeout_s: float = 15.0) -> None:
        """Keep every drone repeating its request (as daemons do) until `what` holds."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for uav in self.wants:
                self._send(uav)
            item = self.grants.get(0.2)
            while item is not None:
                assert isinstance(item.message, QosGrant)
                self.last[item.message.uav] = item.message
                item = self.grants.get_nowait()
            self.seen += [d.message for d in self.decisions.drain() if isinstance(d.message, QosDecision)]
            if what():
                return
        raise AssertionError(f"not within {timeout_s} s; grants: {self.last}; decisions: {self.seen}")

    def grant(self, uav: str) -> Grant | None:
        last = self.last.get(uav)
        return last.grant if last else None

    def close(self) -> None:
        self.bus.close()


def holders(rig: Rig) -> list[str]:
    return sorted(s["uav"] for s in rig.sessions())


def test_one_slot_goes_to_the_highest_risk_and_every_decision_is_published(rig: Rig) -> None:
    fleet = Fleet(rig.zenoh)
    try:
        fleet.ask("uav2", True, "LR")
        fleet.until(lambda: fleet.grant("uav2") is Grant.AVAILABLE and holders(rig) == ["uav2"])
        fleet.ask("uav3", True, "LR")
        fleet.until(lambda: fleet.grant("uav3") is Grant.UNAVAILABLE)
        assert "the arbiter: the budget is held by uav2" in fleet.last["uav3"].reason
        assert holders(rig) == ["uav2"]

        fleet.ask("uav1", True, "HR")  # a high risk takes the slot at once, whatever min_hold says
        fleet.until(
            lambda: (
                fleet.grant("uav1") is Grant.AVAILABLE
                and fleet.grant("uav2") is Grant.UNAVAILABLE
                and holders(rig) == ["uav1"]
            )
        )
        assert "held by uav1 (HR" in fleet.last["uav2"].reason

        # uav1 is done: in its hold-down it keeps the slot only while nobody else needs it. uav3 has
        # waited longest of the two equal low risks, so it is next.
        fleet.ask("uav1", False)
        fleet.until(lambda: fleet.grant("uav3") is Grant.AVAILABLE and holders(rig) == ["uav3"])
        assert fleet.grant("uav2") is Grant.UNAVAILABLE
        fleet.until(lambda: ("uav3", "grant") in [(d.uav, d.action) for d in fleet.seen])
    finally:
        fleet.close()
    actions = [(d.uav, d.action) for d in fleet.seen]
    assert actions[0] == ("uav2", "grant")
    assert actions.index(("uav3", "deny")) < actions.index(("uav2", "revoke"))
    revoked = actions.index(("uav2", "revoke"))
    assert actions[revoked + 1] == ("uav1", "grant")  # one decision: revoke the low, grant the high
    handed_over = actions.index(("uav1", "revoke"))
    assert actions[handed_over + 1] == ("uav3", "grant")
    grant_uav1 = next(d for d in fleet.seen if d.uav == "uav1" and d.action == "grant")
    assert grant_uav1.holders == ("uav1",)
    assert grant_uav1.risk == "HR"
    assert "for uav1 (HR" in fleet.seen[revoked].reason
    log = rig.procs["agent"].stop()
    assert "grants=3 " in log
    assert "revocations=2 " in log
    assert rig.sessions() == []
