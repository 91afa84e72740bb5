"""The GMM paper's simulation scene (Li, Dong, Ding, Guan; ``docs/references.md`` §3), evaluation only.

Seeded; the target ids it returns are truth, for scoring only.
"""

from __future__ import annotations

import numpy as np


def paper_scene(
    rng: np.random.Generator, n: int = 20, at_period: int = -1
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Radars at (0, 0) and (150, 0) km; ``n`` targets uniform in [72, 75]^2 km at the start,
    speed U(5, 200) m/s, heading U(0, 2 pi); errors 60 m / 0.4 deg (A), 80 m / 0.3 deg (B);
    biases U(0, 1000) m and U(-1, 0) deg (A), U(0, 1000) m and U(0, 1) deg (B); 100 periods of
    2 s with plot detection probability 0.9 / 0.7.  Each radar's track is a least-squares
    constant-velocity fit of its detected plots (a converged tracker without process noise),
    taken at period ``at_period`` (default the last; 0 = the dense starting box); the radar
    reports a target's track with the same probability
    (0.9 / 0.7), so some tracks have no counterpart.  Returns positions and the target ids
    (evaluation only)."""
    sites = np.array([[0.0, 0.0], [150e3, 0.0]])
    sigmas = [(60.0, np.radians(0.4)), (80.0, np.radians(0.3))]
    pd = [0.9, 0.7]
    bias = [
        (rng.uniform(0, 1000), -rng.uniform(0, np.radians(1.0))),
        (rng.uniform(0, 1000), rng.uniform(0, np.radians(1.0))),
    ]
    p0 = rng.uniform(72e3, 75e3, (n, 2))
    speed, heading = rng.uniform(5, 200, n), rng.uniform(0, 2 * np.pi, n)
    vel = speed[:, None] * np.column_stack([np.sin(heading), np.cos(heading)])
    t = np.arange(100) * 2.0
    truth = p0[None] + t[:, None, None] * vel[None]
    tt = (t - t[at_period])[:, None]
    out = []
    for s in range(2):
        rel = truth - sites[s]
        r, th = np.hypot(rel[..., 0], rel[..., 1]), np.arctan2(rel[..., 0], rel[..., 1])
        rm = r + bias[s][0] + sigmas[s][0] * rng.standard_normal(r.shape)
        tm = th + bias[s][1] + sigmas[s][1] * rng.standard_normal(r.shape)
        z = sites[s] + np.stack([rm * np.sin(tm), rm * np.cos(tm)], axis=-1)
        w = (rng.random(r.shape) < pd[s]).astype(float)
        s0, s1, s2 = w.sum(0), (w * tt).sum(0), (w * tt**2).sum(0)
        zx, zt = (w[..., None] * z).sum(0), (w[..., None] * tt[..., None] * z).sum(0)
        pos = (s2[:, None] * zx - s1[:, None] * zt) / (s0 * s2 - s1**2)[:, None]
        ids = np.flatnonzero(rng.random(n) < pd[s])
        out.append((pos[ids], ids))
    return out[0][0], out[1][0], out[0][1], out[1][1]
