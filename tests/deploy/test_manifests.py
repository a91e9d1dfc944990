"""Deployment manifests (deploy/k8s, deploy/kserve) agree with the image and the app.

Probes must hit routes the app really serves, ports must match the Dockerfile's EXPOSE and the
Settings default, containers must run non-root on a read-only root filesystem, and the HPA must
target the Deployment.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

yaml = pytest.importorskip("yaml")

ROOT = Path(__file__).resolve().parents[2]
K8S = ROOT / "deploy" / "k8s"
KSERVE = ROOT / "deploy" / "kserve" / "inferenceservice.yaml"
MANIFESTS = [*sorted(K8S.glob("*.yaml")), KSERVE]
IMAGE_UID = 10001
PROBE_PATHS = {"livenessProbe": "/v2/health/live", "readinessProbe": "/v2/health/ready"}


def load(path: Path) -> list[dict]:
    return [doc for doc in yaml.safe_load_all(path.read_text()) if doc]


def by_kind(kind: str) -> dict:
    found = [doc for path in MANIFESTS for doc in load(path) if doc.get("kind") == kind]
    assert len(found) == 1, f"expected one {kind}, found {len(found)}"
    return found[0]


def dockerfile_exposed_port() -> int:
    (port,) = re.findall(r"^EXPOSE\s+(\d+)", (ROOT / "Dockerfile").read_text(), flags=re.MULTILINE)
    return int(port)


def workloads() -> list[tuple[str, dict, dict]]:
    """``(label, pod spec, serving container)`` for the Deployment and the KServe predictor."""
    deployment = by_kind("Deployment")["spec"]["template"]["spec"]
    predictor = by_kind("InferenceService")["spec"]["predictor"]
    return [("Deployment", deployment, deployment["containers"][0]),
            ("InferenceService", predictor, predictor["containers"][0])]


def container_port(container: dict, port) -> int:
    """A probe's ``port`` (number or port name) as a number."""
    if isinstance(port, int):
        return port
    (match,) = [p["containerPort"] for p in container["ports"] if p.get("name") == port]
    return match


WORKLOADS = [pytest.param(*workload, id=workload[0]) for workload in workloads()]


def route_paths(routes) -> set[str]:
    """Paths of ``app.routes``, descending into included routers (FastAPI keeps them lazily)."""
    paths: set[str] = set()
    for route in routes:
        if isinstance(getattr(route, "path", None), str):
            paths.add(route.path)
        candidates = getattr(route, "effective_candidates", None)
        if callable(candidates):
            paths |= route_paths(candidates())
    return paths


@pytest.fixture(scope="module")
def app():
    try:
        from service.api.app import create_app
        from service.core.config import Settings
    except ImportError as exc:
        pytest.skip(f"service.api is not importable yet: {exc}")
    # No lifespan runs here, so no model is loaded: the routes exist, readiness answers 503.
    return create_app(Settings(bundled_models=False))


@pytest.fixture(scope="module")
def app_routes(app) -> set[str]:
    return route_paths(app.routes)


