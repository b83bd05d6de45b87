"""Nomad 200 experiments of thesis Chapter 6 on the MuJoCo robot.

- Learned visual servoing from scratch (Section 6.5): several controllers (a population of
  learners, one simulated robot each) learn while targets are placed in view; every few
  episodes each is evaluated greedily, learning off, on the same step responses: the final
  pixel error to the goal and the time to reach it.
- A proportional controller on the same step responses, as a reference for what the task
  allows.
- Learned wandering (Section 6.4): controllers learn to wander from scratch under the infrared
  veto (vetoed proposals learned twice); distance travelled per collision and vetoes per
  minute early and late in learning, against the hand-coded wandering (Fig 6.7); a path plot
  like Fig 6.9. The veto leaves next to no collisions, so the same is run without it too: metres
  per collision early and late (collisions are in neither the state nor the reward).
- Learning servoing from the wandering behaviour (Section 6.6): robots forage (`sims.nomad.forage`)
  in a room with more balls, the wandering learning as it goes (or hand-coded); a servo learner
  learns from the wandering's actions only while the interest operator's targets are tracked
  (pursuit never dominates), or also pursues every second target; evaluated like the servo controllers learned
  from scratch, against those at the same experience count and against untrained learners.
- The cost of a control tick (physics, infrared ring, carpet matrix, tracker, act).
- Rendered vision (`NomadVisionConfig.source="render"`): the proportional controller's step
  responses on rendered images against the camera model's; the rendered carpet matrix against the
  camera model's on the same states while the hand-coded wandering drives; the tick cost with
  rendering.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from sims.base import Ranges
from sims.nomad import ForageConfig, NomadConfig, NomadForage, NomadVec, handcoded_wander
from sims.nomad.forage import Pursue
from sims.nomad.model import NomadModelConfig
from sims.nomad.transforms import phantom_goals, servo_mirror
from wfnn_bench.common import (
    Progress,
    check_seed,
    finite_median,
    fmt2,
    machine_info,
    no_progress,
    tick_learner,
)
from wfnn_client.step import Decided, Learn, Pupil, robot_step
from wfnn_common.config import LEARNERS, ExplorationConfig, LearnerConfig, check_fields
from wfnn_common.learner import WFNN
from wfnn_common.learners import Learner, make_population
from wfnn_io.persist import save_figure

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
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
    wander_episodes: int = 15
    """Learned wandering: 60 s episodes."""
    forage_minutes: int = 20
    """Learning servoing while the robots forage: simulated minutes per robot."""
    forage_balls: int = 24
    """Balls in the room while foraging (the servo data come from tracking them)."""
    forage_eval_minutes: int = 5
    forage_wander: Literal["learned", "handcoded"] = "learned"
    """The wandering while foraging: learning as it goes (as in the thesis), or hand-coded."""
    forage_wander_noise: float = 0.0
    """Hand-coded wandering: Gaussian noise on its commands, in units of each command's limit."""
    watch_phantoms: int = 4
    """Passive watching: phantom-goal copies learned of each watched experience (Section 6.6)."""
    watch_phantom_px: tuple[float, float, float, float] = (-100.0, 100.0, -40.0, 60.0)
    """...their goals' offsets from the real goal: uniform in x (low, high), y (low, high) pixels
    (y down: positive offsets put the goal lower in the image, so targets far ahead are met)."""
    watch_mirror: bool = True
    """...each experience also learned left-right mirrored (`sims.nomad.transforms`)."""
    watch_bc_weight: float = 0.2
    """...the best wire pulled toward the watched action by this fraction (`LearnerConfig.bc_weight`)."""
    watch_alpha: float = 0.05
    """...the passive learner's learning rate (as the boat's passive learner)."""
    task: NomadConfig = field(default_factory=NomadConfig)
    tick_samples: int = 1000
    render: bool = True
    """Also check rendered vision (needs off-screen GL; reported unavailable otherwise)."""
    render_wander_ticks: int = 1200
    """Ticks of hand-coded wandering per robot in the rendered-vision check (2 robots)."""
    learner: str = "thesis"
    """The servo controllers learning from scratch: the thesis' learner with the settings above,
    or the deep learner with its own defaults (`thinks`, `advantage_k`, `sigma` and
    `exploration` are the thesis' learner's). Every other part uses the thesis' learner."""
    servo_only: bool = False
    """Run servoing from scratch only (and the proportional controller's reference)."""
    seed: int = 0

    def __post_init__(self) -> None:
        check_fields(self)
        check_seed(self.seed)
        if self.learner not in LEARNERS:
            raise ValueError(f"learner must be one of {LEARNERS}, got {self.learner!r}")
        # The passive learner's settings are checked now, not when its part starts hours in.
        one = (-1.0,), (1.0,)
        LearnerConfig(state_low=one[0], state_high=one[1], action_low=one[0], action_high=one[1],
                      bc_weight=self.watch_bc_weight, alpha=self.watch_alpha)  # fmt: skip


