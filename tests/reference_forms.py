"""Plain reference forms (loops) that tests compare the vectorised code against."""

from __future__ import annotations

import numpy as np

from service.correlation.topology import TopologyParams


def brute_force_neighbours(pts: np.ndarray, i: int, prm: TopologyParams) -> list[int]:
    """Point ``i``'s neighbourhood by a full distance scan: the ``max_neighbours`` nearest,
    those within ``radius_m``, or among the ``min_neighbours`` nearest within ``max_radius_m``."""
    d = np.linalg.norm(pts - pts[i], axis=1)
    d[i] = np.inf
    order = np.argsort(d)[: prm.max_neighbours]
    return [
        int(j)
        for r, j in enumerate(order)
        if d[j] <= prm.radius_m or (r < prm.min_neighbours and d[j] <= prm.max_radius_m)
    ]
