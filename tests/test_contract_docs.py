"""docs/contract.md and docs/asyncapi.yaml stay true to the code.

Each check is a function returning a list of problems (empty: the documents agree with the
code), so that the tests below can also show that a check fails when a document or the code
drifts (a renamed endpoint, setting, method, key or schema file).

Conventions of docs/contract.md that the checks rely on:

* a table row or a line that contains the word "planned" describes something not yet built:
  it must *not* exist in the code (when it does, drop the marker);
* tables are found by their header cells (e.g. ``| method and path | answer |``);
* a table with a ``value`` and a ``code`` column gives the value of the code name in its row;
* it is ordered by interface: its ``##`` chapters are :data:`CHAPTERS`, each ``###`` section is
  numbered under its chapter, and no heading sorts text by when it was added.

It must also name everything the shared contract names (its keys, routes, commands and
settings: :data:`SHARED_KEYS` and the tuples after it).
"""

from __future__ import annotations

import argparse
import json
import math
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any, get_args

import pytest
import yaml
from fastapi.routing import APIRoute
from prometheus_client import generate_latest

from service.api.app import create_app
from service.api.metrics import registry_for
from service.cli import build_parser
from service.correlation import METHODS
from service.engine import Engine, EngineConfig
from service.pipeline.correlation_stage import CadenceParams
from service.pipeline.feed import FeedParams
from service.pipeline.sequencer import SequencerParams
from service.pipeline.tracking_stage import SiteParams
from service.reference import ReferenceParams
from service.settings import Settings
from service.transport.node import ServiceNode
from service.transport.session import DEFAULT_LISTEN, ZenohOptions
from service.wire import models, vocabulary
from service.wire.keys import MODEL_BY_KIND, Keys, classify_key

ROOT = Path(__file__).resolve().parents[1]
CONTRACT = ROOT / "docs" / "contract.md"
ASYNCAPI = ROOT / "docs" / "asyncapi.yaml"
SCHEMAS = ROOT / "schemas"

PREFIX = "fusion"
#: A sample value for every key parameter, distinct so that a swapped parameter shows.
SAMPLE_IDS = {"radar_id": "R1", "source_id": "S1", "radar_a": "A1", "radar_b": "B2"}
SETTING = re.compile(r"TOPOFUSION_[A-Z0-9_]*[A-Z0-9](?![A-Za-z0-9_*])")  # not TOPOFUSION_ENGINE__*
PARAM = re.compile(r"\{([A-Za-z_][A-Za-z0-9_]*)\}")


def planned(text: str) -> bool:
    return "planned" in text.lower()


# -- markdown ------------------------------------------------------------------------------


