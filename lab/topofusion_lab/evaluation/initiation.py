"""Evaluation of track initiation: the Hough paper's Table 1 and a monostatic tracker run.

``run(out_dir, runs, seed, progress)`` is called by ``topofusion evaluate``; it writes PNG
figures into ``out_dir`` and returns a markdown section.  Seeded RNGs only; data time only.

1. Table 1 set-up (:mod:`.initiation_bistatic`): initiation accuracy and false-track ratio of
   classic Hough, probabilistic-grid Hough, and PG Hough + velocity fuzzy clustering over
   ``runs`` Monte Carlo realisations (paper: 200), next to the published figures.
2. Monostatic scenario (:mod:`.initiation_monostatic`): 100 targets with clutter through the
   full tracker with each initiator: completeness, false confirmed tracks, position RMSE, time
   to confirm.
"""

from __future__ import annotations

import pathlib
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context

import numpy as np

from service.tracking.clustering import velocity_cluster_published
from service.tracking.groups import Groups
from service.tracking.hough import classic_hough, pg_hough
from service.tracking.initiators import INITIATORS, hough_velocity, location_error
from service.tracking.params import ClusterParams, HoughParams, TrackerParams
from topofusion_lab.evaluation.initiation_bistatic import (
    BistaticPlots,
    BistaticScenario,
    score_groups,
    simulate_bistatic,
)
from topofusion_lab.evaluation.initiation_monostatic import (
    MonostaticResult,
    MonostaticScenario,
    run_monostatic,
)

#: Published Table 1: (accuracy %, false-track ratio %).
PAPER_TABLE1: dict[str, tuple[float, float]] = {
    "Hough": (96.4, 56.4),
    "probabilistic-grid Hough": (97.6, 24.3),
    "Hough + velocity clustering": (97.8, 6.2),
}
#: Rows of our Table 1: method -> the paper's row it is compared with.
METHOD_ROWS: dict[str, str] = {
    "Hough": "Hough",
    "probabilistic-grid Hough": "probabilistic-grid Hough",
    "PG Hough + velocity clustering, Steps 7-8 as published": "Hough + velocity clustering",
    "Hough + velocity clustering": "Hough + velocity clustering",
}

#: Parameters used for the Table 1 set-up (plot errors of 100-500 m in an 8 x 6 km area).
#: ``max_lines`` = 60: with clutter as dense as the true plots, a clutter band through the
#: area holds about as many plots as a target with 12-13 plots, and the strong targets each
#: give several peaks at neighbouring angles; with 25 lines the line of the weaker target of
#: the crossing pair was often not among them (it then had no candidate set, whatever Steps
#: 1-8 did), which was most of the misses.  Bands may share plots and Step 8 selects over all
#: of them, so more lines cost time but add few false tracks.
TABLE1_HOUGH = HoughParams(
    theta_bins=180,
    rho_step_m=400.0,
    cell_m=100.0,
    subsamples=2,
    min_votes=5.0,
    pg_min_votes=5.0,
    member_sigma=3.0,
    member_band_m=500.0,
    min_plots=6,
    max_lines=60,
)
TABLE1_CLUSTER = ClusterParams(
    delta_v_mps=30.0,
    lam=1.0,
    eta=1.0,
    c=2.0,
    merge_overlap=2,
    min_plots=8,
    plot_gate_chi2=5.99,
    fit_confidence=0.99,
    min_span_s=2.0,
    min_speed_mps=30.0,
    max_speed_mps=600.0,
    plot_llr=3.0,
    min_track_score=20.0,
)
#: The published Steps 7-8 (merge on overlap alone) as run by the previous evaluation.
TABLE1_PUBLISHED = ClusterParams(delta_v_mps=30.0, lam=1.0, eta=1.0, c=2.0, merge_overlap=3, min_plots=6)


@dataclass(frozen=True)
class Table1Row:
    method: str
    accuracy: float
    false_ratio: float
    tracks_per_run: float
    ms_per_run: float


