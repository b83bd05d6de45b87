"""Helpers shared by the benchmarks: progress, JSON output, timing."""

from __future__ import annotations

import logging
import os
import platform
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wfnn_common.config import ExplorationConfig, LearnerConfig, with_options
from wfnn_common.learners import Learner, make_learner
from wfnn_io import persist

log = logging.getLogger(__name__)

Progress = Callable[[int], None]
"""Called with how many units of work just finished."""


BENCH_MAX_SEED = (1 << 32) - 1
"""The largest seed a benchmark takes. Each derives its learners' and tasks' seeds from it (the boat's
controllers from seed x 1,000, evaluations from seed + 1,000, a server per seed + i), and every
one of those must stay a seed its learner takes (`config.MAX_SEED`, 2^62 - 1)."""


def check_seed(seed: int) -> None:
    """ValueError unless `seed` is a benchmark's seed (in [0, BENCH_MAX_SEED])."""
    if not 0 <= seed <= BENCH_MAX_SEED:
        raise ValueError(f"seed must be in [0, {BENCH_MAX_SEED}] (a benchmark derives more seeds from it), "
                         f"got {seed}")  # fmt: skip


def no_progress(_: int) -> None:
    """A progress callback that shows nothing."""


def machine_info() -> dict[str, Any]:
    """Where a figure was measured (benchmarks are only comparable on the same machine)."""
    return {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "cpus": os.cpu_count(),
        "machine": platform.machine(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
    }


def write_json(path: Path, data: dict[str, Any]) -> None:
    """Write `data` as JSON atomically (`wfnn_io.persist.write_json`), and say so."""
    persist.write_json(path, data)
    log.info("wrote %s", path)


def finite_median(values: Any) -> float:
    """The median of the finite values; NaN where there are none (no controller got there), quietly."""
    a = np.asarray(values, dtype=np.float64).ravel()
    a = a[np.isfinite(a)]
    return float(np.median(a)) if a.size else float("nan")


def nan_mean(values: Any, axis: int) -> NDArray[np.float64]:
    """np.nanmean along `axis`, NaN where a slice holds only NaN, without numpy's warning there."""
    a = np.asarray(values, dtype=np.float64)
    present = ~np.isnan(a)
    counts = present.sum(axis=axis)
    sums = np.where(present, a, 0.0).sum(axis=axis)
    return np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)


def fmt2(value: float | None) -> str:
    """A figure for a table: two decimals, or "-" where there is none (None, NaN)."""
    return "-" if value is None or not np.isfinite(value) else f"{value:.2f}"


def whole(value: float) -> str:
    """A return for a table: whole units, or three figures in powers of ten where it is huge.

    A diverging task's 1e300 in whole units is 300 digits long.
    """
    return f"{value:.3g}" if np.isfinite(value) and abs(value) >= 1e9 else f"{value:.0f}"


def tick_learner(task: Any, learner: str) -> Learner:
    """A fresh learner of one robot, for timing a control tick.

    The thesis' learner with Gaussian exploration, or the deep learner with its defaults and no
    warm-up (a warm-up action is a random draw, not the network that `act` runs afterwards).
    """
    if learner == "deep":
        deep = LearnerConfig.for_task(task, learner="deep")
        return make_learner(with_options(deep, {"deep": {"warmup": 0}}))
    return make_learner(LearnerConfig.for_task(task, exploration=ExplorationConfig(kind="gaussian")))
