"""Boat navigation, the Section 4.2 protocol: Q-learning vs advantage learning (Fig 4.2).

Each controller learns from scratch while it is scored: 40 targets in turn, each placed one
unit from the boat in a random direction, 200 actions per target, score = mean distance to the
target over those 200 actions. A population of controllers runs as arrays.
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal, NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from sims.boat import HANDCODED_GAINS, BoatConfig, BoatVec, handcoded_boat
from wfnn_bench.common import Progress, check_seed, machine_info, no_progress
from wfnn_client.step import Decided, Learn, Pupil, robot_step
from wfnn_common.config import LEARNERS, LearnerConfig, check_fields, parse_json, with_options
from wfnn_common.learners import make_population
from wfnn_io.persist import save_figure

log = logging.getLogger(__name__)
FloatArray = NDArray[np.float64]

CONDITIONS = {"advantage": 0.2, "q": 1.0}
"""Benchmark condition -> advantage_k (k = 1 is Q-learning)."""


@dataclass(frozen=True, kw_only=True)
class BoatBenchConfig:
    """Options of `wfnn-bench boat`."""

    controllers: int = 20
    """Independently learning controllers per condition."""
    mode: Literal["advantage", "q", "both"] = "both"
    targets: int = 40
    steps_per_target: int = 200
    thinks: int | None = None
    """Experience replays (thesis) or updates (deep) per action; None: the learner's default
    (the thesis' 200, the deep learner's 1)."""
    learner: str = "thesis"
    """Which learner the controllers are: "thesis" or "deep" (its defaults)."""
    learner_options: str = ""
    """Learner config fields over those defaults, a JSON object (as `wfnn-client --learner-options`)."""
    dt: float = 0.1
    """Boat time step per action (see sims.boat)."""
    hold: int = 1
    """A decision interval: each chosen action is held for this many steps (`Hold`), and the
    learner learns one experience per held action. 1 (the thesis' protocol) chooses every step.
    The learner's counts are then of held actions: its warm-up (the deep learner's
    `deep.warmup` actions) lasts `hold` times as many steps, and `thinks` are per held action."""
    greedy_targets: int = 10
    """Fresh targets scored after learning with the greedy policy and learning off."""
    acceptable: float = 0.5
    """A controller is acceptable when its median over the last 10 targets is below this."""
    seed: int = 0

    def __post_init__(self) -> None:
        check_fields(self)
        check_seed(self.seed)
        if self.learner not in LEARNERS:
            raise ValueError(f"learner must be one of {LEARNERS}, got {self.learner!r}")
        BoatConfig(dt=self.dt, steps_per_target=self.steps_per_target)  # the boat's own checks, now
        if self.hold < 1 or self.steps_per_target % self.hold:
            raise ValueError(f"hold must divide steps_per_target ({self.steps_per_target}), got {self.hold}")
        if self.learner_options:
            learner_config(self, 1.0, self.seed)  # a ConfigError (a ValueError) now, not mid-run


def learner_config(bench: BoatBenchConfig, advantage_k: float, seed: int) -> LearnerConfig:
    """The thesis' defaults for the boat (uniform exploration 10%).

    One controller's buffer holds every experience of its run (the thesis erased it between
    controllers). Chapter 4 had neither a divergence monitor (it arrived with the active head,
    Section 7.6.2) nor sanity limits: a boat far from its target is a legitimate state (with
    one time unit per action random thrusting travels ~5 units per target), so only
    non-finite states are refused here.
    """
    thinks = {} if bench.thinks is None else {"thinks_per_action": bench.thinks}
    config = LearnerConfig.for_task(
        BoatVec,
        learner=bench.learner,
        advantage_k=advantage_k,
        replay_capacity=bench.targets * bench.steps_per_target,
        divergence_patience=0,
        valid_margin=1e6,
        seed=seed,
        **thinks,
    )
    if bench.learner_options:
        config = with_options(config, parse_json(bench.learner_options, "learner options"))
    return config


class Hold:
    """A decision interval: `choose`'s action is held for `steps` steps and learned as one experience.

    The experience runs from the state where the action was chosen to the state after its last
    step, with the steps' rewards summed (undiscounted) and valid only where every step was: the
    learner's discount then applies per decision, as it would to a boat whose step is `steps`
    times as long. A new action is chosen every `steps` calls from the first, so with the
    protocol's steps per target a multiple of `steps` every hold lies within one target (the
    target jump is in no experience). For tasks without terminal steps (the boat): a terminal
    step would end one row's hold and not the others', so it is refused. The learner thinks once
    per held action, after learning it.
    """

    def __init__(self, steps: int, choose: Callable[[FloatArray], FloatArray],
                 learn: Learn | None = None, think: Callable[[], object] | None = None) -> None:  # fmt: skip
        self.steps, self._choose, self._learn, self._think = steps, choose, learn, think
        self._taken = 0
        self._state = self._action = self._reward = np.zeros(0)
        self._valid = np.zeros(0, dtype=np.bool_)
        self._learned = False

    def choose(self, x: FloatArray) -> FloatArray:
        """The held action [n, A] for states x [n, S]: a new one every `steps` calls."""
        if self._taken % self.steps == 0:
            self._state, self._action = x.copy(), np.array(self._choose(x), dtype=np.float64)
            self._reward, self._valid = np.zeros(len(x)), np.ones(len(x), dtype=np.bool_)
        self._taken += 1
        return self._action

    def learn(self, state: FloatArray, action: FloatArray, next_state: FloatArray, reward: FloatArray,
              terminal: NDArray[np.bool_], valid: NDArray[np.bool_]) -> None:  # fmt: skip
        """Add one step; at the hold's last step, learn the held action."""
        if np.any(terminal):
            raise ValueError("a held action cannot end at a terminal step: Hold is for tasks without them")
        self._reward = self._reward + reward
        self._valid = self._valid & valid
        if self._learn is not None and self._taken % self.steps == 0:
            self._learn(self._state, self._action, next_state, self._reward, terminal, self._valid)
            self._learned = True

    def think(self) -> None:
        """Think once per learned held action."""
        if self._learned and self._think is not None:
            self._think()
        self._learned = False


