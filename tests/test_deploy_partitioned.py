"""The partitioned deployments, checked statically (no Docker engine, no cluster).

deploy/compose.partitioned.yml (a router, workers 1/N..N/N, the simulator),
deploy/kubernetes/topofusion-partitioned.yaml (a StatefulSet whose pod ordinal gives K) and
deploy/kubernetes/zenoh-router-mesh.yaml with deploy/zenoh/router-site-*.json5 (two sites, two
meshed routers, workers at each).  As in test_container.py: the files lint and parse, and every
command, flag, setting, path and port they name exists in the code.  On top: the workers'
partitions cover 1..N exactly once with one N, and the StatefulSets' shell commands, expanded
the way Kubernetes expands ``$(VAR)`` and run by ``sh`` for each pod ordinal, start
``topofusion run --partition K/N`` with those partitions.
"""

from __future__ import annotations

import functools
import json
import os
import re
import shutil
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest
import yaml
import zenoh

from service.settings import Settings
from tests.support import free_port
from tests.test_container import (
    LAB_COMMANDS,
    LAB_DOCKERFILE,
    _check_cli,
    _compose_resolved,
    _dockerfile_instructions,
    _settings_env_names,
    _tool,
    build_app_paths,
)

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = ROOT / "deploy" / "compose.partitioned.yml"
KUBE = ROOT / "deploy" / "kubernetes"
PARTITIONED = KUBE / "topofusion-partitioned.yaml"
MESH = KUBE / "zenoh-router-mesh.yaml"
SITE_CONFIGS = {
    "a": ROOT / "deploy" / "zenoh" / "router-site-a.json5",
    "b": ROOT / "deploy" / "zenoh" / "router-site-b.json5",
}
NEW_FILES = (COMPOSE, PARTITIONED, MESH, *SITE_CONFIGS.values())
POD_INDEX_FIELD = "metadata.labels['apps.kubernetes.io/pod-index']"
ZENOH_PORT = 7447


def _partition(value: str) -> tuple[int, int]:
    """``K/N`` as the contract writes it (worker K of N, 1 <= K <= N)."""
    match = re.fullmatch(r"(\d+)/(\d+)", value)
    assert match, f"partition {value!r} is not K/N"
    k, n = int(match[1]), int(match[2])
    assert 1 <= k <= n, f"partition {value!r}: K must be in 1..N"
    return k, n


def _assert_cover(partitions: list[tuple[int, int]], where: str) -> int:
    """Every K of 1..N exactly once, all with the same N; returns N."""
    assert partitions, f"{where}: no partitioned worker"
    ns = {n for _, n in partitions}
    assert len(ns) == 1, f"{where}: workers disagree on N: {sorted(partitions)}"
    (n,) = ns
    ks = sorted(k for k, _ in partitions)
    assert ks == list(range(1, n + 1)), f"{where}: K must cover 1..{n} exactly once, got {ks}"
    return n


def _flag(argv: list[str], name: str) -> str | None:
    for i, arg in enumerate(argv):
        if arg == name and i + 1 < len(argv):
            return argv[i + 1]
        if arg.startswith(name + "="):
            return arg.split("=", 1)[1]
    return None


def _port(endpoint: str) -> int:
    return int(endpoint.rsplit(":", 1)[1])


def test_settings_named_in_the_new_files_exist() -> None:
    known = _settings_env_names()
    for path in NEW_FILES:
        for name in set(re.findall(r"TOPOFUSION_[A-Z0-9_]+", path.read_text())):
            assert name in known, f"{path.relative_to(ROOT)} names unknown setting {name}"


# --- compose -------------------------------------------------------------------------------


