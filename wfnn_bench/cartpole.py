"""Cart-pole with pure-delayed reward (Section 4.5, Fig 4.12): steps balanced per attempt.

Several independent runs learn at once. Each attempt ends at failure (terminal, reward -1)
or when it reaches `max_attempt_steps` (counted as balanced that long; the system restarts
and the restart is not learned). The thesis reports the policy degrading after success;
the curve is reported as measured.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sims.cartpole import CartPoleVec
from wfnn_bench.common import Progress, check_seed, machine_info, no_progress
from wfnn_client.step import Decided, Pupil, robot_step
from wfnn_common.config import LearnerConfig, check_fields
from wfnn_common.learner import WFNN
from wfnn_io.persist import save_figure

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class CartPoleBenchConfig:
    """Options of `wfnn-bench cartpole`."""

    runs: int = 8
    steps: int = 30_000
    """Control steps per run (all attempts together)."""
    thinks: int = 100
    max_attempt_steps: int = 10_000
    gamma: float = 0.8
    advantage_k: float = 0.2
    seed: int = 0

    def __post_init__(self) -> None:
        check_fields(self)
        check_seed(self.seed)


def run(bench: CartPoleBenchConfig, progress: Progress = no_progress) -> dict[str, Any]:
    """Learn in `runs` cart-poles -> steps per attempt for each run."""
    task = CartPoleVec(bench.runs)
    config = LearnerConfig.for_task(
        task,
        gamma=bench.gamma,
        advantage_k=bench.advantage_k,
        thinks_per_action=bench.thinks,
        replay_capacity=max(bench.steps, 1),
        divergence_patience=0,
        seed=bench.seed,
    )
    learner = WFNN(config, population=bench.runs)
    rng = np.random.default_rng(bench.seed)
    x = task.reset(rng)
    attempts: list[list[int]] = [[] for _ in range(bench.runs)]
    start = time.perf_counter()
    chunk = max(bench.steps // 100, 1)
    for step in range(bench.steps):
        tr = robot_step(Decided.unchanged(learner.act(x).action), task.step, [Pupil(x, learner.learn)])
        learner.think()
        capped = task.steps >= bench.max_attempt_steps
        for i in np.flatnonzero(tr.terminal):
            attempts[i].append(int(task.last_attempt[i]))
        for i in np.flatnonzero(capped):
            attempts[i].append(bench.max_attempt_steps)
        if capped.any():
            task.restart(capped)
        x = task.observe()
        if (step + 1) % chunk == 0:
            progress(chunk)
    wall = time.perf_counter() - start
    n_attempts = min(len(a) for a in attempts)
    per_attempt = (
        np.array([a[:n_attempts] for a in attempts], dtype=float) if n_attempts else np.zeros((bench.runs, 0))
    )
    return {
        "benchmark": "cartpole",
        "config": bench.__dict__,
        "attempt_steps": attempts,
        "median_per_attempt": np.median(per_attempt, axis=0) if n_attempts else [],
        "best_attempt": [max(a) if a else 0 for a in attempts],
        "attempts_per_run": [len(a) for a in attempts],
        "wall_s": wall,
        "thinks_per_s": float(learner.thinks.sum()) / wall,
        "machine": machine_info(),
    }


def plot(result: dict[str, Any], path: Path) -> None:
    """Fig 4.12: steps balanced per attempt (log scale), one line per run plus the median."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 4.5))
    for run_attempts in result["attempt_steps"]:
        ax.plot(np.arange(1, len(run_attempts) + 1), run_attempts, lw=0.7, alpha=0.5)
    med = result["median_per_attempt"]
    if len(med):
        ax.plot(np.arange(1, len(med) + 1), med, color="k", lw=2, label="median over runs")
        ax.legend()
    ax.set_yscale("log")
    ax.set_xlabel("attempt")
    ax.set_ylabel("steps balanced")
    ax.set_title(
        f"cart-pole, {len(result['attempt_steps'])} runs (cap {result['config']['max_attempt_steps']} steps)"
    )
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def rows(result: dict[str, Any], cfg: CartPoleBenchConfig) -> list[tuple[str, Any]]:
    """The figures of `wfnn-bench cartpole`'s table: (name, value) rows."""
    med = np.asarray(result["median_per_attempt"], dtype=float)
    rows: list[tuple[str, Any]] = [
        ("attempts per run (min)", min(result["attempts_per_run"])),
        ("best attempt per run (median)", float(np.median(result["best_attempt"]))),
        ("median steps, first 10 attempts", float(np.median(med[:10])) if med.size else float("nan")),
        ("median steps, last 10 attempts", float(np.median(med[-10:])) if med.size else float("nan")),
        ("thinks_per_s", result["thinks_per_s"]),
        ("wall_s", result["wall_s"]),
    ]
    return rows
