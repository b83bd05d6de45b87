"""WFNN beside Stable-Baselines3 SAC and TD3 on the same Gymnasium tasks and step budgets.

For each task and algorithm, several seeds learn for the same number of environment steps;
every `eval_every` steps the current policy is scored greedily (SB3: `predict(...,
deterministic=True)`; WFNN: the best wire, no exploration) on `eval_episodes` fresh episodes of
a separate environment instance. Reported per task and algorithm: the evaluation return's
quartiles over seeds at each point, the wall-clock seconds per training step (acting, learning
and, for WFNN, `thinks_per_action` replays), and the act latency: one observation in, one
action out (WFNN `act` on numpy, SB3 `predict` on torch), median over many calls.

WFNN runs each learner in `learners` ("thesis": the thesis' learner and defaults; "deep": deep
wire fitting with its defaults, and `deep_options` over them) over the task's declared ranges
(`sims.gym.GymVec`), as `wfnn-client --env` would; results are keyed by learner name. SB3
runs with its defaults for the algorithm (MlpPolicy), as a user of it would start. With
`reward_scale` every learner trains on the task's rewards multiplied by it, and the returns are
still the task's own: how much a learner's settings depend on the units a task pays in.
Stable-Baselines3 is an optional dependency (`pip install stable-baselines3`); without it only
WFNN runs and the SB3 rows say why. Everything trains on one core (torch's threads set to 1).

The boat is registered as the Gymnasium task `wfnn/Boat-v0` (`sims.boat.BoatEnv`: one target
per 200-action episode, the boat starting at rest).
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from numpy.typing import NDArray

from sims.gym import GymVec, make_env
from wfnn_bench.common import Progress, machine_info, no_progress, whole
from wfnn_common.config import LEARNERS, MAX_SEED, LearnerConfig, check_fields, parse_json, with_options
from wfnn_common.learners import make_learner
from wfnn_io.persist import save_figure

log = logging.getLogger(__name__)
FloatArray = NDArray[np.float64]
ALGORITHMS = ("wfnn", "sac", "td3")
SB3_MAX_SEED = (1 << 32) - 1
"""SB3 seeds numpy's legacy generator, which takes seeds below 2^32."""
MIN_REWARD_SCALE = 1e-6
MAX_REWARD_SCALE = 1e6
"""Bounds of `reward_scale` (a negative one would turn the task's goal around)."""
EVAL_LIMIT = 1000
"""Steps of an evaluation episode of a task without a time limit (as `GymVec` learns it)."""


@dataclass(frozen=True, kw_only=True)
class VsSb3Config:
    """Options of `wfnn-bench vs-sb3`."""

    tasks: tuple[str, ...] = ("wfnn/Boat-v0", "Pendulum-v1")
    steps: tuple[int, ...] = (8000, 15000)
    """Environment steps per task (same order as `tasks`)."""
    algorithms: tuple[str, ...] = ALGORITHMS
    learners: tuple[str, ...] = ("thesis",)
    """The WFNN learners run where `algorithms` has wfnn."""
    deep_options: str = ""
    """Deep learner config fields over its defaults, a JSON object (as `wfnn-client --learner-options`)."""
    seeds: int = 3
    eval_every: int = 2000
    eval_episodes: int = 3
    thinks: int = 200
    """The thesis' learner's replays per action (the thesis' boat figure)."""
    reward_scale: float = 1.0
    """Every reward a learner trains on is multiplied by this; the returns reported are the task's
    own. How a learner's settings depend on the reward's scale: a user's task pays in its own units."""
    act_calls: int = 2000
    seed: int = 0

    def __post_init__(self) -> None:
        check_fields(self)
        if not self.tasks or not all(self.tasks):
            raise ValueError(f"give at least one task, and no empty names: {self.tasks}")
        if len(self.tasks) != len(self.steps):
            raise ValueError("give one step budget per task")
        if not all(1 <= s <= 100_000_000 for s in self.steps):
            raise ValueError(f"step budgets must be in [1, 1e8], got {self.steps}")
        if not self.algorithms:
            raise ValueError(f"give at least one algorithm of {ALGORITHMS}")
        unknown = set(self.algorithms) - set(ALGORITHMS)
        if unknown:
            raise ValueError(f"unknown algorithms {sorted(unknown)}; choose from {ALGORITHMS}")
        if not self.learners or set(self.learners) - set(LEARNERS):
            raise ValueError(f"learners must be some of {LEARNERS}, got {self.learners}")
        named = {"tasks": self.tasks, "algorithms": self.algorithms, "learners": self.learners}
        for name, given in named.items():  # keys of the results: a name's last run would replace the others'
            if len(set(given)) != len(given):
                raise ValueError(f"{name} named twice: {', '.join(given)}")
        if not MIN_REWARD_SCALE <= self.reward_scale <= MAX_REWARD_SCALE:  # NaN fails too
            raise ValueError(f"reward scale must be in [{MIN_REWARD_SCALE:g}, {MAX_REWARD_SCALE:g}], "
                             f"got {self.reward_scale}")  # fmt: skip
        if self.seeds < 1 or not 0 <= self.seed <= self.seed + self.seeds - 1 <= MAX_SEED:
            raise ValueError(
                f"seeds {self.seed} to {self.seed + self.seeds - 1}: they must lie in [0, {MAX_SEED}]"
            )
        if {"sac", "td3"} & set(self.algorithms) and self.seed + self.seeds - 1 > SB3_MAX_SEED:
            raise ValueError(f"SB3 takes seeds up to {SB3_MAX_SEED}, the last one here is "
                             f"{self.seed + self.seeds - 1}")  # fmt: skip
        if self.deep_options:
            options = parse_json(self.deep_options, "deep options")
            if not isinstance(options, dict):
                raise ValueError("deep options must be a JSON object of learner config fields")
            if "learner" in options:
                raise ValueError(
                    "deep options set the deep learner's fields; choose learners with --learners"
                )
            if "seed" in options:  # it gave every seed's run the one learner seed
                raise ValueError("deep options set no seed: each run's is --seed plus its index")
            if "wfnn" not in self.algorithms or "deep" not in self.learners:
                raise ValueError("deep options given, but the deep learner does not run (--learners deep)")


