"""``PairCorrelator``: one radar pair's correlation over time, the same for every method.

Per :meth:`PairCorrelator.update` (all in data time, deterministic):

1. Both track tables are brought to the update time (:mod:`.prediction`: confirmed tracks,
   constant velocity, ``F P F^T + Q``).
2. Once the pair is *registered* (enough confirmed pairs, :mod:`.registration`), both
   snapshots are bias-compensated with the current estimate before any test; the topology
   match then sees almost no residual rotation, and absolute chi-square tests become valid.
   (Only for ``svd-topology``; ``basic-topology`` and ``nearest`` run as published.)
3. The method's single decisions (:class:`~.base.CorrelationMethod`); candidates that are
   currently confirmed pairs get a cost bonus ``confirmed_bonus`` (history as a prior).
   Once registered, the confirmed pairs whose two tracks are present are first re-checked by
   the method's cheap test (:meth:`~.base.CorrelationMethod.reverify`; ``svd-topology``: the
   bias-compensated chi-square of position and velocity, stage 3).  The pairs that pass are
   kept as single decisions of their own, and the method's full decision runs only for the
   other tracks (``DecisionContext.reference_a``/``reference_b``; every track stays a
   neighbour): new tracks, tentative pairs, failed re-checks.  A steady-state update then
   costs the prediction, the compensation and a vectorised test per confirmed pair, plus a
   topology match per track that needs a decision.
   With the history evidence (:mod:`.evidence`, ``svd-topology``): every candidate's residual
   is a look (once registered, every pair within the search distance; before, inside a group
   against its local offset, :mod:`.group_offset`, which also decides the candidates the
   topology could not); a kept pair must also pass its accumulated test and stay the best
   hypothesis of both its tracks, and one a stronger chain through a third radar contradicts
   is decided afresh (:mod:`.cycles`).  A decided candidate with a source of looks is accepted
   from ``min_looks`` looks on while its accumulated test passes, at the cost ``q_rel - 3``.
   A confirmed pair whose re-check chi-square jumps beyond the swap gate while a rival pairing
   of one of its tracks passes is swapped (:mod:`.swap`): decided afresh without the confirmed
   bonus, its two tracks' evidence forgotten before the update's looks, and out of the book at
   once unless chosen again.  A pair is clear (confirmed at its first look, :mod:`.prompt`)
   only when both tracks' quality is at least ``prompt.min_quality`` (NaN: not known, clear).
4. One-to-one assignment with an ambiguity margin (:mod:`.assignment`) of the decided
   candidates (kept pairs share no track with them: nothing to assign); with the history
   evidence the margin is between joint assignments, and a candidate a chain through a third
   radar implies has its cost lowered by the cycle bonus.
5. The M-of-N book (:mod:`.pairs`); a kept pair scores a hit with the re-check's statistic
   and NaN rotation weight and scale (null on the wire: no topology was fitted).  Each pair's
   ``basis`` is what its latest hit rested on, its probability (the published ``score``) the
   evidence's posterior (the hit fraction while it has no evidence).
6. Confirmed pairs feed the registration memory (each row's normal-equation pieces computed
   once; once registered at most ``registered_rows_per_update`` rows, different pairs on
   successive updates), and the pair's own two-radar bias solution is refreshed for the next
   update: on every update until registered, then once per ``solve_interval_s`` of data time,
   warm-started from the previous solution (two Gauss-Newton steps instead of five to eight).

What the stream adds over one snapshot: velocities in the tests (two close aircraft rarely
share a velocity), M-of-N accumulation, registration from confirmed pairs (bias-compensated
association of tracks with too few neighbours; compensation removes the rotation the
topology fit must otherwise find), and the confirmed-pair prior in the assignment.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from service.chi2 import chi2_upper
from service.correlation.assignment import assign_unambiguous
from service.correlation.base import (
    Basis,
    CorrelationMethod,
    DecisionContext,
    Decisions,
    PredictedTracks,
    Reason,
    no_decision,
)
from service.correlation.basic_topology import BasicTopologyCorrelator, BasicTopologyParams
from service.correlation.cfar import CfarParams
from service.correlation.cycles import CycleParams, Implied, contradicted
from service.correlation.evidence import EvidenceBook, EvidenceParams, posterior, registered_residuals
from service.correlation.external import CfarCorrelator, GmmCorrelator
from service.correlation.gmm import GmmParams
from service.correlation.group_offset import GroupOffsetParams, group_residuals
from service.correlation.nearest import NearestCorrelator, NearestParams
from service.correlation.pairkeys import TrackKeys, comparable, find, isin_sorted, pair_keys
from service.correlation.pairs import PairBook, PairBookParams, PairState
from service.correlation.prediction import PredictionParams, predict_tracks
from service.correlation.prompt import PromptParams, clear_of_rivals, isolated, quality_clear
from service.correlation.registration import (
    BiasSolution,
    RadarBias,
    RegistrationMemory,
    RegistrationParams,
    RegistrationRowsData,
    compensate,
    solve_biases,
    to_estimates,
)
from service.correlation.svd_topology import (
    CHI2,
    DOF,
    LONE_STAGE,
    SvdTopologyCorrelator,
    SvdTopologyParams,
)
from service.correlation.swap import SwapParams, jumped, rivals, with_rival
from service.geo import Site
from service.linalg import mahalanobis3
from service.tracking.base import TrackTable

_NONE = np.array(None, dtype=object)


@dataclass(frozen=True)
class CorrelationParams:
    """Everything a :class:`PairCorrelator` uses, per stage."""

    prediction: PredictionParams = field(default_factory=PredictionParams)
    book: PairBookParams = field(default_factory=PairBookParams)
    registration: RegistrationParams = field(default_factory=RegistrationParams)
    svd: SvdTopologyParams = field(default_factory=SvdTopologyParams)
    basic: BasicTopologyParams = field(default_factory=BasicTopologyParams)
    nearest: NearestParams = field(default_factory=NearestParams)
    gmm: GmmParams = field(default_factory=GmmParams)
    cfar: CfarParams = field(default_factory=CfarParams)
    #: The sequential test over each candidate pair's history (``svd-topology``).
    evidence: EvidenceParams = field(default_factory=EvidenceParams)
    #: Consistency around three radars (:mod:`.cycles`; used by the correlation stage).
    cycles: CycleParams = field(default_factory=CycleParams)
    #: The local offset of a group of tracks, the looks before registration (``svd-topology``).
    group: GroupOffsetParams = field(default_factory=GroupOffsetParams)
    #: Clear pairs confirmed at their first update (:mod:`.prompt`; ``svd-topology``).
    prompt: PromptParams = field(default_factory=PromptParams)
    #: A confirmed pair whose compensated residual jumps is re-decided at once (:mod:`.swap`;
    #: ``svd-topology`` once registered).
    swap: SwapParams = field(default_factory=SwapParams)
    #: Ambiguity margin of the one-to-one assignment (chi-square units; 6 ~ likelihood ratio 20).
    ambiguity_margin: float = 6.0
    #: Cost bonus for a candidate that is a currently confirmed pair (hysteresis from history).
    confirmed_bonus: float = 3.0
    #: Bias-compensate before deciding once registered (svd-topology only).
    use_registration: bool = True
    #: Mode S addresses as association evidence: a candidate pair whose two tracks carry
    #: different addresses is never chosen, and a kept pair that comes to differ is decided
    #: afresh.  Off by default: the association then rests on kinematics alone, and the
    #: identity quality figure (``/status`` ``identity``) is an independent check of it.
    identity_veto: bool = False


#: Each method's correlator, built from its section of :class:`CorrelationParams`.  The names
#: are the contract's method names (the wire vocabulary; a test holds the two equal).
CORRELATORS: dict[str, Callable[[CorrelationParams], CorrelationMethod]] = {
    "svd-topology": lambda p: SvdTopologyCorrelator(p.svd),
    "basic-topology": lambda p: BasicTopologyCorrelator(p.basic),
    "nearest": lambda p: NearestCorrelator(p.nearest),
    "gmm": lambda p: GmmCorrelator(p.gmm),
    "cfar": lambda p: CfarCorrelator(p.cfar),
}
METHODS: tuple[str, ...] = tuple(CORRELATORS)


def make_correlator(method: str, params: CorrelationParams) -> CorrelationMethod:
    try:
        return CORRELATORS[method](params)
    except KeyError:
        raise ValueError(
            f"unknown correlation method {method!r}; expected one of {', '.join(METHODS)}"
        ) from None


def _pair_rows(
    ids_a: np.ndarray,
    ids_b: np.ndarray,
    pair_a: np.ndarray,
    pair_b: np.ndarray,
    sorters: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each pair ``(pair_a[k], pair_b[k])``: its rows in ``ids_a``/``ids_b`` and whether it
    is present in both (``sorters``: the argsorts of ``ids_a`` and ``ids_b`` when known)."""
    if len(ids_a) == 0 or len(ids_b) == 0 or len(pair_a) == 0:
        e = np.zeros(len(pair_a), dtype=np.intp)
        return e, e.copy(), np.zeros(len(pair_a), dtype=bool)
    sa, sb = sorters if sorters is not None else (np.argsort(ids_a), np.argsort(ids_b))
    ia = sa[np.minimum(np.searchsorted(ids_a, pair_a, sorter=sa), len(sa) - 1)]
    ib = sb[np.minimum(np.searchsorted(ids_b, pair_b, sorter=sb), len(sb) - 1)]
    ok = (ids_a[ia] == pair_a) & (ids_b[ib] == pair_b)
    return ia.astype(np.intp), ib.astype(np.intp), ok