def split_row(line: str) -> list[str]:
    """The cells of a markdown table row (``\\|`` inside a cell is not a separator)."""
    inner = line.strip()[1:-1] if line.strip().endswith("|") else line.strip()[1:]
    return [c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", inner)]


def tables(text: str) -> Iterator[tuple[list[str], list[tuple[list[str], str]]]]:
    """Every markdown table: its header cells and its rows as ``(cells, raw line)``."""
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        if (
            lines[i].lstrip().startswith("|")
            and i + 1 < len(lines)
            and re.fullmatch(r"\s*\|[\s:|-]+\|?\s*", lines[i + 1])
        ):
            header = [h.lower() for h in split_row(lines[i])]
            rows = []
            i += 2
            while i < len(lines) and lines[i].lstrip().startswith("|"):
                rows.append((split_row(lines[i]), lines[i]))
                i += 1
            yield header, rows
        else:
            i += 1


def rows_of(text: str, *header: str) -> list[tuple[list[str], str]]:
    """The rows of every table whose header starts with ``header``."""
    want = [h.lower() for h in header]
    found = [rows for head, rows in tables(text) if head[: len(want)] == want]
    assert found, f"docs/contract.md has no table with the header {header}"
    return [row for rows in found for row in rows]


# -- HTTP ----------------------------------------------------------------------------------


def app_routes() -> dict[str, set[str]]:
    """Path -> methods of the FastAPI app (routes exist without starting the node)."""
    app = create_app(lambda: None)  # type: ignore[arg-type, return-value]
    routes: dict[str, set[str]] = {}
    for r in app.routes:  # (a path may have a route per method: the probes' HEAD)
        routes.setdefault(r.path, set()).update(getattr(r, "methods", None) or ())  # type: ignore[attr-defined]
    return routes


def api_paths() -> set[str]:
    return {r.path for r in create_app(lambda: None).routes if isinstance(r, APIRoute)}  # type: ignore[arg-type, return-value]


def http_problems(text: str, routes: dict[str, set[str]], api: set[str]) -> list[str]:
    problems = []
    documented = set()
    for cells, line in rows_of(text, "method and path"):
        m = re.match(r"`(GET|POST|PUT|PATCH|DELETE|HEAD) (/[^`?\s]*)", cells[0])
        if m is None:
            problems.append(f"endpoint row without `METHOD /path`: {line}")
            continue
        method, path = m.groups()
        exists = method in routes.get(path, set())
        if planned(line):
            if exists:
                problems.append(f"{method} {path} is implemented: drop its 'planned' marker")
        else:
            documented.add(path)
            if not exists:
                problems.append(f"{method} {path} is in the contract's endpoint table but not in the app")
    problems += [f"endpoint {p} of the app is missing from the contract" for p in sorted(api - documented)]
    return problems


# -- settings, CLI, methods ----------------------------------------------------------------


def settings_problems(text: str) -> list[str]:
    fields = set(Settings.model_fields)
    named: set[str] = set()
    planned_names: set[str] = set()
    for line in text.splitlines():
        for name in SETTING.findall(line):
            (planned_names if planned(line) else named).add(name)
    field = {n: n.removeprefix("TOPOFUSION_").lower() for n in named | planned_names}
    problems = [
        f"{n} is named in the contract but is no Settings field"
        for n in sorted(named)
        if field[n] not in fields
    ]
    problems += [
        f"{n} is a Settings field: drop its 'planned' marker"
        for n in sorted(planned_names - named)
        if field[n] in fields
    ]
    documented = {field[n] for n in named}
    problems += [
        f"setting TOPOFUSION_{f.upper()} is missing from the contract" for f in sorted(fields - documented)
    ]
    return problems


def subcommands() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def cli_problems(text: str) -> list[str]:
    commands = subcommands()
    problems = []
    documented = set()
    for cells, line in rows_of(text, "command", "what it does"):
        m = re.match(r"`topofusion ([a-z-]+)", cells[0])
        if m is None:
            problems.append(f"command row without `topofusion NAME`: {line}")
            continue
        name = m.group(1)
        if planned(line):
            if name in commands:
                problems.append(f"command {name} exists: drop its 'planned' marker")
        else:
            documented.add(name)
            if name not in commands:
                problems.append(f"command {name} is in the contract but not in the CLI")
    problems += [f"command {c} is missing from the contract" for c in sorted(set(commands) - documented)]
    for cells, line in rows_of(text, "flag", "setting", "default"):
        for flag in re.findall(r"--[a-z0-9-]+", cells[0]):
            for command in ("run", "demo"):
                exists = flag in commands[command]._option_string_actions
                if planned(line) and exists:
                    problems.append(f"{command} {flag} exists: drop its 'planned' marker")
                if not planned(line) and not exists:
                    problems.append(f"{command} {flag} is in the contract but not in the CLI")
    for cells, _line in rows_of(text, "command", "flags"):
        command = cells[0].strip("`")
        for flag in re.findall(r"--[a-z0-9-]+", cells[1]):
            if flag not in commands[command]._option_string_actions:
                problems.append(f"{command} {flag} is in the contract but not in the CLI")
    return problems


def method_problems(text: str) -> list[str]:
    line = next((x for x in text.splitlines() if x.startswith("Correlation method names:")), None)
    if line is None:
        return ["the contract has no line 'Correlation method names: ...'"]
    names = re.findall(r"`([^`]+)`", line)
    problems = [
        f"method {n} is in the contract but not in service.correlation.METHODS"
        for n in names
        if n not in METHODS
    ]
    problems += [f"method {m} is missing from the contract" for m in METHODS if m not in names]
    default = re.search(r"`([^`]+)` \(default\)", line)
    if default is None or default.group(1) != Settings.model_fields["method"].default:
        problems.append(f"the default method is {Settings.model_fields['method'].default}")
    return problems


# -- values, reasons, metrics --------------------------------------------------------------

CODE_ROOTS: dict[str, Any] = {
    "models": models,
    "SequencerParams": SequencerParams(),
    "CadenceParams": CadenceParams(),
    "SiteParams": SiteParams(),
    "ReferenceParams": ReferenceParams(),
    "FeedParams": FeedParams(),
}
NUMBER = re.compile(r"-?\d+(?: \d{3})*(?:\.\d+)?")


def value_problems(text: str) -> list[str]:
    problems = []
    checked = 0
    for head, rows in tables(text):
        if "value" not in head or head[-1] != "code":
            continue
        at = head.index("value")
        for cells, line in rows:
            m = re.fullmatch(r"`(\w+)\.([\w.]+)`", cells[-1])
            if m is None or m.group(1) not in CODE_ROOTS:
                problems.append(f"code cell is not `Root.name` of {sorted(CODE_ROOTS)}: {line}")
                continue
            code: Any = CODE_ROOTS[m.group(1)]
            for part in m.group(2).split("."):
                code = getattr(code, part, None)
            number = NUMBER.search(cells[at])
            if code is None or number is None:
                problems.append(f"{cells[-1]}: no such code name, or no number in the value: {line}")
                continue
            doc = number.group().replace(" ", "")
            checked += 1
            same = (
                int(doc) == code
                if isinstance(code, int) and "." not in doc
                else math.isclose(float(doc), float(code))
            )
            if not same:
                problems.append(f"{cells[-1]} is {code!r} in the code, {cells[at]!r} in the contract")
    if checked < 20:
        problems.append(f"only {checked} documented values found (value/code tables lost?)")
    return problems


def reason_problems(text: str) -> list[str]:
    documented = {cells[0].strip("`") for cells, _ in rows_of(text, "reason", "when")}
    reasons = set(get_args(vocabulary.RejectionReason))
    return [f"rejection reason {r} differs between contract and code" for r in sorted(documented ^ reasons)]


def exposed_metrics() -> dict[str, str]:
    node = ServiceNode(EngineConfig(), ZenohOptions())  # never started: no Zenoh session
    exposition = generate_latest(registry_for(node)).decode()
    return dict(re.findall(r"^# TYPE (\S+) (\S+)$", exposition, flags=re.MULTILINE))


def metric_problems(text: str, exposed: dict[str, str]) -> list[str]:
    documented = {cells[0].strip("`"): cells[1] for cells, _ in rows_of(text, "metric", "type")}
    problems = [
        f"metric {m} is in the contract but not exposed" for m in sorted(set(documented) - set(exposed))
    ]
    problems += [
        f"metric {m} is exposed but missing from the contract" for m in sorted(set(exposed) - set(documented))
    ]
    problems += [
        f"metric {m} is a {exposed[m]}, the contract says {t}"
        for m, t in documented.items()
        if m in exposed and exposed[m] != t
    ]
    return problems


# -- AsyncAPI ------------------------------------------------------------------------------


def resolve(doc: dict[str, Any], ref: str) -> Any:
    """A local ``#/a/b`` reference inside ``doc`` (KeyError when it leads nowhere)."""
    node: Any = doc
    for part in ref.removeprefix("#/").split("/"):
        node = node[part.replace("~1", "/").replace("~0", "~")]
    return node


def deref(doc: dict[str, Any], node: Any) -> Any:
    """``node`` with its chain of local ``$ref`` followed."""
    while isinstance(node, dict) and "$ref" in node and str(node["$ref"]).startswith("#"):
        node = resolve(doc, node["$ref"])
    return node


def refs(node: Any) -> Iterator[str]:
    if isinstance(node, dict):
        for key, value in node.items():
            if key == "$ref" and isinstance(value, str):
                yield value
            else:
                yield from refs(value)
    elif isinstance(node, list):
        for value in node:
            yield from refs(value)


def ref_problems(doc: dict[str, Any], base: Path = ASYNCAPI.parent) -> list[str]:
    problems = []
    schema_refs = 0
    for ref in refs(doc):
        if ref.startswith("#"):
            try:
                resolve(doc, ref)
            except (KeyError, TypeError):
                problems.append(f"{ref} leads nowhere in docs/asyncapi.yaml")
            continue
        path = (base / ref.split("#")[0]).resolve()
        if path.parent != SCHEMAS.resolve():
            problems.append(f"{ref} does not point into schemas/")
        elif not path.is_file():
            problems.append(f"{ref}: schemas/{path.name} does not exist")
        else:
            schema_refs += 1
            title = json.loads(path.read_text(encoding="utf-8")).get("title")
            if f"{title}.schema.json" != path.name:
                problems.append(f"{ref}: the schema's title is {title!r}")
    if not schema_refs:
        problems.append("no payload refers to a schema in schemas/")
    return problems


def render(address: str, prefix: str = PREFIX, ids: dict[str, str] | None = None) -> str:
    values = {"prefix": prefix, **(SAMPLE_IDS if ids is None else ids)}
    return PARAM.sub(lambda m: values.get(m.group(1), "{" + m.group(1) + "}"), address)


def built_keys(keys: Keys) -> set[str]:
    """Every key expression the code builds, with the sample ids."""
    s = SAMPLE_IDS
    return {
        keys.site(s["radar_id"]),
        keys.plots(s["radar_id"]),
        keys.ais(s["source_id"]),
        keys.adsb(s["source_id"]),
        keys.tracks(s["radar_id"]),
        keys.pairs(s["radar_a"], s["radar_b"]),
        keys.errors,
        keys.status,
        keys.pairs_all,
        keys.system_tracks,
        keys.performance(s["radar_id"]),
    }


def channel_problems(doc: dict[str, Any]) -> list[str]:
    problems = []
    keys = Keys(PREFIX)
    built = built_keys(keys)
    rendered = {}
    for name, channel in doc["channels"].items():
        address = channel["address"]
        params = set(PARAM.findall(address))
        declared = set(channel.get("parameters", {}))
        if params != declared:
            problems.append(f"channel {name}: parameters {sorted(declared)} != those of {address}")
        if params - {"prefix"} - set(SAMPLE_IDS):
            problems.append(f"channel {name}: unknown parameters in {address}")
        key = rendered[name] = render(address)
        if key not in built:
            problems.append(f"channel {name}: {address} is no key expression service.wire.keys.Keys builds")
        kind = classify_key(key, PREFIX)
        for message in channel.get("messages", {}).values():
            msg = deref(doc, message)
            payload = msg.get("payload")
            if payload is None:
                continue
            stem = Path(payload["$ref"]).name.removesuffix(".schema.json")
            model = MODEL_BY_KIND.get(kind)
            if model is None or model.__name__ != stem:
                problems.append(
                    f"channel {name}: payload {stem} but the key carries {model and model.__name__}"
                )
    if len(set(rendered.values())) != len(rendered):
        problems.append("two channels have the same key expression")
    problems += [f"key {k} the code builds has no channel" for k in sorted(built - set(rendered.values()))]
    return problems


def operation_channels(doc: dict[str, Any], action: str, reply: bool) -> set[str]:
    return {
        resolve(doc, op["channel"]["$ref"])["address"]
        for op in doc["operations"].values()
        if op["action"] == action and ("reply" in op) == reply
    }


def operation_problems(doc: dict[str, Any]) -> list[str]:
    """Operations against what the node subscribes, answers and publishes."""
    node = ServiceNode(EngineConfig(prefix=PREFIX), ZenohOptions())  # never started
    keys = node.keys
    wild = {k: "*" for k in SAMPLE_IDS}
    problems = []
    subscribed = {render(a, ids=wild) for a in operation_channels(doc, "receive", reply=False)}
    if subscribed != set(node._input_keys()):
        problems.append(f"receive operations {sorted(subscribed)} != subscriptions {node._input_keys()}")
    answered = {render(a) for a in operation_channels(doc, "receive", reply=True)}
    performance = keys.performance(SAMPLE_IDS["radar_id"])  # (declared on every radar's key)
    if answered != {keys.status, keys.pairs_all, keys.system_tracks, performance}:
        problems.append(f"request/reply operations {sorted(answered)} != queryables")
    for op in doc["operations"].values():
        if "reply" in op:
            reply_key = render(resolve(doc, op["reply"]["channel"]["$ref"])["address"])
            replies = (
                keys.status,
                keys.system_tracks,
                keys.pairs(SAMPLE_IDS["radar_a"], SAMPLE_IDS["radar_b"]),
                keys.performance(SAMPLE_IDS["radar_id"]),
            )
            if reply_key not in replies:
                problems.append(f"reply channel {reply_key} is not a key the queryables reply on")
    sent = {render(a) for a in operation_channels(doc, "send", reply=False)}
    outputs = {
        keys.tracks(SAMPLE_IDS["radar_id"]),
        keys.pairs(SAMPLE_IDS["radar_a"], SAMPLE_IDS["radar_b"]),
        keys.system_tracks,
        keys.errors,
    }
    if sent != outputs:
        problems.append(f"send operations {sorted(sent)} != the service's outputs {sorted(outputs)}")
    if operation_channels(doc, "send", reply=True):
        problems.append("a send operation has a reply")
    return problems


def engine_output_keys() -> set[str]:
    """The keys a real engine publishes on for a site, a plot batch and a malformed batch."""
    engine = Engine(EngineConfig(prefix=PREFIX))
    keys = engine.keys
    rid = SAMPLE_IDS["radar_id"]
    site = {"radar_id": rid, "latitude_deg": 31.2, "longitude_deg": 118.5}
    batch = {
        "radar_id": rid,
        "seq": 1,
        "time_s": 1763769604.0,
        "plots": {"time_s": [1763769603.5], "range_m": [150000.0], "azimuth_deg": [40.0]},
    }
    out = engine.ingest(keys.site(rid), json.dumps(site).encode())
    out += engine.ingest(keys.plots(rid), json.dumps(batch).encode())
    out += engine.ingest(keys.plots(rid), b"{not json")
    out += engine.flush()  # (a first batch alone is released at the end of the input)
    return {o.key for o in out}


def address_regex(address: str) -> re.Pattern[str]:
    parts = re.split(r"(\{[A-Za-z_]+\})", address)
    body = "".join(
        re.escape(PREFIX)
        if p == "{prefix}"
        else "[A-Za-z0-9_-]{1,64}"
        if PARAM.fullmatch(p)
        else re.escape(p)
        for p in parts
    )
    return re.compile(body)


# -- organisation and the shared contract --------------------------------------------------

#: The top-level chapters of docs/contract.md, in this order: one per interface, not one per
#: round of additions.
CHAPTERS = (
    "1. Zenoh key expressions",
    "2. Payloads",
    "3. HTTP side port",
    "4. Command line",
    "5. Settings",
    "6. Partitioned workers",
    "7. Data time and outputs",
    "8. Operation",
)
FENCE = re.compile(r"^```.*?^```", flags=re.MULTILINE | re.DOTALL)


def organisation_problems(text: str) -> list[str]:
    """The chapters are :data:`CHAPTERS`, each section numbered under its chapter, and no
    heading (nor a bold line standing for one) sorts text by when it was added."""
    headings = re.findall(r"^(#{1,6}) (.+?)\s*$", FENCE.sub("", text), flags=re.MULTILINE)
    chapters = [title for hashes, title in headings if hashes == "##"]
    problems = []
    if chapters != list(CHAPTERS):
        problems.append(f"the chapters are {chapters}, not {list(CHAPTERS)}")
    chapter, section = "", 0
    for hashes, title in headings:
        if hashes == "##":
            chapter, section = title.split(".")[0], 0
        elif hashes == "###":
            section += 1
            if not title.startswith(f"{chapter}.{section} "):
                problems.append(f"section '{title}' is not numbered {chapter}.{section}")
    problems += [f"heading '{t}' sorts by date" for _, t in headings if "addition" in t.lower()]
    problems += [
        f"bold line '{line}' stands for a heading of additions"
        for line in text.splitlines()
        if re.match(r"\*\*Additions?\b", line)
    ]
    return problems


# What the shared contract names: the interface contract TopoFusion shares with the programs
# written against it, which docs/contract.md must say in full (its first paragraph).

#: Every Zenoh key expression of the shared contract, with its payload.
SHARED_KEYS = {
    "{prefix}/radar/{radar_id}/site": "RadarSite",
    "{prefix}/radar/{radar_id}/plots": "PlotBatch",
    "{prefix}/ais/{source_id}/reports": "AisBatch",
    "{prefix}/adsb/{source_id}/reports": "AdsbBatch",
    "{prefix}/radar/{radar_id}/tracks": "TrackBatch",
    "{prefix}/pairs/{radar_a}/{radar_b}": "PairSet",
    "{prefix}/system/tracks": "SystemTrackBatch",
    "{prefix}/errors": "Rejection",
    "{prefix}/status": "Status",
    "{prefix}/pairs/**": "PairSet",
    "{prefix}/radar/{radar_id}/performance": "RadarPerformance",
}
#: Every HTTP route of the shared contract.
SHARED_ROUTES = (
    "GET /healthz",
    "GET /readyz",
    "GET /status",
    "GET /radars",
    "GET /radars/{radar_id}/tracks",
    "GET /radars/{radar_id}/performance",
    "GET /pairs",
    "GET /biases",
    "GET /metrics",
    "GET /system-tracks",
    "GET /picture",
    "GET /openapi.json",
    "GET /docs",
    "GET /redoc",
)
#: Every setting of the shared contract.
SHARED_SETTINGS = (
    "TOPOFUSION_ZENOH_MODE",
    "TOPOFUSION_ZENOH_LISTEN",
    "TOPOFUSION_ZENOH_CONNECT",
    "TOPOFUSION_ZENOH_CONFIG",
    "TOPOFUSION_HTTP_HOST",
    "TOPOFUSION_HTTP_PORT",
    "TOPOFUSION_PREFIX",
    "TOPOFUSION_SITES",
    "TOPOFUSION_METHOD",
    "TOPOFUSION_WINDOW_S",
    "TOPOFUSION_PARTITION",
    "TOPOFUSION_STATE_DIR",
    "TOPOFUSION_API_TOKEN",
)
#: Every command of the shared contract.
SHARED_COMMANDS = ("run", "demo", "simulate", "record", "replay", "evaluate", "schemas", "asterix", "assess")


def shared_problems(text: str) -> list[str]:
    """What the shared contract names and docs/contract.md does not (as built, not planned):
    its keys (with their payloads) in the key table, its routes in the endpoint table, its
    commands in the command table and its settings on some line."""
    keys = {}
    for cells, line in rows_of(text, "key expression", "who writes", "payload"):
        if not planned(line):
            keys[cells[0].strip("`")] = cells[2].strip("`")
    routes = {
        m.group(1)
        for cells, line in rows_of(text, "method and path")
        if not planned(line) and (m := re.match(r"`([A-Z]+ /[^`?\s]*)", cells[0]))
    }
    commands = {
        m.group(1)
        for cells, line in rows_of(text, "command", "what it does")
        if not planned(line) and (m := re.match(r"`topofusion ([a-z-]+)", cells[0]))
    }
    settings = {name for line in text.splitlines() if not planned(line) for name in SETTING.findall(line)}
    problems = [
        f"key {k} ({p}) of the shared contract is not in the key table"
        for k, p in SHARED_KEYS.items()
        if keys.get(k) != p
    ]
    problems += [
        f"route {r} of the shared contract is not in the endpoint table"
        for r in SHARED_ROUTES
        if r not in routes
    ]
    problems += [
        f"command {c} of the shared contract is not in the command table"
        for c in SHARED_COMMANDS
        if c not in commands
    ]
    problems += [
        f"setting {s} of the shared contract is not named" for s in SHARED_SETTINGS if s not in settings
    ]
    return problems


# -- tests ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def contract() -> str:
    return CONTRACT.read_text(encoding="utf-8")


@pytest.fixture(scope="module")
def asyncapi() -> dict[str, Any]:
    doc = yaml.safe_load(ASYNCAPI.read_text(encoding="utf-8"))
    assert isinstance(doc, dict)
    return doc


def test_asyncapi_is_a_3_0_document_with_a_zenoh_server(asyncapi: dict[str, Any]) -> None:
    assert str(asyncapi["asyncapi"]).startswith("3.0.")
    assert asyncapi["info"]["title"] and asyncapi["info"]["version"]
    assert "standard" in asyncapi["info"]["description"].lower()
    servers = asyncapi["servers"]
    assert [s["protocol"] for s in servers.values()] == ["zenoh"]
    (server,) = servers.values()
    assert server["x-zenoh-endpoint"] == DEFAULT_LISTEN
    assert DEFAULT_LISTEN.endswith("/" + server["host"])
    assert {op["action"] for op in asyncapi["operations"].values()} == {"send", "receive"}


def test_asyncapi_refs_resolve_and_schemas_exist(asyncapi: dict[str, Any]) -> None:
    assert ref_problems(asyncapi) == []


def test_asyncapi_channels_are_the_keys_the_code_builds(asyncapi: dict[str, Any]) -> None:
    assert channel_problems(asyncapi) == []


def test_asyncapi_operations_match_the_node(asyncapi: dict[str, Any]) -> None:
    assert operation_problems(asyncapi) == []


def test_asyncapi_send_channels_cover_what_the_engine_publishes(asyncapi: dict[str, Any]) -> None:
    sent = [address_regex(a) for a in operation_channels(asyncapi, "send", reply=False)]
    published = engine_output_keys()
    assert {Keys(PREFIX).tracks(SAMPLE_IDS["radar_id"]), Keys(PREFIX).errors} <= published
    assert [k for k in published if not any(r.fullmatch(k) for r in sent)] == []


def test_asyncapi_parameter_patterns_are_the_code_s(asyncapi: dict[str, Any]) -> None:
    params = asyncapi["components"]["parameters"]
    prefix = Settings.model_json_schema()["properties"]["prefix"]
    assert params["prefix"]["x-pattern"] == prefix["pattern"]
    assert params["prefix"]["default"] == prefix["default"] == PREFIX
    for name in SAMPLE_IDS:
        assert params[name]["x-pattern"] == vocabulary.ID_PATTERN, name
        assert re.fullmatch(params[name]["x-pattern"], params[name]["examples"][0])


def test_contract_keys_are_the_asyncapi_channels(contract: str, asyncapi: dict[str, Any]) -> None:
    channels = {c["address"]: c for c in asyncapi["channels"].values()}
    for cells, line in rows_of(contract, "key expression", "who writes", "payload"):
        address = re.match(r"`([^`]+)`", cells[0])
        assert address is not None, line
        if planned(line):
            assert address.group(1) not in channels, f"{line}: in asyncapi.yaml, so drop 'planned'"
            continue
        assert address.group(1) in channels, line
        channel = channels[address.group(1)]
        # a queryable's payload is that of its replies
        replies = [
            m
            for op in asyncapi["operations"].values()
            if "reply" in op and resolve(asyncapi, op["channel"]["$ref"]) is channel
            for m in op["reply"]["messages"]
        ]
        names = {deref(asyncapi, m)["name"] for m in [*channel["messages"].values(), *replies]}
        assert cells[2].strip("`") in names, line


def test_contract_http_endpoints_exist(contract: str) -> None:
    assert http_problems(contract, app_routes(), api_paths()) == []


def test_contract_settings_exist(contract: str) -> None:
    assert settings_problems(contract) == []


def test_contract_commands_and_flags_exist(contract: str) -> None:
    assert cli_problems(contract) == []


def test_contract_method_names_are_the_code_s(contract: str) -> None:
    assert method_problems(contract) == []


def test_contract_values_are_the_code_s(contract: str) -> None:
    assert value_problems(contract) == []


def test_contract_rejection_reasons_are_the_code_s(contract: str) -> None:
    assert reason_problems(contract) == []


def test_contract_metrics_are_the_exposed_ones(contract: str) -> None:
    assert metric_problems(contract, exposed_metrics()) == []


def test_contract_is_ordered_by_interface(contract: str) -> None:
    assert organisation_problems(contract) == []


def test_contract_names_everything_the_shared_contract_names(contract: str) -> None:
    assert shared_problems(contract) == []


# -- the checks can fail -------------------------------------------------------------------


def test_checks_catch_drift_in_the_contract(contract: str) -> None:
    def broken(old: str, new: str) -> str:
        assert old in contract, old
        return contract.replace(old, new)

    routes, api = app_routes(), api_paths()
    assert http_problems(broken("`GET /healthz`", "`GET /health`"), routes, api)
    assert http_problems(
        broken("| `GET /picture` | 200 HTML", "| `GET /picture` | **planned**: 200 HTML"), routes, api
    )
    assert settings_problems(broken("TOPOFUSION_HTTP_PORT", "TOPOFUSION_HTTP_PRT"))
    marked = "\n".join(
        f"{line} (**planned**)" if "TOPOFUSION_STALL_S" in line else line for line in contract.splitlines()
    )
    assert "TOPOFUSION_STALL_S is a Settings field: drop its 'planned' marker" in settings_problems(marked)
    assert cli_problems(broken("`topofusion schemas`", "`topofusion schema`"))
    assert cli_problems(broken("`--http-port PORT`", "`--http-prt PORT`"))
    assert method_problems(broken("`gmm`, `cfar`.", "`gmm2`, `cfar`."))
    assert value_problems(broken("| 600.0 | `SequencerParams", "| 60.0 | `SequencerParams"))
    assert reason_problems(broken("| `too_large` |", "| `oversized` |"))
    assert metric_problems(broken("`topofusion_tracks`", "`topofusion_track`"), exposed_metrics())
    assert organisation_problems(broken("## 5. Settings", "## 5. Additions (settings)"))
    assert organisation_problems(broken("### 2.9 Status", "### 2.10 Status"))
    swapped = broken("## 7. Data time and outputs", "## 7. Operation").replace(
        "## 8. Operation", "## 8. Data time and outputs"
    )
    assert organisation_problems(swapped)
    assert organisation_problems(contract + "\n**Additions (more).** Something new.\n")
    assert shared_problems(broken("| `{prefix}/errors` |", "| `{prefix}/error` |"))
    assert shared_problems(
        broken(
            "| `{prefix}/status` | service (queryable: answers `get`) | `Status` |",
            "| `{prefix}/status` | service (queryable: answers `get`) | `Stat` |",
        )
    )
    assert shared_problems(broken("| `GET /system-tracks` |", "| `GET /system-track` |"))
    assert shared_problems(broken("| `topofusion assess", "| `topofusion asses"))
    no_token = "\n".join(line for line in contract.splitlines() if "TOPOFUSION_API_TOKEN" not in line)
    assert "setting TOPOFUSION_API_TOKEN of the shared contract is not named" in shared_problems(no_token)


def test_checks_catch_drift_in_the_code(contract: str) -> None:
    routes = app_routes()
    renamed = {("/health" if p == "/healthz" else p): m for p, m in routes.items()}
    assert http_problems(contract, renamed, {("/health" if p == "/healthz" else p) for p in api_paths()})
    exposed = exposed_metrics()
    exposed["topofusion_new_thing"] = exposed.pop("topofusion_uptime_seconds")
    assert metric_problems(contract, exposed)


def test_checks_catch_drift_in_the_asyncapi_document(asyncapi: dict[str, Any]) -> None:
    text = ASYNCAPI.read_text(encoding="utf-8")

    def broken(old: str, new: str) -> dict[str, Any]:
        assert old in text, old
        doc = yaml.safe_load(text.replace(old, new))
        assert isinstance(doc, dict)
        return doc

    assert channel_problems(broken("'{prefix}/radar/{radar_id}/plots'", "'{prefix}/radars/{radar_id}/plots'"))
    assert channel_problems(broken("'{prefix}/ais/{source_id}/reports'", "'{prefix}/ais/{radar_id}/reports'"))
    assert channel_problems(
        broken("$ref: '../schemas/TrackBatch.schema.json'", "$ref: '../schemas/PairSet.schema.json'")
    )
    assert ref_problems(broken("'../schemas/PlotBatch.schema.json'", "'../schemas/Plots.schema.json'"))
    assert ref_problems(broken("'#/components/messages/Status'", "'#/components/messages/State'"))
    assert operation_problems(broken("action: send", "action: receive"))
