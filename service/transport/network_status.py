"""Partitioned workers' ``/status``: one worker's own status and the others' latest, merged
into the whole network's (contract §4.6: every worker's HTTP port answers for the network).

Pure functions of the statuses: the node gathers them (its own, and each live worker's latest
``{prefix}/workers/{k}/status``) and says which workers are alive.
"""

from __future__ import annotations

import logging
from typing import Any

from service.pipeline.partition import BIAS_WORKER, Partition

log = logging.getLogger(__name__)

#: What ``/status`` ``partition.workers`` says of one worker: the age of its status (s, None:
#: never heard), its radars, its pair sets.
Worker = tuple[float | None, list[str], int]


def partition_section(partition: Partition, alive: set[int], workers: dict[int, Worker]) -> dict[str, Any]:
    """``/status`` ``partition``: who owns what, who is alive, which partitions are missing."""
    n = partition.count
    return {
        "partition": str(partition),
        "count": n,
        "bias_worker": BIAS_WORKER,
        "workers": [
            {
                "partition": f"{k}/{n}",
                "alive": k in alive,
                "radars": workers[k][1] if k in workers else [],
                "pair_sets": workers[k][2] if k in workers else 0,
                "status_age_s": _age(workers.get(k)),
            }
            for k in range(1, n + 1)
        ],
        "missing": [k for k in range(1, n + 1) if k not in alive],
    }


def _age(worker: Worker | None) -> float | None:
    return round(worker[0], 3) if worker is not None and worker[0] is not None else None


def merge_statuses(
    own: dict[str, Any], peers: dict[int, tuple[float, dict[str, Any]]], partition: Partition, alive: set[int]
) -> dict[str, Any]:
    """The network's status from this worker's (``own``, changed in place and returned) and
    the live workers' latest (``peers``: worker -> (age s, status)): every radar once, pairs,
    rejections, correlation updates and pending messages summed (the update time histogram
    too, its quantiles the worst worker's), outputs complete through the earliest worker's
    ``outputs_time_s``.  A malformed peer status is passed over (logged at debug level)."""
    radars = {r["radar_id"]: r for r in own["radars"]}
    rejected = dict(own["rejected"])
    corr = dict(own["correlation"])
    workers: dict[int, Worker] = {
        partition.index: (0.0, sorted(radars), own["partition"]["workers"][partition.index - 1]["pair_sets"])
    }
    for k, (age, st) in sorted(peers.items()):
        try:
            for r in st["radars"]:
                radars.setdefault(r["radar_id"], r)
            own["pairs_confirmed"] += int(st["pairs_confirmed"])
            own["pairs_tentative"] += int(st["pairs_tentative"])
            for reason, count in st["rejected"].items():
                rejected[reason] = rejected.get(reason, 0) + int(count)
            c = st["correlation"]
            corr["updates"] += int(c["updates"])
            corr["p50_ms"] = max(corr["p50_ms"], float(c["p50_ms"]))
            corr["p99_ms"] = max(corr["p99_ms"], float(c["p99_ms"]))
            theirs = c.get("duration_buckets", {})
            corr["duration_buckets"] = {
                le: n + int(theirs.get(le, 0)) for le, n in corr["duration_buckets"].items()
            }
            corr["duration_sum_s"] += float(c.get("duration_sum_s", 0.0))
            corr["pending"] = int(corr.get("pending", 0)) + int(c.get("pending", 0))
            # complete through: the network's outputs are only as complete as its slowest worker's
            theirs_s, mine_s = st.get("outputs_time_s"), own.get("outputs_time_s")
            own["outputs_time_s"] = (
                None if theirs_s is None or mine_s is None else min(mine_s, float(theirs_s))
            )
            mine = st["partition"]["workers"][k - 1]
            workers[k] = (age, list(mine["radars"]), int(mine["pair_sets"]))
        except (KeyError, TypeError, ValueError, IndexError):
            log.debug("malformed status of worker %d", k)
    own["radars"] = [radars[k] for k in sorted(radars)]
    own["rejected"] = dict(sorted(rejected.items()))
    own["correlation"] = corr
    progress = own["partition"]["progress"]
    own["partition"] = partition_section(partition, alive, workers)
    own["partition"]["progress"] = progress
    return own
