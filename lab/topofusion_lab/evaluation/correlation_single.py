"""Single-match experiments of the SVD paper's Section 3 (Figs. 1-3) and a larger-bias sweep.

Each experiment draws Monte Carlo trials with :mod:`.correlation_scenario` and calls the
single-decision functions directly (one candidate per trial, all trials in one batch):
:func:`service.correlation.svd_topology.svd_match`,
:func:`service.correlation.basic_topology.basic_match` and the chi-square test of
``nearest`` on the two reference positions.  Fig. 2 adds the one-to-one assignment with the
ambiguity margin (:func:`service.correlation.assignment.assign_unambiguous`), the same for
all three methods.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from scipy.stats import chi2

from service.correlation.assignment import assign_unambiguous
from service.correlation.basic_topology import BasicTopologyParams, basic_match, search_span
from service.correlation.svd_topology import SvdTopologyParams, svd_match
from service.geo import Site
from service.linalg import inv3, quad3
from topofusion_lab.evaluation.correlation_scenario import (
    Biases,
    MatchBatch,
    around,
    make_sites,
    measure,
    reference_first,
    sample_references,
    single_match_batch,
)

METHOD_NAMES = ("svd-topology", "basic-topology", "nearest")
#: Candidates decided per call in the experiments (memory bound only).
CHUNK = 2_500
#: The paper's 3-D rotation model, shown for reference in Fig. 1.
PAPER_FULL = "svd-topology (full 3-D, paper)"


@dataclass(frozen=True)
class Setting:
    """Shared scenario numbers (Section 3)."""

    range_bias_m: float = 100.0
    angle_bias_deg: float = 0.1
    pd_neighbour: float = 0.95
    alpha: float = 0.01
    ambiguity_margin: float = 6.0

    def basic(self) -> BasicTopologyParams:
        """The basic method's search for this setting: just the differential bias (both radars)."""
        return search_span(2.0 * self.angle_bias_deg, 2.0 * self.range_bias_m)