def table1_methods(
    plots: BistaticPlots, hp: HoughParams, cp: ClusterParams
) -> dict[str, tuple[Groups, float]]:
    """Run the methods of Table 1 on one realisation; (groups, seconds) per method."""
    out: dict[str, tuple[Groups, float]] = {}
    t0 = time.perf_counter()
    out["Hough"] = (classic_hough(plots.xy, hp), time.perf_counter() - t0)
    t0 = time.perf_counter()
    pg = pg_hough(plots.xy, plots.cov, hp)
    t_pg = time.perf_counter() - t0
    out["probabilistic-grid Hough"] = (pg, t_pg)
    t0 = time.perf_counter()
    delta = location_error(plots.cov)
    lines = []
    for members in pg.to_lists():  # the published clustering of each sequential PG line
        for sub in velocity_cluster_published(
            plots.time_s[members], plots.xy[members], delta[members], TABLE1_PUBLISHED
        ):
            lines.append(members[sub])
    out["PG Hough + velocity clustering, Steps 7-8 as published"] = (
        Groups.from_lists(lines),
        t_pg + time.perf_counter() - t0,
    )
    t0 = time.perf_counter()
    vc = hough_velocity(plots.time_s, plots.xy, plots.cov, TrackerParams(hough=hp, cluster=cp))
    out["Hough + velocity clustering"] = (Groups.from_lists(vc), time.perf_counter() - t0)
    return out


def _table1_chunk(args: tuple[list[int], int, HoughParams, ClusterParams, BistaticScenario]) -> np.ndarray:
    """Sums ``[initiated, targets, tracks, false, seconds]`` per method over some runs."""
    run_ids, seed, hp, cp, scn = args
    acc = np.zeros((len(METHOD_ROWS), 5))
    for r in run_ids:  # Monte Carlo runs
        plots = simulate_bistatic(scn, np.random.default_rng([seed, r]))
        for q, (groups, secs) in enumerate(table1_methods(plots, hp, cp).values()):
            s = score_groups(groups, plots.label, len(scn.starts_m))
            acc[q] += [s.initiated, s.targets, s.tracks, s.false, secs]
    return acc


def run_table1(
    runs: int,
    seed: int,
    hp: HoughParams = TABLE1_HOUGH,
    cp: ClusterParams = TABLE1_CLUSTER,
    scn: BistaticScenario | None = None,
    workers: int = 1,
) -> list[Table1Row]:
    """Monte Carlo of the Table 1 set-up: pooled accuracy and false-track ratio per method.

    ``workers`` > 1 splits the runs over processes; run ``r`` always uses the RNG
    ``[seed, r]``, so the result does not depend on ``workers``.
    """
    scn = scn if scn is not None else BistaticScenario()
    chunks = [list(range(k, runs, workers)) for k in range(max(workers, 1))]
    jobs = [(c, seed, hp, cp, scn) for c in chunks if c]
    if workers > 1 and len(jobs) > 1:
        with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("fork")) as ex:
            parts = list(ex.map(_table1_chunk, jobs))
    else:
        parts = [_table1_chunk(j) for j in jobs]
    acc = np.sum(parts, axis=0)
    return [
        Table1Row(m, 100 * v[0] / v[1], 100 * v[3] / max(v[2], 1), v[2] / runs, 1000 * v[4] / runs)
        for m, v in zip(METHOD_ROWS, acc, strict=True)
    ]