class ProtocolRun(NamedTuple):
    """What the Section 4.2 protocol measured of `n` controllers on each of `targets` targets."""

    scores: FloatArray
    """Mean distance to the target over its steps [n, targets] (what the thesis reports)."""
    returns: FloatArray
    """Sum of the target's rewards [n, targets] (Eq 3.8, unsquashed, undiscounted)."""
    terms: FloatArray
    """The returns split into Eq 3.8's terms [n, targets, 3]: distance, energy, coarseness."""


TERMS = ("distance", "energy", "coarseness")
"""Eq 3.8's terms, in the order of ProtocolRun.terms."""


def run_protocol(
    boat: BoatVec,
    targets: int,
    rng: np.random.Generator,
    choose: Callable[[FloatArray], FloatArray],
    learn: Learn | None = None,
    think: Callable[[], object] | None = None,
    progress: Progress = no_progress,
) -> ProtocolRun:
    """Run `boat.n` controllers on `targets` successive targets -> scores, returns and their terms.

    `choose(states [n, 7]) -> thrusts [n, 2]`; every step, `learn` (a `robot_step` learner:
    state, action, next state, reward, terminal, valid) records the experience and `think` thinks.
    The boat keeps its motion from one target to the next; the target jump itself is never part
    of an experience. A target's score is the boat's mean distance to it (what the thesis
    reports); its return is the sum of its steps' rewards (Eq 3.8, unsquashed, undiscounted: what
    a learner maximises). The two disagree (thrust and sudden changes of thrust cost reward, not
    score), so the benchmark reports both, and the return's terms say where reward was lost.
    """
    steps = boat.config.steps_per_target
    scores = np.zeros((boat.n, targets))
    returns = np.zeros((boat.n, targets))
    terms = np.zeros((boat.n, targets, len(TERMS)))
    for t in range(targets):
        x = boat.new_targets(rng)
        total = np.zeros(boat.n)
        for _ in range(steps):
            previous = boat.prev_thrust
            tr = robot_step(Decided.unchanged(choose(x)), boat.step, [Pupil(x, learn)] if learn else [])
            if think is not None:
                think()
            total += boat.distance()
            returns[:, t] += tr.reward
            terms[:, t] += boat.reward_terms(boat.prev_thrust, previous)
            x = tr.state
        scores[:, t] = total / steps
        progress(1)
    return ProtocolRun(scores, returns, terms)


def median_terms(terms: FloatArray) -> dict[str, float]:
    """The median over controllers and targets of each term of the returns, terms [n, targets, 3]."""
    return {name: float(np.median(terms[..., i])) for i, name in enumerate(TERMS)}


HANDCODED_GAIN_SCALES = (1.0, 0.5, 0.3, 0.2, 0.1, 0.05)
"""The hand-coded controller's gains are scaled by each of these for the reference sweep: the
full gains give the reference score, and gentler ones trade score for the reward's thrust and
smoothness terms."""


