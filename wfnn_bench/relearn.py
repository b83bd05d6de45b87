"""Relearning from stored experiences after a divergence reset (`wfnn-bench relearn`).

The thesis' answer to a diverged learner (Section 7.6.2, and the server's recovery here): reset
the weights and relearn from the experiences already stored, without the robot. HyDrA 4-DOF
(both cameras, all joints, target on elastic, advantage learning k 0.2: the setting that learns
4-DOF in the HyDrA benchmark), several controllers at once:

1. Learn online for `episodes` episodes of 30 s, with a greedy evaluation (learning off, fixed
   targets) every `eval_every` episodes: the pre-divergence score is the last evaluation.
2. Reset every controller's weights (as the divergence monitor does) and think on the stored
   experiences only, in chunks of one evaluation interval's thinks, evaluating after each.
3. Per controller: the thinks (and robot time) the original learning needed to first come within
   `tolerance` of its pre-divergence score, against the thinks (and wall time, no robot) the
   relearning needed. `relearn_fraction` is the median ratio of thinks.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sims.hydra import HydraConfig, HydraVec
from wfnn_bench.common import Progress, machine_info, no_progress
from wfnn_bench.hydra import EPISODE
from wfnn_common.config import ExplorationConfig, LearnerConfig
from wfnn_common.learner import WFNN

FOUR_DOF = HydraConfig(
    joints=("pan", "tilt", "left", "right"), axes=("left_x", "left_y", "right_x", "right_y"), regime="elastic"
)


@dataclass(frozen=True, kw_only=True)
class RelearnBenchConfig:
    """Options of `wfnn-bench relearn`."""

    controllers: int = 2
    episodes: int = 40
    """30 s episodes of online learning before the reset."""
    eval_every: int = 5
    """Episodes between greedy evaluations (and the relearning's chunk of thinks)."""
    eval_episodes: int = 1
    """Greedy episodes per evaluation (the same targets every time)."""
    thinks: int = 200
    """Thinks per action."""
    advantage_k: float = 0.2
    sigma: float = 0.1
    """Gaussian exploration while learning online."""
    tolerance: float = 0.10
    """Reached: greedy error within this fraction (plus 2 px) of the pre-divergence score."""
    max_relearn_chunks: int | None = None
    """Stop relearning after this many chunks (None: as many as the original learning had)."""
    seed: int = 0


def steps(cfg: RelearnBenchConfig) -> int:
    """Progress units: episodes learned and evaluations."""
    evals = cfg.episodes // cfg.eval_every
    return cfg.episodes + 2 * evals + 1


def greedy_error(learner: WFNN, cfg: RelearnBenchConfig) -> np.ndarray:
    """Mean |pixel error| of each controller over `eval_episodes` greedy episodes [P]."""
    task = HydraVec(learner.population, FOUR_DOF, seed=cfg.seed + 99)
    rng = np.random.default_rng(cfg.seed + 99)
    task.reset(rng)
    frozen = learner.params.copy()
    total = np.zeros(learner.population)
    for _ in range(cfg.eval_episodes):
        x = task.new_targets(rng)
        for _ in range(EPISODE):
            x = task.step(learner.act(x, explore=False, params=frozen).action).state
            total += task.pixel_error()
    return total / (cfg.eval_episodes * EPISODE)


def _first_reached(errors: np.ndarray, goal: np.ndarray) -> list[int | None]:
    """Per controller: the first evaluation (1-based) whose error is within the goal [P]."""
    out: list[int | None] = []
    for i in range(errors.shape[1]):
        hits = np.flatnonzero(errors[:, i] <= goal[i])
        out.append(int(hits[0]) + 1 if hits.size else None)
    return out


def run(cfg: RelearnBenchConfig, progress: Progress = no_progress) -> dict[str, Any]:
    """Learn, reset, relearn from the store; the figures."""
    p = cfg.controllers
    task = HydraVec(p, FOUR_DOF, seed=cfg.seed)
    lcfg = LearnerConfig.for_task(
        task, exploration=ExplorationConfig(kind="gaussian", sigma=cfg.sigma), thinks_per_action=cfg.thinks,
        replay_capacity=cfg.episodes * EPISODE, advantage_k=cfg.advantage_k, seed=cfg.seed,
    )  # fmt: skip
    learner = WFNN(lcfg, population=p)
    rng = np.random.default_rng(cfg.seed)
    task.reset(rng)
    online_errors, online_thinks = [], []
    t0 = time.perf_counter()
    for ep in range(cfg.episodes):
        x = task.new_targets(rng)
        for _ in range(EPISODE):
            u = learner.act(x).action
            tr = task.step(u)
            learner.learn(x, u, tr.state, tr.reward, tr.terminal, tr.learnable)
            learner.think()
            x = tr.state
        progress(1)
        if (ep + 1) % cfg.eval_every == 0:
            online_errors.append(greedy_error(learner, cfg))
            online_thinks.append(learner.thinks.copy())
            progress(1)
    online_wall = time.perf_counter() - t0
    before = online_errors[-1]
    goal = before * (1.0 + cfg.tolerance) + 2.0
    stored = learner.buffer.count.copy()
    resets_online = learner.resets.copy()
    chunk = int(np.median(np.diff([np.zeros(p), *online_thinks], axis=0)))  # thinks per interval

    # The divergence reset: new random weights, the stored experiences kept.
    learner.reset_weights(np.ones(p, dtype=np.bool_))
    thinks_at_reset = learner.thinks.copy()
    untrained = greedy_error(learner, cfg)
    relearn_errors, relearn_thinks, relearn_wall = [], [], []
    thinking_s = 0.0
    chunks = cfg.max_relearn_chunks or len(online_errors)
    for _ in range(chunks):
        t1 = time.perf_counter()
        learner.think(chunk)
        thinking_s += time.perf_counter() - t1  # the evaluations are not part of relearning
        relearn_wall.append(thinking_s)
        relearn_errors.append(greedy_error(learner, cfg))
        relearn_thinks.append(learner.thinks - thinks_at_reset)
        progress(1)
        if (np.array(relearn_errors) <= goal).any(axis=0).all():
            break
    online_hit = _first_reached(np.array(online_errors), goal)
    relearn_hit = _first_reached(np.array(relearn_errors), goal)
    per: list[dict[str, Any]] = []
    for i in range(p):
        o, r = online_hit[i], relearn_hit[i]
        fraction = int(relearn_thinks[r - 1][i]) / int(online_thinks[o - 1][i]) if o and r else None
        per.append({
            "pre_divergence_error_px": float(before[i]),
            "untrained_error_px": float(untrained[i]),
            "online_thinks_to_reach": int(online_thinks[o - 1][i]) if o else None,
            "online_robot_s_to_reach": o * cfg.eval_every * EPISODE / FOUR_DOF.rate_hz if o else None,
            "relearn_thinks_to_reach": int(relearn_thinks[r - 1][i]) if r else None,
            "relearn_wall_s_to_reach": float(relearn_wall[r - 1]) if r else None,
            "relearn_fraction": fraction,
        })  # fmt: skip
    fractions = [c["relearn_fraction"] for c in per if c["relearn_fraction"] is not None]
    return {
        "config": asdict(cfg),
        "machine": machine_info(),
        "controllers": per,
        "relearn_fraction": float(np.median(fractions)) if fractions else None,
        "relearned": sum(r is not None for r in relearn_hit),
        "stored_experiences": stored,
        "server_recovery_thinks": np.minimum(cfg.thinks * stored, 2_000_000),
        "online_error_px": np.array(online_errors),
        "online_thinks": np.array(online_thinks),
        "relearn_error_px": np.array(relearn_errors),
        "relearn_thinks": np.array(relearn_thinks),
        "relearn_wall_s": relearn_wall,
        "online_wall_s": online_wall,
        "online_divergence_resets": resets_online,
        "goal_px": goal,
    }


def plot(result: dict[str, Any], path: Path) -> None:
    """Greedy error against thinks: online learning, and relearning after the reset."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5))
    online, relearn = np.asarray(result["online_error_px"]), np.asarray(result["relearn_error_px"])
    t_on, t_re = np.asarray(result["online_thinks"]), np.asarray(result["relearn_thinks"])
    for i in range(online.shape[1]):
        line = ax.plot(t_on[:, i] / 1e6, online[:, i], marker="o", label=f"controller {i}: online")[0]
        ax.plot(t_re[:, i] / 1e6, relearn[:, i], marker="s", ls="--", color=line.get_color(),
                label=f"controller {i}: relearning from the store after the reset")  # fmt: skip
        ax.axhline(result["goal_px"][i], color=line.get_color(), lw=0.6, ls=":")
    ax.set_xlabel("thinks (millions)")
    ax.set_ylabel("greedy mean |pixel error| (px)")
    fraction = result["relearn_fraction"]
    ax.set_title("HyDrA 4-DOF: relearning after a divergence reset"
                 + (f" (median {fraction:.2f} of the thinks)" if fraction is not None else ""))  # fmt: skip
    ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
