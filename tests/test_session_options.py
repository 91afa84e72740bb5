"""Zenoh options: flags over the config file over the defaults (service/transport/session.py)."""

from __future__ import annotations

import json
from pathlib import Path

from service.transport.session import DEFAULT_LISTEN, ZenohOptions, zenoh_config


def _multicast(opts: ZenohOptions) -> bool:
    return bool(json.loads(zenoh_config(opts).get_json("scouting/multicast/enabled")))


def _file(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "zenoh.json5"
    path.write_text(text)
    return path


def test_defaults_without_a_file() -> None:
    opts = ZenohOptions()
    assert (opts.effective_mode, opts.effective_listen(), opts.effective_connect()) == (
        "peer",
        [DEFAULT_LISTEN],
        [],
    )
    conf = zenoh_config(opts)
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert ZenohOptions(default_mode="client").effective_listen() == []


def test_the_files_mode_listen_and_connect_apply_where_no_flag_is_given(tmp_path: Path) -> None:
    path = _file(
        tmp_path,
        '{ mode: "router", listen: { endpoints: ["tcp/127.0.0.1:17001"] },'
        ' connect: { endpoints: ["tcp/127.0.0.1:17002"] } }',
    )
    opts = ZenohOptions(config_file=path)
    assert opts.effective_mode == "router"
    assert opts.effective_listen() == ["tcp/127.0.0.1:17001"]
    assert opts.effective_connect() == ["tcp/127.0.0.1:17002"]
    flags = ZenohOptions(
        mode="peer", listen=("tcp/127.0.0.1:17003",), connect=("tcp/127.0.0.1:17004",), config_file=path
    )
    assert flags.effective_mode == "peer"
    assert flags.effective_listen() == ["tcp/127.0.0.1:17003"]
    assert flags.effective_connect() == ["tcp/127.0.0.1:17004"]


def test_multicast_scouting_is_off_unless_the_file_sets_it(tmp_path: Path) -> None:
    # "multicast" appears in the text but sets nothing: still off
    mentions = _file(tmp_path, '{ // multicast scouting: leave as is\n mode: "peer" }')
    assert (
        json.loads(zenoh_config(ZenohOptions(config_file=mentions)).get_json("scouting/multicast/enabled"))
        is False
    )
    sets = _file(tmp_path, "{ scouting: { multicast: { enabled: true } } }")
    assert (
        json.loads(zenoh_config(ZenohOptions(config_file=sets)).get_json("scouting/multicast/enabled"))
        is True
    )
