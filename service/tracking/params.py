"""Named, documented parameters of the per-radar tracker and its initiators.

Every threshold used in ``service/tracking`` lives here, in frozen dataclasses, so that a
result can always be traced back to one documented number.  Defaults suit a surveillance
radar of the contract's kind (200 m / 0.2 deg, 4 s scan, air targets up to Mach 2).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

from annotated_types import Ge, Gt, Le


@dataclass(frozen=True)
class MeasurementParams:
    """Polar plot to ENU position."""

    altitude_sigma_m: float = 100.0
    """1-sigma error of a given (or assumed 0) altitude for 2-D radars; it is mapped into an
    elevation sigma ``altitude_sigma_m / (r cos el)`` in place of the site's elevation sigma."""

    coincident_sigma: float = 0.05
    """Plots of one batch in one cell of this many of the site's sigmas on range, azimuth and
    elevation, with the same Mode S address, are one detection: the first is kept, the others
    dropped and counted (``/status`` ``radars[].plots_coincident``;
    :mod:`service.tracking.coincident`).  0: every plot is kept."""


@dataclass(frozen=True)
class FilterParams:
    """Constant-velocity Kalman filter."""

    process_noise_psd: float = 25.0
    """Continuous white-noise acceleration spectral density q (m^2/s^3) per ENU axis.  The
    discretised process noise over dt is ``q [[dt^3/3, dt^2/2], [dt^2/2, dt]]`` per axis
    (Bar-Shalom, Li, Kirubarajan 2001, Eq. 6.2.2-12); q = 25 lets a target change speed by
    about ``sqrt(q T)`` = 10 m/s per 4 s scan, covering gentle manoeuvres."""

    imm: bool = True
    """Whether the filter is an interacting multiple model (:mod:`service.tracking.imm`) of two
    constant-velocity models: a *quiet* one (``quiet_psd``) and a *manoeuvre* one
    (``manoeuvre_psd``).  Off: the one model of ``process_noise_psd``, which also serves the
    initiators' fit of a new track and the duplicate test either way.  Measured (12 aircraft
    in a rate-one turn through 90 degrees, 5 seeds, 0.2 deg / 200 m plots at 60 km): track
    numbers changed 64 times against 108 with the one model, and the position error on
    straight legs fell from 193 to 154 m RMS; in the formation study, tracks astray on a
    neighbour fell by a quarter to a third."""

    quiet_psd: float = 1.0
    """q (m^2/s^3) of the IMM's quiet model: straight flight at a steady speed, about
    ``sqrt(q T)`` = 2 m/s of velocity change per 4 s scan.  A track in it predicts a few
    hundred metres closer than with the manoeuvre model's q after a missed plot, which is
    what keeps the tracks of aircraft flying in formation on their own aircraft."""

    quiet_sojourn_s: Annotated[float, Gt(0)] = 120.0
    """Mean time (s) a target stays in the quiet model (straight legs last minutes): with
    ``manoeuvre_sojourn_s``, the models' switching rates (the two-state chain of
    :meth:`service.tracking.imm.Models.transition`); a new track starts at the long-run
    shares, 0.8 / 0.2 by default."""

    manoeuvre_psd: float = 100.0
    """q (m^2/s^3) of the IMM's manoeuvre model: ``sqrt(q T)`` = 20 m/s of velocity change per
    4 s scan, the order of a rate-one turn's (3 deg/s at 230 m/s is 12 m/s^2).  At 400 it held
    turns better still and lost the formations' gain; at 25 (the one model's) it lost turns as
    that one does."""

    manoeuvre_sojourn_s: Annotated[float, Gt(0)] = 30.0
    """Mean time (s) a target stays in the manoeuvre model (a rate-one turn through 90 degrees
    takes 30 s)."""

    gate_chi2: float = 16.27
    """Association gate on the Mahalanobis distance ``y^T S^-1 y`` of a plot to a track's
    prediction at the plot's own time; chi-square with 3 degrees of freedom at 99.9 %."""

    coarse_gate_max_m: float = 20_000.0
    """Cap (m) on the Euclidean pre-gate radius used for the KD-tree candidate search."""


