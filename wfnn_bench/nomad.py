"""Nomad 200 experiments of thesis Chapter 6 on the MuJoCo robot.

- Learned visual servoing from scratch (Section 6.5): several controllers (a population of
  learners, one simulated robot each) learn while targets are placed in view; every few
  episodes each is evaluated greedily, learning off, on the same step responses: the final
  pixel error to the goal and the time to reach it.
- A proportional controller on the same step responses, as a reference for what the task
  allows.
- The cost of a control tick (physics, infrared ring, carpet matrix, tracker, act).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sims.nomad import NomadConfig, NomadVec
from wfnn_bench.common import Progress, machine_info, no_progress
from wfnn_common.config import ExplorationConfig, LearnerConfig
from wfnn_common.learner import WFNN

FloatArray = NDArray[np.float64]
SERVO_EPISODE = 150
"""Actions per servo training episode (15 s at 10 Hz)."""


@dataclass(frozen=True, kw_only=True)
class NomadBenchConfig:
    """Options of `wfnn-bench nomad`."""

    controllers: int = 8
    servo_episodes: int = 30
    eval_every: int = 5
    """Evaluate the servo controllers every this many training episodes."""
    eval_steps: int = 12
    """Step responses per evaluation (the same targets for every controller and evaluation)."""
    step_ticks: int = 100
    """Actions per step response (10 s)."""
    goal_px: float = 15.0
    """A step response has reached the goal when the pixel error stays below this."""
    thinks: int = 200
    advantage_k: float = 0.2
    """The thesis' advantage learning (with k = 1, Q-learning, the median final error after 30
    episodes was about 80 px against about 20)."""
    sigma: float = 0.1
    exploration: str = "gaussian"
    task: NomadConfig = field(default_factory=NomadConfig)
    tick_samples: int = 1000
    seed: int = 0


def step_responses(policy: Any, cfg: NomadBenchConfig, population: int, seed: int) -> dict[str, FloatArray]:
    """Greedy step responses: targets placed in view, `policy(states) -> actions` for `step_ticks`.

    Returns per controller the median final error (px, lost counted as half the diagonal),
    the median time to the goal (s, NaN when never reached) and the error traces [P, steps, T].
    """
    task = NomadVec(population, replace(cfg.task, behaviour="servo", encoder_glitch=0.0), seed=seed)
    rng = np.random.default_rng(seed)
    task.reset(rng)
    traces = np.zeros((population, cfg.eval_steps, cfg.step_ticks))
    for k in range(cfg.eval_steps):
        x = task.new_targets(rng)
        for t in range(cfg.step_ticks):
            x = task.step(policy(x)).state
            traces[:, k, t] = task.pixel_error()
    final = traces[:, :, -10:].mean(axis=2)
    # Time to the goal: the first tick from which the error stays below goal_px to the end,
    # for at least the last second.
    inside = traces < cfg.goal_px
    stays = np.flip(np.cumprod(np.flip(inside, axis=2), axis=2), axis=2).astype(bool)
    reached = stays[:, :, -int(task.config.rate_hz)]
    first = np.argmax(stays, axis=2).astype(np.float64)
    to_goal = np.where(reached, (first + 1) / task.config.rate_hz, np.nan)
    task.close()
    return {
        "final_error_px": np.median(final, axis=1),
        "time_to_goal_s": np.array([np.nanmedian(r) if np.isfinite(r).any() else np.nan for r in to_goal]),
        "reached_fraction": reached.mean(axis=1),
        "traces": traces,
    }


def proportional(x: FloatArray, cfg: NomadConfig) -> FloatArray:
    """A hand-tuned proportional servo: turn toward the target, drive to bring it to the goal."""
    px, py = np.nan_to_num(x[:, 0]), np.nan_to_num(x[:, 1])
    return np.stack(
        [np.clip(-py / 150 * cfg.max_translation, -cfg.max_translation, cfg.max_translation),
         np.clip(-px / 150 * cfg.max_rotation, -cfg.max_rotation, cfg.max_rotation)], axis=1,
    )  # fmt: skip


def learn_servo(cfg: NomadBenchConfig, progress: Progress) -> dict[str, Any]:
    """Servo controllers learn from scratch; greedy evaluations along the way."""
    p = cfg.controllers
    task = NomadVec(p, replace(cfg.task, behaviour="servo"), seed=cfg.seed)
    lcfg = LearnerConfig.for_task(
        task, exploration=ExplorationConfig(kind=cfg.exploration, sigma=cfg.sigma),  # type: ignore[arg-type]
        thinks_per_action=cfg.thinks,
        advantage_k=cfg.advantage_k, seed=cfg.seed,
    )  # fmt: skip
    learner = WFNN(lcfg, population=p)
    rng = np.random.default_rng(cfg.seed)
    x = task.reset(rng)
    experiences = np.zeros(p)
    evaluations: list[dict[str, Any]] = []

    def greedy(states: FloatArray) -> FloatArray:
        return learner.act(states, explore=False, params=learner.params).action

    t0 = time.perf_counter()
    for episode in range(1, cfg.servo_episodes + 1):
        x = task.new_targets(rng)
        for _ in range(SERVO_EPISODE):
            u = learner.act(x).action
            tr = task.step(u)
            learner.learn(x, u, tr.state, tr.reward, tr.terminal, tr.learnable)
            experiences += tr.learnable
            learner.think()
            x = tr.state
        if episode % cfg.eval_every == 0 or episode == cfg.servo_episodes:
            ev = step_responses(greedy, cfg, p, cfg.seed + 1000)
            evaluations.append({"episode": episode, "experiences": experiences.copy(),
                                **{k: v for k, v in ev.items() if k != "traces"}})  # fmt: skip
            last_traces = ev["traces"]
        progress(1)
    task.close()
    return {
        "evaluations": evaluations,
        "final_traces": last_traces[:, :3].tolist(),
        "divergence_resets": learner.resets.copy(),
        "wall_s": time.perf_counter() - t0,
    }


def tick_cost(cfg: NomadBenchConfig) -> dict[str, float]:
    """Milliseconds per control tick (physics, infrared, carpet matrix, tracker, act), servo and wander."""
    out: dict[str, float] = {}
    for behaviour in ("servo", "wander"):
        task = NomadVec(1, replace(cfg.task, behaviour=behaviour), seed=cfg.seed)
        learner = WFNN(LearnerConfig.for_task(task, exploration=ExplorationConfig(kind="gaussian")))
        x = task.reset(np.random.default_rng(cfg.seed))
        times = np.zeros(cfg.tick_samples)
        for k in range(cfg.tick_samples):
            t0 = time.perf_counter()
            u = learner.act(x[0]).action
            x = task.step(u[None]).state
            times[k] = time.perf_counter() - t0
        out[f"tick_ms_p50_{behaviour}"] = float(np.median(times) * 1e3)
        out[f"tick_ms_p99_{behaviour}"] = float(np.percentile(times, 99) * 1e3)
    out["tick_ms_p50"] = max(out["tick_ms_p50_servo"], out["tick_ms_p50_wander"])
    return out


def run(cfg: NomadBenchConfig, progress: Progress = no_progress) -> dict[str, Any]:
    """All experiments."""
    t0 = time.perf_counter()
    reference = step_responses(lambda x: proportional(x, cfg.task), cfg, 1, cfg.seed + 1000)
    servo = learn_servo(cfg, progress)
    last = servo["evaluations"][-1]
    tick = tick_cost(cfg)
    return {
        "benchmark": "nomad",
        "config": asdict(cfg),
        "machine": machine_info(),
        "servo": servo,
        "servo_final_error_px": float(np.median(last["final_error_px"])),
        "servo_time_to_goal_s": float(np.nanmedian(last["time_to_goal_s"])),
        "servo_experiences": float(np.median(last["experiences"])),
        "proportional": {k: v for k, v in reference.items() if k != "traces"},
        **tick,
        "wall_s": time.perf_counter() - t0,
    }


def plot(result: dict[str, Any], path: Path) -> None:
    """Servo learning (greedy evaluations) and the final controllers' step responses."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(13, 4.5))
    ax = axes[0]
    evals = result["servo"]["evaluations"]
    experiences = np.array([e["experiences"] for e in evals])
    errors = np.array([e["final_error_px"] for e in evals])
    for c in range(errors.shape[1]):
        ax.plot(experiences[:, c], errors[:, c], marker="o", lw=1, label=f"controller {c}")
    ax.axhline(float(np.median(result["proportional"]["final_error_px"])), color="k", ls="--",
               label="proportional controller")  # fmt: skip
    ax.set(xlabel="experiences learned", ylabel="median final |pixel error| (px)",
           title="Nomad: learned visual servoing, greedy step responses")  # fmt: skip
    ax.legend(fontsize=8)
    ax = axes[1]
    traces = np.asarray(result["servo"]["final_traces"])  # [P, 3, T]
    t = np.arange(traces.shape[2]) / 10.0
    for c in range(traces.shape[0]):
        for k in range(traces.shape[1]):
            ax.plot(t, traces[c, k], lw=0.8, color=f"C{c}", alpha=0.8)
    ax.set(xlabel="s", ylabel="|pixel error to the goal| (lost: 200)",
           title="step responses of the final controllers (Fig 6.13)")  # fmt: skip
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
