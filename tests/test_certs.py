"""`dynqos certs`: private keys never readable by others, never written through a link, kept unless
--force, and no certificate outliving its CA (common/certs.py, docs/security.md)."""

from __future__ import annotations

import datetime as dt
import os
import stat
import subprocess
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.x509.oid import NameOID

from dynqos.common import certs
from dynqos.common.certs import DevCa, make_dev_pki
from dynqos.common.errors import DynqosError
from tests.procs import DYNQOS

pytestmark = pytest.mark.timeout(60)


def _certs(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([DYNQOS, "certs", *args], capture_output=True, text=True, timeout=30)


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.lstat().st_mode)


def test_certs_command_makes_a_ca_the_edge_identities_and_one_per_drone(tmp_path: Path) -> None:
    out = tmp_path / "pki"
    proc = _certs("--out", str(out), "--drone", "uav7", "--router-host", "router.example")
    assert proc.returncode == 0, proc.stderr
    names = {p.name for p in out.iterdir()}
    edge = ("edge-mpc", "edge-planner", "edge-fleet-planner", "edge-detector", "edge-qos", "edge-ros2")
    for cn in ("ca", "router", *edge, "uav7"):
        assert {f"{cn}.pem", f"{cn}-key.pem"} <= names
    assert "edge.pem" not in names  # no shared edge identity any more
    cert = x509.load_pem_x509_certificate((out / "uav7.pem").read_bytes())
    assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == "uav7"
    router = x509.load_pem_x509_certificate((out / "router.pem").read_bytes())
    sans = router.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert "router.example" in sans.get_values_for_type(x509.DNSName)
    assert _mode(out) == 0o700
    for path in out.glob("*-key.pem"):
        assert _mode(path) == 0o600, path


def test_rerunning_keeps_every_pair_and_force_replaces_them(tmp_path: Path) -> None:
    out = tmp_path / "pki"
    assert _certs("--out", str(out), "--drone", "uav1").returncode == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    again = _certs("--out", str(out), "--drone", "uav1", "--drone", "uav2")
    assert again.returncode == 0
    assert "uav1: " in again.stdout
    assert "(kept)" in again.stdout.split("uav1: ")[1].splitlines()[0]
    after = {p.name: p.read_bytes() for p in out.iterdir()}
    assert {k: v for k, v in after.items() if k in before} == before  # nothing churned
    assert "uav2-key.pem" in after
    forced = _certs("--out", str(out), "--drone", "uav1", "--force")
    assert forced.returncode == 0
    assert "(kept)" not in forced.stdout
    replaced = {p.name: p.read_bytes() for p in out.iterdir()}
    assert replaced["uav1-key.pem"] != before["uav1-key.pem"]
    assert replaced["edge-mpc-key.pem"] != before["edge-mpc-key.pem"]
    assert replaced["ca.pem"] == before["ca.pem"]  # the CA is kept: other drones' certificates stay valid


def test_a_new_router_host_reissues_only_the_router(tmp_path: Path) -> None:
    out = tmp_path / "pki"
    make_dev_pki(out, ["uav1"], [])
    issued = make_dev_pki(out, ["uav1"], ["router.example"])
    assert not issued["router"].kept
    assert all(pair.kept for name, pair in issued.items() if name != "router")


def test_a_rewritten_key_gets_mode_0600_even_if_the_old_file_was_0644(tmp_path: Path) -> None:
    out = tmp_path / "pki"
    make_dev_pki(out, ["uav1"], [])
    (out / "uav1-key.pem").chmod(0o644)
    make_dev_pki(out, ["uav1"], [], force=True)
    assert _mode(out / "uav1-key.pem") == 0o600


def test_a_symlink_at_a_keys_path_is_replaced_not_followed(tmp_path: Path) -> None:
    out = tmp_path / "pki"
    make_dev_pki(out, ["uav1"], [])
    victim = tmp_path / "victim.txt"
    victim.write_text("not a key")
    victim.chmod(0o644)
    (out / "uav2-key.pem").symlink_to(victim)
    make_dev_pki(out, ["uav1", "uav2"], [])
    assert victim.read_text() == "not a key"  # the planted link's target is untouched
    assert not (out / "uav2-key.pem").is_symlink()
    assert _mode(out / "uav2-key.pem") == 0o600
    assert b"PRIVATE KEY" in (out / "uav2-key.pem").read_bytes()


def test_the_output_folder_is_made_private_and_may_not_be_a_link(tmp_path: Path) -> None:
    out = tmp_path / "pki"
    out.mkdir(mode=0o755)
    os.chmod(out, 0o755)
    make_dev_pki(out, ["uav1"], [])
    assert _mode(out) == 0o700
    link = tmp_path / "link"
    link.symlink_to(out)
    with pytest.raises(DynqosError, match="symbolic link"):
        make_dev_pki(link, ["uav1"], [])


def test_no_certificate_outlives_its_ca(tmp_path: Path) -> None:
    out = tmp_path / "pki"
    make_dev_pki(out, ["uav1"], [], ca_days=30, days=365)
    ca = x509.load_pem_x509_certificate((out / "ca.pem").read_bytes())
    for path in out.glob("*.pem"):
        if not path.name.endswith("-key.pem"):
            cert = x509.load_pem_x509_certificate(path.read_bytes())
            assert cert.not_valid_after_utc <= ca.not_valid_after_utc, path.name
    leaf = x509.load_pem_x509_certificate((out / "uav1.pem").read_bytes())
    assert leaf.not_valid_after_utc - dt.datetime.now(dt.timezone.utc) < dt.timedelta(days=31)


def test_an_expired_ca_is_refused_with_the_way_out(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "pki"
    DevCa(out, ca_days=1)
    later = dt.datetime.now(dt.timezone.utc) + dt.timedelta(days=2)
    monkeypatch.setattr(certs, "_now", lambda: later)  # the clock two days on: the one fake allowed
    with pytest.raises(DynqosError, match=r"expired on .*: make a new CA"):
        DevCa(out)


@pytest.mark.parametrize("drone", ["edge", "router", "edge-mpc", "bad id"])
def test_reserved_or_invalid_drone_ids_are_one_line_and_exit_2(tmp_path: Path, drone: str) -> None:
    bad = _certs("--out", str(tmp_path / "pki"), "--drone", drone)
    assert bad.returncode == 2
    assert bad.stderr.count("\n") == 1, bad.stderr
