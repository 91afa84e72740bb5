"""Running a study's independent runs, in a process pool when there are workers to spare."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import TypeVar

Job = TypeVar("Job")
Result = TypeVar("Result")


def run_jobs(
    run_one: Callable[[Job], Result],
    jobs: Sequence[Job],
    workers: int,
    progress: Callable[[str], None],
    label: str,
) -> list[Result]:
    """Every job's result, in the order they finished (callers sort them); a progress line per
    finished run.  ``run_one`` must be a module-level function (it is pickled for the pool)."""
    t0 = time.perf_counter()
    out: list[Result] = []

    def done(k: int, result: Result) -> None:
        out.append(result)
        progress(f"  {label}: run {k + 1}/{len(jobs)} [{time.perf_counter() - t0:.0f} s]")

    if workers <= 1 or len(jobs) <= 1:
        for k, job in enumerate(jobs):
            done(k, run_one(job))
        return out
    with ProcessPoolExecutor(max_workers=workers) as pool:
        futures = [pool.submit(run_one, job) for job in jobs]
        for k, fut in enumerate(as_completed(futures)):
            done(k, fut.result())
    return out


def ratio(num: float, den: float) -> float:
    """``num / den``, NaN when ``den`` is 0."""
    return num / den if den else math.nan