@dataclass(frozen=True)
class ManagerParams:
    """Track life cycle: M-of-N confirmation, deletion, expected-detection test."""

    confirm_m: Annotated[int, Ge(1), Le(30)] = 4
    """M of the M-of-N confirmation: a track is confirmed once it has ``confirm_m`` hits among
    its last ``confirm_n`` looks (a look = a batch in which a detection was expected)."""

    confirm_n: Annotated[int, Ge(1), Le(30)] = 5
    """N of the M-of-N confirmation (at most 30)."""

    confirmed_max_misses: int = 3
    """A confirmed track is deleted after this many consecutive expected-but-missed looks, or
    more on a radar that misses more often (``deletion_miss_probability``)."""

    deletion_miss_probability: Annotated[float, Le(1)] = 2e-3
    """Deletion by the radar's detection probability: a confirmed track is deleted after the
    shortest run of expected misses in a row that an aircraft still there would give with at
    most this probability, ``(1 - Pd)^k <= p``, for an established track
    (``established_plots``), never fewer than ``confirmed_max_misses`` nor
    more than ``confirmed_misses_cap`` (:mod:`service.tracking.detection`).  ``Pd`` is the
    share of the looks due from the radar's established tracks (one a scan each) in which they
    took a plot.  With 2e-3 a radar of Pd 0.88 or more keeps 3; Pd 0.75 gives 5, 0.7 gives 6.
    0: always ``confirmed_max_misses``."""

    established_plots: Annotated[int, Ge(0)] = 10
    """Only a confirmed track with at least this many plots (established) measures the radar's
    Pd and survives more than ``confirmed_max_misses``.  Clutter makes young confirmed tracks
    that soon miss; counted, they lowered the Pd, which let them live longer, which lowered it
    more (two radars in 3 000 clutter plots a scan: 87 % of the confirmed tracks on clutter
    against 51 % with a fixed three).  0 counts every confirmed track: that loop."""

    confirmed_misses_cap: Annotated[int, Ge(1), Le(60)] = 8
    """The most expected misses in a row an established track survives, whatever the radar's
    Pd (a track that coasts longer is too far off to take its aircraft's plots back); not below
    ``confirmed_max_misses`` (checked at start)."""

    detection_memory_scans: Annotated[float, Gt(0)] = 20.0
    """The memory of the measured Pd, in scans (an exponential weight of data time)."""

    detection_min_looks: Annotated[float, Gt(0)] = 100.0
    """Fewer looks than this (weighted) behind the measured Pd: ``confirmed_max_misses``."""

    detection_min_scans: Annotated[float, Ge(0)] = 5.0
    """Nor before this many scans (weighted) of the radar: at the start its tracks are
    confirmed by the hundred in one scan, each due a look before its sector has come round."""

    coast_scans: float = 3.5
    """Any track not updated for ``coast_scans * scan_period_s`` of data time is deleted
    (catches tracks that left the coverage, where no look is counted); for an established track
    at least its expected misses to deletion plus a half (``deletion_miss_probability``), so
    that the looks decide while the radar still looks."""

    sector_margin_deg: float = 1.0
    """A track only counts a miss when its predicted azimuth lies inside the azimuth arc the
    batch's plots cover by at least this margin (sector batches)."""

    birth_velocity_sigma_mps: float = 1000.0
    """Prior velocity sigma when a track is born from an initiator's plots (weak prior: the
    velocity then comes from the plots)."""

    initiation_interval_scans: float = 0.05
    """The initiators search the window at most once per this many scan periods of the radar's
    data time (a batch closer to the last search only adds its plots to the window, searched
    at the next one).  The search covers the whole window, so without this a radar sending
    hundreds of one-plot batches a second would pay a whole-window search for each; a radar's
    sector batches (8 to 32 a scan) are further apart than this and unaffected."""

    birth_max_mean_nis: float = 12.0
    """A candidate from any initiator is born only if the mean normalised innovation squared
    of its plots after the second one stays below this (a consistency check of the CV fit)."""