def steps(cfg: NomadBenchConfig) -> int:
    """Progress units: episodes, foraging minutes and the rendered-vision check.

    Servo episodes, wandering episodes (with and without the veto), minutes of foraging (watched
    by the thesis' learner and by the passive one, every second target pursued).
    """
    if cfg.servo_only:
        return cfg.servo_episodes
    return (
        cfg.servo_episodes + 2 * (cfg.wander_episodes + max(cfg.wander_episodes // 3, 1))
        + 3 * cfg.forage_minutes + (2 if cfg.render else 0)
    )  # fmt: skip


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


def _learner(
    ranges: NomadVec | Ranges, cfg: NomadBenchConfig, population: int | None = None, **overrides: Any
) -> WFNN:
    """The benchmark's learners over declared ranges (one per robot of a task unless told)."""
    settings: dict[str, Any] = {
        "thinks_per_action": cfg.thinks,
        "advantage_k": cfg.advantage_k,
        "seed": cfg.seed,
    }
    lcfg = LearnerConfig.for_task(
        ranges, exploration=ExplorationConfig(kind=cfg.exploration, sigma=cfg.sigma),  # type: ignore[arg-type]
        **{**settings, **overrides},
    )  # fmt: skip
    return WFNN(lcfg, population=population or (ranges.n if isinstance(ranges, NomadVec) else 1))


def _apply_vetoes(
    vetoes: list[Callable[[FloatArray, FloatArray], FloatArray | None]],
    states: FloatArray,
    proposed: FloatArray,
) -> Decided:
    """Each robot's veto over its proposed action [n, 2]."""
    executed = proposed.copy()
    vetoed = np.zeros(len(vetoes), dtype=np.bool_)
    for i, veto in enumerate(vetoes):
        replacement = veto(states[i], proposed[i])
        if replacement is not None:
            executed[i], vetoed[i] = replacement, True
    return Decided(executed, proposed, vetoed)


def _if_any(learn: Learn) -> Learn:
    """`learn`, skipped on a step with no learnable row."""

    def learn_some(*experience: Any) -> None:
        if experience[5].any():
            learn(*experience)

    return learn_some


def learn_servo(cfg: NomadBenchConfig, progress: Progress) -> dict[str, Any]:
    """Servo controllers learn from scratch; greedy evaluations along the way."""
    p = cfg.controllers
    task = NomadVec(p, replace(cfg.task, behaviour="servo"), seed=cfg.seed)
    learner: Learner = (
        make_population(LearnerConfig.for_task(task, learner="deep", seed=cfg.seed), p)
        if cfg.learner == "deep"
        else _learner(task, cfg)
    )
    rng = np.random.default_rng(cfg.seed)
    x = task.reset(rng)
    experiences = np.zeros(p)
    evaluations: list[dict[str, Any]] = []

    def greedy(states: FloatArray, params: Any) -> FloatArray:
        return learner.act(states, explore=False, params=params).action

    t0 = time.perf_counter()
    for episode in range(1, cfg.servo_episodes + 1):
        x = task.new_targets(rng)
        for _ in range(SERVO_EPISODE):
            tr = robot_step(Decided.unchanged(learner.act(x).action), task.step, [Pupil(x, learner.learn)])
            experiences += tr.learnable
            learner.think()
            x = tr.state
        if episode % cfg.eval_every == 0 or episode == cfg.servo_episodes:
            with learner.evaluating() as frozen:  # evaluating leaves training as it was
                ev = step_responses(lambda x, w=frozen: greedy(x, w), cfg, p, cfg.seed + 1000)
            evaluations.append({"episode": episode, "experiences": experiences.copy(),
                                **{k: v for k, v in ev.items() if k != "traces"}})  # fmt: skip
            last_traces = ev["traces"]
        progress(1)
    task.close()
    return {
        "evaluations": evaluations,
        "final_traces": last_traces[:, :3].tolist(),
        "divergence_resets": learner.resets.copy(),
        "learner_config": learner.config.to_dict(),
        "wall_s": time.perf_counter() - t0,
    }


WANDER_EPISODE = 600
"""Actions per wandering episode (60 s at 10 Hz)."""


def wander(
    cfg: NomadBenchConfig, learned: bool, episodes: int, progress: Progress, veto: bool = True
) -> dict[str, Any]:
    """Wander (learning, or hand-coded) under the veto or without it.

    Per-episode distance, collisions and vetoes.
    """
    p = cfg.controllers
    task = NomadVec(p, replace(cfg.task, behaviour="wander"), seed=cfg.seed)
    learner = _learner(task, cfg) if learned else None
    vetoes = [task.veto(i) for i in range(p)] if veto else []
    rng = np.random.default_rng(cfg.seed)
    x = task.reset(rng)
    shape = (p, episodes)
    out = {k: np.zeros(shape) for k in ("distance_m", "collisions", "vetoes")}
    path: list[list[float]] = []
    for ep in range(episodes):
        distance0, collisions0 = task.distance.copy(), task.collisions.copy()
        for _ in range(WANDER_EPISODE):
            if learner is not None:
                proposed = learner.act(x).action
            else:
                proposed = np.array([handcoded_wander(task.carpet[i]) for i in range(p)])
            decided = _apply_vetoes(vetoes, x, proposed) if veto else Decided.unchanged(proposed)
            # Learning twice: a vetoed proposal is learned too, with its own reward (Eq 5.4).
            pupils = [Pupil(x, learner.learn, reward=task.reward)] if learner is not None else []
            tr = robot_step(decided, task.step, pupils)
            if learner is not None:
                learner.think()
            out["vetoes"][:, ep] += decided.vetoed
            path.append(task.pose()[0, :2].tolist())
            x = tr.state
        out["distance_m"][:, ep] = task.distance - distance0
        out["collisions"][:, ep] = task.collisions - collisions0
        progress(1)
    task.close()
    third = max(episodes // 3, 1)

    early, late = slice(0, third), slice(episodes - third, episodes)

    def per(events: str, sl: slice) -> float | None:
        """Metres per event (None without one: no collision, say)."""
        hits = float(out[events][:, sl].sum())
        return float(out["distance_m"][:, sl].sum() / hits) if hits else None

    return {
        **out,
        "m_per_collision": per("collisions", slice(None)),
        "m_per_collision_early": per("collisions", early),
        "m_per_collision_late": per("collisions", late),
        "collisions_early": float(out["collisions"][:, early].sum()),
        "collisions_late": float(out["collisions"][:, late].sum()),
        "m_per_veto_early": per("vetoes", early),
        "m_per_veto_late": per("vetoes", late),
        "vetoes_per_min_early": float(out["vetoes"][:, :third].mean()),
        "vetoes_per_min_late": float(out["vetoes"][:, episodes - third :].mean()),
        "m_per_min_early": float(out["distance_m"][:, :third].mean()),
        "m_per_min_late": float(out["distance_m"][:, episodes - third :].mean()),
        "path": path,
        "divergence_resets": learner.resets.copy() if learner is not None else None,
    }


def forage_servo(
    cfg: NomadBenchConfig, pursue: Pursue, progress: Progress, passive: bool = False
) -> dict[str, Any]:
    """A servo learner on foraging robots (Section 6.6).

    The wandering (learning, or hand-coded: `cfg.forage_wander`) drives until the interest
    operator finds a target; with `pursue` "never" the servo learner only ever watches (it
    learns from the wandering's actions while a target is tracked), with "every_second" it
    pursues every second target (learning from its own actions too). A learning wanderer learns
    from every action, the servo learner's included. The room holds `forage_balls` balls,
    scattered again every minute. Greedy step responses (as for the controllers learned from
    scratch) every `forage_eval_minutes`.

    `passive`: the servo learner is the passive one (`watch_*`): the best wire pulled toward the
    actions it learns from, a lower learning rate, and each experience also learned mirrored and
    as `watch_phantoms` copies with phantom goals. Its replays per action stay `thinks`.
    """
    p = cfg.controllers
    task = NomadVec(p, replace(cfg.task, behaviour="wander", balls=cfg.forage_balls), seed=cfg.seed + 1)
    forage = NomadForage(task, ForageConfig(pursue=pursue))
    settings: dict[str, Any] = {}
    if passive:
        settings = {"bc_weight": cfg.watch_bc_weight, "alpha": cfg.watch_alpha,
                    "symmetries": (servo_mirror(cfg.task),) if cfg.watch_mirror else ()}  # fmt: skip
    learner = _learner(forage.ranges("servo"), cfg, p, **settings)
    phantom_rng = np.random.default_rng(cfg.seed + 2)
    x_lo, x_hi, y_lo, y_hi = cfg.watch_phantom_px
    wanderer = _learner(task, cfg) if cfg.forage_wander == "learned" else None
    vetoes = [task.veto(i) for i in range(p)]
    rng = np.random.default_rng(cfg.seed + 1)
    x = task.reset(rng)
    limits = np.asarray(task.action_high)
    watched, own = np.zeros(p), np.zeros(p)
    evaluations: list[dict[str, Any]] = []

    def greedy(states: FloatArray, params: Any) -> FloatArray:
        return learner.act(states, explore=False, params=params).action

    def watch(
        state: FloatArray, u: FloatArray, xn: FloatArray, r: FloatArray, term: BoolArray, valid: BoolArray
    ) -> None:
        """The servo learner learns the executed action, and passively its phantom-goal copies."""
        if not valid.any():
            return
        learner.learn(state, u, xn, r, term, valid)
        if passive:
            # Untracked rows (NaN) are not learnable; zeros keep the arithmetic quiet.
            tracked, tracked_next = np.nan_to_num(state), np.nan_to_num(xn)
            for _ in range(cfg.watch_phantoms):
                offset = np.stack(
                    [phantom_rng.uniform(x_lo, x_hi, p), phantom_rng.uniform(y_lo, y_hi, p)], axis=1
                )
                block = phantom_goals(tracked, u, tracked_next, r, offset, task.config)
                learner.learn(*block, term, valid)

    for tick in range(1, cfg.forage_minutes * WANDER_EPISODE + 1):
        pursuing = forage.driving() == 0
        s = forage.observe("servo")
        if wanderer is not None:
            proposed = wanderer.act(x).action
        else:
            proposed = np.array([handcoded_wander(task.carpet[i]) for i in range(p)])
            proposed += rng.normal(0.0, cfg.forage_wander_noise, proposed.shape) * limits
        if pursuing.any():
            proposed[pursuing] = learner.act(np.nan_to_num(s)).action[pursuing]
        decided = _apply_vetoes(vetoes, s, proposed)
        # Both behaviours learn the executed action; a vetoed proposal is learned too (Eq 5.4) by the
        # behaviour that proposed it.
        pupils = [Pupil(s, watch, "servo", partial(forage.reward, "servo"), pursuing, learner.learn)]
        if wanderer is not None:
            pupils.insert(0, Pupil(x, _if_any(wanderer.learn), "wander", partial(forage.reward, "wander"),
                                   ~pursuing))  # fmt: skip
        steps = robot_step(decided, forage.step, pupils)
        for name, who in (("wander", wanderer), ("servo", learner)):
            if who is not None and steps[name].learnable.any():
                who.think()
        x = steps["wander"].state
        ok = steps["servo"].learnable
        watched += ok & ~pursuing
        own += ok & pursuing
        if tick % WANDER_EPISODE == 0:
            for i in range(p):
                task.scatter_balls(i, rng)
            progress(1)
        if tick % (cfg.forage_eval_minutes * WANDER_EPISODE) == 0:
            with learner.evaluating() as frozen:
                ev = step_responses(lambda x, w=frozen: greedy(x, w), cfg, p, cfg.seed + 1000)
            evaluations.append({"minutes": tick / WANDER_EPISODE, "experiences": (watched + own).copy(),
                                **{k: v for k, v in ev.items() if k != "traces"}})  # fmt: skip
    task.close()
    last = evaluations[-1]
    return {
        "pursue": pursue,
        "passive": passive,
        "learner": learner.config.to_dict(),
        "wander": cfg.forage_wander,
        "balls": cfg.forage_balls,
        "distance_m": task.distance,
        "collisions": task.collisions,
        "experiences_watched": watched,
        "experiences_own": own,
        # What the servo learner stored: mirrored and phantom-goal copies included (those whose
        # phantom errors fall outside the state's declared ranges are refused).
        "experiences_stored": learner.buffer.count.copy(),
        "targets_found_per_min": forage.forage.found / cfg.forage_minutes,
        "targets_reached_per_min": forage.forage.reached / cfg.forage_minutes,
        "evaluations": evaluations,
        "final_error_px": last["final_error_px"],
        "time_to_goal_s": last["time_to_goal_s"],
        "divergence_resets": learner.resets.copy(),
    }


def untrained(cfg: NomadBenchConfig) -> dict[str, Any]:
    """Fresh servo learners' greedy step responses: what a score must beat to be non-trivial."""
    learner = _learner(NomadVec(1, replace(cfg.task, behaviour="servo")), cfg, cfg.controllers)
    ev = step_responses(
        lambda x: learner.act(x, explore=False, params=learner.params).action, cfg, cfg.controllers,
        cfg.seed + 1000,
    )  # fmt: skip
    return {k: v for k, v in ev.items() if k != "traces"}


def _scratch_at(servo: dict[str, Any], count: float) -> dict[str, float]:
    """The from-scratch evaluation whose median experience count is nearest `count`."""
    nearest = min(servo["evaluations"], key=lambda e: abs(float(np.median(e["experiences"])) - count))
    return {
        "experiences": float(np.median(nearest["experiences"])),
        "final_error_px": float(np.median(nearest["final_error_px"])),
    }


def _rendered(task: NomadConfig) -> NomadConfig:
    return replace(task, vision=replace(task.vision, source="render"))


def render_check(cfg: NomadBenchConfig, progress: Progress) -> dict[str, Any]:
    """Rendered vision against the camera model: servoing, the carpet matrix, interest, tick cost."""
    from sims.nomad.vision import carpet_mismatch, interesting_cells
    from sims.render import RenderUnavailable

    rendered_cfg = replace(cfg, task=_rendered(cfg.task))
    try:
        servo = step_responses(lambda x: proportional(x, cfg.task), rendered_cfg, 1, cfg.seed + 1000)
        progress(1)
        task = NomadVec(2, replace(rendered_cfg.task, behaviour="wander"), seed=cfg.seed)
        vetoes = [task.veto(i) for i in range(task.n)]
        rng = np.random.default_rng(cfg.seed)
        x = task.reset(rng)
        agree, difference, found = [], [], {"render": 0, "projection": 0}
        for _ in range(cfg.render_wander_ticks):
            proposed = np.array([handcoded_wander(task.carpet[i]) for i in range(task.n)])
            x = task.step(_apply_vetoes(vetoes, x, proposed).executed).state
            for i in range(task.n):
                # The camera model's raw matrix on the same state (its own noise draws).
                model_raw = carpet_mismatch(task.model, *task.camera.look(task.model, task.data[i]),
                                            task.config.vision, rng)  # fmt: skip
                agree.append(np.mean((model_raw >= 0.5) == (task.carpet_raw[i] >= 0.5)))
                difference.append(np.abs(model_raw - task.carpet_raw[i]).mean())
                found["render"] += bool(task.interesting(i))
                found["projection"] += bool(interesting_cells(model_raw, task.config.vision))
        minutes, distance = task.time.sum() / 60.0, float(task.distance.sum())
        task.close()
        progress(1)
        tick = tick_cost(replace(rendered_cfg, tick_samples=max(cfg.tick_samples // 4, 50)))
    except RenderUnavailable as exc:
        return {"available": False, "reason": str(exc)}
    ticks = len(agree)
    return {
        "available": True,
        "servo_final_error_px": float(np.median(servo["final_error_px"])),
        "servo_time_to_goal_s": finite_median(servo["time_to_goal_s"]),
        # Cells both call carpet (< 0.5), or both not, on the same states.
        "carpet_agreement": float(np.mean(agree)),
        "carpet_mean_abs_difference": float(np.mean(difference)),
        # Ticks on which the interest operator finds an object.
        "interest_fraction": {k: v / ticks for k, v in found.items()},
        "wander_m_per_min": distance / minutes,
        "tick_ms_p50_servo": tick["tick_ms_p50_servo"],
        "tick_ms_p50_wander": tick["tick_ms_p50_wander"],
    }


def tick_cost(cfg: NomadBenchConfig) -> dict[str, float]:
    """Milliseconds per control tick (physics, infrared, carpet matrix, tracker, act), servo and wander.

    Servoing acts with the servo controllers' kind of learner, wandering with the thesis'.
    """
    out: dict[str, float] = {}
    for behaviour in ("servo", "wander"):
        task = NomadVec(1, replace(cfg.task, behaviour=behaviour), seed=cfg.seed)
        learner = tick_learner(task, cfg.learner if behaviour == "servo" else "thesis")
        x = task.reset(np.random.default_rng(cfg.seed))
        times = np.zeros(cfg.tick_samples)
        for k in range(cfg.tick_samples):
            t0 = time.perf_counter()
            u = learner.act(x[0]).action
            x = task.step(u[None]).state
            times[k] = time.perf_counter() - t0
        task.close()
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
    servo_figures = {
        "servo": servo,
        "servo_final_error_px": float(np.median(last["final_error_px"])),
        "servo_time_to_goal_s": finite_median(last["time_to_goal_s"]),
        "servo_experiences": float(np.median(last["experiences"])),
        "proportional": {k: v for k, v in reference.items() if k != "traces"},
    }
    if cfg.servo_only:
        return {"benchmark": "nomad", "config": asdict(cfg), "machine": machine_info(), **servo_figures,
                "wall_s": time.perf_counter() - t0}  # fmt: skip
    learned_wander = wander(cfg, True, cfg.wander_episodes, progress)
    handcoded = wander(cfg, False, max(cfg.wander_episodes // 3, 1), progress)
    # Without the veto the robots do collide: metres per collision as the wandering is learned.
    learned_bare = wander(cfg, True, cfg.wander_episodes, progress, veto=False)
    handcoded_bare = wander(cfg, False, max(cfg.wander_episodes // 3, 1), progress, veto=False)
    from_wander = forage_servo(cfg, "never", progress)
    from_wander_passive = forage_servo(cfg, "never", progress, passive=True)
    every_second = forage_servo(cfg, "every_second", progress)
    fresh = untrained(cfg)
    tick = tick_cost(cfg)
    rendered = render_check(cfg, progress) if cfg.render else None
    return {
        "benchmark": "nomad",
        "config": asdict(cfg),
        "machine": machine_info(),
        **servo_figures,
        "wander": learned_wander,
        "wander_handcoded": handcoded,
        "wander_m_per_collision": {
            "early": learned_wander["m_per_collision_early"],
            "late": learned_wander["m_per_collision_late"],
            "handcoded": handcoded["m_per_collision"],
            "no_veto_early": learned_bare["m_per_collision_early"],
            "no_veto_late": learned_bare["m_per_collision_late"],
            "no_veto_handcoded": handcoded_bare["m_per_collision"],
        },
        "wander_no_veto": learned_bare,
        "wander_handcoded_no_veto": handcoded_bare,
        "wander_m_per_veto": {
            "early": learned_wander["m_per_veto_early"],
            "late": learned_wander["m_per_veto_late"],
        },
        "servo_untrained": fresh,
        "servo_untrained_px": float(np.median(fresh["final_error_px"])),
        "servo_from_wander": from_wander,
        "servo_from_wander_score": float(np.median(from_wander["final_error_px"])),
        "servo_from_wander_experiences": float(np.median(from_wander["experiences_watched"])),
        "servo_from_scratch_same_experiences": _scratch_at(
            servo, float(np.median(from_wander["experiences_watched"]))
        ),
        "servo_from_wander_passive": from_wander_passive,
        "servo_from_wander_passive_score": float(np.median(from_wander_passive["final_error_px"])),
        "servo_every_second_target": every_second,
        "servo_every_second_target_score": float(np.median(every_second["final_error_px"])),
        **tick,
        "render": rendered,
        "wall_s": time.perf_counter() - t0,
    }


def plot(result: dict[str, Any], path: Path) -> None:
    """Servo learning, step responses (Fig 6.13), a wandering path (Fig 6.9), vetoes and collisions."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    servo_only = "wander" not in result
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.5)) if servo_only else plt.subplots(2, 2, figsize=(13, 9))
    axes = np.asarray(axes).reshape(-1, 2)
    ax = axes[0, 0]
    evals = result["servo"]["evaluations"]
    experiences = np.array([e["experiences"] for e in evals])
    errors = np.array([e["final_error_px"] for e in evals])
    for c in range(errors.shape[1]):
        ax.plot(experiences[:, c], errors[:, c], marker="o", lw=1, color=f"C{c % 10}")
    ax.axhline(float(np.median(result["proportional"]["final_error_px"])), color="k", ls="--",
               label="proportional controller")  # fmt: skip
    forages = (("servo_from_wander", "x", ":", "learned watching the wandering only"),
               ("servo_from_wander_passive", "d", "--", "the same, passive learner (pull, phantom goals)"),
               ("servo_every_second_target", "+", "-.", "every second target pursued"))  # fmt: skip
    for key, marker, ls, label in forages if not servo_only else ():
        fe = result[key]["evaluations"]
        counts = [float(np.median(e["experiences"])) for e in fe]
        ax.plot(counts, [float(np.median(e["final_error_px"])) for e in fe], marker=marker, color="k", ls=ls,
                label=f"{label} (median)")  # fmt: skip
    if not servo_only:
        ax.axhline(result["servo_untrained_px"], color="gray", ls=":", label="untrained (greedy)")
    ax.set(xlabel="experiences learned", ylabel="median final |pixel error| (px)",
           title="learned visual servoing, greedy step responses (one line per controller)")  # fmt: skip
    ax.legend(fontsize=8)
    ax = axes[0, 1]
    traces = np.asarray(result["servo"]["final_traces"])  # [P, 3, T]
    t = np.arange(traces.shape[2]) / 10.0
    for c in range(traces.shape[0]):
        for k in range(traces.shape[1]):
            ax.plot(t, traces[c, k], lw=0.8, color=f"C{c % 10}", alpha=0.8)
    ax.set(xlabel="s", ylabel="|pixel error to the goal| (lost: 200)",
           title="step responses of the final controllers (Fig 6.13)")  # fmt: skip
    if servo_only:
        _save(fig, path)
        return
    ax = axes[1, 0]
    trail = np.asarray(result["wander"]["path"])
    room = NomadModelConfig()
    ax.plot(trail[:, 0], trail[:, 1], lw=0.6)
    ax.plot(*trail[0], "go", label="start")
    for x, y in room.pillars:
        ax.add_patch(plt.Rectangle((x - 0.15, y - 0.15), 0.3, 0.3, color="gray"))
    ax.add_patch(plt.Circle(room.plant, 0.2, color="green"))
    minutes = len(trail) / WANDER_EPISODE
    ax.set(xlim=(-room.arena[0] / 2, room.arena[0] / 2), ylim=(-room.arena[1] / 2, room.arena[1] / 2),
           aspect="equal", xlabel="m", ylabel="m",
           title=f"learned wandering, one robot, {minutes:.0f} minutes (Fig 6.9)")  # fmt: skip
    ax.legend(fontsize=8)
    ax = axes[1, 1]
    learned, handcoded = result["wander"], result["wander_handcoded"]
    episodes = np.arange(1, np.asarray(learned["vetoes"]).shape[1] + 1)
    ax.plot(episodes, np.mean(learned["vetoes"], axis=0), marker="o", label="vetoes per minute, learned")
    ax.plot(
        episodes,
        np.mean(learned["collisions"], axis=0) * 10,
        marker="s",
        label="collisions per minute x10, learned",
    )
    ax.plot(episodes, np.mean(learned["distance_m"], axis=0), marker="^", label="metres per minute, learned")
    bare = result.get("wander_no_veto")
    if bare is not None:
        ax.plot(np.arange(1, np.asarray(bare["collisions"]).shape[1] + 1),
                np.sum(bare["distance_m"], axis=0) / np.maximum(np.sum(bare["collisions"], axis=0), 1) * 10,
                marker="v", ls=":", label="metres per collision x10, learned without the veto")  # fmt: skip
    ax.axhline(
        float(np.mean(handcoded["vetoes"])), color="C0", ls="--", label="vetoes per minute, hand-coded"
    )
    ax.axhline(
        float(np.mean(handcoded["distance_m"])), color="C2", ls="--", label="metres per minute, hand-coded"
    )
    ax.set(
        xlabel="minute of learning to wander",
        title="wandering: vetoes, collisions, distance (means over robots)",
    )
    ax.legend(fontsize=7)
    _save(fig, path)


def _save(fig: Any, path: Path) -> None:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    plt.close(fig)


def rows(result: dict[str, Any], cfg: NomadBenchConfig) -> list[tuple[str, Any]]:
    """The figures of `wfnn-bench nomad`'s table: (name, value) rows."""
    rows: list[tuple[str, Any]] = []
    for e in result["servo"]["evaluations"]:
        label = f"servo after {e['episode']} episodes ({np.median(e['experiences']):.0f} experiences)"
        to_goal = fmt2(finite_median(e["time_to_goal_s"]))
        reached = float(np.median(e["reached_fraction"]))
        rows.append((f"{label}: final error px / time to goal s / reached",
                     f"{np.median(e['final_error_px']):.1f} / {to_goal} / {reached:.2f}"))  # fmt: skip
    ref = result["proportional"]
    ref_goal = fmt2(finite_median(ref["time_to_goal_s"]))
    rows += [
        ("proportional controller: final error px / time to goal s",
         f"{float(np.median(ref['final_error_px'])):.1f} / {ref_goal}"),
        ("servo_final_error_px", result["servo_final_error_px"]),
        ("servo_time_to_goal_s", result["servo_time_to_goal_s"]),
    ]  # fmt: skip
    if not cfg.servo_only:
        rows += _rows_after_servoing(result)
    rows.append(("wall_s", result["wall_s"]))
    return rows


def _rows_after_servoing(result: dict[str, Any]) -> list[tuple[str, Any]]:
    """The Nomad benchmark's rows after servoing from scratch."""
    rows: list[tuple[str, Any]] = [
        ("servo_untrained_px (fresh learners, greedy)", result["servo_untrained_px"]),
    ]
    scratch = result["servo_from_scratch_same_experiences"]
    for key, label in (("servo_from_wander", "learned watching the wandering only"),
                       ("servo_from_wander_passive", "the same, passive learner"),
                       ("servo_every_second_target", "every second target pursued")):  # fmt: skip
        f = result[key]
        for e in f["evaluations"]:
            to_goal = fmt2(finite_median(e["time_to_goal_s"]))
            rows.append((f"{label}, {e['minutes']:.0f} min ({np.median(e['experiences']):.0f} experiences): "
                         "final error px / time to goal s",
                         f"{np.median(e['final_error_px']):.1f} / {to_goal}"))  # fmt: skip
        found, reached = np.median(f["targets_found_per_min"]), np.median(f["targets_reached_per_min"])
        rows.append((f"  {label}: experiences watched / own, targets found / reached per min",
                     f"{np.median(f['experiences_watched']):.0f} / {np.median(f['experiences_own']):.0f}, "
                     f"{found:.1f} / {reached:.2f}"))  # fmt: skip
    rows += [
        ("servo_from_wander_score (final error px, median)", result["servo_from_wander_score"]),
        ("servo_from_wander_passive_score (px, median)", result["servo_from_wander_passive_score"]),
        ("  from scratch with about as many experiences: final error px",
         f"{scratch['final_error_px']:.1f} ({scratch['experiences']:.0f} experiences)"),
    ]  # fmt: skip
    w, h = result["wander"], result["wander_handcoded"]
    rows += [
        ("wander_m_per_collision early / late / hand-coded (-: no collision)",
         " / ".join(fmt2(result["wander_m_per_collision"][k]) for k in ("early", "late", "handcoded"))),
        ("wander collisions early / late (all robots)",
         f"{w['collisions_early']:.0f} / {w['collisions_late']:.0f}"),
        ("without the veto: metres per collision early / late / hand-coded",
         " / ".join(fmt2(result["wander_m_per_collision"][k])
                    for k in ("no_veto_early", "no_veto_late", "no_veto_handcoded"))),
        ("without the veto: collisions early / late (all robots)",
         "{collisions_early:.0f} / {collisions_late:.0f}".format(**result["wander_no_veto"])),
        ("wander_m_per_veto early / late", " / ".join(fmt2(v) for v in result["wander_m_per_veto"].values())),
        ("wander vetoes per minute early / late / hand-coded",
         f"{w['vetoes_per_min_early']:.0f} / {w['vetoes_per_min_late']:.0f} / {np.mean(h['vetoes']):.0f}"),
        ("wander metres per minute early / late / hand-coded",
         f"{w['m_per_min_early']:.1f} / {w['m_per_min_late']:.1f} / {np.mean(h['distance_m']):.1f}"),
        ("tick_ms_p50 servo", result["tick_ms_p50_servo"]),
        ("tick_ms_p50 wander", result["tick_ms_p50_wander"]),
    ]  # fmt: skip
    r = result.get("render")
    if r is not None and r["available"]:
        rows += [
            ("rendered vision: proportional servo final error px / time to goal s",
             f"{r['servo_final_error_px']:.1f} / {fmt2(r['servo_time_to_goal_s'])}"),
            ("rendered vision: carpet cells agreeing with the camera model / mean |difference|",
             f"{r['carpet_agreement']:.3f} / {r['carpet_mean_abs_difference']:.3f}"),
            ("rendered vision: ticks with an interesting object, rendered / camera model",
             f"{r['interest_fraction']['render']:.3f} / {r['interest_fraction']['projection']:.3f}"),
            ("rendered vision: tick_ms_p50 servo / wander",
             f"{r['tick_ms_p50_servo']:.2f} / {r['tick_ms_p50_wander']:.2f}"),
        ]  # fmt: skip
    elif r is not None:
        rows.append(("rendered vision", f"not checked: {r['reason']}"))
    return rows
