"""Relearning from stored experiences after a divergence reset (`wfnn-bench relearn`).

The thesis' answer to a diverged learner (Section 7.6.2, and the server's recovery here): reset
the weights and relearn from the experiences already stored, without the robot. HyDrA 4-DOF
(both cameras, all joints, target on elastic, advantage learning k 0.2: the setting that learns
4-DOF in the HyDrA benchmark), several controllers at once:

1. Learn online from scratch for `episodes` episodes of 30 s, with a greedy evaluation
   (learning off, fixed targets) every `eval_every` episodes: the pre-divergence score is the
   best evaluation (controllers whose best is above `competent_px` are left out).
2. Diagnosis: the trained weights think on the store alone; does replay keep the controller?
   (`trained_then_store_only_error_px`). Then the trained weights are put back and:
3. Reset every controller's weights (as the divergence monitor does) and think on the stored
   experiences alone (no robot), in chunks of one evaluation interval's thinks, evaluating after
   each: passive relearning. Twice: with the learner that learned online (the thesis' way), and
   with the passive learner of `wfnn-bench passive` (Q-learning, the best wire pulled toward
   the stored actions, `LearnerConfig.bc_weight`, and a smaller learning rate).
4. Reset again and learn online as in 1, the store kept (the robot's new experiences join it):
   what the thesis did after each divergence (Section 7.6.2) and what a think server does.
5. Per controller: the robot time the learning from scratch needed to first come within
   `tolerance` (and 2 px) of its pre-divergence score, against the robot time with the store
   kept (`relearn_fraction`: median over the competent controllers that got there; how many did
   is `relearned_with_store`); and whether the store alone got there.
"""

from __future__ import annotations

import copy
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from sims.hydra import HydraConfig, HydraVec
from wfnn_bench.common import Progress, check_seed, fmt2, machine_info, no_progress
from wfnn_bench.hydra import EPISODE, learn_episode
from wfnn_bench.passive import PassiveBenchConfig
from wfnn_common.config import ExplorationConfig, LearnerConfig, check_fields
from wfnn_common.learner import WFNN
from wfnn_io.persist import save_figure

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
    competent_px: float = 30.0
    """A controller whose best evaluation is above this never learned to fixate: it has no
    score to relearn and is left out of `relearn_fraction`."""
    max_relearn_chunks: int | None = None
    """Stop relearning after this many chunks (None: as many as the original learning had)."""
    passive_bc_weight: float = PassiveBenchConfig.bc_weight
    passive_alpha: float = PassiveBenchConfig.passive_alpha
    passive_advantage_k: float = PassiveBenchConfig.passive_advantage_k
    """The passive learner relearning from the store alone (`bc_weight`, `alpha`, `advantage_k`;
    the passive benchmark's)."""
    seed: int = 0

    def __post_init__(self) -> None:
        check_fields(self)
        check_seed(self.seed)


def steps(cfg: RelearnBenchConfig) -> int:
    """Progress units: episodes learned and evaluations."""
    evals = cfg.episodes // cfg.eval_every
    return 2 * (cfg.episodes + evals) + 3 * (cfg.max_relearn_chunks or evals)


def greedy_error(learner: WFNN, cfg: RelearnBenchConfig) -> np.ndarray:
    """Mean |pixel error| of each controller over `eval_episodes` greedy episodes [P]."""
    task = HydraVec(learner.population, FOUR_DOF, seed=cfg.seed + 99)
    rng = np.random.default_rng(cfg.seed + 99)
    task.reset(rng)
    total = np.zeros(learner.population)
    with learner.evaluating() as frozen:  # evaluating leaves training as it was
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