@dataclass(frozen=True)
class LogicParams:
    """The fast M/N logic initiator with velocity gates (3 plots, 3 looks)."""

    min_dt_scans: float = 0.5
    """Shortest time (in scan periods) between two plots of one candidate."""

    max_dt_scans: float = 2.5
    """Longest time (in scan periods) between two plots of one candidate (allows one miss)."""

    min_speed_mps: float = 0.0
    """Velocity gate, lower bound (m/s) on the two-point speed (with a 3-sigma allowance)."""

    max_speed_mps: float = 700.0
    """Velocity gate, upper bound (m/s) on the two-point speed (with a 3-sigma allowance)."""

    max_accel_mps2: float = 5.0
    """Acceleration allowance in the third-plot gate: adds ``(a dt^2 / 2)^2`` per axis."""

    gate_chi2: float = 11.34
    """Third-plot gate on the Mahalanobis distance to the straight-line prediction; chi-square
    with 3 degrees of freedom at 99 %."""

    support_weight: float = 8.0
    """Conflicting triples are ranked by ``d^2 - support_weight * ln(support)`` instead of their
    ``d^2`` alone (:func:`service.tracking.logic.velocity_support`): a triple whose velocity
    many nearby triples share wins over one that only its own plots show.  In a formation every
    aircraft flies the common velocity, while a triple across the formation (one aircraft's
    plot, then a neighbour's, then the next one's: as straight as one aircraft's when the
    spacing is about a scan's travel) has the common velocity plus a lattice step per scan,
    which fewer triples share.  An aircraft alone has support 1 (ln 1 = 0): its ranking is as
    before.  Measured in the formation study (3 seeds, 8 points, docs/results.md): ID switches
    per aircraft-hour fell at 7 of 8 points (2x: 13.7 to 7.6; merging: 8.6 to 8.8), correct
    pairs rose at 6 (4x: 77 to 87 %); a weight of 4 gave less, 16 no more.  0 turns the rule
    off."""

    support_radius_m: Annotated[float, Gt(0)] = 10_000.0
    """Triples support each other when their first plots lie within this distance (m) on each
    horizontal axis: a formation's extent, so that aircraft far apart with the same velocity
    (an airway's traffic) do not rank each other's candidates."""

    support_sigma: float = 2.0
    """... and their two-point velocities (first to third plot, horizontal) within this many
    velocity errors on each axis; the error is the median over the call's triples of the
    first and third plots' horizontal position sigma (root of the trace of their summed
    covariances) over their time apart."""

    support_max_pairs: int = 10_000_000
    """Work bound of the support count (:func:`service.tracking.logic.velocity_support`): the
    (triple, neighbour) pairs it may visit, estimated as the sum of the squared counts of the
    triples' cells; beyond it, a triple's support is its cell's count.  Measured, about 0.04 s
    per million pairs (5 000 triples all within one another's reach, 4.8 million pairs: 0.39 s;
    20 000: 4.6 s; the formation study's densest first scans, 12 000 triples and 12.9 million
    estimated: 0.55 s), so one count costs at most about 0.4 s.  The national network's counts
    took 0.09 s in all over 120 s of data; a flood of 100 000 plots a scan counts cells."""


@dataclass(frozen=True)
class HoughParams:
    """Classic and probabilistic-grid Hough transforms (Hough paper Section 1, Eq. 2-6)."""

    theta_bins: int = 180
    """Number of normal-angle cells over [0, pi) in the (theta, rho) parameter space."""

    rho_step_m: float = 400.0
    """Size of a rho cell (m); the paper: pick it from the measurement error (Section 1)."""

    cell_m: float = 200.0
    """Size of a square cell of the probabilistic grid (Eq. 4) in the surveillance plane (m)."""

    subsamples: int = 2
    """Eq. (4) integrates the density over each cell; the midpoint rule on a
    ``subsamples x subsamples`` lattice per cell is used."""

    truncate_sigma: float = 3.0
    """Eq. (2) is truncated outside this many sigma (the paper: 3-sigma region)."""

    min_votes: float = 3.0
    """A peak of the accumulator (votes, or summed probability for the PG form) must reach this
    to start a preliminary track."""

    pg_min_votes: float = 1.5
    """The same for the probabilistic-grid form, whose votes are summed cell probabilities: a
    plot spreads its unit mass over the rho cells its error ellipse crosses, so a line of
    three plots with errors near ``rho_step_m`` peaks at about half its plot count."""

    member_sigma: float = 2.5
    """A plot belongs to a peak's line if its distance to the line is within ``member_sigma``
    times its own position sigma normal to the line (PG form) ..."""

    member_band_m: float = 400.0
    """... or, for the classic Hough, within this fixed half-band (m) of the line."""

    min_plots: int = 3
    """A preliminary track needs at least this many plots (not claimed by a stronger peak)."""

    peak_neighbourhood: int = 3
    """Peaks are local maxima over ``peak_neighbourhood x peak_neighbourhood`` cells."""

    max_lines: int = 200
    """At most this many lines are extracted per call (sequential extraction)."""