def _figure_table1(out_dir: pathlib.Path, seed: int) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plots = simulate_bistatic(BistaticScenario(), np.random.default_rng([seed, 0]))
    res = table1_methods(plots, TABLE1_HOUGH, TABLE1_CLUSTER)
    fig, axes = plt.subplots(1, 1 + len(res), figsize=(4.4 * (1 + len(res)), 4.6), sharex=True, sharey=True)
    lab = plots.label
    ax = axes[0]
    ax.scatter(plots.xy[lab < 0, 0] / 1e3, plots.xy[lab < 0, 1] / 1e3, s=6, c="0.6", label="clutter")
    for k in range(int(lab.max()) + 1):
        m = lab == k
        ax.scatter(plots.xy[m, 0] / 1e3, plots.xy[m, 1] / 1e3, s=10, label=f"target {k + 1}")
    ax.set_title("plots (truth)")
    ax.legend(fontsize=6)
    for ax, (name, (groups, _)) in zip(axes[1:], res.items(), strict=True):
        ax.scatter(plots.xy[:, 0] / 1e3, plots.xy[:, 1] / 1e3, s=4, c="0.8")
        for members in groups.to_lists():
            o = members[np.argsort(plots.time_s[members])]
            ax.plot(plots.xy[o, 0] / 1e3, plots.xy[o, 1] / 1e3, ".-", lw=0.8, ms=4)
        short = name.replace(", Steps 7-8 as published", "\n(Steps 7-8 as published)")
        ax.set_title(f"{short}: {groups.count} tracks", fontsize=9)
    for ax in axes:
        ax.set_xlabel("x (km)")
    axes[0].set_ylabel("y (km)")
    fig.tight_layout()
    name = "initiation_table1.png"
    fig.savefig(out_dir / name, dpi=110)
    plt.close(fig)
    return name


def _figure_monostatic(out_dir: pathlib.Path, results: dict[str, list[MonostaticResult]]) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name, rs in results.items():
        curve = np.mean([r.completeness_curve for r in rs], axis=0)
        ax.plot(rs[0].scan_times, 100 * curve, label=name)
    ax.set_xlabel("data time (s)")
    ax.set_ylabel("completeness (%)")
    ax.set_title("Monostatic, 100 targets + clutter: targets with a confirmed track")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    name = "initiation_monostatic.png"
    fig.savefig(out_dir / name, dpi=110)
    plt.close(fig)
    return name


def _mono_job(args: tuple[str, int]) -> tuple[str, MonostaticResult, float]:
    name, seed = args
    t0 = time.perf_counter()
    res = run_monostatic(MonostaticScenario(), name, seed)
    return name, res, time.perf_counter() - t0


#: Initiators run in the monostatic study (``hough`` is an alias of ``hough-velocity``).
MONO_INITIATORS: tuple[str, ...] = tuple(n for n in INITIATORS if n != "hough")


def run(
    out_dir: pathlib.Path, runs: int | None = None, seed: int = 0, progress: Callable[[str], None] = print
) -> str:
    """Both evaluations; ``runs`` None = the paper's 200 Monte Carlo runs for Table 1 (the
    monostatic tracker runs use ``max(1, runs // 100)`` realisations, 2 by default).  Runs are
    spread over two processes (results do not depend on it)."""
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    n1 = 200 if runs is None else int(runs)
    n2 = max(1, n1 // 100)
    workers = 2
    t_start = time.perf_counter()
    progress(f"initiation: Table 1 set-up, {n1} Monte Carlo runs on {workers} processes")
    rows = run_table1(n1, seed, workers=workers)
    progress(f"initiation: Table 1 done in {time.perf_counter() - t_start:.0f} s")
    fig1 = _figure_table1(out_dir, seed)
    scn = MonostaticScenario()
    mono: dict[str, list[MonostaticResult]] = {n: [] for n in MONO_INITIATORS}
    secs: dict[str, float] = {n: 0.0 for n in MONO_INITIATORS}
    jobs = [(name, seed * 1000 + k) for name in MONO_INITIATORS for k in range(n2)]
    progress(f"initiation: monostatic scenario, {', '.join(MONO_INITIATORS)}, {n2} runs each")
    with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("fork")) as ex:
        for name, res, dt in ex.map(_mono_job, jobs):
            mono[name].append(res)
            secs[name] += dt / n2
            progress(f"initiation: monostatic {name} run {len(mono[name])}/{n2} ({dt:.1f} s)")
    fig2 = _figure_monostatic(out_dir, mono)
    progress(f"initiation: done in {time.perf_counter() - t_start:.0f} s")
    return _markdown(rows, n1, fig1, scn, n2, mono, secs, fig2)