def _nearest(batch: MatchBatch, a: Site, b: Site, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """Chi-square test of the two reference positions (absolute, ECEF): accepted, cost."""
    ya = a.enu_to_ecef(batch.pa[:, 0])
    yb = b.enu_to_ecef(batch.pb[:, 0])
    s = a.rotation @ batch.ca[:, 0] @ a.rotation.T + b.rotation @ batch.cb[:, 0] @ b.rotation.T
    s_inv, ok = inv3(s)
    q = quad3(ya - yb, s_inv)
    return ok & (q <= chi2.ppf(1 - alpha, 3)), q - 3.0


def decide_all(
    batch: MatchBatch, a: Site, b: Site, setting: Setting, basic: BasicTopologyParams, svd: SvdTopologyParams
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Accepted flags and assignment costs per method for a batch of candidates.

    Large batches are decided in chunks of ``CHUNK`` candidates (bounds the memory of the
    ``(P, K, K)`` pairing arrays; results are identical).
    """
    if len(batch.pa) > CHUNK:
        parts = [
            _decide_all(batch.take(np.arange(s, min(s + CHUNK, len(batch.pa)))), a, b, setting, basic, svd)
            for s in range(0, len(batch.pa), CHUNK)
        ]
        return {
            m: (np.concatenate([p[m][0] for p in parts]), np.concatenate([p[m][1] for p in parts]))
            for m in parts[0]
        }
    return _decide_all(batch, a, b, setting, basic, svd)


def _decide_all(
    batch: MatchBatch, a: Site, b: Site, setting: Setting, basic: BasicTopologyParams, svd: SvdTopologyParams
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    r = svd_match(batch.pa, batch.ca, batch.ma, batch.pb, batch.cb, batch.mb, batch.m0, svd)
    out["svd-topology"] = (r.accepted, r.cost)
    rb = basic_match(batch.pa, batch.ca, batch.ma, batch.pb, batch.cb, batch.mb, batch.m0, basic)
    out["basic-topology"] = (rb.accepted, np.where(np.isfinite(rb.chi2), rb.chi2 - rb.dof, np.inf))
    out["nearest"] = _nearest(batch, a, b, setting.alpha)
    return out


def fig1_correct_vs_neighbours(
    runs: int,
    seed: int,
    setting: Setting,
    counts: tuple[int, ...] = tuple(range(2, 13)),
    pd: float | None = None,
    neighbour_model: str = "disc",
    with_full: bool = True,
) -> dict[str, list[float]]:
    """Correct-correlation rate of one match (true pair accepted) vs neighbour count.

    ``neighbour_model``: :func:`~topofusion_lab.evaluation.correlation_scenario.around`
    (``"sphere"`` = the paper's 10 km ball).  ``with_full``: also the paper's 3-D fit.
    """
    rng = np.random.default_rng(seed)
    a, b = make_sites()
    res: dict[str, list[float]] = {m: [] for m in (*METHOD_NAMES, PAPER_FULL)}
    full = replace(SvdTopologyParams(), rotation_model="full")
    for n in counts:
        ba = Biases.random_sign(rng, runs, setting.range_bias_m, setting.angle_bias_deg)
        bb = Biases.random_sign(rng, runs, setting.range_bias_m, setting.angle_bias_deg)
        batch, _ = single_match_batch(
            rng,
            a,
            b,
            n,
            runs,
            ba,
            bb,
            pd_neighbour=setting.pd_neighbour if pd is None else pd,
            neighbour_model=neighbour_model,
        )
        dec = decide_all(batch, a, b, setting, setting.basic(), SvdTopologyParams())
        for m in METHOD_NAMES:
            res[m].append(float(dec[m][0].mean()))
        if with_full:
            acc = [
                svd_match(x.pa, x.ca, x.ma, x.pb, x.cb, x.mb, x.m0, full).accepted
                for x in (batch.take(np.arange(s, min(s + CHUNK, runs))) for s in range(0, runs, CHUNK))
            ]
            res[PAPER_FULL].append(float(np.concatenate(acc).mean()))
    return res


def two_reference_batch(
    rng: np.random.Generator,
    a: Site,
    b: Site,
    spacing_m: float,
    runs: int,
    setting: Setting,
    neighbours: int = 6,
) -> MatchBatch:
    """Fig. 2 trials: references T1, T2 ``spacing_m`` apart plus ``neighbours`` others; 4 candidates each.

    Candidate ``4 t + 2 i + j`` is (A's T_i, B's T_j).
    """
    ref = sample_references(rng, a, b, runs)
    enu = a.ecef_to_enu(ref)
    ang = rng.uniform(0, 2 * np.pi, runs)
    t2 = enu + spacing_m * np.column_stack([np.sin(ang), np.cos(ang), np.zeros(runs)])
    others = around(rng, a, ref, neighbours)
    truth = np.concatenate([ref[:, None], a.enu_to_ecef(t2)[:, None], others], axis=1)
    ba = Biases.random_sign(rng, runs, setting.range_bias_m, setting.angle_bias_deg)
    bb = Biases.random_sign(rng, runs, setting.range_bias_m, setting.angle_bias_deg)
    pa, ca = measure(rng, a, truth, ba)
    pb, cb = measure(rng, b, truth, bb)
    parts = []
    for i in (0, 1):
        for j in (0, 1):
            parts.append(
                (
                    reference_first(pa, i),
                    reference_first(ca, i),
                    reference_first(pb, j),
                    reference_first(cb, j),
                )
            )
    stack = [np.stack([p[k] for p in parts], axis=1).reshape(-1, *parts[0][k].shape[1:]) for k in range(4)]
    mask = np.ones(stack[0].shape[:2], dtype=bool)
    return MatchBatch(stack[0], stack[1], mask, stack[2], stack[3], mask.copy(), b.rotation.T @ a.rotation)


def fig2_false_vs_spacing(
    runs: int, seed: int, setting: Setting, spacings: tuple[float, ...]
) -> dict[str, dict[str, list[float]]]:
    """False- and correct-correlation rate per reference vs spacing of two reference targets."""
    rng = np.random.default_rng(seed)
    a, b = make_sites()
    out: dict[str, dict[str, list[float]]] = {m: {"false": [], "correct": []} for m in METHOD_NAMES}
    for s in spacings:
        batch = two_reference_batch(rng, a, b, s, runs, setting)
        k = np.arange(4 * runs)
        ia = 2 * (k // 4) + (k % 4) // 2
        ib = 2 * (k // 4) + k % 2
        true = (k % 4) // 2 == k % 2
        dec = decide_all(batch, a, b, setting, setting.basic(), SvdTopologyParams())
        for m in METHOD_NAMES:
            acc, cost = dec[m]
            chosen, _ = assign_unambiguous(ia, ib, cost, acc, setting.ambiguity_margin)
            out[m]["false"].append(float((chosen & ~true).sum() / (2 * runs)))
            out[m]["correct"].append(float((chosen & true).sum() / (2 * runs)))
    return out


def time_per_match(
    seed: int, biases_deg: tuple[float, ...], reps: int = 200, neighbours: int = 6
) -> dict[str, list[float]]:
    """Fig. 3: wall time (ms) of one match (one candidate per call, median of ``reps`` calls) vs
    azimuth bias of radar A.

    The basic method searches +-(bias + 0.5 deg), the span it must cover, in 0.25 deg steps,
    and +-200 m in 50 m steps; svd-topology has nothing to search.  Also the amortised time
    per candidate when the SVD match runs batched over 1000 candidates.
    """
    rng = np.random.default_rng(seed)
    a, b = make_sites()
    out: dict[str, list[float]] = {"svd-topology": [], "basic-topology": [], "svd-topology (batched)": []}
    svd = SvdTopologyParams()
    for bias in biases_deg:
        ba = Biases.fixed(reps, 100.0, bias)
        bb = Biases.fixed(reps, 0.0, 0.0)
        batch, _ = single_match_batch(rng, a, b, neighbours, reps, ba, bb, pd_neighbour=1.0)
        basic = BasicTopologyParams(max_azimuth_bias_deg=bias + 0.5)
        one = [batch.take(np.array([i])) for i in range(reps)]
        for name, fn in (
            ("svd-topology", lambda x: svd_match(x.pa, x.ca, x.ma, x.pb, x.cb, x.mb, x.m0, svd)),
            ("basic-topology", lambda x, p=basic: basic_match(x.pa, x.ca, x.ma, x.pb, x.cb, x.mb, x.m0, p)),
        ):
            fn(one[0])
            calls = []
            for x in one:
                t0 = time.perf_counter()
                fn(x)
                calls.append(time.perf_counter() - t0)
            # median of the calls: a preemption or collection on this shared machine moves a
            # mean, not the typical call
            out[name].append(float(np.median(calls)) * 1e3)
        big = batch.take(np.arange(1000) % reps)
        t0 = time.perf_counter()
        svd_match(big.pa, big.ca, big.ma, big.pb, big.cb, big.mb, big.m0, svd)
        out["svd-topology (batched)"].append((time.perf_counter() - t0) / 1000 * 1e3)
    return out


def bias_sweep(
    runs: int,
    seed: int,
    setting: Setting,
    levels: tuple[float, ...],
    neighbours: int = 6,
    progress: Callable[[str], None] | None = None,
) -> dict[str, list[float]]:
    """Correct-correlation rate of one match as both radars' biases grow to ``k`` km / ``k`` deg.

    Each radar gets range bias ``+-1000 k`` m and azimuth and elevation bias ``+-k`` deg
    (random signs), so the differential rotation reaches ``2 k`` deg.  The basic method
    searches +-(2 k + 0.25) deg (range search kept at +-200 m: range bias barely changes
    topology vectors).
    """
    rng = np.random.default_rng(seed)
    a, b = make_sites()
    res: dict[str, list[float]] = {m: [] for m in METHOD_NAMES}
    for k in levels:
        ba = Biases.random_sign(rng, runs, 1000.0 * k, k)
        bb = Biases.random_sign(rng, runs, 1000.0 * k, k)
        batch, _ = single_match_batch(rng, a, b, neighbours, runs, ba, bb, pd_neighbour=setting.pd_neighbour)
        basic = BasicTopologyParams(max_azimuth_bias_deg=2 * k + 0.25)
        dec = decide_all(batch, a, b, setting, basic, SvdTopologyParams())
        for m in METHOD_NAMES:
            res[m].append(float(dec[m][0].mean()))
        if progress:
            progress(f"  bias sweep {k:g} km/deg done")
    return res
