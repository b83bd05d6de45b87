"""A simulated robot learning in one process: act-learn-think-MT at a fixed tick.

The control loop runs on an absolute schedule (no drift), acts on the newest weight snapshot,
and queues experiences; thinking runs in a background thread. At the end the run directory
holds the weights (with their config), the experiences, metrics as JSON and a learning-curve
PNG.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from sims.base import VecTask
from sims.boat import BoatConfig, BoatVec
from sims.positioning import PositioningVec
from wfnn_common.architectures import ActLearnThinkMT
from wfnn_common.config import ExplorationConfig, LearnerConfig
from wfnn_common.learner import WFNN
from wfnn_common.persist import save_experiences, save_weights

log = logging.getLogger(__name__)
FloatArray = NDArray[np.float64]
SimName = Literal["boat", "positioning"]


@dataclass(frozen=True)
class SimSpec:
    """How the client drives one simulated task."""

    make: Callable[[float], VecTask]
    """Build the task (one instance) given the time step option."""
    episode_steps: int
    new_episode: Callable[[Any, np.random.Generator], None]
    metric: Callable[[Any], FloatArray]
    """Per-step performance figure (lower is better), averaged per episode."""
    metric_name: str


SIMS: dict[str, SimSpec] = {
    "boat": SimSpec(
        make=lambda dt: BoatVec(1, BoatConfig(dt=dt)),
        episode_steps=200,
        new_episode=lambda task, rng: task.new_targets(rng),
        metric=lambda task: task.distance(),
        metric_name="mean distance to target",
    ),
    "positioning": SimSpec(
        make=lambda dt: PositioningVec(1),
        episode_steps=200,
        new_episode=lambda task, rng: None,
        metric=lambda task: np.abs(task.target - task.position),
        metric_name="mean position error",
    ),
}


@dataclass(frozen=True, kw_only=True)
class ClientConfig:
    """Options of `wfnn-client` for a local (in-process thinking) run."""

    sim: SimName = "boat"
    episodes: int = 40
    """Episodes (boat: targets) to run."""
    rate_hz: float = 50.0
    """Control rate; 0 runs as fast as possible."""
    boat_dt: float = 0.1
    """Boat time per action (see sims.boat)."""
    think_batch: int = 50
    """Replays per think-thread iteration (one weight snapshot each)."""
    exploration: ExplorationConfig = field(default_factory=ExplorationConfig)
    out: Path = Path("runs/latest")
    seed: int = 0


@dataclass
class TickStats:
    """Timing of the control loop."""

    latency_s: list[float] = field(default_factory=list)
    """Sense-to-act time per tick."""
    lateness_s: list[float] = field(default_factory=list)
    """How late each tick started against its absolute deadline."""
    overruns: int = 0
    """Ticks that started more than one period late."""

    def summary(self) -> dict[str, float]:
        """Percentiles in milliseconds."""
        lat = np.asarray(self.latency_s) * 1e3
        late = np.asarray(self.lateness_s) * 1e3
        return {
            "act_latency_ms_p50": float(np.percentile(lat, 50)) if lat.size else float("nan"),
            "act_latency_ms_p99": float(np.percentile(lat, 99)) if lat.size else float("nan"),
            "tick_jitter_ms_p50": float(np.percentile(late, 50)) if late.size else float("nan"),
            "tick_jitter_ms_p99": float(np.percentile(late, 99)) if late.size else float("nan"),
            "overruns": self.overruns,
        }


def learner_config(task: VecTask, config: ClientConfig) -> LearnerConfig:
    """The thesis' defaults over the task's declared ranges."""
    return LearnerConfig(
        state_low=task.state_low,
        state_high=task.state_high,
        action_low=task.action_low,
        action_high=task.action_high,
        exploration=config.exploration,
        seed=config.seed,
    )


def run(config: ClientConfig, progress: Callable[[int, float], None] | None = None) -> dict[str, Any]:
    """Run the simulated robot; returns the metrics also written to `out/metrics.json`.

    `progress(episode_done, score)` is called after every episode.
    """
    from wfnn_bench.common import write_json  # JSON helper shared with the benchmarks

    spec = SIMS[config.sim]
    task = spec.make(config.boat_dt)
    rng = np.random.default_rng(config.seed)
    lcfg = learner_config(task, config)
    learner = WFNN(lcfg)
    period = 1.0 / config.rate_hz if config.rate_hz > 0 else 0.0
    ticks = TickStats()
    scores: list[float] = []
    log.info("learner: %s", lcfg.short_repr())
    x = task.reset(rng)[0]
    with ActLearnThinkMT(learner, think_batch=config.think_batch) as mt:
        start = time.perf_counter()
        tick = 0
        for episode in range(config.episodes):
            spec.new_episode(task, rng)
            x = task.observe()[0]
            total = 0.0
            for _ in range(spec.episode_steps):
                if period:
                    deadline = start + tick * period
                    now = time.perf_counter()
                    if now < deadline:
                        time.sleep(deadline - now)
                    late = time.perf_counter() - deadline
                    ticks.lateness_s.append(late)
                    if late > period:
                        ticks.overruns += 1
                t0 = time.perf_counter()
                u = mt.act(x).action
                ticks.latency_s.append(time.perf_counter() - t0)
                tr = task.step(u[None])
                mt.learn(x, u, tr.state[0], tr.reward[0], tr.terminal[0], tr.learnable[0])
                total += float(spec.metric(task)[0])
                x = tr.state[0]
                tick += 1
            scores.append(total / spec.episode_steps)
            if progress is not None:
                progress(episode + 1, scores[-1])
            if mt.error is not None:
                raise RuntimeError("think thread failed") from mt.error
        wall = time.perf_counter() - start
        mt.stop()
    out = Path(config.out)
    save_weights(out / "weights.npz", lcfg, learner.params, {"sim": config.sim, "episodes": config.episodes})
    save_experiences(out / "experiences.npz", lcfg, learner.buffer.contents(0))
    metrics: dict[str, Any] = {
        "sim": config.sim,
        "metric": spec.metric_name,
        "scores": scores,
        "first10_median": float(np.median(scores[:10])),
        "last10_median": float(np.median(scores[-10:])),
        "thinks": int(learner.thinks.sum()),
        "thinks_per_action": float(learner.thinks.sum()) / max(tick, 1),
        "snapshots": mt.version,
        "divergence_resets": int(learner.resets.sum()),
        "experiences": int(learner.buffer.count[0]),
        "wall_s": wall,
        "config": {
            "client": {**dataclasses.asdict(config), "out": str(config.out)},
            "learner": lcfg.to_dict(),
        },
        **ticks.summary(),
    }
    write_json(out / "metrics.json", metrics)
    plot(metrics, out / "learning_curve.png")
    return metrics


def plot(metrics: dict[str, Any], path: Path) -> None:
    """Score per episode."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    scores = metrics["scores"]
    ax.plot(np.arange(1, len(scores) + 1), scores, marker="o", ms=3)
    ax.set_xlabel("episode")
    ax.set_ylabel(metrics["metric"])
    ax.set_title(f"{metrics['sim']}: act-learn-think-MT, {metrics['thinks']} thinks")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
