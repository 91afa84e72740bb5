"""System tracks: one fused, bias-compensated track per target (contract §4.4), pure numpy.

Input, at one data time: every source's tracks as *members* (radar tracks bias-compensated
with the current joint estimate, :func:`service.correlation.registration.compensate`, with the
covariance the estimate's uncertainty adds; reference tracks as they are) and the confirmed
pairs between them as *links*, each with its evidence (``score``).

1. **Groups.**  A link whose two members have *diverged* (their bias-compensated positions
   differ by more than a chi-square gate of their summed covariances,
   :attr:`SystemTrackParams.split_alpha`: a track swapped onto another aircraft, or two
   aircraft that flew apart while their pair still stands) is left out first, so the system
   track they made splits at this update (each part keeps or takes a number, step 2).  The
   other links form a graph; each connected group with at most one track per source
   is one system track.  A group that holds two tracks of one source (a chain A1-B1-A2) is cut:
   its links are taken strongest first and a link that would put a second track of a source
   into a group is left out (the weakest link goes).  Only such groups take this step, a plain
   loop over their links; all others are found by one sparse connected-components pass.
2. **Numbers.**  A group takes the number most of its members had (ties: the oldest number); a
   number two groups claim (a split) stays with the one that holds more of its old members,
   the other takes a new number.  Numbers are never reused (nor across restarts with a state
   directory: each start numbers from its epoch's first number), so a number follows its
   aircraft through member changes: a radar leaving or joining changes the members, not the
   number.
3. **State.**  Members of radars are fused by **covariance intersection** with the fast
   trace weights ``w_i ~ 1/tr P_i``: their errors are correlated (one target's manoeuvres enter
   every radar's track; all biases come from one joint solution), with a cross-covariance nobody
   knows, and CI is consistent whatever it is.  Members of bias-free references (AIS, ADS-B)
   have errors of their own (GNSS), independent of the radars': they are added to the CI result
   in **information form**.  Positions and velocities are fused as two 3x3 blocks (the trackers'
   position-velocity cross-covariance is left out: what it adds is second order here).
4. **Status.**  A system track is confirmed when one of its members is, but for a young lone
   radar track near another system track that lacks its radar (:class:`SystemTrackParams`):
   that is most likely a radar's new view of an aircraft already held, and stays tentative
   until its pairs link it or it has stood alone long enough.  A radar track without links is
   a system track of one member; a reference track becomes one only through a link (a
   reference alone is not part of the radar picture).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from service.chi2 import chi2_upper
from service.correlation.pairkeys import SEP  # a member's key: source, SEP, track id
from service.linalg import inv3, mahalanobis3
from service.tracking.base import first_number

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class Members:
    """Every member candidate at one data time, columnar (row ``i`` is one source track)."""

    source: NDArray[np.str_]
    track_id: NDArray[np.str_]
    reference: NDArray[np.bool_]  # a bias-free reference track
    confirmed: NDArray[np.bool_]
    position: FloatArray  # (n, 3) ECEF, bias-compensated
    velocity: FloatArray  # (n, 3)
    pos_cov: FloatArray  # (n, 3, 3), compensation uncertainty included
    vel_cov: FloatArray  # (n, 3, 3)

    def __len__(self) -> int:
        return int(self.source.shape[0])

    def keys(self) -> NDArray[np.str_]:
        return np.char.add(np.char.add(self.source.astype(str), SEP), self.track_id.astype(str))


@dataclass(frozen=True)
class SystemTracks:
    """The system tracks of one update, columnar; ``member_group[i]`` is the row of the system
    track member ``i`` of the input belongs to (-1: none)."""

    number: IntArray
    confirmed: NDArray[np.bool_]
    position: FloatArray
    velocity: FloatArray
    pos_cov: FloatArray
    vel_cov: FloatArray
    member_group: IntArray

    def __len__(self) -> int:
        return int(self.number.shape[0])

    def position_sigma_m(self) -> FloatArray:
        """RMS position error per axis, ``sqrt(tr P / 3)``."""
        return np.sqrt(np.clip(np.trace(self.pos_cov, axis1=1, axis2=2), 0.0, None) / 3.0)


def groups(n: int, source_code: IntArray, link_a: IntArray, link_b: IntArray, score: FloatArray) -> IntArray:
    """Group of each of ``n`` members (see module, step 1), -1 for none; groups numbered by
    their smallest member."""
    comp = _components(n, link_a, link_b)
    n_src = int(source_code.max()) + 1 if n else 1
    key = comp.astype(np.int64) * n_src + source_code
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    crowded = np.unique(comp[counts[inverse] > 1])
    if crowded.size:
        comp = comp.copy()
        next_group = n
        for c in crowded.tolist():  # only groups holding two tracks of one source
            inside = np.flatnonzero(comp == c)
            on = np.isin(link_a, inside) & np.isin(link_b, inside)
            sub = _constrained(inside, source_code, link_a[on], link_b[on], score[on])
            comp[inside] = sub + next_group
            next_group += int(sub.max()) + 1
    # canonical numbering: by each group's smallest member
    first = np.full(comp.max() + 1 if n else 0, n, dtype=np.int64)
    np.minimum.at(first, comp, np.arange(n))
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(order.shape[0])
    return rank[comp].astype(np.int64)


def diverged(members: Members, link_a: IntArray, link_b: IntArray, alpha: float) -> NDArray[np.bool_]:
    """Per link: have its two members' positions diverged (:attr:`SystemTrackParams.split_alpha`;
    a singular covariance never splits; ``alpha`` 0: none has)?"""
    if alpha <= 0.0 or link_a.shape[0] == 0:
        return np.zeros(link_a.shape[0], dtype=bool)
    d = members.position[link_a] - members.position[link_b]
    d2, ok = mahalanobis3(d, members.pos_cov[link_a] + members.pos_cov[link_b])
    return np.asarray(ok & (d2 > chi2_upper(alpha, 3.0)))


def _components(n: int, a: IntArray, b: IntArray) -> IntArray:
    graph = coo_matrix((np.ones(a.shape[0]), (a, b)), shape=(n, n))
    return connected_components(graph, directed=False)[1].astype(np.int64)


def _constrained(
    inside: IntArray, source_code: IntArray, a: IntArray, b: IntArray, score: FloatArray
) -> IntArray:
    """Groups of one crowded component: links strongest first, a link that would join two
    tracks of one source is left out (union-find, at most ``len(inside)`` unions)."""
    local = {int(m): k for k, m in enumerate(inside.tolist())}
    parent = list(range(inside.shape[0]))
    sources = [{int(source_code[m])} for m in inside.tolist()]

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    order = np.lexsort((b, a, -score))  # strongest first; ties by member rows
    for i, j in zip(a[order].tolist(), b[order].tolist(), strict=True):
        ri, rj = root(local[i]), root(local[j])
        if ri == rj or sources[ri] & sources[rj]:
            continue
        parent[rj] = ri
        sources[ri] |= sources[rj]
    roots = np.array([root(k) for k in range(inside.shape[0])], dtype=np.int64)
    return np.unique(roots, return_inverse=True)[1].astype(np.int64)


def _inv3(m: FloatArray) -> FloatArray:
    """Inverse of a stack of covariances (closed form; a singular one gives zero information)."""
    return inv3(m)[0]


def fuse(
    members: Members, group: IntArray, n_groups: int
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Fused position, velocity and their covariances per group (module, step 3)."""
    radar = ~members.reference & (group >= 0)
    ref = members.reference & (group >= 0)
    pos, pos_cov = _fuse_block(members.position, members.pos_cov, group, radar, ref, n_groups)
    vel, vel_cov = _fuse_block(members.velocity, members.vel_cov, group, radar, ref, n_groups)
    return pos, vel, pos_cov, vel_cov