@dataclass(frozen=True)
class ClusterParams:
    """Velocity fuzzy clustering (Hough paper Section 2, Eq. 7-10, Steps 1-8)."""

    delta_v_mps: float = 100.0
    """Speed resolution Delta v of Eq. (8) (m/s): the velocity difference two targets must show
    to be told apart."""

    lam: float = 4.0
    """Threshold coefficient lambda of Eq. (8), scaling the diagonal (threshold) term."""

    eta: float = 1.0
    """Weighting exponent eta of Eq. (8) on location errors and plot distances."""

    c: float = 2.0
    """Fuzzy weighting exponent c > 1 of Eq. (9).  Note: within one column k of U_i the
    denominator of Eq. (9) is common, so the Step 5 test ``u_ijk > u_ikk`` equals
    ``d_ijk > d_ikk`` for every c > 1; c only changes the reported similarities."""

    min_dt_s: float = 1e-4
    """Pairs closer in time than this (the time-stamp resolution, 0.1 ms in the paper) give no
    velocity (Eq. 7 needs t_i != t_j); such plots can still join through Step 7 merging."""

    merge_overlap: int = 2
    """Step 7: sets sharing at least this many plots are merged (the paper: 2)."""

    min_plots: int = 3
    """Step 8 outputs only sets of at least this many plots (each non-empty set of Step 5 has
    at least three)."""

    # -- fixes of Steps 7-8 (see service/tracking/velocity_tracks.py) ---------------------
    plot_gate_chi2: float = 13.82
    """Constant-velocity consistency: every plot of a track must lie within this normalised
    squared distance ``r^T C^-1 r`` of the set's least-squares CV line (chi-square, 2 degrees
    of freedom, 99.9 %); also the gate (with the fit's own uncertainty) for absorbing further
    plots of the preliminary track in Step 8."""

    fit_confidence: float = 0.999
    """... and the set's total residual ``chi2`` must stay below the chi-square quantile at
    this confidence with ``2 n - 4`` degrees of freedom."""

    min_span_s: float = 2.0
    """A set must span at least this much time for its velocity to count as measured (shorter
    sets are degenerate: no decision)."""

    min_speed_mps: float = 0.0
    """Speed gate, lower bound (m/s), on the fitted velocity of a track."""

    max_speed_mps: float = 700.0
    """Speed gate, upper bound (m/s), on the fitted velocity of a track."""

    plot_llr: float = 5.0
    """Step 8 takes the candidate with the largest score ``sum_p (plot_llr - d_p^2 / 2)`` first
    (``d_p^2`` its plot's normalised distance to the set's CV line): a track log-likelihood
    ratio against clutter whose per-plot constant is ``plot_llr``, so a plot adds to a track
    only when it lies within ``sqrt(2 plot_llr)`` sigma of it."""

    min_track_score: float = 0.0
    """Step 8 starts a track only if that score reaches this (a sequential-test style
    threshold: clutter sets that happen to fit a straight line score low)."""

    line_angle_deg: float = 10.0
    """A candidate's fitted velocity must run along its preliminary track's Hough line within
    this angle (plus 3 sigma of the velocity's normal component)."""

    same_target_chi2: float = 18.47
    """Step 8: two started tracks whose CV states (position and velocity) differ by at most
    this Mahalanobis distance are one target and are merged (chi-square, 4 degrees of
    freedom, 99.9 %)."""

    extend: bool = True
    """Step 8: absorb the preliminary track's remaining plots that fall in the prediction gate
    of an accepted set's CV fit (so a target is not left with a second, partial track)."""

    refine_rounds: int = 3
    """Step 8: rounds of giving each plot of the selected tracks to the track it fits best
    (then refitting); 0 disables."""

    grow_rounds: int = 6
    """Step 7 (fixed): at most this many refit-and-regate rounds per set (a handful)."""