def handcoded_sweep(n: int, targets: int, boat_config: BoatConfig, seed: int) -> list[dict[str, Any]]:
    """The hand-coded controller at each of HANDCODED_GAIN_SCALES -> median score, return and its terms."""
    out = []
    for scale in HANDCODED_GAIN_SCALES:
        gains = tuple(scale * g for g in HANDCODED_GAINS)
        rng = np.random.default_rng(seed)  # the same targets for every scale
        boat = BoatVec(n, boat_config)
        boat.reset(rng)
        run = run_protocol(boat, targets, rng, functools.partial(handcoded_boat, gains=gains))
        out.append({"gain_scale": scale, "score": float(np.median(run.scores)),
                    "return": float(np.median(run.returns)),
                    "return_terms": median_terms(run.terms)})  # fmt: skip
    return out


def reference_scores(n: int, targets: int, boat_config: BoatConfig, seed: int) -> dict[str, FloatArray]:
    """Scores of uniform random thrusting and of the hand-coded controller, [n, targets]."""
    out: dict[str, FloatArray] = {}
    rng = np.random.default_rng(seed)
    policies: dict[str, Callable[[FloatArray], FloatArray]] = {
        "random": lambda x: rng.uniform(-1.0, 1.0, size=(x.shape[0], 2)),
        "handcoded": handcoded_boat,
    }
    for name, policy in policies.items():
        boat = BoatVec(n, boat_config)
        boat.reset(rng)
        out[name] = run_protocol(boat, targets, rng, policy).scores
    return out


def run_condition(bench: BoatBenchConfig, condition: str, progress: Progress = no_progress) -> dict[str, Any]:
    """Train and score `bench.controllers` learners of one condition."""
    k = CONDITIONS[condition]
    seed = bench.seed * 1000 + (1 if condition == "advantage" else 2)
    learner = make_population(learner_config(bench, k, seed), bench.controllers)
    boat = BoatVec(bench.controllers, BoatConfig(dt=bench.dt, steps_per_target=bench.steps_per_target))
    rng = np.random.default_rng(seed)
    boat.reset(rng)
    think_s = [0.0]

    def choose(x: FloatArray) -> FloatArray:
        return learner.act(x).action

    def think() -> None:
        t0 = time.perf_counter()
        learner.think()
        think_s[0] += time.perf_counter() - t0

    learn: Learn = learner.learn
    if bench.hold > 1:
        held = Hold(bench.hold, choose, learner.learn, think)
        choose, learn, think = held.choose, held.learn, held.think
    start = time.perf_counter()
    scores, returns, terms = run_protocol(boat, bench.targets, rng, choose, learn, think, progress)
    wall = time.perf_counter() - start
    # Greedy evaluation on fresh targets: no exploration, no learning.
    frozen = learner.snapshot()

    def greedy_choose(x: FloatArray) -> FloatArray:
        return learner.act(x, explore=False, params=frozen).action

    if bench.hold > 1:
        greedy_choose = Hold(bench.hold, greedy_choose).choose
    greedy, greedy_returns, greedy_terms = run_protocol(boat, bench.greedy_targets, rng, greedy_choose)
    last = slice(-min(10, bench.targets), None)  # the last 10 targets
    per_controller = np.median(scores[:, last], axis=1)
    thinks = int(learner.thinks.sum())
    return {
        "condition": condition,
        "advantage_k": k,
        "controllers": bench.controllers,
        "scores": scores,
        "median_per_target": np.median(scores, axis=0),
        "controller_median_last10": per_controller,
        "median_last10": float(np.median(per_controller)),
        "frac_acceptable": float(np.mean(per_controller < bench.acceptable)),
        "greedy_scores": greedy,
        "greedy_median": float(np.median(greedy)),
        "returns": returns,
        "median_return_last10": float(np.median(np.median(returns[:, last], axis=1))),
        "greedy_returns": greedy_returns,
        "greedy_median_return": float(np.median(greedy_returns)),
        "return_terms_last10": median_terms(terms[:, last]),
        "greedy_return_terms": median_terms(greedy_terms),
        "divergence_resets": int(learner.resets.sum()),
        "thinks": thinks,
        "wall_s": wall,
        "thinks_per_s": thinks / think_s[0] if think_s[0] > 0 else float("nan"),
        "learner_config": learner.config.to_dict(),
    }


