"""The evaluation entry point runs end to end with tiny counts and writes its figures."""

from __future__ import annotations

import pathlib

import pytest

from topofusion_lab.evaluation.correlation import run


@pytest.mark.slow
def test_run_small(tmp_path: pathlib.Path) -> None:
    lines: list[str] = []
    md = run(tmp_path, runs=40, seed=1, progress=lines.append)
    assert "Fig. 1" in md and "Fig. 2" in md and "Fig. 3" in md and "Stream" in md
    for name in ("fig1_correct_vs_neighbours", "fig2_false_vs_spacing", "fig3_time_vs_bias", "bias_sweep"):
        assert (tmp_path / f"correlation_{name}.png").stat().st_size > 1000
    assert lines