def _fuse_block(
    x: FloatArray, p: FloatArray, group: IntArray, radar: NDArray[np.bool_], ref: NDArray[np.bool_], n: int
) -> tuple[FloatArray, FloatArray]:
    info = _inv3(p)
    # covariance intersection of the radar members, fast trace weights (Niehsen 2002 form)
    inv_tr = np.where(radar, 1.0 / np.maximum(np.trace(p, axis1=1, axis2=2), 1e-12), 0.0)
    total = np.bincount(group[radar], weights=inv_tr[radar], minlength=max(n, 1))
    w = np.where(radar, inv_tr / np.maximum(total[np.maximum(group, 0)], 1e-300), 0.0)
    # references (independent of the radars) enter in information form: weight 1
    weight = np.where(radar, w, np.where(ref, 1.0, 0.0))
    use = radar | ref
    g = group[use]
    big_i = _group_sum(g, (weight[use, None, None] * info[use]).reshape(-1, 9), n).reshape(n, 3, 3)
    big_y = _group_sum(g, weight[use, None] * np.einsum("nij,nj->ni", info[use], x[use]), n)
    cov = _inv3(big_i)
    return np.einsum("nij,nj->ni", cov, big_y), cov


def _group_sum(group: IntArray, values: FloatArray, n: int) -> FloatArray:
    """Row sums of ``values`` (m, k) per group (one bincount per column: faster than add.at)."""
    return np.stack(
        [np.bincount(group, weights=values[:, j], minlength=n) for j in range(values.shape[1])], axis=1
    )


