"""One settings root (service/settings.py, the engine's part service/config.py): file,
environment and flags, validated at start."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from dataclasses import fields, is_dataclass
from pathlib import Path

import pytest
from pydantic import ValidationError

from service.cli.common import setup_logging
from service.cli.serve import api_token
from service.config import (
    SIGNED_PARAMETERS,
    ConfigError,
    EngineConfig,
    as_dict,
    engine_config_from,
    from_environment,
    load_file,
)
from service.engine import Engine
from service.pipeline.partition import Partition
from service.settings import REDACTED, Settings, engine_config, flag_overrides
from service.startup import start_engine
from service.transport.options import NodeOptions
from tests.scenario_helpers import scenario_messages


def test_defaults_round_trip_through_their_printed_form() -> None:
    assert engine_config_from(as_dict(EngineConfig())) == EngineConfig()
    assert engine_config_from({}) == EngineConfig()


@pytest.mark.parametrize("suffix", [".toml", ".yaml", ".json"])
def test_a_file_sets_any_parameter(tmp_path: Path, suffix: str) -> None:
    text = {
        ".toml": "[cadence]\ncadence_scans = 2.0\n[correlation.svd]\nalpha_position = 0.01\n"
        "[tracking.bounds]\nmax_window_plots = 1234\n",
        ".yaml": "cadence: {cadence_scans: 2.0}\ncorrelation: {svd: {alpha_position: 0.01}}\n"
        "tracking: {bounds: {max_window_plots: 1234}}\n",
        ".json": json.dumps(
            {
                "cadence": {"cadence_scans": 2.0},
                "correlation": {"svd": {"alpha_position": 0.01}},
                "tracking": {"bounds": {"max_window_plots": 1234}},
            }
        ),
    }[suffix]
    path = tmp_path / f"engine{suffix}"
    path.write_text(text)
    config = engine_config(Settings(config=path))
    assert config.cadence.cadence_scans == 2.0
    assert config.correlation.svd.alpha_position == 0.01
    assert config.tracking.bounds.max_window_plots == 1234
    assert config.sequencer == EngineConfig().sequencer  # the rest keeps its defaults


def test_environment_over_file_and_flags_over_both(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "engine.toml"
    path.write_text('method = "nearest"\n[sequencer]\nmax_clock_skew_s = 60.0\nmax_lag_s = 5.0\n')
    monkeypatch.setenv("TOPOFUSION_ENGINE__SEQUENCER__MAX_CLOCK_SKEW_S", "120")
    config = engine_config(Settings(config=path))
    assert config.sequencer.max_clock_skew_s == 120.0 and config.sequencer.max_lag_s == 5.0
    assert config.method == "nearest"  # the file's: no flag or setting given
    assert engine_config(Settings(config=path, method="gmm")).method == "gmm"  # a flag wins


@pytest.mark.parametrize(
    ("data", "named"),
    [
        ({"correlation": {"svd": {"alpha_postion": 0.1}}}, "correlation.svd.alpha_postion: unknown key"),
        ({"cadence": {"cadence_scans": "often"}}, "cadence.cadence_scans"),
        ({"sequencer": 3}, "sequencer"),
        ({"nonsense": {}}, "nonsense: unknown key"),
        # values a parameter cannot take: each named, before the engine divides by them
        ({"cadence": {"bias_interval_s": 0}}, "cadence.bias_interval_s: Input should be greater than 0"),
        ({"cadence": {"system_interval_s": -2}}, "cadence.system_interval_s"),
        ({"sequencer": {"max_lag_s": -5}}, "sequencer.max_lag_s"),
        ({"sequencer": {"max_sources": 0}}, "sequencer.max_sources"),
        ({"feed": {"stale_s": -1}}, "feed.stale_s"),
        ({"cadence": {"bias_lag_s": float("nan")}}, "cadence.bias_lag_s: must be a finite number"),
        (
            {"tracking": {"manager": {"coast_scans": float("inf")}}},
            "tracking.manager.coast_scans: must be a finite",
        ),
    ],
)
def test_errors_name_the_key(data: dict[str, object], named: str) -> None:
    with pytest.raises(ConfigError, match=named.replace(".", r"\.")):
        engine_config_from(data)


#: Parameters a value of which made every batch fail in the tracker or the correlation, or the
#: engine refuse to start without naming them (a probe of every number at 0 and -1 on a
#: three-radar stream): now refused at start, each named.
FAILED_AT = [
    ("tracking.logic.support_radius_m", 0),
    ("tracking.noise.min_samples", 0),
    ("tracking.filter.quiet_sojourn_s", 0),
    ("tracking.manager.confirm_m", 0),
    ("tracking.manager.confirm_m", 6),  # above confirm_n (5)
    ("tracking.manager.confirmed_misses_cap", 2),  # below confirmed_max_misses (3)
    ("tracking.manager.detection_memory_scans", 0),
    ("tracking.manager.confirm_n", 31),
    ("correlation.book.window", 0),
    ("correlation.book.window", 33),
    ("correlation.registration.prior_range_m", 0),
    ("correlation.registration.prior_range_gain_ppm", 0),
    ("correlation.registration.prior_time_bias_s", 0),
    ("correlation.registration.max_rows_per_update", 0),
    ("correlation.registration.registered_rows_per_update", 0),
    ("correlation.svd.prior_scale_sigma", 0),
    ("correlation.group.max_votes", 0),
    ("sequencer.max_clock_skew_s", -1),
    ("tracking.revisit.neighbours", -1),
    ("tracking.noise.max_samples", -1),
]


def _nested(key: str, value: object) -> dict[str, object]:
    """The whole default tree (a section may need all its fields) with ``key`` set."""
    data = as_dict(EngineConfig())
    d = data
    *path, last = key.split(".")
    for k in path:
        d = d[k]
    d[last] = value
    return data


def _numbers(obj: object, path: str = "") -> list[str]:
    out = []
    for f in fields(obj):  # type: ignore[arg-type]
        value = getattr(obj, f.name)
        if is_dataclass(value):
            out += _numbers(value, f"{path}{f.name}.")
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            out.append(f"{path}{f.name}")
    return out


@pytest.mark.parametrize(("key", "value"), FAILED_AT)
def test_values_that_made_every_batch_fail_are_refused_at_start_naming_the_key(key: str, value: int) -> None:
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        engine_config_from(_nested(key, value))


def test_no_engine_number_but_the_signed_ones_may_be_negative() -> None:
    """Every number of the tree at -1 is refused naming its key, but those documented signed;
    and each of these is taken below zero."""
    keys = [k for k in _numbers(EngineConfig()) if not k.startswith("partition.")]
    assert len(keys) > 200 and set(keys) >= SIGNED_PARAMETERS
    for key in keys:
        if key in SIGNED_PARAMETERS:
            engine_config_from(_nested(key, -1.0))
        else:
            # (named by its key, or by its field where its section checks it: ``assessment``)
            with pytest.raises(ConfigError, match=key.rsplit(".", 1)[-1]):
                engine_config_from(_nested(key, -1))


def test_environment_values_are_json_or_strings() -> None:
    env = {"TOPOFUSION_ENGINE__CADENCE__CADENCE_SCANS": "2", "TOPOFUSION_ENGINE__METHOD": "gmm", "OTHER": "x"}
    assert from_environment(env) == {"cadence": {"cadence_scans": 2}, "method": "gmm"}


def test_unreadable_files_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not found"):
        load_file(tmp_path / "missing.toml")
    bad = tmp_path / "engine.ini"
    bad.write_text("x=1")
    with pytest.raises(ConfigError, match=r"\.toml"):
        load_file(bad)
    broken = tmp_path / "engine.toml"
    broken.write_text("[cadence\n")
    with pytest.raises(ConfigError, match="cannot be read"):
        load_file(broken)


def test_parameters_reach_the_stages() -> None:
    """Each section is the one its stage uses: a window cap of 40 plots in the trackers, a
    registration threshold in the pair correlators, a cadence of three scans."""
    stream = scenario_messages("two-radar", duration_s=40.0)
    capped = Engine(engine_config_from({"tracking": {"bounds": {"max_window_plots": 40}}}))
    tuned = Engine(
        engine_config_from(
            {"correlation": {"registration": {"min_pairs": 7}}, "cadence": {"cadence_scans": 3.0}}
        )
    )
    for key, payload in stream:
        capped.ingest(key, payload)
        tuned.ingest(key, payload)
    radars = capped.snapshot().status_core()["radars"]
    assert all(r["window_plots"] <= 40 and r["window_evicted"] > 0 for r in radars)
    (corr,) = tuned.pair_correlators()
    assert corr.params.registration.min_pairs == 7
    assert tuned.correlation.stage.params.cadence_scans == 3.0  # type: ignore[attr-defined]


def test_config_show_prints_the_effective_tree_and_refuses_bad_keys(tmp_path: Path) -> None:
    cli = [sys.executable, "-m", "service", "config"]
    shown = subprocess.run([*cli, "--show", "--format", "json"], capture_output=True, text=True, check=True)
    engine = as_dict(EngineConfig())
    assert {k: v for k, v in json.loads(shown.stdout).items() if k in engine} == engine
    bad = tmp_path / "engine.yaml"
    bad.write_text("tracking: {filter: {process_noise_psd: -x}}\n")
    run = subprocess.run([*cli, "--config", str(bad)], capture_output=True, text=True, check=False)
    assert run.returncode == 2 and "tracking.filter.process_noise_psd" in run.stderr


# -- the settings root: one precedence for settings and engine parameters ----------------------


@pytest.fixture
def clean_env(monkeypatch: pytest.MonkeyPatch) -> pytest.MonkeyPatch:
    """No TOPOFUSION_* variable of the machine running the tests."""
    import os

    for name in list(os.environ):
        if name.upper().startswith("TOPOFUSION_"):
            monkeypatch.delenv(name)
    return monkeypatch


def test_one_precedence_file_engine_variables_settings_flags(
    tmp_path: Path, clean_env: pytest.MonkeyPatch
) -> None:
    """defaults < file < TOPOFUSION_ENGINE__* < TOPOFUSION_* < flags, for a setting that is an
    engine parameter too, read under either name; the engine takes the setting's value."""
    path = tmp_path / "topofusion.toml"
    path.write_text('method = "nearest"\nqueue_size = 7\n[sequencer]\nmax_lag_s = 5.0\n')
    assert Settings.load(path).method == "nearest"  # the file over the default
    clean_env.setenv("TOPOFUSION_ENGINE__METHOD", "gmm")
    assert Settings.load(path).method == "gmm"  # the engine's variable (the old name) over the file
    clean_env.setenv("TOPOFUSION_METHOD", "cfar")
    settings = Settings.load(path)
    assert settings.method == "cfar" and settings.engine.method == "cfar"  # the setting over both
    flags = Settings.load(path, {"method": "basic-topology", "prefix": None})
    assert flags.method == flags.engine.method == "basic-topology" and flags.prefix == "fusion"
    assert flags.queue_size == 7 and flags.engine.sequencer.max_lag_s == 5.0  # the rest of the file


