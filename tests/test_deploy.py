"""deploy/: the Kubernetes manifests, the systemd unit, the container image and their configs, checked
offline (docs/deploy.md). Where a checker is missing on this machine the test says so and skips."""

from __future__ import annotations

import fnmatch
import re
import shutil
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path
from typing import Any

import pytest

from dynqos.common.config import load_config

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"
K8S_VERSION = "1.30.0"  # the oldest Kubernetes we promise

yaml = pytest.importorskip("yaml")
kubernetes_validate = pytest.importorskip("kubernetes_validate")


def _kustomize(folder: Path) -> list[dict[str, Any]]:
    kubectl = shutil.which("kubectl")
    if kubectl is None:
        pytest.skip("kubectl is not installed here, so the kustomize overlays cannot be rendered")
    out = subprocess.run([kubectl, "kustomize", str(folder)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return [doc for doc in yaml.safe_load_all(out.stdout) if doc]


def _validate(docs: list[dict[str, Any]]) -> None:
    for doc in docs:
        try:
            kubernetes_validate.validate(doc, K8S_VERSION, strict=True)
        except kubernetes_validate.ValidationError as exc:
            name = f"{doc.get('kind')}/{doc.get('metadata', {}).get('name')}"
            raise AssertionError(f"{name}: {exc.message} at {list(exc.path)}") from None


def _base_files() -> list[Path]:
    return [p for p in sorted((DEPLOY / "k8s" / "base").glob("*.yaml")) if p.name != "kustomization.yaml"]


def test_every_base_manifest_validates_against_the_kubernetes_schema() -> None:
    docs = [doc for path in _base_files() for doc in yaml.safe_load_all(path.read_text()) if doc]
    assert {d["kind"] for d in docs} == {"Namespace", "Deployment", "Service"}
    _validate(docs)


def test_a_broken_manifest_is_caught() -> None:
    """The validator is not a no-op: a misspelt field fails in strict mode."""
    doc = yaml.safe_load((DEPLOY / "k8s" / "base" / "planner.yaml").read_text())
    doc["spec"]["template"]["spec"]["containers"][0]["imagePullPolicyy"] = "Always"
    with pytest.raises(AssertionError, match="imagePullPolicyy"):
        _validate([doc])


@pytest.mark.parametrize("folder", ["base", "overlays/production"])
def test_kustomize_renders_valid_manifests(folder: str) -> None:
    docs = _kustomize(DEPLOY / "k8s" / folder)
    _validate(docs)
    workloads = [d for d in docs if d["kind"] in ("Deployment", "StatefulSet")]
    assert {w["metadata"]["name"] for w in workloads} == {
        "dynqos-router", "dynqos-mpc", "dynqos-planner", "dynqos-detector", "dynqos-qos", "dynqos-ros2",
    }  # fmt: skip
    (qos,) = [w for w in workloads if w["metadata"]["name"] == "dynqos-qos"]
    # a rolling update starts the new agent first: it stands by, and the old one hands it the sessions
    assert qos["spec"]["strategy"] == {
        "type": "RollingUpdate",
        "rollingUpdate": {"maxSurge": 1, "maxUnavailable": 0},
    }
    (qos_env,) = qos["spec"]["template"]["spec"]["containers"][0]["env"]
    assert qos_env["name"] == "DYNQOS_QOS__REPLICA_ID"
    for workload in workloads:
        assert workload["metadata"]["namespace"] == "dynqos"
        pod = workload["spec"]["template"]["spec"]
        assert pod["securityContext"]["runAsNonRoot"] is True
        for container in pod["containers"]:
            assert container["args"][0] in ("edge",)
            assert "limits" in container["resources"]
            assert "requests" in container["resources"]
            assert container["livenessProbe"]
            assert container["readinessProbe"]


def _configs(docs: list[dict[str, Any]], tmp_path: Path) -> dict[str, Path]:
    (configmap,) = [d for d in docs if d["kind"] == "ConfigMap"]
    paths = {}
    for name, text in configmap["data"].items():
        paths[name] = tmp_path / name
        paths[name].write_text(text)
    return paths


SERVICES = {"dynqos-router": "router", "dynqos-mpc": "mpc", "dynqos-planner": "planner",
            "dynqos-detector": "detector", "dynqos-qos": "qos", "dynqos-ros2": "ros2"}  # fmt: skip


def test_production_overlay_turns_on_mtls_access_control_and_mpc_replicas(tmp_path: Path) -> None:
    docs = _kustomize(DEPLOY / "k8s" / "overlays" / "production")
    configs = _configs(docs, tmp_path)
    router = load_config(configs["router.toml"]).zenoh
    edge = load_config(configs["edge.toml"]).zenoh
    assert router.tls
    assert edge.tls
    assert router.acl_drones
    assert router.acl == "on"
    workloads = {d["metadata"]["name"]: d for d in docs if d["kind"] in ("Deployment", "StatefulSet")}
    for name, workload in workloads.items():
        pod = workload["spec"]["template"]["spec"]
        mounts = pod["containers"][0]["volumeMounts"]
        assert {"name": "certs", "mountPath": "/etc/dynqos/certs", "readOnly": True} in mounts
        (certs,) = [v for v in pod["volumes"] if v["name"] == "certs"]
        assert certs["secret"]["secretName"] == f"dynqos-{SERVICES[name]}-tls"  # its own identity only
    for cfg in (router, edge):  # the same paths in every pod: each mounts its own Secret there
        assert (cfg.tls_ca, cfg.tls_cert, cfg.tls_key) == tuple(
            f"/etc/dynqos/certs/{f}" for f in ("ca.pem", "cert.pem", "key.pem")
        )
    mpc = workloads["dynqos-mpc"]
    assert (mpc["kind"], mpc["spec"]["replicas"]) == ("Deployment", 2)  # a primary and a standby per drone
    container = mpc["spec"]["template"]["spec"]["containers"][0]
    env = {e["name"]: e for e in container["env"]}
    assert env["DYNQOS_MPC__REPLICA_ID"]["valueFrom"]["fieldRef"]["fieldPath"] == "metadata.name"
    assert not any("shard" in arg for arg in container["args"])  # no setting has to equal the replica count
    spread = mpc["spec"]["template"]["spec"]["affinity"]["podAntiAffinity"]
    assert spread["preferredDuringSchedulingIgnoredDuringExecution"][0]["podAffinityTerm"]["topologyKey"] == (
        "kubernetes.io/hostname"
    )
    (budget,) = [
        d for d in docs if d["kind"] == "PodDisruptionBudget" and d["metadata"]["name"] == "dynqos-mpc"
    ]
    assert budget["spec"]["maxUnavailable"] == 1  # a drain never takes the last standby
    (hpa,) = [d for d in docs if d["kind"] == "HorizontalPodAutoscaler"]
    assert hpa["spec"]["scaleTargetRef"] == {
        "apiVersion": "apps/v1",
        "kind": "Deployment",
        "name": "dynqos-mpc",
    }
    assert hpa["spec"]["minReplicas"] >= 2
    pods_metrics = [m["pods"]["metric"]["name"] for m in hpa["spec"]["metrics"] if m["type"] == "Pods"]
    assert pods_metrics == ["dynqos_mpc_drones_flying"]
    assert pods_metrics[0] in _mpc_metric_names()  # what the HPA reads is what the MPC exports
    planner = workloads["dynqos-planner"]
    assert planner["spec"]["replicas"] == 2
    (planner_env,) = planner["spec"]["template"]["spec"]["containers"][0]["env"]
    assert planner_env["name"] == "DYNQOS_PLANNER__REPLICA_ID"
    qos = workloads["dynqos-qos"]
    assert qos["spec"]["replicas"] == 2  # one active, one standing by (docs/qos.md)
    assert "podAntiAffinity" in qos["spec"]["template"]["spec"]["affinity"]
    (qos_budget,) = [
        d for d in docs if d["kind"] == "PodDisruptionBudget" and d["metadata"]["name"] == "dynqos-qos"
    ]
    assert qos_budget["spec"]["maxUnavailable"] == 1
    resources = container["resources"]
    assert resources["requests"] == resources["limits"]  # the Guaranteed QoS class: never CFS-throttled
    assert str(resources["limits"]["cpu"]).isdigit()  # whole CPUs (the static CPU manager pins them)
    (service,) = [d for d in docs if d["kind"] == "Service" and d["metadata"]["name"] == "dynqos-router"]
    assert {p["port"] for p in service["spec"]["ports"]} == {7447, 7448}


def test_production_network_policies_let_in_only_the_flows_and_let_edge_services_reach_only_the_router() -> (
    None
):
    docs = _kustomize(DEPLOY / "k8s" / "overlays" / "production")
    policies = {d["metadata"]["name"]: d["spec"] for d in docs if d["kind"] == "NetworkPolicy"}
    deny = policies["dynqos-default-deny"]
    assert deny["podSelector"] == {}
    assert set(deny["policyTypes"]) == {"Ingress", "Egress"}
    assert "ingress" not in deny  # nothing allowed by it
    assert "egress" not in deny
    ingress = {n: p for n, p in policies.items() if "Ingress" in p["policyTypes"] and p.get("ingress")}
    assert set(ingress) == {"dynqos-router-flows", "dynqos-metrics"}
    flows = ingress["dynqos-router-flows"]  # only the router is reachable from anywhere, on its flow ports
    assert flows["podSelector"] == {"matchLabels": {"app.kubernetes.io/name": "dynqos-router"}}
    assert [(p["port"], p["protocol"]) for rule in flows["ingress"] for p in rule["ports"]] == [
        (7447, "TCP"),
        (7448, "TCP"),
    ]
    (scrape,) = ingress["dynqos-metrics"]["ingress"]  # the metrics port, only from the monitoring namespace
    assert scrape["ports"] == [{"port": 9464, "protocol": "TCP"}]
    assert [f["namespaceSelector"] for f in scrape["from"]] == [
        {"matchLabels": {"kubernetes.io/metadata.name": "monitoring"}}
    ]
    edge = policies["dynqos-edge-to-router"]
    assert set(edge["podSelector"]["matchExpressions"][0]["values"]) == set(SERVICES) - {"dynqos-router"}
    to_router, to_dns = edge["egress"]
    assert to_router["to"] == [{"podSelector": {"matchLabels": {"app.kubernetes.io/name": "dynqos-router"}}}]
    assert {p["port"] for p in to_dns["ports"]} == {53}
    other_egress = [n for n, p in policies.items() if p.get("egress") and n != "dynqos-edge-to-router"]
    assert other_egress == ["dynqos-qos-to-operator"]  # the QoD API; no other service reaches out
    assert [p["port"] for p in policies["dynqos-qos-to-operator"]["egress"][0]["ports"]] == [443]
    (pdb,) = [
        d for d in docs if d["kind"] == "PodDisruptionBudget" and d["metadata"]["name"] == "dynqos-router"
    ]
    assert pdb["spec"]["selector"] == {"matchLabels": {"app.kubernetes.io/name": "dynqos-router"}}
    assert pdb["spec"]["minAvailable"] == 1


def test_the_zenohd_overlay_runs_the_official_router_with_the_generated_config() -> None:
    import zenoh

    docs = _kustomize(DEPLOY / "k8s" / "overlays" / "production-zenohd")
    _validate(docs)
    (router,) = [d for d in docs if d["kind"] == "Deployment" and d["metadata"]["name"] == "dynqos-router"]
    container = router["spec"]["template"]["spec"]["containers"][0]
    image, tag = container["image"].rsplit(":", 1)
    assert image == "eclipse/zenoh"
    assert tag == version("eclipse-zenoh")  # the router speaks the drones' zenoh
    assert container["args"] == ["-c", "/etc/zenoh/router.json5"]
    assert "exec" not in container["livenessProbe"]  # zenohd writes no dynqos health file
    (zenohd_config,) = [d for d in docs if d["kind"] == "ConfigMap" and "zenohd" in d["metadata"]["name"]]
    text = zenohd_config["data"]["router.json5"]
    assert text == (DEPLOY / "zenoh" / "router-production.json5").read_text()
    zenoh.Config.from_json5(text)  # zenoh's own parser and schema accept it
    assert '"default_permission": "deny"' in text
    assert '"edge-detector"' in text


def test_the_image_is_named_in_one_place_with_the_package_version() -> None:
    from dynqos import __version__

    kustomization = yaml.safe_load((DEPLOY / "k8s" / "base" / "kustomization.yaml").read_text())
    (image,) = kustomization["images"]
    assert image["name"] == "dynqos-edge"
    assert image["newTag"] == __version__
    dockerfile = (DEPLOY / "container" / "Dockerfile").read_text()
    assert f"ARG VERSION={__version__}" in dockerfile
    assert f"-t {image['newName']}:{__version__} ." in dockerfile  # the build command it documents
    for path in (DEPLOY / "k8s" / "base").glob("*.yaml"):
        for doc in yaml.safe_load_all(path.read_text()):
            for container in (
                (doc or {}).get("spec", {}).get("template", {}).get("spec", {}).get("containers", [])
            ):
                assert container["image"] == "dynqos-edge", path  # replaced by kustomize's images: only


@pytest.mark.parametrize("folder", ["base", "overlays/production"])
def test_every_service_is_probed_and_scraped_on_its_metrics_port(folder: str, tmp_path: Path) -> None:
    docs = _kustomize(DEPLOY / "k8s" / folder)
    for name in ("router.toml", "edge.toml"):
        metrics = load_config(_configs(docs, tmp_path)[name]).metrics
        assert (metrics.port, metrics.host) == (9464, "0.0.0.0")  # reachable from the kubelet and Prometheus
    for workload in (d for d in docs if d["kind"] in ("Deployment", "StatefulSet")):
        template = workload["spec"]["template"]
        assert template["metadata"]["annotations"] == {
            "prometheus.io/scrape": "true", "prometheus.io/port": "9464", "prometheus.io/path": "/metrics",
        }  # fmt: skip
        (container,) = template["spec"]["containers"]
        assert {"name": "metrics", "containerPort": 9464} in container["ports"]
        for probe in ("readinessProbe", "livenessProbe"):
            assert container[probe]["httpGet"] == {"path": "/healthz", "port": "metrics"}, workload[
                "metadata"
            ]


def _documented_metrics() -> set[str]:
    """The metric names in docs/observability.md's tables (first column, in backticks)."""
    text = (ROOT / "docs" / "observability.md").read_text()
    return set(re.findall(r"^\| `(dynqos_[a-z_]+)`", text, re.M))


def test_the_grafana_dashboard_uses_only_documented_metrics() -> None:
    import json

    dashboard = json.loads((DEPLOY / "grafana" / "dynqos-dashboard.json").read_text())
    exprs = [t["expr"] for p in dashboard["panels"] for t in p.get("targets", [])]
    assert len(exprs) > 15
    used = {
        re.sub(r"_(bucket|count|sum)$", "", name) for e in exprs for name in re.findall(r"dynqos_[a-z_]+", e)
    }
    documented = _documented_metrics()
    assert used - documented == set()
    variables = {v["name"]: v for v in dashboard["templating"]["list"]}
    assert "dynqos_cc_rtt_seconds_count, uav" in variables["uav"]["query"]
    titles = {p["title"] for p in dashboard["panels"]}
    assert {"C&C round trip", "Supervisor state", "MPC solve time", "Throughput per bearer"} <= titles


def test_base_configs_load(tmp_path: Path) -> None:
    for name in ("router.toml", "edge.toml"):
        cfg = load_config(DEPLOY / "k8s" / "base" / name)
        assert not cfg.zenoh.tls
    onboard = load_config(DEPLOY / "systemd" / "onboard.toml")
    assert onboard.zenoh.tls
    assert Path(onboard.zenoh.tls_cert).stem == onboard.drone.id  # the CN the router's ACL matches
    assert onboard.onboard.takeoff is False


def test_systemd_unit_verifies(tmp_path: Path) -> None:
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze is not installed here")
    unit = (DEPLOY / "systemd" / "dynqos-onboard.service").read_text()
    assert "Type=notify" in unit
    assert re.search(r"^WatchdogSec=", unit, re.M)
    assert re.search(r"^Restart=on-failure", unit, re.M)
    # verify insists that ExecStart exists: point it at this environment's dynqos.
    dynqos = Path(sys.executable).parent / "dynqos"
    copy = tmp_path / "dynqos-onboard.service"
    copy.write_text(unit.replace("/opt/dynqos/venv/bin/dynqos", str(dynqos)))
    out = subprocess.run([analyze, "verify", str(copy)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    complaints = [line for line in out.stderr.splitlines() if copy.name in line]
    assert complaints == []  # unknown keys are only warnings: fail on those too


def _dockerignore_allows(path: str) -> bool:
    allowed = False
    for line in (ROOT / ".dockerignore").read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        negate = line.startswith("!")
        pattern = line.lstrip("!").rstrip("/")
        if (
            fnmatch.fnmatch(path, pattern)
            or path.startswith(pattern + "/")
            or fnmatch.fnmatch(path, pattern.replace("**/", "*/"))
        ):
            allowed = negate
    return allowed


def test_dockerfile_lints_copies_what_the_context_holds_and_its_entrypoint_runs() -> None:
    dockerfile = DEPLOY / "container" / "Dockerfile"
    text = dockerfile.read_text()
    hadolint = shutil.which("hadolint") or str(Path(sys.executable).parent / "hadolint")
    if Path(hadolint).exists():
        out = subprocess.run([hadolint, str(dockerfile)], capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stdout + out.stderr
    assert re.search(r"^USER 10001$", text, re.M)  # non-root
    sources = [src for line in re.findall(r"^COPY (?!--from)(.+)$", text, re.M) for src in line.split()[:-1]]
    assert sources
    for src in sources:
        assert (ROOT / src).exists(), src
        assert _dockerignore_allows(src.rstrip("/")), f".dockerignore leaves {src} out of the context"
    assert not _dockerignore_allows(".venv")
    assert not _dockerignore_allows("edge/__pycache__/x.pyc")
    entrypoint = re.search(r'^ENTRYPOINT \["(\w+)"\]$', text, re.M)
    assert entrypoint is not None
    assert entrypoint.group(1) == "dynqos"
    out = subprocess.run(
        [str(Path(sys.executable).parent / "dynqos"), "edge", "mpc", "--help"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0
    assert "--health-file" in out.stdout


def _build_stage_copies(text: str) -> list[tuple[str, str]]:
    """(source, destination) of every COPY in the Dockerfile's first (build) stage."""
    build = text.split("\nFROM ", 2)[1]
    copies = []
    for line in re.findall(r"^COPY (?!--from)(.+)$", build, re.M):
        *sources, destination = line.split()
        copies += [(src, destination) for src in sources]
    return copies


@pytest.mark.timeout(300)
def test_the_wheel_builds_from_exactly_what_the_dockerfile_copies(tmp_path: Path) -> None:
    """What the image's build stage does, without a container runtime: the Dockerfile's COPY lines into
    an empty folder, then `pip wheel` there. A package directory the Dockerfile forgets fails here."""
    import zipfile

    text = (DEPLOY / "container" / "Dockerfile").read_text()
    assert re.search(r'^RUN pip wheel --wheel-dir /wheels "\.\[edge,ros2\]"$', text, re.M)
    context = tmp_path / "src"
    context.mkdir()
    for source, destination in _build_stage_copies(text):
        assert _dockerignore_allows(source.rstrip("/")), f".dockerignore leaves {source} out of the context"
        target = context / destination.rstrip("/") if destination not in ("./", ".") else context / source
        if (ROOT / source).is_dir():
            shutil.copytree(ROOT / source, target, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            shutil.copy2(ROOT / source, target)
    pip_wheel = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q"]
    out = subprocess.run(
        [*pip_wheel, "-w", str(tmp_path), "."], cwd=context, capture_output=True, text=True, timeout=240
    )
    assert out.returncode == 0, out.stderr[-3000:]
    (wheel,) = tmp_path.glob("dynqos-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    for module in (
        "dynqos/cli/main.py",
        "dynqos/bench/suite.py",
        "dynqos/edge/mpc/service.py",
        "dynqos/edge/qos/agent.py",
        "dynqos/scenarios/baseline.toml",
    ):
        assert module in names, module


def test_zenoh_configs_in_deploy_are_in_sync_and_parse(tmp_path: Path) -> None:
    """deploy/zenoh/*.json5 are what `dynqos config zenoh` prints for the deploy configs (for zenohd)."""
    import zenoh

    script = (DEPLOY / "zenoh" / "generate.sh").read_text()
    runs = re.findall(r'"\$DYNQOS" config zenoh (\S+) --role (\w+) >(\S+)', script)
    assert len(runs) == 5
    dynqos = str(Path(sys.executable).parent / "dynqos")
    for source, role, target in runs:
        out = subprocess.run(
            [dynqos, "config", "zenoh", str(ROOT / source), "--role", role],
            capture_output=True, text=True, timeout=60, check=True,
        )  # fmt: skip
        assert out.stdout == (ROOT / target).read_text(), f"{target} is stale: run deploy/zenoh/generate.sh"
        zenoh.Config.from_file(str(ROOT / target))  # zenoh's own JSON5 parser and schema accept it
    production = (DEPLOY / "zenoh" / "router-production.json5").read_text()
    assert '"enable_mtls": true' in production
    assert '"default_permission": "deny"' in production


def _mpc_metric_names() -> set[str]:
    """The metric families an MPC process exports (on an in-memory bus, registry only)."""
    from dynqos.common.bus import MemoryBus
    from dynqos.common.config import load_config
    from dynqos.common.metrics import ProcessMetrics
    from dynqos.edge import metrics
    from dynqos.edge.mpc.service import MpcService
    from dynqos.edge.runtime import Ports

    config = load_config(None, ['mpc.replica_id="m1"'])
    service = MpcService(config, Ports(MemoryBus()))
    registry = ProcessMetrics("mpc", config.metrics)
    metrics.mpc(service, registry)
    return {family.name for family in registry.registry.collect()}