def sb3_problem() -> str | None:
    """Why Stable-Baselines3 cannot run here, or None."""
    try:
        import stable_baselines3  # noqa: F401
    except ImportError as exc:
        return f"stable-baselines3 is not installed ({exc}); pip install stable-baselines3"
    return None


def _evaluate(policy: Any, env_id: str, episodes: int, seed: int) -> tuple[float, float]:
    """Mean return and mean length (steps) of `policy(obs) -> action` over fresh episodes.

    The length tells returns of the same size apart: on Hopper a return near 1,000 can be a
    whole episode standing still, and one near 200 a lunge that falls within 100 steps. A task
    with no time limit of its own is cut at `EVAL_LIMIT` steps (a good policy never ends there).
    """
    env = gym.make(env_id)
    limit = env.spec.max_episode_steps if env.spec and env.spec.max_episode_steps else EVAL_LIMIT
    dtype = env.action_space.dtype  # as training's steps give it (a task may check its actions' type)
    total, length = 0.0, 0
    try:
        for k in range(episodes):
            obs, _ = env.reset(seed=seed + k)
            done, steps = False, 0
            while not done and steps < limit:
                obs, reward, terminated, truncated, _ = env.step(np.asarray(policy(obs), dtype=dtype))
                total += float(reward)
                length += 1
                steps += 1
                done = terminated or truncated
    except Exception as exc:  # one line naming the task (a step failing only here said "boom in step")
        raise RuntimeError(f"{env_id} failed in a greedy evaluation: {type(exc).__name__}: {exc}") from exc
    finally:
        env.close()
    return total / episodes, length / episodes


def _act_us(policy: Any, obs: FloatArray, calls: int) -> tuple[float, float]:
    """Microseconds of one `policy(obs)` call: (median, 99th percentile)."""
    for _ in range(50):
        policy(obs)
    times = np.empty(calls)
    for k in range(calls):
        t0 = time.perf_counter()
        policy(obs)
        times[k] = time.perf_counter() - t0
    return float(np.median(times) * 1e6), float(np.percentile(times, 99) * 1e6)


def learner_config(task: GymVec, learner: str, seed: int, cfg: VsSb3Config) -> LearnerConfig:
    """The config a learner runs with here: its defaults over the task (and the options given)."""
    if learner == "thesis":
        return LearnerConfig.for_task(task, thinks_per_action=cfg.thinks, seed=seed)
    base = LearnerConfig.for_task(task, learner="deep", seed=seed)
    return with_options(base, parse_json(cfg.deep_options, "deep options")) if cfg.deep_options else base