def test_the_engine_form_of_a_shared_setting_is_taken_everywhere(
    tmp_path: Path, clean_env: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "topofusion.yaml"
    path.write_text(
        "partition: {index: 2, count: 3}\nassessment: {window_s: 300, requirements: {pd_min: 0.9}}\n"
    )
    settings = Settings.load(path)
    assert settings.partition == "2/3" and settings.engine.partition == Partition(2, 3)
    assert settings.performance_window_s == 300 and settings.engine.assessment.window_s == 300
    assert settings.performance_pd_min == 0.9
    clean_env.setenv("TOPOFUSION_ENGINE__PARTITION__INDEX", "3")
    clean_env.setenv("TOPOFUSION_ENGINE__PARTITION__COUNT", "3")
    assert Settings.load(path).engine.partition == Partition(3, 3)
    clean_env.setenv("TOPOFUSION_PERFORMANCE_WINDOW_S", "120")
    assert Settings.load(path).engine.assessment.window_s == 120
    # the partition's salt: its own setting, or the engine tree's partition.salt
    clean_env.delenv("TOPOFUSION_ENGINE__PARTITION__INDEX")
    clean_env.delenv("TOPOFUSION_ENGINE__PARTITION__COUNT")
    path.write_text("partition: {index: 2, count: 3, salt: 46}\n")
    assert Settings.load(path).engine.partition == Partition(2, 3, 46)
    clean_env.setenv("TOPOFUSION_PARTITION_SALT", "7")
    assert Settings.load(path).engine.partition == Partition(2, 3, 7)
    assert Settings.load(path).effective()["partition_salt"] == 7
    # the salt alone, as the contract allows for any engine parameter: the one worker's salt
    clean_env.delenv("TOPOFUSION_PARTITION_SALT")
    path.write_text("partition: {salt: 5}\n")
    assert Settings.load(path).engine.partition == Partition(1, 1, 5)
    clean_env.setenv("TOPOFUSION_ENGINE__PARTITION__SALT", "9")
    assert Settings.load().engine.partition == Partition(1, 1, 9)


def test_a_file_key_neither_setting_nor_engine_section_is_refused(
    tmp_path: Path, clean_env: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "topofusion.yaml"
    path.write_text("http_prot: 8080\n")
    with pytest.raises(ConfigError, match="http_prot: unknown key"):
        Settings.load(path)
    path.write_text("http_port: 99999\n")
    with pytest.raises(ValidationError, match="http_port"):
        Settings.load(path)
    clean_env.setenv("TOPOFUSION_CONFIG", str(tmp_path / "missing.toml"))
    with pytest.raises(ConfigError, match="not found"):
        Settings()


def test_the_effective_settings_are_a_config_file_with_secrets_redacted(
    tmp_path: Path, clean_env: pytest.MonkeyPatch
) -> None:
    clean_env.setenv("TOPOFUSION_API_TOKEN", "s3cret")
    clean_env.setenv("TOPOFUSION_ENGINE__CADENCE__CADENCE_SCANS", "2")
    settings = Settings.load(overrides={"http_port": 9000, "partition": "1/2"})
    shown = settings.effective()
    assert shown["api_token"] == REDACTED and "s3cret" not in settings.render() + settings.render("json")
    assert shown["http_port"] == 9000 and shown["cadence"]["cadence_scans"] == 2
    assert shown["partition"] == {"index": 1, "count": 2, "salt": 0}  # shared keys in the engine's form
    assert {k: shown[k] for k in as_dict(settings.engine)} == as_dict(settings.engine)
    for fmt in ("yaml", "json"):
        path = tmp_path / f"shown.{fmt}"
        path.write_text(settings.render(fmt))  # type: ignore[arg-type]
        again = Settings.load(path)
        assert again.effective() == shown and again.engine == settings.engine
        clean_env.delenv("TOPOFUSION_API_TOKEN")
        assert Settings.load(path).api_token is None  # the redaction is never taken for the token
        clean_env.setenv("TOPOFUSION_API_TOKEN", "s3cret")


def test_flags_are_overrides_by_their_settings_names() -> None:
    import argparse

    flags = {
        "mode": "client",
        "connect": ["tcp/127.0.0.1:7447"],
        "window": 30.0,
        "queue_bytes": 1,
        "prefix": None,
    }
    assert flag_overrides(flags) == {
        "zenoh_mode": "client",
        "zenoh_connect": ["tcp/127.0.0.1:7447"],
        "window_s": 30.0,
    }  # (record's own --queue-bytes is no setting's flag)
    assert flag_overrides(argparse.Namespace(**flags)) == flag_overrides(flags)


def test_the_node_options_are_the_settings_of_their_names(clean_env: pytest.MonkeyPatch) -> None:
    assert NodeOptions() == NodeOptions.from_settings(Settings())  # one set of defaults
    clean_env.setenv("TOPOFUSION_QUEUE_WAIT_S", "0.25")
    options = NodeOptions.from_settings(Settings.load(overrides={"radars": ["A", "B"], "stall_s": 5}))
    assert (options.radars, options.queue_wait_s, options.stall_s) == (("A", "B"), 0.25, 5)


def test_a_state_directory_that_cannot_be_used_is_named(
    tmp_path: Path, clean_env: pytest.MonkeyPatch
) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    settings = Settings.load(overrides={"state_dir": blocker / "state", "correlation_process": False})
    with pytest.raises(RuntimeError, match=f"state directory {blocker / 'state'} cannot be used"):
        start_engine(settings)


def test_an_empty_variable_leaves_the_config_files_value(
    tmp_path: Path, clean_env: pytest.MonkeyPatch
) -> None:
    """Compose passes ``TOPOFUSION_API_TOKEN=${TOPOFUSION_API_TOKEN:-}``: empty, it is not set,
    and the token of the config file must still hold (else the API would run without one)."""
    sites = tmp_path / "sites.json"
    sites.write_text("[]")
    cfg = tmp_path / "service.toml"
    cfg.write_text(f'api_token = "filetoken"\nsites = "{sites}"\n')
    clean_env.setenv("TOPOFUSION_API_TOKEN", "")
    clean_env.setenv("TOPOFUSION_SITES", "  ")
    s = Settings.load(config_file=cfg)
    assert s.api_token is not None and s.api_token.get_secret_value() == "filetoken"
    assert s.sites is not None and Path(str(s.sites)) == sites
    clean_env.setenv("TOPOFUSION_API_TOKEN", "envtoken")  # a set variable still wins
    assert Settings.load(config_file=cfg).api_token.get_secret_value() == "envtoken"  # type: ignore[union-attr]


def test_healthcheck_says_unhealthy_not_usage_error_on_a_bad_setting(tmp_path: Path) -> None:
    """The contract's healthcheck exits 0 or 1 (a container runtime reserves 2)."""
    for bad in (
        {"TOPOFUSION_CONFIG": str(tmp_path / "missing.toml")},
        {"TOPOFUSION_ENGINE__METHOD": "bogus"},
        {"TOPOFUSION_HTTP_PORT": "not-a-port"},
    ):
        run = _command("healthcheck", bad)
        assert run.returncode == 1, (bad, run.stderr)
        assert "healthcheck:" in run.stderr


def test_a_partitioned_worker_runs_its_correlation_in_its_own_process_only_when_told(
    clean_env: pytest.MonkeyPatch,
) -> None:
    """Unset, the correlation process is a whole-network worker's (two cores for one worker)
    and not a partitioned worker's (the workers are the parallelism); set, it is as set; and
    the effective configuration says which."""
    assert Settings.load().two_processes
    assert not Settings.load(overrides={"partition": "2/3"}).two_processes
    clean_env.setenv("TOPOFUSION_PARTITION", "1/2")
    assert not Settings.load().two_processes
    clean_env.setenv("TOPOFUSION_CORRELATION_PROCESS", "true")
    partitioned = Settings.load()
    assert partitioned.two_processes and partitioned.effective()["correlation_process"] is True
    clean_env.delenv("TOPOFUSION_PARTITION")
    clean_env.setenv("TOPOFUSION_CORRELATION_PROCESS", "false")
    assert Settings.load().effective()["correlation_process"] is False


def test_the_start_says_whether_the_http_port_asks_for_a_token(
    clean_env: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="topofusion")
    clean_env.setenv("TOPOFUSION_API_TOKEN", "")  # (compose's unset variable)
    assert api_token(Settings.load()) is None
    clean_env.setenv("TOPOFUSION_API_TOKEN", "s3cret")
    assert api_token(Settings.load()) == "s3cret"
    said = [r.getMessage() for r in caplog.records if r.name == "topofusion"]
    assert said == [
        "HTTP side port: no token asked (TOPOFUSION_API_TOKEN unset or empty)",
        "HTTP side port: a bearer token is asked on every route but /healthz and /readyz",
    ]


def test_config_files_and_levels_that_cannot_be_read_are_named(tmp_path: Path) -> None:
    """One line naming the file or the setting (they said "[Errno 21] Is a directory", a
    codec's error or "Unknown level"), and a file of many unknown keys does not make a line of
    megabytes."""
    binary = tmp_path / "bad.toml"
    binary.write_bytes(b"\xff\xfe[x]\n")
    for path, said in ((binary, "is not UTF-8 text"), (tmp_path, "is a directory")):
        with pytest.raises(ConfigError, match=f"config file {path} {said}"):
            load_file(path)
    many = {"sequencer": {f"k{i}": 1 for i in range(1000)}}
    with pytest.raises(ConfigError) as err:
        engine_config_from(many)
    assert len(str(err.value)) < 5000 and str(err.value).endswith("and 990 more unknown keys")
    with pytest.raises(ValueError, match="TOPOFUSION_LOG_LEVEL"):
        setup_logging("LOUD")


def test_config_refuses_what_run_would_refuse_at_start(tmp_path: Path) -> None:
    """``topofusion config`` checks what ``run`` checks at start (it passed all three)."""
    a_file = tmp_path / "state"
    a_file.write_text("")
    for bad, said in (
        ({"TOPOFUSION_INITIATOR": "foo"}, "unknown initiator 'foo'"),
        ({"TOPOFUSION_ZENOH_CONFIG": str(tmp_path / "none.json5")}, "none.json5: no such file"),
        (
            {"TOPOFUSION_STATE_DIR": str(a_file)},
            f"TOPOFUSION_STATE_DIR {a_file} cannot be used: {a_file} is not a directory",
        ),
    ):
        run = _command("config", bad)
        assert run.returncode == 2 and said in run.stderr, (bad, run.stderr)


def _command(name: str, settings: dict[str, str]) -> subprocess.CompletedProcess[str]:
    """``python -m service NAME`` with ``settings`` and no other ``TOPOFUSION_*`` variable."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("TOPOFUSION_")}
    return subprocess.run(
        [sys.executable, "-m", "service", name],
        capture_output=True,
        text=True,
        env={**env, **settings},
        timeout=60,
    )