def _markdown(
    rows: list[Table1Row],
    n1: int,
    fig1: str,
    scn: MonostaticScenario,
    n2: int,
    mono: dict[str, list[MonostaticResult]],
    secs: dict[str, float],
    fig2: str,
) -> str:
    bs = BistaticScenario()
    lines = [
        "## Track initiation",
        "",
        f"### Hough paper Table 1 set-up ({n1} Monte Carlo runs)",
        "",
        "Bistatic network (transmitter at the origin, receivers at (-50 km, 0) and (50 km, 0), "
        "150 m / 5 mrad and 200 m / 8 mrad), 5 targets over 10 s (two on one line, a parallel "
        "pair 1.2 km apart, a crossing pair) at 250-360 m/s, each receiver sampling each target at "
        f"random times ({bs.mean_interval_s:.1f} s mean interval, about 20 plots per target), "
        "time stamps to 0.1 ms, uniform clutter about equal to the true plots.",
        "",
        "Accuracy = targets with a true track / targets; false-track ratio = false tracks / all "
        "tracks; a track is true for target X when more than half its plots are X's and it is the "
        "first such track (duplicates, mixed and clutter tracks are false).  The paper gives no "
        "definition; these are the usual ones.",
        "",
        "| method | accuracy (%) | false-track ratio (%) | paper accuracy (%) | paper false (%) "
        "| tracks / run | ms / run |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        pa, pf = PAPER_TABLE1[METHOD_ROWS[r.method]]
        lines.append(
            f"| {r.method} | {r.accuracy:.1f} | {r.false_ratio:.1f} | {pa} | {pf} | "
            f"{r.tracks_per_run:.2f} | {r.ms_per_run:.0f} |"
        )
    lines += [
        "",
        "Hough + velocity clustering runs Steps 1-8 on the bands of the 60 strongest Hough peaks "
        "(``TABLE1_HOUGH.max_lines``).  With 25 peaks it reached 97.0 % / 4.2 %: with clutter as "
        "dense as the true plots a clutter band holds about as many plots as a target with 12-13 "
        "plots, the strong targets each give several peaks at neighbouring angles, and the line "
        "of the weaker target of the crossing pair was then often not among the 25, so it had no "
        "candidate set at all.  The misses left (seed 0: 10 of 1000 targets) are mostly the "
        "crossing pair (8): targets 4 and 5 meet at one point at t = 6.7 s, the plots within "
        "about a second of it fit both, the track taken first keeps them and its partner is left "
        "split or short of ``min_plots``; the others are targets with fewer plots than "
        "``min_plots`` (8) or barely more (5 and 9 plots).  Giving such candidates a second "
        "chance (sharing the crossing plots, or provisional shorter tracks settled by the final "
        "reassignment) recovered them but started clutter tracks (false-track ratio 11-27 % on "
        "50-run samples), so it is not used.",
        "",
        f"![Table 1 set-up, one realisation]({fig1})",
        "",
        f"### Monostatic tracker, {scn.n_targets} targets + {scn.clutter_per_scan} clutter plots per scan "
        f"({n2} runs, {scn.scans} scans of {scn.scan_period_s:.0f} s in {scn.sectors} sector batches)",
        "",
        "Hough initiators run on local clusters of the window's unused plots (``hough`` = "
        "``hough-velocity``).",
        "",
        "| initiator | completeness (%) | false confirmed (%) | duplicates (%) | position RMSE (m) "
        "| time to confirm (s) | s / run |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, rs in mono.items():
        lines.append(
            f"| {name} | {100 * np.mean([r.completeness for r in rs]):.1f} "
            f"| {100 * np.mean([r.false_ratio for r in rs]):.1f} "
            f"| {100 * np.mean([r.duplicate_ratio for r in rs]):.1f} "
            f"| {np.nanmean([r.rmse_m for r in rs]):.0f} "
            f"| {np.nanmean([r.time_to_confirm_s for r in rs]):.1f} | {secs[name]:.1f} |"
        )
    lines += ["", f"![Monostatic completeness over time]({fig2})", ""]
    return "\n".join(lines)