def run_wfnn(
    env_id: str,
    steps: int,
    seed: int,
    cfg: VsSb3Config,
    learner_name: str = "thesis",
    progress: Progress = no_progress,
) -> dict[str, Any]:
    """One WFNN learner on the task: evaluation returns along the way, seconds per step, act latency.

    `progress` hears of the environment steps done at each evaluation.
    """
    import torch

    torch.set_num_threads(1)  # per core, as SB3 below
    task = GymVec(env_id, seed=seed)
    learner = make_learner(learner_config(task, learner_name, seed, cfg))
    rng = np.random.default_rng(seed)
    x = task.reset(rng)[0]

    def greedy(obs: FloatArray, params: Any = None) -> FloatArray:
        return learner.act(np.asarray(obs, dtype=np.float64), explore=False, params=params).action

    points, returns, lengths, reported = [], [], [], 0
    step_s = np.empty(steps)
    for step in range(1, steps + 1):
        t0 = time.perf_counter()
        u = learner.act(x).action
        tr = task.step(u[None])
        learner.learn(x, u, tr.state[0], tr.reward[0] * cfg.reward_scale, tr.terminal[0], tr.learnable[0])
        learner.think()
        x = task.observe()[0]
        step_s[step - 1] = time.perf_counter() - t0
        if step % cfg.eval_every == 0 or step == steps:
            points.append(step)
            with learner.evaluating() as frozen:  # evaluating leaves training as it was
                mean_return, mean_length = _evaluate(lambda obs, p=frozen: greedy(obs, p), env_id,
                                                     cfg.eval_episodes, 10_000 + seed)  # fmt: skip
            returns.append(mean_return)
            lengths.append(mean_length)
            progress(step - reported)
            reported = step
    act = _act_us(greedy, x, cfg.act_calls)
    task.close()
    refused = int(learner.rejected[0])
    if refused:  # its returns are of a learner that learned from the rest only: said beside them
        log.warning("%s %s seed %d: %d of %d experiences refused (not finite, or beyond the learner's "
                    "ranges)", env_id, learner_name, seed, refused, steps)  # fmt: skip
    # Every step counts, one-off costs too (torch.compile's graph, numba's kernels on a cold cache),
    # as SB3's seconds per step count its own; the slowest step's excess over a typical one is told
    # beside them, to judge a run of one or two seeds by.
    return {"steps": points, "returns": returns, "lengths": lengths,
            "s_per_step": float(step_s.sum()) / steps, "one_off_s": float(step_s.max() - np.median(step_s)),
            "act_us": act[0], "act_us_p99": act[1], "refused": refused,
            "config": learner.config.to_dict()}  # fmt: skip


def run_sb3(
    algorithm: str, env_id: str, steps: int, seed: int, cfg: VsSb3Config, progress: Progress = no_progress
) -> dict[str, Any]:
    """One SB3 model (defaults, MlpPolicy) on the task, trained in chunks between evaluations.

    `progress` hears of the environment steps done at each evaluation.
    """
    import torch
    from stable_baselines3 import SAC, TD3
    from stable_baselines3.common.logger import Logger

    torch.set_num_threads(1)  # the comparison is per core, as WFNN's learner runs on one
    env = gym.make(env_id)
    if cfg.reward_scale != 1.0:
        scale = cfg.reward_scale
        env = gym.wrappers.TransformReward(env, lambda r: scale * float(r))
    model = {"sac": SAC, "td3": TD3}[algorithm]("MlpPolicy", env, seed=seed, verbose=0)
    # A logger with no outputs: SB3's own makes an empty folder in the system's temporary
    # directory at every `learn` call, which a run of many chunks would leave behind.
    model.set_logger(Logger(folder=None, output_formats=[]))

    def greedy(obs: FloatArray) -> FloatArray:
        return model.predict(obs, deterministic=True)[0]

    points, returns, lengths, train_s, done = [], [], [], 0.0, 0
    while done < steps:
        chunk = min(cfg.eval_every, steps - done)
        t0 = time.perf_counter()
        model.learn(total_timesteps=chunk, reset_num_timesteps=False)
        train_s += time.perf_counter() - t0
        done += chunk
        points.append(done)
        mean_return, mean_length = _evaluate(greedy, env_id, cfg.eval_episodes, 10_000 + seed)
        returns.append(mean_return)
        lengths.append(mean_length)
        progress(chunk)
    obs, _ = gym.make(env_id).reset(seed=seed)
    act = _act_us(greedy, obs, cfg.act_calls)
    return {"steps": points, "returns": returns, "lengths": lengths, "s_per_step": train_s / steps,
            "act_us": act[0], "act_us_p99": act[1]}  # fmt: skip