def _lookup_pairs(
    ids_a: np.ndarray,
    ids_b: np.ndarray,
    pair_a: np.ndarray,
    pair_b: np.ndarray,
    sorters: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Row indices in ``ids_a``/``ids_b`` of the pairs ``(pair_a, pair_b)`` present in both."""
    ia, ib, ok = _pair_rows(ids_a, ids_b, pair_a, pair_b, sorters)
    return ia[ok], ib[ok]


def _shifted(old: BiasSolution, new: BiasSolution | None, k_sigma: float) -> bool:
    """Whether a bias of ``new`` lies more than ``k_sigma`` of ``old``'s own sigma from ``old``'s."""
    if new is None:
        return False
    for rid in old.radar_ids:
        b_old, p_old = old.of(rid)
        b_new, _ = new.of(rid)
        sigma = np.sqrt(np.maximum(np.diag(p_old), 0.0))
        if np.any(np.abs(b_new - b_old) > k_sigma * sigma):
            return True
    return False


def positions_at(table: TrackTable, time_s: float) -> np.ndarray:
    """Every track's ECEF position brought to ``time_s`` at its velocity."""
    return np.asarray(table.position_ecef_m + table.velocity_ecef_mps * (time_s - table.time_s)[:, None])


#: Up to this many anchors :func:`_near` takes each row's difference to each anchor directly (a
#: prompt decision's few new tracks: a third of the product form's time, and exact).
_FEW_ANCHORS = 8


def _near(positions: np.ndarray, anchors: np.ndarray, reach_m: float) -> np.ndarray:
    """``(rows, anchors)``: whether each row of ``positions`` lies within ``reach_m`` of each
    anchor (NaN rows and anchors are never near)."""
    if len(anchors) <= _FEW_ANCHORS:
        d = positions[:, None, :] - anchors[None, :, :]
        return np.asarray(np.einsum("ijk,ijk->ij", d, d) <= reach_m**2)
    finite = np.flatnonzero(np.isfinite(anchors).all(axis=1))
    if len(positions) == 0 or len(finite) == 0:
        return np.zeros((len(positions), len(anchors)), dtype=bool)
    # |p - q|^2 = |p|^2 + |q|^2 - 2 p.q for every row and anchor in one product, about a
    # finite anchor (ECEF magnitudes squared, 4e13 m^2, would leave centimetres of rounding;
    # near it the reach, kilometres, is what counts).
    p, q = positions - anchors[finite[0]], anchors - anchors[finite[0]]
    d2 = np.einsum("ij,ij->i", p, p)[:, None] + np.einsum("ij,ij->i", q, q)[None, :] - 2.0 * (p @ q.T)
    return np.asarray(d2 <= reach_m**2)


def _within(
    positions: np.ndarray, anchors: np.ndarray, reach_m: float, busy: np.ndarray | None = None
) -> np.ndarray:
    """The rows of ``positions`` within ``reach_m`` of any anchor and not among ``busy``."""
    near = np.asarray(_near(positions, anchors, reach_m).any(axis=1))
    if busy is not None:
        near[busy] = False
    return np.flatnonzero(near)


def _pairs_within(
    pos_a: np.ndarray, pos_b: np.ndarray, rows_a: np.ndarray, rows_b: np.ndarray, gate_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """The pairs ``(i, j)`` of ``rows_a`` x ``rows_b`` closer than ``gate_m``, in (i, j) order (a
    few rows each: one distance matrix)."""
    d = pos_a[rows_a][:, None, :] - pos_b[rows_b][None, :, :]
    ia, ib = np.nonzero(np.einsum("ijk,ijk->ij", d, d) <= gate_m**2)
    return rows_a[ia].astype(np.intp), rows_b[ib].astype(np.intp)


def _qualities(
    dec: Decisions, a: PredictedTracks, b: PredictedTracks
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Each decision's two tracks' qualities (``TrackTable.quality``; None: the side gives none)."""
    return (
        None if a.quality is None else a.quality[dec.index_a],
        None if b.quality is None else b.quality[dec.index_b],
    )


def _other_rows(n: int, rows: np.ndarray) -> np.ndarray:
    """The rows ``0..n-1`` not in ``rows``, ascending."""
    free = np.ones(n, dtype=bool)
    free[rows] = False
    return np.flatnonzero(free)


class PairCorrelator:
    """Live correlation of radar ``site_a`` with ``site_b`` (None: a bias-free reference source)."""

    def __init__(
        self,
        method: str,
        site_a: Site,
        site_b: Site | None,
        params: CorrelationParams | None = None,
        keys: tuple[TrackKeys, TrackKeys] | None = None,
    ) -> None:
        """``keys``: each side's track keys (:class:`~.pairkeys.TrackKeys`; a radar's are shared
        by all its pairs, so that its tables are keyed once; None: this pair's own)."""
        self.method = method
        self.params = params or CorrelationParams()
        self.correlator = make_correlator(method, self.params)
        if site_b is None and self.correlator.requires_sites:
            raise ValueError(
                f"method {method!r} needs two radar sites; a reference source needs 'nearest' or 'cfar'"
            )
        self.site_a = site_a
        self.site_b = site_b
        self.book = PairBook(self.params.book)
        #: Each side's track keys: the book and the evidence identify tracks by them; the
        #: track ids name the book's pairs.
        self.track_keys = keys if keys is not None else (TrackKeys(), TrackKeys())
        #: The track ids of each side the book's pairs were last checked against (the tables'
        #: own arrays: a radar's next table is a new object).
        self._checked: tuple[np.ndarray | None, np.ndarray | None] = (None, None)
        #: Evidence over the candidate pairs' history (None: the method gives no residuals).
        self.evidence = (
            EvidenceBook(self.params.evidence)
            if self.params.evidence.enabled and method == "svd-topology"
            else None
        )
        self.memory = RegistrationMemory(site_a, site_b)
        #: The rows the last update added to the memory (None: none).
        self.last_rows: RegistrationRowsData | None = None
        self.solution: BiasSolution | None = None
        self._solved_s = float("-inf")
        #: Confirmed pairs of the book at the last solve (``RegistrationParams.resolve_growth``).
        self._solved_pairs = 1
        self.last_update_ms: float = 0.0
        self.last_decisions: Decisions = Decisions.empty()
        #: Confirmed pairs the last update kept by the method's re-check (no full decision).
        self.last_reverified = 0
        #: Confirmed pairs the last update found swapped (:mod:`.swap`), and all so far.
        self.last_swaps = 0
        self.swaps = 0
        self.time_s: float = float("nan")
        #: Data time of the first update (the lone rule waits ``svd.lone_after_scans`` from it).
        self.first_s: float = float("nan")
        self.updates = 0
        self.settled = False

    @property
    def registered(self) -> bool:
        return (
            self.params.use_registration
            and self.method == "svd-topology"
            and self.solution is not None
            and (
                min(self.solution.pairs_used.values()) >= self.params.registration.min_pairs
                or 0 < self.params.registration.min_track_pairs <= self.solution.clusters
            )
        )

    def update(
        self, tracks_a: TrackTable, tracks_b: TrackTable, time_s: float, implied: Implied | None = None
    ) -> None:
        """One correlation update at data time ``time_s``; ``implied``: the pairs confirmed pairs
        through third radars imply (:mod:`.cycles`; None: no cycle step)."""
        t0 = time.perf_counter()
        prm = self.params
        if np.isnan(self.first_s):
            self.first_s = float(time_s)
        keys_a, keys_b = self._keys(tracks_a, tracks_b)
        raw_a, raw_b, a, b, ctx_kw = self._predicted(tracks_a, tracks_b, time_s, keys_a, keys_b)
        ka, kb = a.keys, b.keys  # (raw_a, raw_b: the same rows)
        registered = bool(ctx_kw)
        ev = self.evidence
        conf = self.book.confirmed
        sorters = (np.argsort(ka), np.argsort(kb))  # the rows of a, b and raw_a, raw_b
        ca_idx, cb_idx = _lookup_pairs(ka, kb, self.book.id_a[conf], self.book.id_b[conf], sorters)
        ctx = DecisionContext(time_s=time_s, confirmed_a=ca_idx, confirmed_b=cb_idx, **ctx_kw)  # type: ignore[arg-type]
        # The method's re-check of the confirmed pairs (before the looks: it reads none).
        kept = self.correlator.reverify(a, b, ca_idx, cb_idx, ctx)
        jump = self._jumps(kept, len(ca_idx), a, b, ctx)  # (re-check rows: the confirmed pairs', in order)
        jumped_a, jumped_b = ka[ca_idx[jump]], kb[cb_idx[jump]]
        if len(jumped_a):
            # Swapped (module swap): not kept, no confirmed bonus, the two tracks' evidence reset
            # before this update's looks; the book lets the pairs go below unless chosen again.
            assert kept is not None
            ca_idx, cb_idx = ca_idx[~jump], cb_idx[~jump]
            ctx = replace(ctx, confirmed_a=ca_idx, confirmed_b=cb_idx)
            kept = kept.take(~jump)
            if ev is not None:
                ev.forget_tracks(jumped_a, jumped_b)
        self.last_swaps = len(jumped_a)
        self.swaps += len(jumped_a)
        if ev is not None and registered:
            # Every candidate within the gate is one look at its pair (no censoring by the
            # decisions); a known pair outside it is no hypothesis any more.
            extra_a, extra_b = ctx_kw["registration_cov_a"], ctx_kw["registration_cov_b"]
            ia_e, ib_e, r, s_noise, s_common = registered_residuals(a, b, extra_a, extra_b, ev.params)  # type: ignore[arg-type]
            ev.observe(time_s, ka[ia_e], kb[ib_e], r, s_noise, s_common)
            ev.prune(time_s, ka, kb, unobserved_present=True)
        parts = []
        if implied is not None:
            # The implied pairs present in both snapshots, by rows (module cycles; by track ids,
            # as integer codes where they have them: the chains join books of other workers'
            # radar pairs, whose keys are their own).
            ids = comparable(a.track_id, b.track_id, implied.track_a, implied.track_b)
            ia_i, ib_i, found = _pair_rows(ids[0], ids[1], ids[2], ids[3])
            imp_a, imp_b, imp_s = ia_i[found], ib_i[found], implied.strength[found]
        if kept is not None:
            kept = kept.take(kept.accepted)
            if ev is not None:
                # A kept pair must also pass its history and be the best hypothesis of both its
                # tracks (``keep_margin``); else it is decided in full with the rest.
                e = find(ev.keys, pair_keys(ka[kept.index_a], kb[kept.index_b]))
                bad = e < 0
                ok = ~bad
                bad[ok] = ev.rejected()[e[ok]] | ev.rivals_better(e[ok], ev.params.keep_margin)
                kept = kept.take(~bad)
                hist = ev.looks[e[~bad]] >= ev.params.min_looks
            if implied is not None and len(implied) and len(kept):
                # The weakest link of a contradicted cycle goes: decided afresh (module cycles).
                at = find(self.book.keys, pair_keys(ka[kept.index_a], kb[kept.index_b]))
                own = np.where(at >= 0, self.book.score[np.maximum(at, 0)], 0.0)
                weak = contradicted(kept.index_a, kept.index_b, own, imp_a, imp_b, imp_s, len(a), len(b))
                kept = kept.take(~weak)
                if ev is not None:
                    hist = hist[~weak]
            if prm.identity_veto:
                same = ~_identities_differ(a, b, kept)
                kept = kept.take(same)
                if ev is not None:
                    hist = hist[same]
            if ev is not None:
                kept.extras["basis"] = np.where(hist, float(Basis.HISTORY), float(Basis.REGISTERED))
            # Kept pairs are decided; only the other tracks are candidate references.
            parts.append(kept)
            ctx = replace(
                ctx,
                reference_a=_other_rows(len(a), kept.index_a),
                reference_b=_other_rows(len(b), kept.index_b),
            )
        self.last_reverified = len(kept) if kept is not None else 0
        decided = self.correlator.decide(a, b, ctx)
        decided = self._lone_apart(decided, a, b, (tracks_a, keys_a), (tracks_b, keys_b), time_s)
        clear = self._clear(decided, a, b, (tracks_a, keys_a), (tracks_b, keys_b), time_s)
        decided = self._with_history(decided, a, b, time_s, registered, clear)
        if prm.identity_veto:
            decided = replace(decided, accepted=decided.accepted & ~_identities_differ(a, b, decided))
        if ev is not None and not registered:
            ev.prune(time_s, ka, kb)
        cost = decided.cost
        if len(decided) and len(ca_idx):
            # Confirmed pairs by row indices (those present in both snapshots).
            nb = max(len(b), 1)
            is_conf = np.isin(decided.index_a * nb + decided.index_b, ca_idx * nb + cb_idx)
            cost = np.where(is_conf, cost - prm.confirmed_bonus, cost)
        if implied is not None and len(implied) and len(decided):
            # A candidate a chain through a third radar implies: the cycle's evidence (by row
            # indices, as the confirmed pairs above: no string keys over every candidate).
            nb = max(len(b), 1)
            is_implied = np.isin(decided.index_a * nb + decided.index_b, imp_a * nb + imp_b)
            cost = np.where(is_implied, cost - prm.cycles.bonus, cost)
        chosen, _ambiguous = assign_unambiguous(
            decided.index_a,
            decided.index_b,
            cost,
            decided.accepted,
            prm.ambiguity_margin,
            # Joint ambiguity on the accumulated costs (None: single pairs, on one update's).
            self.evidence.params.null_cost if self.evidence is not None else None,
        )
        # Kept pairs share no track with the decided candidates: the assignment would take
        # each of them as it is (no rival), so they are chosen without it.
        dec = Decisions.concat([*parts, decided])
        sel = Decisions.concat([*parts, decided.take(chosen)])
        now = np.concatenate([np.zeros(sum(len(x) for x in parts), dtype=bool), clear[chosen]])
        self._checked = (tracks_a.track_id, tracks_b.track_id)
        self.book.update(
            time_s,
            keys_a,
            keys_b,
            ka[sel.index_a],
            kb[sel.index_b],
            sel.statistic,
            sel.rotation_weight,
            sel.scale,
            sel.neighbors,
            _basis_codes(sel.extras["basis"]) if "basis" in sel.extras else None,
            confirm_now=now,
            quality=self.book.pair_quality(len(sel), *_qualities(sel, a, b)),
            names=(a.track_id[sel.index_a], b.track_id[sel.index_b]),
        )
        if len(jumped_a):
            self.book.release(jumped_a, jumped_b, time_s)  # (unless this update chose them again)
        if ev is not None:
            # A pair's probability from its accumulated evidence; a pair with none (before
            # registration and outside any group) keeps the hit fraction: one update's
            # decision among a formation's rivals measured as no better than a guess there.
            e = find(ev.keys, self.book.keys)
            self.book.set_probability(np.append(ev.probability(), np.nan)[e])  # -1: none
            self.book.hold_ambiguous()
        # Registration rows from the confirmed pairs (raw, uncompensated positions).
        conf = self.book.confirmed
        pa_idx, pb_idx = _lookup_pairs(ka, kb, self.book.id_a[conf], self.book.id_b[conf], sorters)
        self.last_rows = None
        if len(pa_idx):
            cap = None
            if self.registered:
                # the cap is per scan: an update after several scans (a settled pair) takes as
                # many rows as one per scan would have taken, so registration learns as fast
                scan = self._slower_scan_s()
                scans = (time_s - self.time_s) / scan if np.isfinite(self.time_s) and scan > 0 else 1.0
                cap = round(prm.registration.registered_rows_per_update * max(1.0, scans))
            self.last_rows = self.memory.add(
                time_s, raw_a, raw_b, pa_idx, pb_idx, prm.registration, max_rows=cap
            )
        if self.method == "svd-topology" and prm.use_registration and len(self.memory):
            # Re-solve on a data-time schedule once registered (every update before that), and
            # whenever the confirmed pairs have grown ``resolve_growth`` times since the last
            # solve: a first registration rests on a few pairs of one area, and its estimate
            # can be off by more than its sigma says until the pairs spread.
            confirmed = int(np.count_nonzero(self.book.confirmed))
            due = (
                not self.registered
                or time_s >= self._solved_s + prm.registration.solve_interval_s
                or time_s < self._solved_s
                or confirmed >= prm.registration.resolve_growth * self._solved_pairs
            )
            if due:
                # Warm start once registered: the rows changed little since the last solve.
                was = self.solution if self.registered else None
                self.solution = solve_biases([self.memory], time_s, prm.registration, initial=was)
                self._solved_s = time_s
                self._solved_pairs = max(confirmed, 1)
                if ev is not None and was is not None and _shifted(was, self.solution, ev.params.reset_sigma):
                    # The looks were compensated with an estimate the new one refutes: their
                    # residuals carry its error, and would reject right pairs for minutes.
                    ev.clear()
                elif ev is not None and was is not None and ev.params.recompensate:
                    # (a, b: this update's snapshots, compensated with ``was``)
                    self._recompensate(a, b, raw_a, raw_b)
        self.last_decisions = dec
        #: Nothing left to settle: registered, no tentative pair but held ones (they wait for
        #: their evidence, which the pair's usual cadence brings), no candidate accepted but
        #: not chosen or left undecided (the stage may then correlate the pair less often,
        #: :class:`CadenceParams`).
        open_ = (decided.accepted & ~chosen) | no_decision(decided.reason)
        waiting = ~self.book.confirmed & ~self.book.held
        self.settled = self.registered and not waiting.any() and not open_.any()
        self.time_s = time_s
        self.updates += 1
        self.last_update_ms = (time.perf_counter() - t0) * 1e3

    def _recompensate(
        self, was_a: PredictedTracks, was_b: PredictedTracks, raw_a: PredictedTracks, raw_b: PredictedTracks
    ) -> None:
        """The remembered looks of the pairs of present tracks moved to the new solution
        (``EvidenceParams.recompensate``) from the one ``was_a``/``was_b`` were compensated
        with (``raw_a``/``raw_b`` uncompensated, the same rows): by the change of each track's
        compensated position, in the looks' frame (:func:`.evidence.registered_residuals`)."""
        ev, new = self.evidence, self.solution
        if ev is None or new is None or len(ev) == 0:
            return
        ia = find(raw_a.keys, ev.track_a)
        ib = find(raw_b.keys, ev.track_b)
        ok = (ia >= 0) & (ib >= 0)
        if not ok.any():
            return
        ia, ib = ia[ok], ib[ok]
        sa, sb = self.site_a.site_id, self.site_b.site_id if self.site_b else None
        da = compensate(raw_a, *new.of(sa))[0].position - was_a.position
        db = compensate(raw_b, *new.of(sb))[0].position - was_b.position
        site = raw_b.site if raw_b.site is not None else raw_a.site
        rot = np.eye(3) if site is None else site.rotation
        ev.shift(np.flatnonzero(ok), (da[ia] - db[ib]) @ rot)

    def _jumps(
        self, checked: Decisions | None, n: int, a: PredictedTracks, b: PredictedTracks, ctx: DecisionContext
    ) -> NDArray[np.bool_]:
        """Per confirmed pair present (``n``, the rows of the re-check ``checked``; None: no
        re-check): is it swapped (:mod:`.swap`): its compensated chi-square jumped beyond the
        swap gate and (``require_rival``) a rival pairing of one of its tracks passes the
        re-check?  The re-check's chi-square extras are taken out of ``checked``."""
        if checked is None:
            return np.zeros(n, dtype=bool)
        q, dof = checked.extras.pop(CHI2, None), checked.extras.pop(DOF, None)
        prm = self.params.swap
        if not prm.enabled or q is None or dof is None:
            return np.zeros(len(checked), dtype=bool)
        jump = jumped(q, dof, prm.alpha)
        rows = np.flatnonzero(jump)
        if rows.size and prm.require_rival:
            # (only when a pair jumped: a few rows against the other radar's tracks)
            k, ri, rj = rivals(checked.index_a[rows], checked.index_b[rows], len(a), len(b))
            rival = self.correlator.reverify(a, b, ri, rj, ctx)
            passed = rival.accepted if rival is not None else np.zeros(len(k), dtype=bool)
            jump[rows] = with_rival(k, passed, rows.size)
        return jump

    def _keys(
        self, tracks_a: TrackTable, tracks_b: TrackTable
    ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Each table's track keys, row for row."""
        return self.track_keys[0].of(tracks_a.track_id), self.track_keys[1].of(tracks_b.track_id)

    def _predicted(
        self,
        tracks_a: TrackTable,
        tracks_b: TrackTable,
        time_s: float,
        keys_a: NDArray[np.int64],
        keys_b: NDArray[np.int64],
    ) -> tuple[PredictedTracks, PredictedTracks, PredictedTracks, PredictedTracks, dict[str, object]]:
        """Both tables brought to ``time_s`` (raw), the same bias-compensated once registered,
        and the decision context's registration fields (empty: not registered); ``keys_*``:
        each table's track keys."""
        prm = self.params
        raw_a = predict_tracks(tracks_a, self.site_a, time_s, prm.prediction, keys_a)
        raw_b = predict_tracks(tracks_b, self.site_b, time_s, prm.prediction, keys_b)
        if not self.registered or self.solution is None:
            return raw_a, raw_b, raw_a, raw_b, {}
        ba, pa = self.solution.of(self.site_a.site_id)
        bb, pb = self.solution.of(self.site_b.site_id if self.site_b else None)
        a, extra_a = compensate(raw_a, ba, pa)
        b, extra_b = compensate(raw_b, bb, pb)
        return (
            raw_a,
            raw_b,
            a,
            b,
            {"registered": True, "registration_cov_a": extra_a, "registration_cov_b": extra_b},
        )

    def _quality_ok(self, dec: Decisions, a: PredictedTracks, b: PredictedTracks) -> np.ndarray:
        """Per candidate of ``dec``: are both tracks' qualities at least ``prompt.min_quality``
        (:func:`.prompt.quality_clear`; all True with the rule off or no quality given)?"""
        m = self.params.prompt.min_quality
        if m <= 0.0 or (a.quality is None and b.quality is None):
            return np.ones(len(dec), dtype=bool)
        return quality_clear(*_qualities(dec, a, b), m)

    def _slower_scan_s(self) -> float:
        """The scan period of the slower of the pair's radars (a reference source has none)."""
        return max(self.site_a.scan_period_s, self.site_b.scan_period_s if self.site_b else 0.0)

    def _lone_apart(
        self,
        dec: Decisions,
        a: PredictedTracks,
        b: PredictedTracks,
        tracks_a: tuple[TrackTable, NDArray[np.int64]],
        tracks_b: tuple[TrackTable, NDArray[np.int64]],
        time_s: float,
    ) -> Decisions:
        """``dec`` with its lone decisions (``SvdTopologyParams.lone_pairs``) left undecided
        within ``svd.lone_after_scans`` scans (of the slower radar) of the pair's first update,
        and where a tentative track of either radar lies within the candidate gate of that
        radar's track (:func:`.prompt.isolated`): the method sees confirmed tracks only, and
        while the radars' tables fill, or a second aircraft is being confirmed, a track may
        look alone before its neighbours do (``tracks_*``: each table with its track keys)."""
        stage = dec.extras.get("stage")
        if stage is None:
            return dec
        rows = np.flatnonzero(stage == LONE_STAGE)
        if rows.size == 0:
            return dec
        svd = self.params.svd
        if time_s < self.first_s + svd.lone_after_scans * self._slower_scan_s():
            out = rows
        else:  # (velocity 0: only a tentative track counts as a neighbour)
            alone = self._isolated(dec, rows, a, b, tracks_a, tracks_b, time_s, svd.candidates.gate_m, 0.0)
            out = rows[~alone]
        if out.size == 0:
            return dec
        accepted, reason, cost = dec.accepted.copy(), dec.reason.copy(), dec.cost.copy()
        stage = stage.copy()
        accepted[out] = False
        reason[out] = Reason.TOO_FEW_NEIGHBOURS
        cost[out] = np.inf  # (undecided, as the method leaves such a candidate)
        stage[out] = 0.0
        extras = {**dec.extras, "stage": stage}
        return replace(dec, accepted=accepted, reason=reason, cost=cost, extras=extras)

    def _isolated(
        self,
        dec: Decisions,
        rows: NDArray[np.intp],
        a: PredictedTracks,
        b: PredictedTracks,
        tracks_a: tuple[TrackTable, NDArray[np.int64]],
        tracks_b: tuple[TrackTable, NDArray[np.int64]],
        time_s: float,
        radius_m: float,
        velocity_mps: float,
    ) -> np.ndarray:
        """Per candidate ``rows`` of ``dec``: are both its tracks isolated within their own
        radar's table (:func:`.prompt.isolated`; ``tracks_*``: each table and its track keys)?
        Each track is looked at once however many candidates it is in."""
        ua, inv_a = np.unique(dec.index_a[rows], return_inverse=True)
        ub, inv_b = np.unique(dec.index_b[rows], return_inverse=True)
        (table_a, keys_a), (table_b, keys_b) = tracks_a, tracks_b
        iso_a = isolated(table_a, self.site_a, time_s, a.keys[ua], radius_m, velocity_mps, keys_a)
        iso_b = isolated(table_b, self.site_b, time_s, b.keys[ub], radius_m, velocity_mps, keys_b)
        return np.asarray(iso_a[inv_a] & iso_b[inv_b])

    def _clear(
        self,
        dec: Decisions,
        a: PredictedTracks,
        b: PredictedTracks,
        tracks_a: tuple[TrackTable, NDArray[np.int64]],
        tracks_b: tuple[TrackTable, NDArray[np.int64]],
        time_s: float,
    ) -> np.ndarray:
        """Which of the update's candidates are clear (:mod:`.prompt`): no rival within the
        margin, both tracks of at least ``min_quality``, and both isolated within their own
        radar's tables (``tracks_*``: each table and its track keys)."""
        prm = self.params.prompt
        if not prm.enabled or self.method != "svd-topology" or len(dec) == 0:
            return np.zeros(len(dec), dtype=bool)
        clear = clear_of_rivals(dec.index_a, dec.index_b, dec.cost, dec.accepted, prm.clear_margin)
        stage = dec.extras.get("stage")
        if stage is not None:  # a lone decision waits for the book (``SvdTopologyParams.lone_pairs``)
            clear &= stage != LONE_STAGE
        clear &= self._quality_ok(dec, a, b)
        rows = np.flatnonzero(clear)
        if rows.size:
            clear[rows] = self._isolated(
                dec, rows, a, b, tracks_a, tracks_b, time_s, prm.isolation_m, prm.isolation_velocity_mps
            )
        return clear

    def decide_new(
        self,
        tracks_a: TrackTable,
        tracks_b: TrackTable,
        time_s: float,
        fresh_a: NDArray[np.int64],
        fresh_b: NDArray[np.int64],
        now_a: np.ndarray | None = None,
        now_b: np.ndarray | None = None,
    ) -> bool:
        """Tracks confirmed since the pair's last update (``fresh_a``, ``fresh_b``: their track
        keys, :attr:`track_keys`) between two updates: the clear pairs among them
        (:mod:`.prompt`) enter the book confirmed now, without waiting for the pair's next
        update (which scores the book).  Whether the book changed.

        Only a registered pair (before, it is updated every scan, and the topology decision
        needs the whole tables' neighbourhoods), by the compensated test of the method's
        re-check, and only on the tracks near a fresh one: its candidates and their rivals lie
        within two candidate gates of it.  ``now_a``, ``now_b``: every track's position brought
        to ``time_s`` (:func:`positions_at`), when known."""
        prm = self.params
        if not (prm.prompt.enabled and self.method == "svd-topology" and self.registered):
            return False
        reach = 2.0 * prm.svd.candidates.gate_m
        now_a = positions_at(tracks_a, time_s) if now_a is None else now_a
        now_b = positions_at(tracks_b, time_s) if now_b is None else now_b
        keys_a, keys_b = self._keys(tracks_a, tracks_b)
        anchors_a = now_a[isin_sorted(keys_a, fresh_a)]
        anchors = np.concatenate([anchors_a, now_b[isin_sorted(keys_b, fresh_b)]])
        near_a, near_b = _near(now_a, anchors, reach), _near(now_b, anchors, reach)
        k = len(anchors_a)
        if not (near_b[:, :k].any() or near_a[:, k:].any()):
            return False  # no partner track within reach of a fresh one: nothing to decide
        rows_a, rows_b = np.flatnonzero(near_a.any(axis=1)), np.flatnonzero(near_b.any(axis=1))
        sub_a, sub_b = tracks_a.take(rows_a), tracks_b.take(rows_b)
        sub_keys = (keys_a[rows_a], keys_b[rows_b])
        _, _, a, b, ctx_kw = self._predicted(sub_a, sub_b, time_s, *sub_keys)
        ka, kb = a.keys, b.keys
        fa, fb = isin_sorted(ka, fresh_a), isin_sorted(kb, fresh_b)
        if not (fa.any() or fb.any()):
            return False
        conf = self.book.confirmed
        ca_idx, cb_idx = _lookup_pairs(ka, kb, self.book.id_a[conf], self.book.id_b[conf])
        ref_a = _within(a.position, anchors, reach, busy=ca_idx)
        ref_b = _within(b.position, anchors, reach, busy=cb_idx)
        ctx = DecisionContext(
            time_s=time_s,
            confirmed_a=ca_idx,
            confirmed_b=cb_idx,
            reference_a=ref_a,
            reference_b=ref_b,
            **ctx_kw,  # type: ignore[arg-type]
        )
        ia, ib = _pairs_within(a.position, b.position, ref_a, ref_b, prm.svd.candidates.gate_m)
        # the compensated test decides (as the method's stage 2 would); without it, the method
        checked = self.correlator.reverify(a, b, ia, ib, ctx)
        dec = checked if checked is not None else self.correlator.decide(a, b, ctx)
        fresh = fa[dec.index_a] | fb[dec.index_b]
        clear = self._clear(dec, a, b, (sub_a, sub_keys[0]), (sub_b, sub_keys[1]), time_s) & fresh
        # a fresh track with an accepted candidate that is not clear waits for the pair's
        # next full update, which must then not wait long; but not one held back only by a
        # track's low quality: it waits for the evidence's looks, which the pair's updates on
        # their usual cadence bring (hurrying them cost 11 % of the stage's CPU on the national
        # stream and gained nothing)
        open_ = np.flatnonzero(fresh & ~clear)  # (few: the reasons are read for these only)
        unclear = dec.accepted[open_] | no_decision(dec.reason[open_])
        self.settled &= not (unclear & self._quality_ok(dec, a, b)[open_]).any()
        ev = self.evidence
        if ev is not None and clear.any() and len(ev):
            e = find(ev.keys, pair_keys(ka[dec.index_a], kb[dec.index_b]))
            clear &= ~((e >= 0) & ev.rejected()[np.maximum(e, 0)])
        if not clear.any():
            return False
        # (two clear candidates cannot share a track: each would cost ``clear_margin`` less)
        probability = (
            posterior(ka[dec.index_a], kb[dec.index_b], dec.cost, ev.params)[clear]
            if ev is not None
            else None
        )
        take = dec.take(clear)
        # A side whose table is the one the book was last checked against lost no track since.
        seen_a, seen_b = self._checked
        self._checked = (tracks_a.track_id, tracks_b.track_id)
        return self.book.admit(
            time_s,
            None if seen_a is tracks_a.track_id else keys_a,
            None if seen_b is tracks_b.track_id else keys_b,
            ka[take.index_a],
            kb[take.index_b],
            take.statistic,
            take.rotation_weight,
            take.scale,
            take.neighbors,
            _basis_codes(self._basis(take)),
            probability,
            self.book.pair_quality(len(take), *_qualities(take, a, b)),
            names=(a.track_id[take.index_a], b.track_id[take.index_b]),
        )

    def _basis(self, dec: Decisions) -> np.ndarray:
        """Each decision's :class:`~.base.Basis` code (as float; NaN: none to give)."""
        if self.site_b is None:
            return np.full(len(dec), float(Basis.REFERENCE))
        if "stage" in dec.extras:
            return np.where(dec.extras["stage"] >= 2, float(Basis.REGISTERED), float(Basis.TOPOLOGY))
        if self.method == "basic-topology":
            return np.full(len(dec), float(Basis.TOPOLOGY))
        return np.full(len(dec), np.nan)

    def _with_history(
        self,
        dec: Decisions,
        a: PredictedTracks,
        b: PredictedTracks,
        time_s: float,
        registered: bool,
        clear: np.ndarray,
    ) -> Decisions:
        """The update's decisions with the history evidence (:mod:`.evidence`) applied.

        The looks: once registered every candidate's compensated residual (taken in
        :meth:`update`); before, the residual of a candidate inside a group against the group's
        local offset (:mod:`.group_offset`), which also decides the candidates the topology
        could not.  A candidate with a source of looks is accepted only from ``min_looks``
        looks on and while its accumulated test passes; it then enters the one-to-one
        assignment with the accumulated statistic's excess ``q_rel - 3`` as its cost, so the
        (joint) ambiguity margin is applied to the history's log-likelihood ratio.  A candidate
        with no source of looks (outside any group before registration) is decided by its
        update alone.  A clear candidate (:mod:`.prompt`) is accepted on its update alone too,
        unless its history rejects it.
        """
        prm = self.params
        basis = self._basis(dec)
        ev = self.evidence
        if ev is None or len(dec) == 0:
            dec.extras["basis"] = basis
            return dec
        # Candidates with a source of looks this update: every one once registered (taken in
        # update()); before, those inside a group.  The others are decided by their update.
        sourced = np.full(len(dec), registered)
        if not registered and prm.group.enabled:
            dec, sourced = self._group_stage(dec, a, b, time_s)
        e = find(ev.keys, pair_keys(a.keys[dec.index_a], b.keys[dec.index_b]))
        e0 = np.maximum(e, 0)
        have = e >= 0
        hist = have & (ev.looks[e0] >= ev.params.min_looks) if len(ev) else have
        rej = hist & (ev.rejected()[e0] if len(ev) else False)
        accepted = dec.accepted & ~rej & (hist | ~sourced | clear | ev.params.accept_without_history)
        reason = np.where(dec.accepted & rej, np.int8(Reason.HISTORY), dec.reason).astype(np.int8)
        use = hist & accepted
        return replace(
            dec,
            accepted=accepted,
            reason=reason,
            cost=np.where(hist, (ev.q_rel[e0] - 3.0) if len(ev) else 0.0, dec.cost),
            extras={**dec.extras, "basis": np.where(use, float(Basis.HISTORY), basis)},
        )

    def _group_stage(
        self, dec: Decisions, a: PredictedTracks, b: PredictedTracks, time_s: float
    ) -> tuple[Decisions, np.ndarray]:
        """Candidates inside a group, against the group's local offset (before registration):
        a look for the residual evidence, and the decision of those the topology could not
        decide (chi-square with 3 dof at ``alpha_position``, cost ``q - 3``); also which
        candidates got a look."""
        assert self.evidence is not None
        ok, r, s_noise, s_common = group_residuals(a, b, dec.index_a, dec.index_b, self.params.group)
        rows = np.flatnonzero(ok)
        if rows.size == 0:
            return dec, ok
        self.evidence.observe(
            time_s, a.keys[dec.index_a[rows]], b.keys[dec.index_b[rows]], r, s_noise, s_common
        )
        q, good = mahalanobis3(r, s_noise + s_common)
        undecided = no_decision(dec.reason[rows]) & good
        sub = rows[undecided]
        q = q[undecided]
        passed = q <= chi2_upper(self.params.svd.alpha_position, 3)
        accepted = dec.accepted.copy()
        accepted[sub] = passed
        reason = dec.reason.copy()
        reason[sub] = np.where(passed, Reason.ACCEPTED, Reason.GATE)
        cost = dec.cost.copy()
        cost[sub] = q - 3.0
        statistic = dec.statistic.copy()
        statistic[sub] = q / 3.0
        return replace(dec, accepted=accepted, reason=reason, cost=cost, statistic=statistic), ok

    def pairs(self) -> list[PairState]:
        """Current pair book sorted by (track_a, track_b)."""
        return self.book.states()


def joint_solution(
    correlators: Sequence[PairCorrelator | _HasMemory],
    time_s: float,
    params: RegistrationParams | None = None,
    initial: BiasSolution | None = None,
) -> BiasSolution | None:
    """Joint bias least squares over every radar pair's remembered confirmed pairs.

    See :mod:`service.correlation.registration` for the model and what is observable: the
    weak prior makes unobservable components shrink to zero (minimum-norm-like) instead of
    diverging; with two radars the relative effect is determined, the split can be
    prior-driven for poorly spread geometry.  Radars without confirmed pairs are omitted.
    ``initial``: the previous joint solution, a warm start (same fixed point, fewer steps).
    """
    first = correlators[0] if correlators else None
    prm = params or (first.params.registration if isinstance(first, PairCorrelator) else RegistrationParams())
    mems = [c.memory for c in correlators if len(c.memory)]
    return solve_biases(mems, time_s, prm, initial=initial)


class _HasMemory(Protocol):
    """A mirror of another worker's pair: its registration memory only."""

    memory: RegistrationMemory


def estimate_biases(
    correlators: Sequence[PairCorrelator], time_s: float, params: RegistrationParams | None = None
) -> list[RadarBias]:
    """:func:`joint_solution` as one :class:`RadarBias` per radar."""
    return to_estimates(joint_solution(correlators, time_s, params), time_s)


def _basis_codes(basis: np.ndarray) -> NDArray[np.int8]:
    """The book's basis codes of :meth:`PairCorrelator._basis` values (NaN, none to give: -1)."""
    return np.nan_to_num(basis, nan=-1.0).astype(np.int8)


def _identities_differ(a: PredictedTracks, b: PredictedTracks, d: Decisions) -> NDArray[np.bool_]:
    """Candidates whose two tracks both carry a Mode S address, and different ones."""
    if a.mode_s is None or b.mode_s is None or not len(d):
        return np.zeros(len(d), dtype=bool)
    sa, sb = a.mode_s[d.index_a], b.mode_s[d.index_b]
    both = np.not_equal(sa, _NONE, dtype=bool) & np.not_equal(sb, _NONE, dtype=bool)
    return np.asarray(both & (sa != sb), dtype=bool)