@pytest.mark.parametrize("path", MANIFESTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_manifest_parses_with_kind_and_api_version(path):
    docs = load(path)
    assert docs
    for doc in docs:
        assert doc.get("apiVersion") and doc.get("kind"), doc


@pytest.mark.parametrize(("label", "pod", "container"), WORKLOADS)
def test_probes_point_at_routes_the_app_serves(label, pod, container, app_routes):
    import httpx
    from api_server import main_server

    server = main_server()  # a real server process (the tests' shared one), over real HTTP
    probes = [container[name]["httpGet"]["path"] for name in (*PROBE_PATHS, "startupProbe") if name in container]
    for probe, path in PROBE_PATHS.items():
        assert container[probe]["httpGet"]["path"] == path, f"{label} {probe}"
    for path in probes:
        assert path in app_routes, f"{label}: probe path {path} is not a route of service.api.app"
        assert httpx.get(server.url + path, timeout=10).status_code == 200, f"{label}: GET {path} is not served"


@pytest.mark.parametrize(("label", "pod", "container"), WORKLOADS)
def test_ports_match_the_image_and_the_settings_default(label, pod, container):
    config = pytest.importorskip("service.core.config")
    default_port = config.Settings.model_fields["port"].default
    exposed = dockerfile_exposed_port()
    assert exposed == default_port == 8080
    assert [p["containerPort"] for p in container["ports"]] == [exposed], label
    for probe in PROBE_PATHS:
        assert container_port(container, container[probe]["httpGet"]["port"]) == exposed, f"{label} {probe}"
    env = {e["name"]: e.get("value") for e in container.get("env", [])}
    assert env.get("MFGNET_PORT", str(default_port)) == str(exposed)
    assert env.get("MFGNET_HOST") == "0.0.0.0"


@pytest.mark.parametrize(("label", "pod", "container"), WORKLOADS)
def test_runs_non_root_on_a_read_only_root_filesystem(label, pod, container):
    context = {**pod.get("securityContext", {}), **container["securityContext"]}
    assert context["runAsNonRoot"] is True, label
    assert context["runAsUser"] == IMAGE_UID, label
    assert container["securityContext"]["readOnlyRootFilesystem"] is True, label
    assert container["securityContext"]["allowPrivilegeEscalation"] is False, label
    assert container["securityContext"]["capabilities"]["drop"] == ["ALL"], label
    assert not container["securityContext"].get("privileged", False)
    mounts = {m["mountPath"]: m["name"] for m in container.get("volumeMounts", [])}
    volumes = {v["name"]: v for v in pod.get("volumes", [])}
    assert "emptyDir" in volumes[mounts["/tmp"]], f"{label}: /tmp must be a writable emptyDir"


QUANTITY = {"Ki": 2**10, "Mi": 2**20, "Gi": 2**30}


@pytest.mark.parametrize(("label", "pod", "container"), WORKLOADS)
def test_tmp_holds_the_uploads_the_server_admits_at_once(label, pod, container):
    """Every admitted request (running or queued) reads its multipart upload into ``/tmp`` before it waits for a
    worker: the emptyDir's ``sizeLimit`` must hold that many uploads of ``MFGNET_MAX_UPLOAD_BYTES`` and two of the
    page's aligned answers (at most 512 MB each), or the kubelet evicts the pod (it was 256Mi: one upload)."""
    from service.core.config import Settings

    env = {e["name"]: e["value"] for e in container.get("env", []) if "value" in e}
    settings = Settings(**{key.removeprefix("MFGNET_").lower(): value for key, value in env.items()
                           if key.startswith("MFGNET_")})
    mounts = {m["mountPath"]: m["name"] for m in container.get("volumeMounts", [])}
    limit = {v["name"]: v for v in pod.get("volumes", [])}[mounts["/tmp"]]["emptyDir"]["sizeLimit"]
    number, unit = re.fullmatch(r"(\d+)(Ki|Mi|Gi)", limit).groups()
    admitted = settings.max_concurrency + settings.max_queue
    needed = admitted * settings.max_upload_bytes + 2 * 512 * 10**6
    assert int(number) * QUANTITY[unit] >= needed, f"{label}: sizeLimit {limit} < {needed / 2**30:.2f} GiB"


@pytest.mark.parametrize(("label", "pod", "container"), WORKLOADS)
def test_resources_are_requested_and_limited(label, pod, container):
    resources = container["resources"]
    assert set(resources["requests"]) >= {"cpu", "memory"} and set(resources["limits"]) >= {"cpu", "memory"}


def test_deployment_drains_before_the_grace_period_ends():
    pod = by_kind("Deployment")["spec"]["template"]["spec"]
    pre_stop = pod["containers"][0]["lifecycle"]["preStop"]["exec"]["command"]
    assert pre_stop[0] == "sleep"
    assert pod["terminationGracePeriodSeconds"] > int(pre_stop[1])


def test_hpa_targets_the_deployment_on_cpu():
    hpa, deployment = by_kind("HorizontalPodAutoscaler"), by_kind("Deployment")
    assert hpa["apiVersion"] == "autoscaling/v2"
    target = hpa["spec"]["scaleTargetRef"]
    assert (target["apiVersion"], target["kind"], target["name"]) == ("apps/v1", "Deployment",
                                                                      deployment["metadata"]["name"])
    assert [m["resource"]["name"] for m in hpa["spec"]["metrics"]] == ["cpu"]
    assert 1 <= hpa["spec"]["minReplicas"] <= hpa["spec"]["maxReplicas"]
    # CPU utilisation is relative to the request: the container must declare one.
    assert by_kind("Deployment")["spec"]["template"]["spec"]["containers"][0]["resources"]["requests"]["cpu"]


def test_service_selects_the_deployment_pods_on_the_http_port():
    service, deployment = by_kind("Service"), by_kind("Deployment")
    labels = deployment["spec"]["template"]["metadata"]["labels"]
    assert service["spec"]["selector"].items() <= labels.items()
    assert deployment["spec"]["selector"]["matchLabels"].items() <= labels.items()
    container = deployment["spec"]["template"]["spec"]["containers"][0]
    (port,) = service["spec"]["ports"]
    assert container_port(container, port["targetPort"]) == dockerfile_exposed_port()


def test_kserve_predictor_in_serverless_mode_sets_only_what_knative_accepts():
    """KServe's default mode makes a Knative Service of the predictor; Knative's webhook rejects a container
    ``lifecycle`` (its queue-proxy drains the pod) and, under its default Knative Pod Autoscaler, any scale metric
    but concurrency and rps (KServe copies ``scaleMetric`` into ``autoscaling.knative.dev/metric``)."""
    isvc = by_kind("InferenceService")
    annotations = isvc["metadata"].get("annotations", {})
    if annotations.get("serving.kserve.io/deploymentMode") in ("RawDeployment", "Standard"):
        pytest.skip("raw deployment: a plain Deployment and HPA, no Knative")
    predictor = isvc["spec"]["predictor"]
    (container,) = predictor["containers"]
    assert "lifecycle" not in container, "Knative rejects a preStop hook on the user container"
    knative_class = annotations.get("autoscaling.knative.dev/class", "kpa.autoscaling.knative.dev")
    if knative_class == "kpa.autoscaling.knative.dev":
        assert predictor.get("scaleMetric", "concurrency") in ("concurrency", "rps")
    assert not {"terminationGracePeriodSeconds", "initContainers", "automountServiceAccountToken"} & set(predictor)


def test_kserve_concurrency_target_is_the_registrations_a_pod_runs_at_once():
    predictor = by_kind("InferenceService")["spec"]["predictor"]
    if predictor.get("scaleMetric") != "concurrency":
        pytest.skip("not scaled on concurrency")
    (container,) = predictor["containers"]
    env = {e["name"]: e.get("value") for e in container["env"]}
    assert predictor["scaleTarget"] == int(env["MFGNET_MAX_CONCURRENCY"])


@pytest.mark.parametrize(("label", "pod", "container"), WORKLOADS)
def test_environment_names_settings_the_service_reads(label, pod, container):
    """Every ``MFGNET_*`` variable a manifest sets is a field of ``Settings`` (a typo would be ignored silently:
    the settings ignore unknown names), and the literal values are valid settings."""
    config = pytest.importorskip("service.core.config")
    fields = set(config.Settings.model_fields)
    env = {e["name"]: e for e in container.get("env", [])}
    names = [name for name in env if name.startswith("MFGNET_")]
    assert names, label
    for name in names:
        assert name.removeprefix("MFGNET_").lower() in fields, f"{label}: {name} is not a setting"
    literal = {name.removeprefix("MFGNET_").lower(): env[name]["value"] for name in names if "value" in env[name]}
    config.Settings(**literal)  # raises on a value the service would refuse at start


def comment_blocks(text: str) -> list[str]:
    """Runs of whole-line ``#`` comments, each joined into one string (inline comments: a block of their own)."""
    blocks: list[list[str]] = [[]]
    for line in text.splitlines():
        stripped = line.strip()
        if stripped.startswith("#"):
            blocks[-1].append(stripped.lstrip("#").strip())
            continue
        blocks.append([line.split(" # ", 1)[1]] if " # " in line else [])
        blocks.append([])
    return [" ".join(block) for block in blocks if block]


@pytest.mark.parametrize("path", [*MANIFESTS, ROOT / "Dockerfile"], ids=lambda p: str(p.relative_to(ROOT)))
def test_comments_pointing_at_deployment_md_name_its_sections(path):
    """A comment that sends the reader to ``docs/DEPLOYMENT.md, "Section"`` names headings that exist."""
    headings = set(re.findall(r"^#+\s+(.+?)\s*$", (ROOT / "docs" / "DEPLOYMENT.md").read_text(), flags=re.MULTILINE))
    for block in comment_blocks(path.read_text()):
        if "DEPLOYMENT.md" not in block:
            continue
        for section in re.findall(r'"([^"]+)"', block):
            assert any(heading == section or heading.startswith(section + " ") for heading in headings), (
                f"{path.name} points at DEPLOYMENT.md section {section!r}; its headings: {sorted(headings)}")


def test_kserve_predictor_speaks_open_inference_protocol_v2():
    isvc = by_kind("InferenceService")
    assert isvc["apiVersion"] == "serving.kserve.io/v1beta1"
    (container,) = isvc["spec"]["predictor"]["containers"]
    assert container["name"] == "kserve-container"
    # A custom predictor declares its protocol through the PROTOCOL variable (KServe's protocolVersion).
    assert {e["name"]: e.get("value") for e in container["env"]}["PROTOCOL"] == "v2"
    assert "storageUri" not in str(isvc), "the models are baked into the image"