class _Counted:
    """A progress callback that also counts the steps it heard (`done`)."""

    def __init__(self, progress: Progress) -> None:
        self.progress = progress
        self.done = 0

    def __call__(self, n: int) -> None:
        self.done += n
        self.progress(n)


def steps_total(cfg: VsSb3Config) -> int:
    """Progress units: environment steps, over every task, algorithm or learner, and seed.

    Steps rather than whole runs, so that a long run (a Hopper seed takes minutes) shows how far
    it has got; SAC's steps cost several times the deep learner's, so an estimate of the time left
    made early in a run of both is only rough.
    """
    return sum(cfg.steps) * len(_runs(cfg)) * cfg.seeds


def _runs(cfg: VsSb3Config) -> list[str]:
    """What runs on each task: the learners (for wfnn), then the SB3 algorithms."""
    return [name for a in cfg.algorithms for name in (cfg.learners if a == "wfnn" else (a,))]


def check_tasks(cfg: VsSb3Config) -> None:
    """Every task, and each WFNN learner's config over it, checked before the first run.

    So a typo, or a task too large for a learner, does not wait an hour. A fault names its task.
    """
    for env_id in cfg.tasks:
        make_env(env_id).close()
    learners = [a for a in _runs(cfg) if a in LEARNERS]
    for env_id in cfg.tasks if learners else ():
        task = GymVec(env_id, seed=cfg.seed)
        try:
            for learner in learners:
                made = learner_config(task, learner, cfg.seed, cfg)
                if made.learner == "deep":  # else found only when its first run starts, after the others
                    from wfnn_common.deep_torch import check_device

                    check_device(made.deep.device)
        except ValueError as exc:
            raise ValueError(f"{env_id}: {exc}") from exc
        finally:
            task.close()


def run(cfg: VsSb3Config, progress: Progress = no_progress) -> dict[str, Any]:
    """Every task x algorithm x seed -> a JSON-ready dict."""
    import sims.boat  # noqa: F401  # registers wfnn/Boat-v0

    check_tasks(cfg)
    t0 = time.perf_counter()
    problem = sb3_problem()
    if problem is None or "deep" in cfg.learners:
        from wfnn_common.deep_torch import keep_freed_memory

        # The deep learner's trainer keeps freed memory for reuse (its update's temporaries would
        # page-fault otherwise); set for the whole process first, so that every algorithm timed
        # here runs under the same allocator settings.
        keep_freed_memory()
    out: dict[str, Any] = {"benchmark": "vs-sb3", "config": asdict(cfg), "machine": machine_info(),
                           "sb3": problem or "available", "tasks": {}}  # fmt: skip
    for env_id, steps in zip(cfg.tasks, cfg.steps, strict=True):
        out["tasks"][env_id] = {}
        for algorithm in _runs(cfg):
            if algorithm not in LEARNERS and problem is not None:
                out["tasks"][env_id][algorithm] = {"skipped": problem}
                progress(steps * cfg.seeds)
                continue
            runs, finished, failed = [], [], []
            for k in range(cfg.seeds):
                seed = cfg.seed + k
                if algorithm in LEARNERS:
                    runs.append(run_wfnn(env_id, steps, seed, cfg, algorithm, progress))
                    continue
                counted = _Counted(progress)
                try:
                    runs.append(run_sb3(algorithm, env_id, steps, seed, cfg, counted))
                    finished.append(seed)
                except Exception as exc:  # SB3 learns whatever the task gives it (a NaN reward, say)
                    # A comparator's failure loses neither its other seeds nor the other runs.
                    first_line = (str(exc).splitlines() or [""])[0][:300]
                    why = f"seed {seed}: {type(exc).__name__}: {first_line}"
                    log.warning("%s %s failed (%s): the run goes on without it", env_id, algorithm, why)
                    failed.append(why)
                    progress(steps - counted.done)
            # Where seeds failed, its figures are over the seeds that finished, which are named.
            failure = {"failed": failed, "finished_seeds": finished} if failed else {}
            if not runs:
                out["tasks"][env_id][algorithm] = failure
                continue
            returns = np.array([r["returns"] for r in runs])  # [seeds, points]
            lengths = np.array([r["lengths"] for r in runs])  # [seeds, points]: mean greedy episode
            q25, q50, q75 = np.percentile(returns, [25, 50, 75], axis=0)
            out["tasks"][env_id][algorithm] = {
                **failure,
                "steps": runs[0]["steps"], "return_q25": q25, "return_median": q50, "return_q75": q75,
                "returns": returns, "final_return_median": float(q50[-1]),
                "final_returns": returns[:, -1],
                "lengths": lengths, "final_lengths": lengths[:, -1],
                "s_per_step": float(np.median([r["s_per_step"] for r in runs])),
                "act_us": float(np.median([r["act_us"] for r in runs])),
                "act_us_p99": float(np.median([r["act_us_p99"] for r in runs])),
                **({"refused": [r["refused"] for r in runs]} if "refused" in runs[0] else {}),
                **({"config": runs[0]["config"]} if "config" in runs[0] else {}),
            }  # fmt: skip
        task = out["tasks"][env_id]
        for name in cfg.learners:
            for sb3 in ("sac", "td3"):
                other = task.get(sb3, {})
                if name in task and "act_us" in other and "failed" not in other:
                    task[f"{sb3}_act_over_{name}_act"] = other["act_us"] / task[name]["act_us"]
                    task[f"{name}_s_per_step_over_{sb3}"] = task[name]["s_per_step"] / other["s_per_step"]
    out["wall_s"] = time.perf_counter() - t0
    return out