@dataclass(frozen=True)
class SystemTrackParams:
    """When a lone radar track is not (yet) a confirmed system track (module, step 4)."""

    #: A one-member system track whose radar track joined the picture less than this long ago
    #: (data s) ...
    solo_hold_s: float = 60.0
    #: ... and lies within this distance (m, bias-compensated) of another system track that has
    #: no track of its radar stays tentative: most likely that radar's new view of an aircraft
    #: the other holds (it came into the radar's cover, or the radar restarted its track), whose
    #: pairs confirm a few scans later.  Both chosen from the system-track study
    #: (docs/evaluation/system.md): such stray tracks are younger than a minute and sit within a
    #: few kilometres (a young track at 300 km is off by up to about 1 km per 0.2 deg of noise).
    solo_gate_m: float = 5_000.0
    #: Two linked members have diverged when the squared Mahalanobis distance of their position
    #: difference under the sum of their position covariances (compensation uncertainty
    #: included) exceeds the chi-square's upper ``split_alpha`` quantile with 3 degrees of
    #: freedom (1e-6: 30.7): a right link does so once in a million pictures, as the
    #: correlation's swap rule (``SwapParams.alpha``), which re-decides such a pair within a
    #: scan; the split takes the two aircraft apart at the picture already.  0: never split.
    split_alpha: float = 1e-6