@dataclass(frozen=True)
class BoundParams:
    """Bounds on the memory and work of one update, whatever a batch holds.

    The contract allows batches of up to 100 000 plots (``service.messages.MAX_BATCH_ITEMS``),
    and a dense one can put tens of thousands of plots within one initiator search radius
    (``max_speed * dt`` plus a few sigma: tens of kilometres).  Without bounds the candidate
    pairs, triples and local clusters grow quadratically or worse with the plots and one batch
    exhausts the memory.  Normal traffic stays far below every bound (figures below: the
    tracking benchmark, 1 000 targets + 200 clutter plots per scan), so results there are
    exactly those of the unbounded search.
    """

    max_window_plots: int = 50_000
    """At most this many plots stay in the sliding window; beyond it the oldest (by plot time,
    then arrival) are evicted and counted (``Tracker.window_evicted``).  A window of three scans
    normally holds some 600-1 800 plots (the benchmark), so this is about 30 times the busiest
    normal window yet half a contract batch.  A full window of uniform clutter costs the logic
    initiator about 0.4 s per update on 2 cores (measurements of all its plots, the grid count
    of the pair search, ``max_pairs`` candidates) and the window itself some 25 MB."""

    max_pairs: int = 1_000_000
    """Work bound of the initiators' pair searches: candidate pairs (a plot and a later one in
    the 3x3 grid cells of the search radius around it, inside its time gate;
    :mod:`service.tracking.pairs`) examined per update.  Beyond it whole grid cells are
    searched, the least crowded first, up to this many candidates; the crowded cells wait for
    a later update.  The benchmark's windows have at most about 30 000 candidates; 4 million
    take about half a second on a 300 000-plot window.  It was 4 million: one radar sending
    200 plots 15 m apart every half second (valid plots, a hostile or broken feed) then cost
    the logic initiator about 0.5 s an update, as long in CPU as the data it carried, and held
    every other radar's outputs back; at 1 million, 1.1 s for those 20 s of data."""

    max_triples: int = 200_000
    """Work bound of the logic initiator's triples: pairs ``(i, j)`` are joined with the pairs
    ``(j, k)``, the pairs with the fewest continuations first, stopping before the pair whose
    triples would pass this.  The benchmark's windows form at most about 600 triples, the
    formation study's tightest point (30 aircraft 403 m apart) 23 548; it was 1 million, whose
    conflict resolution and velocity support took seconds an update on a flood of plots."""

    block: int = 250_000
    """Candidate pairs or triples held in memory at once (the searches run in blocks of this
    many, plus at most one plot's own candidates).  A candidate pair costs about 100 bytes of
    temporaries and a triple about 300, so a block stays under 100 MB; splitting into blocks
    changes no result."""

    gate_block: int = 32_768
    """Association: (track, plot) candidate predictions of the exact gate made at once, one per
    filter model (so with the two-model filter, half this many candidates a block; the KD-tree
    pre-gate search runs on chunks of tracks of the same memory).  A prediction costs about
    1.3 kB (its own 6x6 covariance and temporaries), so a block about 40 MB (47 MB measured
    with the two-model filter's mixing); the benchmark's
    batches have at most about 4 000 candidates, so they stay one block."""

    max_cluster_plots: int = 200
    """The Hough family initiators run on local clusters of plots that one target could have
    produced; a cluster with more plots than this is not transformed in that update (its plots
    stay in the window).  Velocity clustering builds ``S x S x S`` arrays over the ``S`` plots
    of a Hough band (at most the cluster): 64 MB per array at 200 plots, 8 GB at 1 000.  The
    monostatic scenario with 300 targets and 300 clutter plots per scan forms clusters of at
    most about 60 plots."""


