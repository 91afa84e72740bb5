"""One configuration root (service/config.py): file, environment and flags, validated at start."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from service.config import ConfigError, EngineConfig, as_dict, engine_config_from, from_environment, load_file
from service.engine import Engine
from service.settings import Settings, engine_config
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
    ],
)
def test_errors_name_the_key(data: dict[str, object], named: str) -> None:
    with pytest.raises(ConfigError, match=named.replace(".", r"\.")):
        engine_config_from(data)


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
    assert json.loads(shown.stdout) == as_dict(EngineConfig())
    bad = tmp_path / "engine.yaml"
    bad.write_text("tracking: {filter: {process_noise_psd: -x}}\n")
    run = subprocess.run([*cli, "--config", str(bad)], capture_output=True, text=True, check=False)
    assert run.returncode == 2 and "tracking.filter.process_noise_psd" in run.stderr