class SystemTracker:
    """System tracks over time: the numbers their members carried before (module, step 2)."""

    def __init__(self, params: SystemTrackParams | None = None, epoch: int = 0) -> None:
        """``epoch``: the service's start with its state directory (``service.state``); numbers
        begin at :func:`~service.tracking.base.first_number` of it, so none is reused across
        restarts."""
        self.params = params or SystemTrackParams()
        self._keys = np.empty(0, dtype=str)  # sorted member keys of the last update
        self._numbers = np.empty(0, dtype=np.int64)  # their system track numbers
        self._since = np.empty(0)  # when each joined the picture (data s)
        self._next = first_number(epoch)

    def update(
        self, members: Members, link_a: IntArray, link_b: IntArray, score: FloatArray, time_s: float = 0.0
    ) -> SystemTracks:
        n = len(members)
        keep = ~diverged(members, link_a, link_b, self.params.split_alpha)
        link_a, link_b, score = link_a[keep], link_b[keep], score[keep]
        linked = np.zeros(n, dtype=bool)
        linked[link_a] = linked[link_b] = True
        _, source_code = np.unique(members.source.astype(str), return_inverse=True)
        group = groups(n, source_code.astype(np.int64), link_a, link_b, score)
        # a reference track is a member only through a link
        group = np.where(members.reference & ~linked, -1, group)
        used, group = np.unique(group, return_inverse=True)
        group = group.astype(np.int64) - (1 if used.size and used[0] == -1 else 0)
        n_groups = int(used.size - (1 if used.size and used[0] == -1 else 0))
        all_keys = members.keys()
        since = self._since_of(all_keys, time_s)
        numbers = self._numbers_for(all_keys, group, n_groups)
        pos, vel, pos_cov, vel_cov = fuse(members, group, n_groups)
        confirmed = np.zeros(n_groups, dtype=bool)
        member = group >= 0
        np.logical_or.at(confirmed, group[member], members.confirmed[member])
        confirmed &= ~self._held_solo(members, source_code.astype(np.int64), group, since, pos, time_s)
        keys = all_keys[member]
        order = np.argsort(keys)
        self._keys, self._numbers = keys[order], numbers[group[member]][order]
        self._since = since[member][order]
        return SystemTracks(numbers, confirmed, pos, vel, pos_cov, vel_cov, group)

    def _since_of(self, keys: NDArray[np.str_], time_s: float) -> FloatArray:
        """When each member joined the picture (``time_s`` for new ones)."""
        since = np.full(keys.shape[0], time_s)
        if self._keys.shape[0] and keys.shape[0]:
            at = np.minimum(np.searchsorted(self._keys, keys), self._keys.shape[0] - 1)
            hit = self._keys[at] == keys
            since[hit] = self._since[at[hit]]
        return since

    def _held_solo(
        self,
        members: Members,
        source_code: IntArray,
        group: IntArray,
        since: FloatArray,
        position: FloatArray,
        time_s: float,
    ) -> NDArray[np.bool_]:
        """Groups held tentative: young lone radar tracks near another system track that has
        no track of their radar (:class:`SystemTrackParams`)."""
        p = self.params
        n_groups = position.shape[0]
        held = np.zeros(n_groups, dtype=bool)
        member = np.flatnonzero(group >= 0)
        size = np.bincount(group[member], minlength=n_groups)
        solo = member[(size[group[member]] == 1) & ~members.reference[member]]
        solo = solo[time_s - since[solo] < p.solo_hold_s]
        if not solo.shape[0] or n_groups < 2:
            return held
        tree = cKDTree(position)
        near = tree.query_ball_point(position[group[solo]], r=p.solo_gate_m)
        # (group, source) pairs present, to ask "has that system track a track of this radar?":
        # a flag each (groups x sources bytes, 270 kB for 6 000 system tracks of 45 radars)
        n_src = int(source_code.max()) + 1
        present = np.zeros(n_groups * n_src, dtype=bool)
        present[group[member] * n_src + source_code[member]] = True
        lone_group = group[solo]
        counts = np.fromiter((len(x) for x in near), dtype=np.int64, count=len(near))
        cand = (
            np.concatenate([np.asarray(x, dtype=np.int64) for x in near])
            if counts.sum()
            else np.empty(0, np.int64)
        )
        owner = np.repeat(np.arange(solo.shape[0]), counts)
        other = cand != lone_group[owner]
        has_radar = present[cand * n_src + source_code[solo][owner]]
        # Two young lone tracks (one new aircraft seen by two radars at once) must not hold
        # each other back: of those, the one that joined first (then the lower group) stands.
        young = np.zeros(n_groups, dtype=bool)
        young[lone_group] = True
        joined = np.full(n_groups, np.inf)
        joined[lone_group] = since[solo]
        mine = lone_group[owner]
        earlier = (joined[cand] < joined[mine]) | ((joined[cand] == joined[mine]) & (cand < mine))
        hit = other & ~has_radar & (~young[cand] | earlier)
        held[lone_group[np.unique(owner[hit])]] = True
        return held

    def _numbers_for(self, keys: NDArray[np.str_], group: IntArray, n_groups: int) -> IntArray:
        member = np.flatnonzero(group >= 0)
        old = np.full(member.shape[0], -1, dtype=np.int64)
        if self._keys.shape[0] and member.shape[0]:
            at = np.minimum(np.searchsorted(self._keys, keys[member]), self._keys.shape[0] - 1)
            hit = self._keys[at] == keys[member]
            old[hit] = self._numbers[at[hit]]
        g = group[member]
        had = old >= 0
        # votes: (group, old number) -> members; each group's leading number (ties: oldest).
        # One int64 key per (group, number) pair: a 1-D unique (a row-wise one sorts a view).
        span = int(old.max()) + 1 if had.any() else 1
        codes, votes = np.unique(g[had] * span + old[had], return_counts=True)
        pairs = np.stack([codes // span, codes % span], axis=1)
        number = np.full(n_groups, -1, dtype=np.int64)
        if pairs.shape[0]:
            order = np.lexsort((pairs[:, 1], -votes, pairs[:, 0]))
            pairs, votes = pairs[order], votes[order]
            lead = np.r_[True, pairs[1:, 0] != pairs[:-1, 0]]
            cand_g, cand_n, cand_v = pairs[lead, 0], pairs[lead, 1], votes[lead]
            # a number claimed by two groups stays with the one holding more of its members
            # (ties: the group with the smallest member row, i.e. the lower group index)
            order = np.lexsort((cand_g, -cand_v, cand_n))
            cand_g, cand_n = cand_g[order], cand_n[order]
            keep = np.r_[True, cand_n[1:] != cand_n[:-1]]
            number[cand_g[keep]] = cand_n[keep]
        fresh = np.flatnonzero(number < 0)  # in group order: by smallest member row
        number[fresh] = self._next + np.arange(fresh.shape[0])
        self._next += int(fresh.shape[0])
        return number