def run(bench: BoatBenchConfig, progress: Progress = no_progress) -> dict[str, Any]:
    """The whole benchmark -> a JSON-ready dict (see the README for its fields)."""
    start = time.perf_counter()
    conditions = ["advantage", "q"] if bench.mode == "both" else [bench.mode]
    boat_config = BoatConfig(dt=bench.dt, steps_per_target=bench.steps_per_target)
    refs = reference_scores(max(bench.controllers, 20), bench.targets, boat_config, bench.seed + 7)
    step1 = reference_scores(20, bench.targets, replace(boat_config, dt=1.0), bench.seed + 8)
    random_ref = float(np.median(refs["random"]))
    handcoded_ref = float(np.median(refs["handcoded"]))
    results = []
    for condition in conditions:
        res = run_condition(bench, condition, progress)
        res["random_ref"] = random_ref
        res["handcoded_ref"] = handcoded_ref
        results.append(res)
        log.info(
            "%s: median last-10 %.3f, acceptable %.0f%%, greedy %.3f, %.0f thinks/s",
            condition, res["median_last10"], 100 * res["frac_acceptable"], res["greedy_median"],
            res["thinks_per_s"],
        )  # fmt: skip
    out: dict[str, Any] = {
        "benchmark": "boat",
        "config": bench.__dict__,
        "results": results,
        "random_ref": random_ref,
        "handcoded_ref": handcoded_ref,
        "step1_random_ref": float(np.median(step1["random"])),
        "step1_handcoded_ref": float(np.median(step1["handcoded"])),
        "handcoded_gains": handcoded_sweep(20, bench.targets, boat_config, bench.seed + 9),
        "machine": machine_info(),
    }
    if len(results) == 2:
        adv, q = (r["controller_median_last10"] for r in results)
        out["tests"] = {
            "ranksum_p": float(stats.ranksums(adv, q).pvalue),
            "ranksum_p_advantage_better": float(stats.ranksums(adv, q, alternative="less").pvalue),
            "ks_p": float(stats.ks_2samp(adv, q).pvalue),
        }
    out["wall_s"] = time.perf_counter() - start
    out["thinks_per_s"] = float(np.mean([r["thinks_per_s"] for r in results]))
    return out


def plot(result: dict[str, Any], path: Path) -> None:
    """Fig 4.2: a box-and-whisker plot per target for each condition, outliers clipped at 2."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    results = result["results"]
    fig, axes = plt.subplots(len(results), 1, figsize=(12, 3.6 * len(results)), squeeze=False)
    for ax, res in zip(axes[:, 0], results, strict=True):
        scores = np.minimum(np.asarray(res["scores"], dtype=float), 2.0)
        ax.boxplot(scores, notch=True, sym="+", widths=0.6)
        ax.axhline(result["random_ref"], color="tab:red", ls="--", lw=1, label="random")
        ax.axhline(result["handcoded_ref"], color="tab:green", ls="--", lw=1, label="hand-coded")
        ax.set_ylim(0, 2.05)
        ax.set_ylabel("mean distance to target")
        ax.set_title(
            f"{res['condition']} (k={res['advantage_k']}): {res['controllers']} controllers, "
            f"median of last {min(10, scores.shape[1])} = {res['median_last10']:.3f}, "
            f"acceptable {100 * res['frac_acceptable']:.0f}%"
        )
        ax.legend(loc="upper right")
    axes[-1, 0].set_xlabel("target number")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def rows(result: dict[str, Any], cfg: BoatBenchConfig) -> list[tuple[str, Any]]:
    """The figures of `wfnn-bench boat`'s table: (name, value) rows."""
    rows: list[tuple[str, Any]] = [
        ("random_ref", result["random_ref"]),
        ("handcoded_ref", result["handcoded_ref"]),
        ("step1_random_ref (dt=1)", result["step1_random_ref"]),
        ("step1_handcoded_ref (dt=1)", result["step1_handcoded_ref"]),
    ]
    rows += [(f"hand-coded x{h['gain_scale']:g}: score / return", f"{h['score']:.3f} / {h['return']:.1f}")
             for h in result.get("handcoded_gains", [])]  # fmt: skip
    for res in result["results"]:
        c = res["condition"]
        greedy_terms = " / ".join(f"{res['greedy_return_terms'][t]:.1f}" for t in TERMS)
        rows += [
            (f"{c}: median_last10", res["median_last10"]),
            (f"{c}: frac_acceptable", res["frac_acceptable"]),
            (f"{c}: greedy_median", res["greedy_median"]),
            (f"{c}: median_return_last10", res["median_return_last10"]),
            (f"{c}: greedy_median_return", res["greedy_median_return"]),
            (f"{c}: greedy return terms: " + " / ".join(TERMS), greedy_terms),
            (f"{c}: divergence_resets", res["divergence_resets"]),
            (f"{c}: thinks_per_s", res["thinks_per_s"]),
        ]
    for name, p in result.get("tests", {}).items():
        rows.append((name, p))
    rows.append(("wall_s", result["wall_s"]))
    return rows
