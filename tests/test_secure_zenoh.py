"""The production zenoh setup on 127.0.0.1: mutual TLS with `dynqos certs` certificates and the
router's access control by certificate common name (deploy/, docs/deploy.md).

The router runs as a real `dynqos edge router` process from a config file like the production one;
the drone and edge sessions are opened here with the same transport code the daemons use.
Negative checks need no sleeps: after the forbidden messages, an allowed sentinel goes out on the
same session, priority and link, so once the sentinel has arrived anything forbidden would have too.
"""

from __future__ import annotations

import dataclasses
import queue
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from dynqos.common.certs import make_dev_pki
from dynqos.common.config import ZenohConfig, load_config
from dynqos.common.errors import ConfigError, TransportError
from dynqos.common.transport import Role, open_session
from tests.conftest import free_tcp_port
from tests.procs import DYNQOS, DynqosProcess

pytestmark = [pytest.mark.integration, pytest.mark.timeout(90)]

Seen = queue.Queue[tuple[str, bytes]]


@dataclasses.dataclass
class Pki:
    folder: Path
    cfg: ZenohConfig  # ports and CA; certificate fields set per session with `as_`

    def as_(self, name: str) -> ZenohConfig:
        return dataclasses.replace(
            self.cfg,
            tls_cert=str(self.folder / f"{name}.pem"),
            tls_key=str(self.folder / f"{name}-key.pem"),
        )


PRODUCTION_ROUTER = Path(__file__).resolve().parents[1] / "deploy/k8s/overlays/production/router.toml"


@pytest.fixture
def secure_router(tmp_path: Path) -> Iterator[Pki]:
    """The production router config (deploy/), moved to 127.0.0.1, free ports and fresh certificates."""
    pki = tmp_path / "pki"
    make_dev_pki(pki, ["uav1", "uav2"], [])
    overrides = [
        "zenoh.router_listen_host=127.0.0.1",
        f"zenoh.default_port={free_tcp_port()}",
        f"zenoh.priority_port={free_tcp_port()}",
        f'zenoh.tls_ca="{pki}/ca.pem"',
        f'zenoh.tls_cert="{pki}/router.pem"',
        f'zenoh.tls_key="{pki}/router-key.pem"',
    ]
    config = load_config(PRODUCTION_ROUTER, overrides)
    assert config.zenoh.acl_drones == ("uav1", "uav2")
    args = ["edge", "router", *(arg for o in overrides for arg in ("--set", o))]
    router = DynqosProcess(args, PRODUCTION_ROUTER)
    try:
        yield Pki(pki, dataclasses.replace(config.zenoh, acl_drones=(), edge_host="127.0.0.1"))
    finally:
        router.stop()


def _collect(session: zenoh.Session, key: str, seen: Seen) -> zenoh.Subscriber[None]:
    return session.declare_subscriber(key, lambda s: seen.put((str(s.key_expr), bytes(s.payload))))


def _wait_for(seen: Seen, sentinel: tuple[str, bytes]) -> list[tuple[str, bytes]]:
    """Everything that arrived up to and including `sentinel` (which must arrive)."""
    got: list[tuple[str, bytes]] = []
    while True:
        item = seen.get(timeout=10)
        got.append(item)
        if item == sentinel:
            return got


def _wait_matched(session: zenoh.Session, key: str) -> zenoh.Publisher:
    publisher = session.declare_publisher(key, allowed_destination=zenoh.Locality.REMOTE)
    listener = publisher.declare_matching_listener(zenoh.handlers.FifoChannel(4))
    if not publisher.matching_status.matching:
        status = listener.recv()  # blocks until a subscriber for `key` is known
        assert status.matching
    return publisher