@dataclass(frozen=True)
class FormationParams:
    """Tracks in formations: the quality of a track's associations (``Track.quality``), and
    duplicate tracks (two tracks of one radar fed by one aircraft's plots in turn;
    :mod:`service.tracking.duplicates`)."""

    quality_memory_looks: float = 5.0
    """``Track.quality`` is an exponential average of the clarity of a track's associations
    (:func:`service.tracking.assignment.clarity`) with this memory, in associations: each one
    moves it ``1 / quality_memory_looks`` of the way to that association's clarity, so a swap
    between two close aircraft shows within a few scans and fades after about this many clear
    ones; a track's first association sets it."""

    update_clarity_floor: Annotated[float, Gt(0)] = 0.25
    """A track flying in a formation (``hold_formations``' search) is updated by its plot of
    clarity ``w`` < 1 (:func:`service.tracking.assignment.clarity`) as by a plot of covariance
    ``R / max(w, update_clarity_floor)`` (:func:`service.tracking.assignment.weighted_covariance`):
    a plot its neighbour's gate held as well pulls the track by the share of the association
    the chosen one holds, as JPDA weighs it, so one neighbour's plot moves it a fraction of the
    spacing instead of the filter's full gain, and the next scan's prediction stays on its own
    aircraft.  The floor keeps the most ambiguous plot's weight at a quarter, so a track whose
    plots are all contested still follows them.  1: the plain update (a track out of every
    formation always has it: lone aircraft and national traffic are untouched).  Measured in
    the formation study (docs/evaluation/formation.md)."""

    merge_duplicates: bool = True
    """Whether duplicate tracks are looked for, and the weaker of each duplicate pair dropped."""

    duplicate_chi2: float = 16.81
    """Two tracks of one radar are *close* when the Mahalanobis distance of their state
    difference (position and velocity, predicted to the batch's time, covariance the sum of
    theirs) is at most this: chi-square with 6 degrees of freedom at 99 %."""

    duplicate_looks: int = 8
    """... and a close pair is a *duplicate* when, over the last this many looks of each, the
    two never had a plot in the same look: one aircraft gives at most one plot a look, two
    aircraft this close both give one.  Two real aircraft with detection probability ``Pd``
    pass this by chance with probability ``(1 - Pd^2)^duplicate_looks`` per window of looks:
    0.1 % at Pd 0.75, 0.5 % at Pd 0.7 (at 4, 7 % at Pd 0.7: too many); a duplicate lives about
    this many looks before it is dropped.  At most 62."""

    hold_formations: bool = True
    """Whether a track flying in a formation (:mod:`service.tracking.formation`: a neighbour of
    its radar within ``formation_radius_m`` at a velocity within ``formation_speed_mps``)
    predicts with the quiet model of ``formation_quiet_psd`` and ``formation_quiet_sojourn_s``
    instead of the filter's (the manoeuvre model is the same), unless its formation manoeuvred
    within ``formation_release_s``.  Off: every track the filter's models."""

    formation_radius_m: float = 3000.0
    """A track's neighbour closer than this flies in formation with it: wider than the
    formations' spacing (up to 1.6 km in the formation study), narrower than the 3 NM
    (5.6 km) separation of controlled traffic in a terminal area."""

    formation_speed_mps: float = 50.0
    """... at a velocity within this of its own: aircraft in formation fly one velocity, and
    their tracks' velocities differ by their errors (20-35 m/s on the formation study's radar
    with the largest cross-range error)."""

    formation_neighbours: int = 8
    """... among its this many nearest tracks (within ``formation_radius_m``): a lattice
    member's nearest are its own formation's, and the search's work stays ``8 n`` however
    crowded a radar's tracks are (every pair within the radius would be ``n^2``)."""

    formation_interval_scans: float = 1.0
    """Formations are searched for once per this many scan periods of the radar's data time
    (formations form and break up over minutes; a search at every batch would cost every
    message), over all the radar's tracks; a track born since is in none until the next."""

    formation_quiet_psd: float = 0.1
    """q (m^2/s^3) of the quiet model of a track in formation (the filter's ``quiet_psd`` is
    1): about 0.6 m/s of velocity change per 4 s scan."""

    formation_quiet_sojourn_s: Annotated[float, Gt(0)] = 3600.0
    """Mean time (s) a track in formation stays in its quiet model (the filter's
    ``quiet_sojourn_s`` is 120): the switch to the manoeuvre model needs the plots' evidence,
    not the prior's drift."""

    formation_manoeuvre_chi2: float = 11.34
    """A formation manoeuvres when the sum of its associated members' innovations (without the
    member that deviates most on its own) lies beyond this chi-square (3 degrees of freedom;
    99 %) of its covariance, the sum of theirs (:func:`service.tracking.formation.manoeuvring`):
    a common deviation that no member's own noise explains."""

    formation_manoeuvre_members: int = 3
    """... tested only with at least this many members associated in the batch (two, one left
    out, would be one track's own test)."""

    formation_release_s: float = 60.0
    """... and its tracks then predict with the filter's own models (model probabilities back
    to the filter's long-run shares) for this long (data s), enough for a rate-one turn
    through 90 degrees (30 s) and the tracks to settle on the new leg; a turn still going on
    at its end releases them again."""

    formation_velocity_sigma_mps: float = 10.0
    """A track flying in a formation (manoeuvring or not): at each of its plots its quiet
    model takes the mean velocity of its formation's other members as a measurement of its
    own velocity (:func:`service.tracking.formation.common_velocity`), of this 1-sigma (m/s)
    per axis besides the mean's own error: the members of a formation fly one velocity
    within a few m/s, and the members' estimates share part of their errors (each took the
    others' mean before).  0: off.  Measured in the formation study (4 seeds a point, 2x /
    3x / 4x / Pd 0.95 / merging, against 0): 10 gave the fewest duplicates, tracks astray and
    ID switches at 2x (4.4 / 17.5 % / 4.2 an aircraft-hour against 9.9 / 34.4 % / 8.5); 5
    and 20 did worse at 2x, 20 a little better at 3x.  Held also while the formation is
    released from its quiet model (``formation_release_s``): fewer duplicates, tracks astray
    and ID switches at 7 of 8 points than with the release lifting it (2x: false pairs 24.2 ->
    14.8 %)."""

    formation_velocity_chi2: float = 9.21
    """... only when its quiet model's velocity lies within this chi-square (2 degrees of
    freedom, 99 %) of that mean, with the sum of its own velocity covariance and the
    measurement's: a track that flies otherwise keeps its own."""

    @staticmethod
    def off() -> FormationParams:
        """The tracker as it was before these rules: no duplicate search, every track the
        filter's models and the plain update.  (Quality is reported either way; association
        does not read it.)"""
        return FormationParams(merge_duplicates=False, hold_formations=False, update_clarity_floor=1.0)