def _learn_online(
    learner: WFNN, task: HydraVec, rng: np.random.Generator, cfg: RelearnBenchConfig, progress: Progress
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """`episodes` of acting, learning and thinking; greedy errors and thinks at each evaluation."""
    errors, thinks = [], []
    for ep in range(cfg.episodes):
        learn_episode(learner, task, rng)
        progress(1)
        if (ep + 1) % cfg.eval_every == 0:
            errors.append(greedy_error(learner, cfg))
            thinks.append(learner.thinks.copy())
            progress(1)
    return errors, thinks


def _store_only(
    learner: WFNN, chunks: int, chunk: int, goal: np.ndarray, cfg: RelearnBenchConfig, progress: Progress
) -> dict[str, Any]:
    """Reset the weights and think on the stored experiences alone, `chunk` thinks at a time.

    Evaluates after each chunk; stops when every controller has been within its goal once.
    """
    learner.reset_weights(np.ones(learner.population, dtype=np.bool_))
    thinks_at_reset = learner.thinks.copy()
    untrained = greedy_error(learner, cfg)
    errors, thinks, wall = [], [], []
    thinking_s = 0.0
    for _ in range(chunks):
        t1 = time.perf_counter()
        learner.think(chunk)
        thinking_s += time.perf_counter() - t1  # the evaluations are not part of relearning
        wall.append(thinking_s)
        errors.append(greedy_error(learner, cfg))
        thinks.append(learner.thinks - thinks_at_reset)
        progress(1)
        if (np.array(errors) <= goal).any(axis=0).all():
            progress(chunks - len(errors))  # the chunks not needed count as done
            break
    return {"untrained": untrained, "errors": errors, "thinks": thinks, "wall": wall,
            "hit": _first_reached(np.array(errors), goal)}  # fmt: skip


def run(cfg: RelearnBenchConfig, progress: Progress = no_progress) -> dict[str, Any]:
    """Learn, reset, relearn from the store (alone, then while acting again); the figures."""
    p = cfg.controllers
    task = HydraVec(p, FOUR_DOF, seed=cfg.seed)
    lcfg = LearnerConfig.for_task(
        task, exploration=ExplorationConfig(kind="gaussian", sigma=cfg.sigma), thinks_per_action=cfg.thinks,
        replay_capacity=2 * cfg.episodes * EPISODE, advantage_k=cfg.advantage_k, seed=cfg.seed,
    )  # fmt: skip
    learner = WFNN(lcfg, population=p)
    rng = np.random.default_rng(cfg.seed)
    task.reset(rng)
    t0 = time.perf_counter()
    online_errors, online_thinks = _learn_online(learner, task, rng, cfg, progress)
    online_wall = time.perf_counter() - t0
    # The pre-divergence score: the best a controller did (4-DOF controllers lose the target
    # again now and then, so the last evaluation may be a bad one).
    before = np.min(np.array(online_errors), axis=0)
    goal = before * (1.0 + cfg.tolerance) + 2.0
    competent = before <= cfg.competent_px
    stored = learner.buffer.count.copy()
    resets_online = learner.resets.copy()
    chunk = int(np.median(np.diff([np.zeros(p), *online_thinks], axis=0)))  # thinks per interval

    # Diagnosis: the trained weights, thinking on the store alone (does replay keep them?).
    trained = learner.params.flat.copy()
    kept_errors = []
    for _ in range(cfg.max_relearn_chunks or len(online_errors)):
        learner.think(chunk)
        kept_errors.append(greedy_error(learner, cfg))
        progress(1)
    learner.params.flat[:] = trained

    # The divergence reset: new random weights, the stored experiences kept. First the store
    # alone (no robot), in chunks of one evaluation interval's thinks: by the learner itself,
    # then by the passive learner (the same stored experiences).
    chunks = cfg.max_relearn_chunks or len(online_errors)
    store = _store_only(learner, chunks, chunk, goal, cfg, progress)
    passive_cfg = replace(
        lcfg, bc_weight=cfg.passive_bc_weight, alpha=cfg.passive_alpha, advantage_k=cfg.passive_advantage_k
    )
    passive_learner = WFNN(passive_cfg, population=p)
    passive_learner.buffer = copy.deepcopy(learner.buffer)
    pulled = _store_only(passive_learner, chunks, chunk, goal, cfg, progress)
    # Then as the thesis did (Section 7.6.2) and a think server does: reset again and learn
    # actively with the store kept, the robot's new experiences joining it.
    learner.reset_weights(np.ones(p, dtype=np.bool_))
    thinks_at_reset = learner.thinks.copy()
    active_errors, active_thinks = _learn_online(learner, task, rng, cfg, progress)
    active_thinks = [t - thinks_at_reset for t in active_thinks]

    online_hit = _first_reached(np.array(online_errors), goal)
    passive_hit, pulled_hit = store["hit"], pulled["hit"]
    active_hit = _first_reached(np.array(active_errors), goal)
    robot_s = cfg.eval_every * EPISODE / FOUR_DOF.rate_hz  # robot time per evaluation interval
    per: list[dict[str, Any]] = []
    for i in range(p):
        o, r, b, a = online_hit[i], passive_hit[i], pulled_hit[i], active_hit[i]
        per.append({
            "competent": bool(competent[i]),
            "pre_divergence_error_px": float(before[i]),
            "untrained_error_px": float(store["untrained"][i]),
            "online_robot_s_to_reach": o * robot_s if o else None,
            "online_thinks_to_reach": int(online_thinks[o - 1][i]) if o else None,
            "store_only_thinks_to_reach": int(store["thinks"][r - 1][i]) if r else None,
            "store_only_wall_s_to_reach": float(store["wall"][r - 1]) if r else None,
            "store_only_best_error_px": float(np.min(np.array(store["errors"])[:, i])),
            "store_only_passive_thinks_to_reach": int(pulled["thinks"][b - 1][i]) if b else None,
            "store_only_passive_wall_s_to_reach": float(pulled["wall"][b - 1]) if b else None,
            "store_only_passive_best_error_px": float(np.min(np.array(pulled["errors"])[:, i])),
            "with_store_robot_s_to_reach": a * robot_s if a else None,
            "relearn_fraction": a / o if o and a and competent[i] else None,
        })  # fmt: skip
    fractions = [c["relearn_fraction"] for c in per if c["relearn_fraction"] is not None]
    return {
        "benchmark": "relearn",
        "config": asdict(cfg),
        "machine": machine_info(),
        "controllers": per,
        "relearn_fraction": float(np.median(fractions)) if fractions else None,
        "competent_controllers": int(competent.sum()),
        "relearned_with_store": sum(
            a is not None and bool(c) for a, c in zip(active_hit, competent, strict=True)
        ),
        "relearned_store_only": sum(
            r is not None and bool(c) for r, c in zip(passive_hit, competent, strict=True)
        ),
        "relearned_store_only_passive": sum(
            b is not None and bool(c) for b, c in zip(pulled_hit, competent, strict=True)
        ),
        "stored_experiences": stored,
        "server_recovery_thinks": np.minimum(cfg.thinks * stored, 2_000_000),
        "online_error_px": np.array(online_errors),
        "online_thinks": np.array(online_thinks),
        "store_only_error_px": np.array(store["errors"]),
        "store_only_thinks": np.array(store["thinks"]),
        "store_only_wall_s": store["wall"],
        "passive_learner": {
            "bc_weight": cfg.passive_bc_weight,
            "alpha": cfg.passive_alpha,
            "advantage_k": cfg.passive_advantage_k,
        },
        "store_only_passive_error_px": np.array(pulled["errors"]),
        "store_only_passive_thinks": np.array(pulled["thinks"]),
        "store_only_passive_wall_s": pulled["wall"],
        "with_store_error_px": np.array(active_errors),
        "trained_then_store_only_error_px": np.array(kept_errors),
        "with_store_thinks": np.array(active_thinks),
        "online_wall_s": online_wall,
        "online_divergence_resets": resets_online,
        "goal_px": goal,
    }


def plot(result: dict[str, Any], path: Path) -> None:
    """Greedy error against robot time: learning from scratch, and after the reset with the store."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4.5))
    cfg = result["config"]
    robot_min = cfg["eval_every"] * EPISODE / FOUR_DOF.rate_hz / 60
    online, active = np.asarray(result["online_error_px"]), np.asarray(result["with_store_error_px"])
    store, t_store = np.asarray(result["store_only_error_px"]), np.asarray(result["store_only_thinks"])
    chunk_m = float(t_store[0, 0]) / 1e6  # thinks per evaluation interval, millions
    pulled = np.asarray(result["store_only_passive_error_px"])
    t_pulled = np.asarray(result["store_only_passive_thinks"])
    kept = np.asarray(result["trained_then_store_only_error_px"])
    for i in range(online.shape[1]):
        minutes = robot_min * np.arange(1, online.shape[0] + 1)
        line = a.plot(minutes, online[:, i], marker="o", label=f"controller {i}: from scratch")[0]
        a.plot(robot_min * np.arange(1, active.shape[0] + 1), active[:, i], marker="s", ls="--",
               color=line.get_color(), label=f"controller {i}: after the reset, store kept")  # fmt: skip
        a.axhline(result["goal_px"][i], color=line.get_color(), lw=0.6, ls=":")
        b.plot(t_store[:, i] / 1e6, store[:, i], marker="s", color=line.get_color(),
               label=f"controller {i}: reset weights")  # fmt: skip
        b.plot(t_pulled[:, i] / 1e6, pulled[:, i], marker="x", ls="-.", color=line.get_color(),
               label=f"controller {i}: reset weights, passive learner")  # fmt: skip
        b.plot(chunk_m * np.arange(1, kept.shape[0] + 1), kept[:, i], marker="^", ls="--",
               color=line.get_color(), label=f"controller {i}: its trained weights")  # fmt: skip
        b.axhline(result["goal_px"][i], color=line.get_color(), lw=0.6, ls=":")
    a.set_xlabel("robot time (minutes)")
    a.set_ylabel("greedy mean |pixel error| (px)")
    fraction = result["relearn_fraction"]
    a.set_title(
        "HyDrA 4-DOF: learning online" + (f" (relearning {fraction:.2f} of the time)" if fraction else "")
    )
    a.legend(fontsize=7)
    b.set_xlabel("thinks on the store alone (millions)")
    b.set_title("thinking on the store alone (no robot)")
    b.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def _reached(value: Any) -> str:
    """A figure of reaching the goal, "-" where it was never reached (None), as the other tables show it."""
    return "-" if value is None else str(value)


def rows(result: dict[str, Any], cfg: RelearnBenchConfig) -> list[tuple[str, Any]]:
    """The figures of `wfnn-bench relearn`'s table: (name, value) rows."""
    rows: list[tuple[str, Any]] = [("relearn_fraction (robot time after a reset, store kept / from scratch)",
                                    result["relearn_fraction"])]  # fmt: skip
    for i, c in enumerate(result["controllers"]):
        rows += [
            (f"controller {i}: pre-divergence / untrained error px",
             f"{c['pre_divergence_error_px']:.1f} / {c['untrained_error_px']:.1f}"),
            (f"controller {i}: robot s to reach: from scratch / store kept",
             f"{_reached(c['online_robot_s_to_reach'])} / {_reached(c['with_store_robot_s_to_reach'])}"),
            (f"controller {i}: store alone: thinks to reach / best error px",
             f"{_reached(c['store_only_thinks_to_reach'])} / {c['store_only_best_error_px']:.1f}"),
            (f"controller {i}: store alone, passive learner: thinks / wall s to reach / best error px",
             f"{_reached(c['store_only_passive_thinks_to_reach'])} / "
             f"{fmt2(c['store_only_passive_wall_s_to_reach'])} / "
             f"{c['store_only_passive_best_error_px']:.1f}"),
        ]  # fmt: skip
    rows += [("competent controllers / relearned with the store kept / with the store alone / "
              "with the store alone by the passive learner",
              f"{result['competent_controllers']} / {result['relearned_with_store']} / "
              f"{result['relearned_store_only']} / {result['relearned_store_only_passive']}"),
             ("online divergence resets", str(result["online_divergence_resets"].tolist())),
             ("stored experiences", str(result["stored_experiences"].tolist())),
             ("online wall_s", result["online_wall_s"])]  # fmt: skip
    return rows