def test_a_drone_reaches_only_its_own_keys(secure_router: Pki) -> None:
    edge = open_session(secure_router.as_("edge"), Role.EDGE)
    uav1 = open_session(secure_router.as_("uav1"), Role.DRONE)
    try:
        at_edge: Seen = queue.Queue()
        at_uav1: Seen = queue.Queue()
        subs = [_collect(edge, "dynqos/**", at_edge)]
        subs.append(_collect(uav1, "dynqos/uav1/down/**", at_uav1))
        subs.append(_collect(uav1, "dynqos/uav2/down/**", at_uav1))  # declared, but refused by the router

        # uav1 publishes: its own state passes; uav2's keys and any down key do not.
        state = _wait_matched(uav1, "dynqos/uav1/up/priority/state")
        remote = zenoh.Locality.REMOTE  # not to uav1's own subscribers in this same session
        uav1.put("dynqos/uav2/up/priority/state", b"uav1 pretending to be uav2", allowed_destination=remote)
        uav1.put("dynqos/uav1/down/cmd", b"uav1 forging its own command", allowed_destination=remote)
        uav1.put("dynqos/uav2/down/cmd", b"uav1 commanding uav2", allowed_destination=remote)
        state.put(b"uav1 state")
        got = _wait_for(at_edge, ("dynqos/uav1/up/priority/state", b"uav1 state"))
        assert got == [("dynqos/uav1/up/priority/state", b"uav1 state")]

        # The edge commands both drones: uav1 receives its own commands only.
        command = _wait_matched(edge, "dynqos/uav1/down/cmd")
        edge.put("dynqos/uav2/down/cmd", b"for uav2", allowed_destination=remote)
        command.put(b"for uav1")
        got = _wait_for(at_uav1, ("dynqos/uav1/down/cmd", b"for uav1"))
        assert got == [("dynqos/uav1/down/cmd", b"for uav1")]
        assert at_edge.qsize() == 0  # nothing forbidden reached the edge meanwhile either
        for sub in subs:
            sub.undeclare()
    finally:
        uav1.close()  # type: ignore[no-untyped-call]
        edge.close()  # type: ignore[no-untyped-call]


def test_a_session_without_a_certificate_cannot_connect(secure_router: Pki, tmp_path: Path) -> None:
    cfg = secure_router.cfg
    zcfg = zenoh.Config()
    for key, value in (
        ("mode", '"client"'),
        ("connect/endpoints", f'["tls/127.0.0.1:{cfg.default_port}"]'),
        ("transport/link/tls/root_ca_certificate", f'"{cfg.tls_ca}"'),  # trusts the router...
        ("connect/timeout_ms", "3000"),  # ...but has no certificate of its own to show
        ("connect/exit_on_failure", "true"),
    ):
        zcfg.insert_json5(key, value)
    with pytest.raises(zenoh.ZError):
        zenoh.open(zcfg)
    # A certificate from another CA fails the same way, through our own error path.
    other = make_dev_pki(tmp_path / "other", ["uav1"], [])
    rogue = dataclasses.replace(
        cfg, tls_cert=str(other["uav1"].cert), tls_key=str(other["uav1"].key), connect_timeout_s=3
    )
    with pytest.raises(TransportError, match="cannot open zenoh"):
        open_session(rogue, Role.DRONE)


def test_tls_config_errors_name_the_key(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="tls_cert"):
        ZenohConfig(tls=True, tls_ca="ca.pem")
    with pytest.raises(ConfigError, match="acl_drones"):
        ZenohConfig(acl_drones=("uav1",))  # access control without TLS has no identity to match
    with pytest.raises(ConfigError, match="acl_drones"):
        ZenohConfig(tls=True, tls_ca="a", tls_cert="b", tls_key="c", acl_drones=("bad id",))
    config = tmp_path / "c.toml"
    config.write_text(
        f'[zenoh]\ntls = true\ntls_ca = "{tmp_path}/missing.pem"\ntls_cert = "x"\ntls_key = "y"\n'
    )
    proc = subprocess.run(
        [DYNQOS, "edge", "mpc", "--config", str(config)], capture_output=True, text=True, timeout=30
    )
    assert proc.returncode == 2
    assert "tls_ca" in proc.stderr
    assert "missing.pem" in proc.stderr


def test_certs_command_makes_a_ca_and_per_drone_certificates(tmp_path: Path) -> None:
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    out = tmp_path / "pki"
    proc = subprocess.run(
        [DYNQOS, "certs", "--out", str(out), "--drone", "uav7", "--router-host", "router.example"],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert proc.returncode == 0, proc.stderr
    cert = x509.load_pem_x509_certificate((out / "uav7.pem").read_bytes())
    assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == "uav7"
    router = x509.load_pem_x509_certificate((out / "router.pem").read_bytes())
    names = router.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert "router.example" in names.get_values_for_type(x509.DNSName)
    assert (out / "uav7-key.pem").stat().st_mode & 0o077 == 0  # private keys readable by the owner only
    ca_before = (out / "ca.pem").read_bytes()
    again = subprocess.run(
        [DYNQOS, "certs", "--out", str(out), "--drone", "uav8"], capture_output=True, timeout=30
    )
    assert again.returncode == 0
    assert (out / "ca.pem").read_bytes() == ca_before  # the CA is kept: earlier certificates stay valid
    bad = subprocess.run(
        [DYNQOS, "certs", "--out", str(out), "--drone", "edge"], capture_output=True, text=True, timeout=30
    )
    assert bad.returncode == 2
    assert bad.stderr.count("\n") == 1