@dataclass(frozen=True)
class RevisitParams:
    """How a radar's revisit period is measured from its plots, against the one its site
    declares (:mod:`.revisit`)."""

    enabled: bool = True
    """Off: the declared ``scan_period_s`` always stands."""
    interval_s: float = 30.0
    """Data time (s) between two measurements of one radar; a tenth of it between tries until one
    counts."""
    max_plots: int = 2_000
    """The newest plots of a radar a measurement uses: its cost is a KD-tree of this many points."""
    radius_m: float = 5_000.0
    """Two plots further apart than this (m, horizontally) are not one aircraft's consecutive
    looks: 300 m/s for 15 s, with the plots' errors."""
    min_dt_s: float = 0.25
    """Plots closer in time than this (s) are one look (other aircraft of the same sweep)."""
    neighbours: int = 8
    """Nearest neighbours in space of a plot whose time gaps to it are counted."""
    peak_width: float = 0.04
    """Relative width of the span of gaps taken as the period (4 %: a radar's period varies by
    far less, and neighbouring multiples are 50 % apart)."""
    min_samples: int = 30
    """Least number of gaps at the period for a measurement to count."""
    prominence: float = 3.0
    """The gaps at the period must be this many times those half a period beyond it (where an
    aircraft leaves none): evenly spread gaps (clutter) show no period."""
    min_share: float = 0.25
    """A longer period than the declared one contradicts it only while the gaps at the declared
    period are fewer than this share of those at the observed one (:func:`.revisit.contradicted`)."""
    tolerance: float = 0.25
    """The declared period stands while the observed one is within this share of it."""


@dataclass(frozen=True)
class NoiseParams:
    """How a radar's sigmas are grown when its tracks' innovations say they are too small
    (:mod:`.noise`)."""

    enabled: bool = True
    """Off: the site's sigmas always stand."""
    interval_s: float = 30.0
    """Data time (s) between two readings of one radar's innovations; a tenth of it between
    tries while too few have come."""
    max_samples: int = 1_000
    """The newest associations' NIS a reading takes."""
    min_samples: Annotated[int, Ge(1)] = 100
    """Least number of associations for a reading."""
    high_median: float = 4.5
    """Above this median NIS the sigmas grow (consistent: 2.37; honest radars in every lab
    scenario, formations included: 1.9-3.2; sigmas declared at half the truth: 6.7)."""
    low_median: float = 1.5
    """Below this median NIS a grown scale shrinks back (never below the site's sigmas)."""
    max_scale: float = 10.0
    """The most the sigmas are multiplied by."""
    min_drop: float = 0.85
    """A growth must bring the next reading's median NIS below this share of the one that
    called for it, else it is undone and the scale held (:mod:`.noise`: clutter)."""