def test_compose_config_is_valid() -> None:
    res = subprocess.run(
        [_tool("docker-compose"), "-f", str(COMPOSE), "config", "-q"],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert res.returncode == 0, res.stdout + res.stderr


@functools.cache
def _compose_model() -> dict[str, Any]:
    """The compose file as compose resolves it: anchors merged, paths absolute, ports parsed."""
    return _compose_resolved(COMPOSE)


def _compose_workers() -> dict[str, dict[str, Any]]:
    return {n: s for n, s in _compose_model()["services"].items() if s.get("command", [""])[0] == "run"}


def _compose_partition(svc: dict[str, Any]) -> str:
    """The flag wins over the setting, as in the service."""
    value = _flag(svc["command"], "--partition") or svc.get("environment", {}).get("TOPOFUSION_PARTITION")
    assert value, "a worker without a partition runs as 1/1 and duplicates the others"
    return str(value)


def test_compose_partitions_cover_one_to_n() -> None:
    workers = _compose_workers()
    parts = {name: _partition(_compose_partition(svc)) for name, svc in workers.items()}
    n = _assert_cover(list(parts.values()), COMPOSE.name)
    assert n == 3
    for name, (k, _) in parts.items():
        assert name == f"worker-{k}", f"{name} runs partition {k}"


def test_compose_workers_share_one_definition() -> None:
    raw = yaml.safe_load(COMPOSE.read_text())
    assert "x-worker" in raw, "the worker is defined once (x-worker) and reused"

    def differences_removed(svc: dict[str, Any]) -> dict[str, Any]:
        svc = json.loads(json.dumps(svc))
        svc.get("environment", {}).pop("TOPOFUSION_PARTITION", None)
        svc.pop("ports", None)
        svc.pop("volumes", None)
        return svc

    workers = list(_compose_workers().values())
    assert all(differences_removed(w) == differences_removed(workers[0]) for w in workers)
    # what differs: the partition, the host port, and the state volume (a state file is one
    # partition's: a worker refuses another's)
    state = [
        v["source"]
        for w in workers
        for v in w["volumes"]
        if v["target"] == w["environment"]["TOPOFUSION_STATE_DIR"]
    ]
    assert len(state) == len(set(state)) == len(workers)


def test_compose_names_only_what_exists() -> None:
    services = _compose_model()["services"]
    router = services["router"]
    assert router["image"].startswith("eclipse/zenoh:")
    assert router["command"][0].startswith("-"), "the eclipse/zenoh image takes zenohd arguments only"
    [config] = [Path(v["source"]) for v in router["volumes"] if v["source"].endswith(".json5")]
    conf = zenoh.Config.from_file(str(config))  # exists and parses as a Zenoh config
    assert {_port(e) for e in json.loads(conf.get_json("listen/endpoints"))} == {ZENOH_PORT}
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    known = _settings_env_names()
    for name, svc in services.items():
        if name == "router":
            continue
        command = svc["command"]
        _check_cli(command)
        build = svc["build"]
        assert Path(build["context"]) == ROOT, f"{name}: build from the checkout's root"
        assert (ROOT / build["dockerfile"]).exists()
        if command[0] in LAB_COMMANDS:
            assert build["dockerfile"] == LAB_DOCKERFILE, f"{name} runs {command[0]} without the lab"
        env = svc.get("environment", {})
        assert set(env) <= known, f"{name} sets unknown settings {set(env) - known}"
        endpoints = [env.get("TOPOFUSION_ZENOH_CONNECT", ""), _flag(command, "--connect")]
        assert f"tcp/router:{ZENOH_PORT}" in endpoints, f"{name} does not connect to router"
        assert "client" in (env.get("TOPOFUSION_ZENOH_MODE"), _flag(command, "--mode"))


def test_compose_simulates_a_lab_scenario() -> None:
    from topofusion_lab.scenarios.catalog import SCENARIOS

    [sim] = [s for s in _compose_model()["services"].values() if s["command"][0] == "simulate"]
    assert _flag(sim["command"], "--scenario") in SCENARIOS


def test_compose_workers_parse_and_serve_http_on_distinct_host_ports() -> None:
    published = []
    for name, svc in _compose_workers().items():
        _check_cli([*svc["command"], "--partition", _compose_partition(svc)])
        env = svc["environment"]
        assert env["TOPOFUSION_HTTP_HOST"] == "0.0.0.0", f"{name}: HTTP unreachable from outside"
        http_port = int(env.get("TOPOFUSION_HTTP_PORT", Settings().http_port))
        [port] = svc["ports"]
        assert port["target"] == http_port, f"{name} publishes {port['target']}, serves {http_port}"
        published.append(int(port["published"]))
    assert sorted(published) == [8001, 8002, 8003]


# --- Kubernetes ----------------------------------------------------------------------------


@functools.cache
def _docs(path: Path) -> tuple[dict[str, Any], ...]:
    return tuple(d for d in yaml.safe_load_all(path.read_text()) if d is not None)


@pytest.mark.parametrize("path", [PARTITIONED, MESH], ids=lambda p: p.name)
def test_every_document_has_apiversion_kind_and_name(path: Path) -> None:
    docs = _docs(path)
    assert docs
    for doc in docs:
        assert isinstance(doc, dict) and doc.get("apiVersion") and doc.get("kind"), doc
        assert doc["metadata"]["name"]


def _kubernetes_expand(text: str, env: dict[str, str]) -> str:
    """Kubernetes' expansion of ``$(VAR)`` in command and args: ``$$`` is ``$``, an unknown name
    is left as written (k8s.io/kubernetes third_party/forked/golang/expansion)."""
    out, i = [], 0
    while i < len(text):
        if text[i] == "$" and i + 1 < len(text):
            nxt = text[i + 1]
            close = text.find(")", i + 2) if nxt == "(" else -1
            if nxt == "$":
                out.append("$")
                i += 2
            elif close != -1:
                name = text[i + 2 : close]
                out.append(env.get(name, f"$({name})"))
                i = close + 1
            else:
                out.append(text[i : i + 2])
                i += 2
        else:
            out.append(text[i])
            i += 1
    return "".join(out)


def test_kubernetes_expansion_model() -> None:
    env = {"A": "1"}
    assert _kubernetes_expand("$(A) $$(A) $((A + 1)) $(B) $(", env) == "1 $(A) $((A + 1)) $(B) $("


@pytest.fixture
def stub_topofusion(tmp_path: Path) -> Path:
    """A directory holding a ``topofusion`` that prints its arguments, one a line."""
    stub = tmp_path / "topofusion"
    stub.write_text('#!/bin/sh\nfor a in "$@"; do printf "%s\\n" "$a"; done\n')
    stub.chmod(0o755)
    return tmp_path


def _worker_container(statefulset: dict[str, Any]) -> dict[str, Any]:
    [container] = statefulset["spec"]["template"]["spec"]["containers"]
    return container


def _started_argv(container: dict[str, Any], pod_index: str | None, stub_dir: Path) -> list[str] | None:
    """What the container starts for one pod ordinal: its command, expanded by Kubernetes, then
    run by ``sh``; the argv of ``topofusion``, or None if the command fails before it."""
    env = {e["name"]: str(e["value"]) for e in container.get("env", []) if "value" in e}
    if pod_index is not None:
        env["POD_INDEX"] = pod_index  # what the downward API gives
    argv = [_kubernetes_expand(a, env) for a in [*container["command"], *container.get("args", [])]]
    sh = shutil.which("sh")
    assert sh, "no sh to run the command with"
    assert argv[0] == "sh", "a shell works out K from the ordinal"
    res = subprocess.run(
        [sh, *argv[1:]],
        env={**env, "PATH": f"{stub_dir}{os.pathsep}{os.defpath}"},
        capture_output=True,
        text=True,
        timeout=10,
    )
    if res.returncode != 0:
        return None
    return res.stdout.splitlines()


def _statefulsets(path: Path) -> list[dict[str, Any]]:
    return [d for d in _docs(path) if d["kind"] == "StatefulSet"]


def _statefulset_partitions(ss: dict[str, Any], stub_dir: Path) -> list[tuple[int, int]]:
    container = _worker_container(ss)
    out = []
    for index in range(ss["spec"]["replicas"]):
        argv = _started_argv(container, str(index), stub_dir)
        assert argv is not None, f"pod {index} does not start"
        assert argv[0] == "run"
        value = _flag(argv, "--partition")
        assert value, f"pod {index} starts without --partition: {argv}"
        out.append(_partition(value))
    return out


def test_statefulset_n_equals_replicas(stub_topofusion: Path) -> None:
    [ss] = _statefulsets(PARTITIONED)
    n = _assert_cover(_statefulset_partitions(ss, stub_topofusion), PARTITIONED.name)
    assert n == ss["spec"]["replicas"] == 3


def test_mesh_partitions_cover_one_to_n_across_sites(stub_topofusion: Path) -> None:
    sets = _statefulsets(MESH)
    assert {ss["metadata"]["namespace"] for ss in sets} == {"topofusion-site-a", "topofusion-site-b"}
    parts = [p for ss in sets for p in _statefulset_partitions(ss, stub_topofusion)]
    assert _assert_cover(parts, MESH.name) == 2


@pytest.mark.parametrize("path", [PARTITIONED, MESH], ids=lambda p: p.name)
def test_statefulset_commands_name_only_what_exists(path: Path, stub_topofusion: Path) -> None:
    for ss in _statefulsets(path):
        container = _worker_container(ss)
        for index in range(ss["spec"]["replicas"]):
            argv = _started_argv(container, str(index), stub_topofusion)
            assert argv is not None
            _check_cli(argv)
        names = {e["name"] for e in container["env"]}
        assert {n for n in names if n.startswith("TOPOFUSION_")} <= _settings_env_names()


@pytest.mark.parametrize("path", [PARTITIONED, MESH], ids=lambda p: p.name)
def test_pod_index_comes_from_the_downward_api(path: Path, stub_topofusion: Path) -> None:
    for ss in _statefulsets(path):
        container = _worker_container(ss)
        [pod_index] = [e for e in container["env"] if e["name"] == "POD_INDEX"]
        assert pod_index["valueFrom"]["fieldRef"]["fieldPath"] == POD_INDEX_FIELD
        # without the label (Kubernetes < 1.28) the pod fails instead of running partition 1 twice
        assert _started_argv(container, None, stub_topofusion) is None
        assert _started_argv(container, "", stub_topofusion) is None


def test_the_image_has_the_shell_the_commands_need() -> None:
    """``command`` replaces the image's ENTRYPOINT (topofusion); ``sh`` must be in the image."""
    ins = _dockerfile_instructions()
    final_from = [r for w, r in ins if w == "FROM"][-1]
    assert re.fullmatch(r"python:[\d.]+-slim(-\w+)?", final_from), "a Debian base with /bin/sh"
    assert json.loads(next(r for w, r in reversed(ins) if w == "ENTRYPOINT")) == ["topofusion"]


def _grace_period_of_the_single_worker() -> int:
    [dep] = [
        d
        for d in _docs(KUBE / "topofusion.yaml")
        if d["kind"] == "Deployment" and d["metadata"]["name"] == "topofusion"
    ]
    return int(dep["spec"]["template"]["spec"]["terminationGracePeriodSeconds"])


def _in_namespace(path: Path, namespace: str | None) -> list[dict[str, Any]]:
    return [
        d for d in _docs(path) if d["metadata"].get("namespace") == namespace and d["kind"] != "Namespace"
    ]


def _namespaces(path: Path) -> list[str | None]:
    return sorted({d["metadata"].get("namespace") for d in _statefulsets(path)}, key=str)


@pytest.mark.parametrize("path", [PARTITIONED, MESH], ids=lambda p: p.name)
def test_workers_probes_ports_services_and_router(path: Path) -> None:
    app = build_app_paths()
    for namespace in _namespaces(path):
        docs = _in_namespace(path, namespace)
        [ss] = [d for d in docs if d["kind"] == "StatefulSet"]
        pod = ss["spec"]["template"]["spec"]
        container = _worker_container(ss)
        env = {e["name"]: e.get("value") for e in container["env"]}
        http_port = int(env.get("TOPOFUSION_HTTP_PORT") or Settings().http_port)
        assert env["TOPOFUSION_HTTP_HOST"] == "0.0.0.0"
        named = {p.get("name"): p["containerPort"] for p in container["ports"]}
        assert list(named.values()) == [http_port]
        for probe, path_ in (("livenessProbe", "/healthz"), ("readinessProbe", "/readyz")):
            get = container[probe]["httpGet"]
            assert get["path"] == path_ and path_ in app
            assert named.get(get["port"], get["port"]) == http_port, f"{probe} port"
        assert pod["terminationGracePeriodSeconds"] == _grace_period_of_the_single_worker()
        assert pod["securityContext"]["runAsNonRoot"] is True
        assert {"cpu", "memory"} <= set(container["resources"]["requests"])
        services = {d["metadata"]["name"]: d for d in docs if d["kind"] == "Service"}
        headless = services[ss["spec"]["serviceName"]]
        labels = ss["spec"]["template"]["metadata"]["labels"]
        assert headless["spec"]["clusterIP"] == "None"
        assert headless["spec"]["selector"] == ss["spec"]["selector"]["matchLabels"] == labels
        assert [p["targetPort"] for p in headless["spec"]["ports"]] == [http_port]
        # the workers reach their own (local) router by Service name and the zenohd port
        assert env["TOPOFUSION_ZENOH_MODE"] == "client"
        assert env["TOPOFUSION_ZENOH_CONNECT"] == f"tcp/router:{ZENOH_PORT}"
        assert [p["port"] for p in services["router"]["spec"]["ports"]] == [ZENOH_PORT]
        config = _router_config(docs)
        assert ZENOH_PORT in {_port(e) for e in json.loads(config.get_json("listen/endpoints"))}
        assert json.loads(config.get_json("scouting/multicast/enabled")) is False


def _router_config(docs: list[dict[str, Any]]) -> zenoh.Config:
    [router] = [d for d in docs if d["kind"] == "Deployment" and d["metadata"]["name"] == "zenoh-router"]
    [zenohd] = router["spec"]["template"]["spec"]["containers"]
    assert zenohd["image"].startswith("eclipse/zenoh:") and zenohd["args"][0].startswith("-")
    [volume] = router["spec"]["template"]["spec"]["volumes"]
    [cm] = [
        d for d in docs if d["kind"] == "ConfigMap" and d["metadata"]["name"] == volume["configMap"]["name"]
    ]
    [mount] = zenohd["volumeMounts"]
    [key] = cm["data"]
    assert zenohd["args"] == ["--config", f"{mount['mountPath']}/{key}"]
    return zenoh.Config.from_json5(cm["data"][key])


def test_partitioned_manifest_router_is_the_single_worker_manifests() -> None:
    """Same router objects as topofusion.yaml: applying either manifest leaves one router."""

    def router_objects(path: Path) -> list[dict[str, Any]]:
        return [d for d in _docs(path) if d["metadata"]["name"] in ("zenohd", "zenoh-router", "router")]

    assert router_objects(PARTITIONED) == router_objects(KUBE / "topofusion.yaml")
    single = {(d["kind"], d["metadata"]["name"]) for d in _docs(KUBE / "topofusion.yaml")}
    workers = {(d["kind"], d["metadata"]["name"]) for d in _docs(PARTITIONED)} - {
        (d["kind"], d["metadata"]["name"]) for d in router_objects(PARTITIONED)
    }
    assert not workers & single, "the worker objects must not overwrite the single worker's"


# --- the two-site router mesh --------------------------------------------------------------


@pytest.mark.parametrize("path", sorted(ROOT.glob("deploy/**/*.json5")), ids=lambda p: p.name)
def test_every_router_config_file_loads(path: Path) -> None:
    conf = zenoh.Config.from_file(str(path))
    assert json.loads(conf.get_json("mode")) == "router"
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False


def _config_file(site: str) -> zenoh.Config:
    return zenoh.Config.from_file(str(SITE_CONFIGS[site]))


def _get(conf: zenoh.Config, key: str) -> Any:
    return json.loads(conf.get_json(key))


def test_site_b_router_connects_to_site_a() -> None:
    a, b = _config_file("a"), _config_file("b")
    assert _get(a, "connect/endpoints") == [], "site A only listens"
    [endpoint] = _get(b, "connect/endpoints")
    assert _port(endpoint) in {_port(e) for e in _get(a, "listen/endpoints")}
    assert _get(b, "connect/exit_on_failure") is False, "site B's router outlives an outage of A"
    assert _get(b, "connect/timeout_ms") == -1


def test_mesh_manifest_routers_are_the_config_files() -> None:
    """The ConfigMaps hold the files' configuration, but for the address of site A's router."""
    namespaces = {"a": "topofusion-site-a", "b": "topofusion-site-b"}
    for site, namespace in namespaces.items():
        docs = _in_namespace(MESH, namespace)
        assert all(d["metadata"]["labels"]["site"] == site for d in docs), "kubectl apply -l site=..."
        config, file = _router_config(docs), _config_file(site)
        for key in ("mode", "listen/endpoints", "scouting/multicast/enabled", "connect/timeout_ms"):
            assert _get(config, key) == _get(file, key), f"site {site}: {key}"
        assert _get(config, "connect/exit_on_failure") == _get(file, "connect/exit_on_failure")
        assert [_port(e) for e in _get(config, "connect/endpoints")] == [
            _port(e) for e in _get(file, "connect/endpoints")
        ]
    namespace_labels = {
        d["metadata"]["name"]: d["metadata"]["labels"]["site"]
        for d in _docs(MESH)
        if d["kind"] == "Namespace"
    }
    assert namespace_labels == {v: k for k, v in namespaces.items()}
    [endpoint] = _get(_router_config(_in_namespace(MESH, namespaces["b"])), "connect/endpoints")
    host = endpoint.split("/", 1)[1].rsplit(":", 1)[0]
    assert host.split(".")[:2] == ["router", namespaces["a"]], "site B connects to site A's router Service"


def test_mesh_routes_between_sites_on_loopback() -> None:
    """The two site configurations, moved onto loopback ports: a put by a client of router A
    reaches a subscriber that is a client of router B."""
    port_a, port_b = free_port(), free_port()
    conf_a, conf_b = _config_file("a"), _config_file("b")
    conf_a.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port_a}"]))
    conf_b.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port_b}"]))
    conf_b.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port_a}"]))

    def client(port: int) -> zenoh.Session:
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        return zenoh.open(conf)

    sessions = [zenoh.open(conf_a), zenoh.open(conf_b)]
    try:
        sessions += [client(port_a), client(port_b)]
        at_a, at_b = sessions[2], sessions[3]
        received: list[str] = []
        at_b.declare_subscriber("fusion/radar/**", lambda s: received.append(str(s.key_expr)))

        deadline = time.monotonic() + 15.0
        while not received and time.monotonic() < deadline:  # until the routers have met
            at_a.put("fusion/radar/A/tracks", b"{}")
            time.sleep(0.2)
        assert set(received) == {"fusion/radar/A/tracks"}
    finally:
        for session in reversed(sessions):
            session.close()