def plot(result: dict[str, Any], path: Path) -> None:
    """Return versus environment steps per task: median and quartiles over seeds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = result["tasks"]
    fig, axes = plt.subplots(1, len(tasks), figsize=(6 * len(tasks), 4.2), squeeze=False)
    for ax, (env_id, algos) in zip(axes[0], tasks.items(), strict=True):
        for algorithm, r in algos.items():
            if not isinstance(r, dict) or "steps" not in r:
                continue
            ax.plot(
                r["steps"], r["return_median"], marker="o", label=f"{algorithm} ({r['act_us']:.0f} us/act)"
            )
            ax.fill_between(r["steps"], r["return_q25"], r["return_q75"], alpha=0.2)
        ax.set(
            xlabel="environment steps", ylabel="greedy return (median, quartiles over seeds)", title=env_id
        )
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    plt.close(fig)


def rows(result: dict[str, Any], cfg: VsSb3Config) -> list[tuple[str, Any]]:
    """The figures of `wfnn-bench vs-sb3`'s table: (name, value) rows."""
    rows: list[tuple[str, Any]] = []
    for env_id, algos in result["tasks"].items():
        for algorithm, r in algos.items():
            if not isinstance(r, dict):
                continue
            if "skipped" in r:
                rows.append((f"{env_id} {algorithm}", f"skipped: {r['skipped']}"))
                continue
            if "failed" in r:
                finished = ", ".join(str(s) for s in r["finished_seeds"]) or "none"
                failed = "; ".join(r["failed"])
                rows.append((f"{env_id} {algorithm}", f"failed: {failed} (seeds finished: {finished})"))
                if "steps" not in r:
                    continue
            curve = " / ".join(whole(v) for v in r["return_median"])
            rows.append((f"{env_id} {algorithm}: greedy return median at {r['steps']} steps", curve))
            rows.append((f"{env_id} {algorithm}: final return per seed",
                         " / ".join(whole(v) for v in r["final_returns"])))  # fmt: skip
            rows.append((f"{env_id} {algorithm}: final greedy episode length per seed",
                         " / ".join(f"{v:.0f}" for v in r["final_lengths"])))  # fmt: skip
            if any(r.get("refused", ())):
                rows.append((f"{env_id} {algorithm}: experiences refused per seed (not learned from)",
                             " / ".join(str(v) for v in r["refused"])))  # fmt: skip
            rows.append(
                (
                    f"{env_id} {algorithm}: s_per_step / act_us p50 / p99",
                    f"{r['s_per_step'] * 1e3:.2f} ms / {r['act_us']:.1f} / {r['act_us_p99']:.1f} us",
                )
            )
        for name in cfg.learners:
            for sb3 in ("sac", "td3"):
                if f"{sb3}_act_over_{name}_act" in algos:
                    latency = algos[f"{sb3}_act_over_{name}_act"]
                    cost = algos[f"{name}_s_per_step_over_{sb3}"]
                    what = f"{sb3.upper()} predict / {name} act latency; {name} / {sb3.upper()} s per step"
                    rows.append((f"{env_id}: {what}", f"{latency:.1f}x; {cost:.2f}"))
    rows.append(("wall_s", result["wall_s"]))
    return rows