@dataclass(frozen=True)
class AidParams:
    """Association aided by another radar's track of the same aircraft (:mod:`.aid`).
    Measured in a formation among other traffic (the lab's formation bounds, ``--bound aided``,
    docs/evaluation/formation-bounds.md): false pairs at 2x and 3x spacing cut from 4.3 and
    3.4 % to 1.1 and 1.8 %; a formation alone about as it was until ``registration_sigma_m``
    let it act there too (below)."""

    enabled: bool = True
    """Whether a track in a formation with a confirmed partner is aided.  On by default: it acts
    only on tracks in a formation whose partner's registration is known (where it halves the
    false pairs in traffic), the rest of a network pays a look per batch, one worker's national
    replay was as fast with it, and partitioned workers stay ``lag_s`` apart, not in step
    (docs/results.md, "The aid of another radar").  Off: each radar's association rests on its
    own plots alone."""
    lag_s: float = 10.0
    """A batch at data time ``t`` is aided by every pair's confirmed pairs and registration as
    they were at the latest crossing of the links' grid at or before ``t - lag_s``, and the
    engine waits for them before the batch: the same aid whether the correlation runs here, in
    its own process or in other workers, and however the input arrives.  From 2 to 10 s the
    lab's false pairs in a formation in traffic move by less than its seeds do (2x 1.05 to
    1.87 %, 3x 1.38 to 1.81 %), at 20 s they are the worst (2.32 and 2.24 %:
    docs/evaluation/formation-bounds.md); more than zero, so a batch never waits on its own
    answer."""
    registration_sigma_m: float = 300.0
    """A partner aids only while the pair's registration, through the transform into this
    radar's view, puts it within this horizontal 1-sigma (m); the partner must also be more
    precise than the track, its covariance with the registration's, so a looser limit lets
    the comparison decide.  A formation alone is the registration's worst case: its
    registration rests on the formation's pairs only, 90-140 m 1-sigma through the transform
    there (in traffic within 50 m for 94 % of the candidates, docs/results.md), so at 50 m the
    aid seldom acted on it (one 2x run: 79 of 5 147 candidates, none of the noisiest radar's).
    Formation study (3 seeds, docs/evaluation/formation.md), false pairs % (worst seed) /
    correct % at 50 -> 300:
    2x 2.97 (3.67) / 38.7 -> 1.81 (1.93) / 39.5; 3x 4.97 (12.35) / 77.8 -> 2.55 (6.82) / 80.2;
    4x 0.28 (0.42) / 95.6 -> 0.03 (0.09) / 97.6; 3x in traffic 1.47 (3.31) / 87.9 -> 0.61
    (0.85) / 90.6; at Pd 0.7 7.87 -> 9.16 (13.06 both) / 22.9 -> 22.6, merging 17.0 -> 18.8.
    150 gained about half as much at 2x and 3x; 600 and no limit gave 300's figures to the
    digit (none was refused at 300 there)."""
    reference_psd: Annotated[float, Ge(0)] = 1.0
    """A partner's table is of the crossing ``lag_s`` or more before the plot (the pipeline's
    partner aid): its position is moved to the plot's time on its velocity, its covariance
    with the velocity's and with this white-noise acceleration spectral density (m^2/s^3 per
    axis; the form of ``FilterParams.process_noise_psd``).  1, the quiet model's
    (``FilterParams.quiet_psd``): a formation flies straight, and a partner moved 12 s adds
    about 24 m of 1-sigma for it.  Formation bounds in traffic (3 seeds), false pairs at 2x / 3x
    (worst seed): 0, 2.09 / 1.67 % (3.29 / 2.53); 1, 1.05 / 1.81 % (1.78 / 2.52); 4, 2.37 / 1.54 %
    (4.11 / 2.96); 25, 3.91 / 3.42 % (5.87 / 5.23), where the partner is seldom more precise than
    the track any longer (the tracker alone: 4.27 / 3.44 %)."""


@dataclass(frozen=True)
class TrackerParams:
    """All parameters of one radar's tracker."""

    measurement: MeasurementParams = field(default_factory=MeasurementParams)
    filter: FilterParams = field(default_factory=FilterParams)
    manager: ManagerParams = field(default_factory=ManagerParams)
    logic: LogicParams = field(default_factory=LogicParams)
    hough: HoughParams = field(default_factory=HoughParams)
    cluster: ClusterParams = field(default_factory=ClusterParams)
    bounds: BoundParams = field(default_factory=BoundParams)
    formation: FormationParams = field(default_factory=FormationParams)
    revisit: RevisitParams = field(default_factory=RevisitParams)
    noise: NoiseParams = field(default_factory=NoiseParams)
    aid: AidParams = field(default_factory=AidParams)
