"""Passive and off-policy learning on the boat (thesis Sections 2.x, 3.4.2; issue: learn from data).

- Logs: the hand-coded boat controller and noisy variants of it (Gaussian noise on its thrusts)
  drive boats through the Section 4.2 protocol; every experience is recorded in the experience
  log format (`wfnn_client.journal.Recorder`, one log per behaviour policy, named in each
  batch's `weights_source`, noisy actions flagged as explored) and read back from disk.
- Passive: learners that never act learn from those logs only (all experiences stored, then
  `think`), and are scored greedily on the Section 4.2 protocol, learning off; also with the
  logs' experiences re-targeted to phantom targets only (the real target never learned).
  Three learners: the one this project uses for passive learning (Q-learning with the best
  wire pulled toward the logged actions, `LearnerConfig.bc_weight`), the same without the
  pull, and the thesis' learner (advantage learning, no pull).
- Two figures per controller, on the same targets: the score (mean distance to the target,
  Section 4.2) and the mean squashed reward per action (Eq 3.6 of Eq 3.8), which is what the
  learners maximise (discounted). They disagree: the hand-coded controller's bang-bang thrust
  is charged heavily by Eq 3.8's energy and coarseness terms. Zero thrust is a reference too.
- Phantom targets, as in the thesis (Section 3.4.2): learners act online on the protocol but
  learn each experience only as copies re-targeted to random phantom targets.
- Mirror images: learners act online and learn each experience and its left-right mirror image;
  the real experiences they need to reach the plain learners' final score, as a ratio.
- Diagnosis: in states of the logs, the value of the greedy (best-wire) action against the
  values of the logged actions (a greedy value far above every logged action's is an
  extrapolation to actions the data never tried).
- Learners: `learner` names the learner of the pulled, unpulled and phantom-only passive
  conditions and of the online ones ("thesis" or "deep", each with its own defaults); the
  thesis' passive learner is the thesis' whatever `learner` says, as the reference.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Literal, NamedTuple

import numpy as np
from numpy.typing import NDArray

from sims.boat import BoatConfig, BoatVec, handcoded_boat, mirror, phantom
from wfnn_bench.boat import BoatBenchConfig, learner_config, run_protocol
from wfnn_bench.common import Progress, check_seed, machine_info, no_progress
from wfnn_client.brain import Experience, Recorder
from wfnn_common.config import DEEP_DEFAULTS, LEARNERS, LearnerConfig, check_fields
from wfnn_common.learners import make_population
from wfnn_common.update import squash_reward
from wfnn_io import logs
from wfnn_io.persist import save_figure
from wfnn_io.protocol import EXP_EXPLORED

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True, kw_only=True)
class PassiveBenchConfig:
    """Options of `wfnn-bench passive`."""

    controllers: int = 8
    """Learners per condition (a population learning at once)."""
    learner: Literal["thesis", "deep"] = "thesis"
    """The learner of the pulled, unpulled and phantom-only passive conditions and of the online
    ones (the thesis' passive condition is always the thesis' learner)."""
    learner_options: str = ""
    """Config fields of `learner` over its defaults, a JSON object (as `wfnn-bench boat`'s); the
    passive learners' k, pull and (thesis) rate come from the fields below, over these."""
    dt: float = 0.1
    """Boat time per action (see sims.boat)."""
    noise: tuple[float, ...] = (0.0, 0.3, 1.0)
    """Behaviour policies of the logs: the hand-coded controller with this Gaussian noise on its
    thrusts (0: the controller itself)."""
    log_boats: int = 4
    log_targets: int = 10
    """Each behaviour policy drives `log_boats` boats through this many targets (200 actions each)."""
    passive_thinks: int | None = None
    """Replays per passive learner; None: its `thinks_per_action` per logged experience, what a
    `wfnn-server --replay-only` gives it (4.8 million replays of the thesis' learner for the
    default logs; 24,000 updates of a minibatch of the deep learner)."""
    passive_checks: int = 4
    """Greedy evaluations along the passive thinking (a curve)."""
    online_targets: int = 40
    thinks: int | None = None
    """Replays (thesis) or updates (deep) per action of the online learners; None: the learner's
    own (the thesis' 200, the deep learner's 1)."""
    phantoms: int = 1
    """Phantom copies learned per real experience."""
    phantom_radius: float = 1.0
    """Phantom targets lie uniformly in a disc of this radius around the real target."""
    eval_targets: int = 10
    advantage_k: float | None = None
    """k of the online learners and of the thesis' passive learner; None: the learner's own (the
    thesis' 0.2, the deep learner's 1.0)."""
    passive_advantage_k: float = 1.0
    """k of the passive learners with and without the pull. Q-learning: measured here (8
    learners, 400,000 thinks, pull 0.5, alpha 0.25) it scored 0.27 / 0.33 at dt 1 / 0.1 against 0.59 / 0.42
    with k 0.2; advantage learning widens the action gaps for online exploration, which
    passive learning does not do."""
    passive_alpha: float = 0.05
    """Learning rate of the thesis' learner where it learns passively with and without the pull
    (the thesis' passive condition keeps 0.25; the deep learner keeps its Adam step, deep.lr).
    Replaying a fixed set millions of times, the thesis' 0.25 left the greedy controller
    changing from one evaluation to the next (pulled, dt 0.1: 0.33-0.48 over four
    evaluations of 400,000 thinks); 0.05 settles (8 learners, dt 1: 0.27 -> 0.08 at 3.2 million
    thinks)."""
    bc_weight: float = 0.5
    """Pull of the best wire toward the logged actions (`LearnerConfig.bc_weight`) of the
    passive learners (0.2, 0.5 and 1.0 scored alike here: 0.28-0.31 at dt 0.1, 0.07-0.08 at
    dt 1, 8 learners, 4.8 million thinks)."""
    seed: int = 0

    def __post_init__(self) -> None:
        check_fields(self)
        check_seed(self.seed)
        if self.learner not in LEARNERS:
            raise ValueError(f"learner must be one of {LEARNERS}, got {self.learner!r}")
        # A bad learner_options, bc_weight or k is a ConfigError now, not after the logs are made.
        _config(self, 1, self.learner, **pulled(self))


PASSIVE_LEARNERS = ("passive", "passive_no_bc", "passive_thesis")
"""JSON keys of the passive conditions: with the pull, without it, the thesis' learner."""


def pulled(cfg: PassiveBenchConfig) -> dict[str, Any]:
    """LearnerConfig fields of the passive learners with the pull (over `cfg.learner_options`)."""
    fields: dict[str, Any] = {"advantage_k": cfg.passive_advantage_k, "bc_weight": cfg.bc_weight}
    if cfg.learner == "thesis":
        fields["alpha"] = cfg.passive_alpha
    return fields


def _config(
    cfg: PassiveBenchConfig, capacity: int, kind: str = "thesis", reference: bool = False, **overrides: Any
) -> LearnerConfig:
    """The boat benchmark's learner of `kind`, with `cfg.advantage_k` and `overrides`.

    `kind`'s defaults, and `cfg.learner_options` and `cfg.thinks` over them where `kind` is
    `cfg.learner`; a `reference` (the thesis' passive learner, the logs' spec, the evaluations'
    gamma) keeps the thesis' own, whatever the options.
    """
    own = kind == cfg.learner and not reference
    bench = BoatBenchConfig(thinks=cfg.thinks if own else None, dt=cfg.dt, learner=kind,
                            learner_options=cfg.learner_options if own else "")  # fmt: skip
    default_k = DEEP_DEFAULTS["advantage_k"] if kind == "deep" else LearnerConfig.advantage_k
    k = default_k if cfg.advantage_k is None else cfg.advantage_k
    base = learner_config(bench, k, cfg.seed + 11)
    return replace(base, replay_capacity=capacity, **overrides)


def _boat(cfg: PassiveBenchConfig, n: int) -> BoatVec:
    return BoatVec(n, BoatConfig(dt=cfg.dt))


class Evaluation(NamedTuple):
    """Figures of n controllers on the same `eval_targets` fresh targets."""

    scores: FloatArray
    """Median over targets of the Section 4.2 score (mean distance to the target) [n]."""
    rewards: FloatArray
    """Mean squashed reward per action (Eq 3.6 of Eq 3.8, with the thesis' gamma 0.8), what the
    thesis' learner maximises [n]."""
    returns: FloatArray
    """Median over targets of the target's return (Eq 3.8 summed, unsquashed), what the deep
    learner maximises (discounted) [n]."""


def evaluate(policy: Callable[[FloatArray], FloatArray], n: int, cfg: PassiveBenchConfig) -> Evaluation:
    """N controllers on the same `eval_targets` fresh targets, learning off."""
    boat = _boat(cfg, n)
    rng = np.random.default_rng(cfg.seed + 99)
    boat.reset(rng)
    gamma = _config(cfg, 1, "thesis", reference=True).gamma  # one scale for every learner's figure
    rewards = np.zeros(n)

    def add(*experience: Any) -> None:  # only the reward counts
        rewards[:] += squash_reward(experience[3], gamma)

    run = run_protocol(boat, cfg.eval_targets, rng, policy, add)
    per_action = rewards / (cfg.eval_targets * boat.config.steps_per_target)
    return Evaluation(np.median(run.scores, axis=1), per_action, np.median(run.returns, axis=1))


def greedy_eval(learner: Any, cfg: PassiveBenchConfig) -> Evaluation:
    """`evaluate` of each learner's greedy controller, learning off ([P] figures).

    Training is left as it was (`WFNN.evaluating`).
    """
    with learner.evaluating() as frozen:
        return evaluate(
            lambda x: learner.act(x, explore=False, params=frozen).action, learner.population, cfg
        )


def greedy_score(learner: Any, cfg: PassiveBenchConfig) -> FloatArray:
    """Each learner's median score over `eval_targets` fresh targets, greedy, learning off [P]."""
    return greedy_eval(learner, cfg).scores


def record_logs(cfg: PassiveBenchConfig, directory: Path) -> dict[str, Any]:
    """Drive boats with each behaviour policy, recording experience logs; their protocol scores."""
    rng = np.random.default_rng(cfg.seed)
    config = _config(cfg, 1, reference=True)
    scores: dict[str, float] = {}
    for sigma in cfg.noise:
        name = "handcoded" if sigma == 0 else f"handcoded_noise{sigma:g}"
        boats = _boat(cfg, cfg.log_boats)
        boats.reset(rng)
        # Client ids must differ between policies too: a merge keeps each client's numbering once.
        recorders = [
            Recorder(directory / f"{name}_{b}", config, f"hc{sigma:g}_{b}") for b in range(cfg.log_boats)
        ]

        def policy(x: FloatArray, sigma: float = sigma) -> FloatArray:
            return np.clip(handcoded_boat(x) + rng.normal(0.0, sigma, (x.shape[0], 2)), -1.0, 1.0)

        def keep(
            x: FloatArray, u: FloatArray, xn: FloatArray, r: FloatArray, terminal: BoolArray, _: BoolArray,
            name: str = name, sigma: float = sigma, recorders: list[Recorder] = recorders,
        ) -> None:  # fmt: skip
            # A log keeps every step, learnable or not, as a robot's journal does.
            for b, recorder in enumerate(recorders):
                experience = Experience(x[b], u[b], xn[b], float(r[b]), bool(terminal[b]),
                                        EXP_EXPLORED if sigma > 0 else 0)  # fmt: skip
                recorder.add(experience, name, 0)

        scores[name] = float(np.median(run_protocol(boats, cfg.log_targets, rng, policy, keep).scores))
        for recorder in recorders:
            recorder.close()
    return {"policy_scores": scores, "logs": sorted(str(p) for p in directory.iterdir())}


def _phantom_offsets(rng: np.random.Generator, n: int, radius: float) -> FloatArray:
    """Uniform in a disc [n, 2]."""
    angle = rng.uniform(-np.pi, np.pi, n)
    r = radius * np.sqrt(rng.uniform(0.0, 1.0, n))
    return np.stack([r * np.cos(angle), r * np.sin(angle)], axis=1)


def passive(
    cfg: PassiveBenchConfig,
    arrays: dict[str, Any],
    phantom_only: bool,
    progress: Progress,
    kind: str,
    **overrides: Any,
) -> dict[str, Any]:
    """Learn from the logs only (or only from their phantom-target copies); a greedy curve.

    `kind`: the learner; `overrides`: `_config`'s, LearnerConfig fields that differ from its boat
    benchmark config, or `reference=True` for the thesis' own settings.
    """
    s, a, sn, r = (
        np.asarray(arrays[k], dtype=np.float64) for k in ("state", "action", "next_state", "reward")
    )
    terminal = np.asarray(arrays["terminal"], dtype=np.bool_)
    if phantom_only:
        rng = np.random.default_rng(cfg.seed + 5)
        boat_cfg = BoatConfig(dt=cfg.dt)
        copies = [phantom(s, a, sn, r, _phantom_offsets(rng, len(r), cfg.phantom_radius), boat_cfg)
                  for _ in range(max(cfg.phantoms, 1))]  # fmt: skip
        s, a, sn, r = (np.concatenate(part) for part in zip(*copies, strict=True))
        terminal = np.tile(terminal, len(copies))
    config = _config(cfg, len(r) + 1, kind, **overrides)
    learner = make_population(config, cfg.controllers)
    stored = int(learner.learn_many(s, a, sn, r, terminal).sum())
    curve: list[dict[str, Any]] = []
    thinks = cfg.passive_thinks if cfg.passive_thinks is not None else config.thinks_per_action * stored
    per_check = thinks // cfg.passive_checks
    for _ in range(cfg.passive_checks):
        for _ in range(per_check // 1000):
            learner.think(1000)
        learner.think(per_check % 1000)
        ev = greedy_eval(learner, cfg)
        curve.append({"thinks": int(learner.thinks[0]), "scores": ev.scores, "rewards": ev.rewards,
                      "returns": ev.returns})  # fmt: skip
        progress(1)
    return {"learner": config.learner, "advantage_k": config.advantage_k, "bc_weight": config.bc_weight,
            "alpha": config.alpha if config.learner == "thesis" else config.deep.lr,
            "experiences": stored, "curve": curve, "score": float(np.median(ev.scores)),
            "reward": float(np.median(ev.rewards)), "return": float(np.median(ev.returns)),
            "diagnosis": value_gap(learner, s, a, cfg.seed)}  # fmt: skip


def value_gap(
    learner: Any, state: FloatArray, action: FloatArray, seed: int, n: int = 300
) -> dict[str, float]:
    """Median over logged states of the greedy action's value and the logged action's value."""
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(state), size=min(n, len(state)), replace=False)
    p = learner.population
    greedy = learner.greedy_values(state[idx]).T  # [n, P]
    logged = np.array([learner.q_value(np.repeat(state[i][None], p, 0), np.repeat(action[i][None], p, 0))
                       for i in idx]).reshape(len(idx), p)  # fmt: skip
    return {"greedy_value": float(np.median(greedy)), "logged_action_value": float(np.median(logged)),
            "greedy_above_logged_fraction": float(np.mean(greedy > logged + 0.1))}  # fmt: skip


def online(cfg: PassiveBenchConfig, kind: str, progress: Progress) -> dict[str, Any]:
    """Learners act on the protocol and learn as `kind` says.

    `plain`: each experience; `mirror`: each experience and its mirror image; `phantom`: each
    experience only as phantom-target copies.
    """
    p = cfg.controllers
    capacity = cfg.online_targets * 200 * (2 if kind == "mirror" else max(cfg.phantoms, 1))
    learner = make_population(_config(cfg, capacity, cfg.learner), p)
    boat = _boat(cfg, p)
    rng = np.random.default_rng(cfg.seed + 3)
    boat.reset(rng)
    boat_cfg = BoatConfig(dt=cfg.dt)

    def learn(
        x: FloatArray, u: FloatArray, xn: FloatArray, r: FloatArray, terminal: BoolArray, valid: BoolArray
    ) -> None:
        executed = np.clip(u, -1.0, 1.0)
        if kind == "phantom":
            for _ in range(max(cfg.phantoms, 1)):
                offsets = _phantom_offsets(rng, p, cfg.phantom_radius)
                ps, pu, psn, pr = phantom(x, executed, xn, r, offsets, boat_cfg)
                learner.learn(ps, pu, psn, pr, terminal, valid)
        else:
            learner.learn(x, executed, xn, r, terminal, valid)
            if kind == "mirror":
                ms, mu, msn, mr = mirror(x, executed, xn, r)
                learner.learn(ms, mu, msn, mr, terminal, valid)

    choose: Callable[[FloatArray], FloatArray] = lambda x: learner.act(x).action  # noqa: E731
    run = run_protocol(boat, cfg.online_targets, rng, choose, learn, learner.think, progress)
    greedy = greedy_eval(learner, cfg)
    return {"learner": cfg.learner, "scores": run.scores, "median_per_target": np.median(run.scores, axis=0),
            # As `wfnn-bench boat` reports it: each controller's median over its last 10 targets,
            # then the median over controllers (not one median over every controller's targets).
            "score_last10": float(np.median(np.median(run.scores[:, -10:], axis=1))),
            "greedy": float(np.median(greedy.scores)),
            "return_last10": float(np.median(np.median(run.returns[:, -10:], axis=1))),
            "greedy_return": float(np.median(greedy.returns))}  # fmt: skip


def experiences_to_reach(median_per_target: FloatArray, level: float, window: int = 5) -> int | None:
    """Real experiences until the running median score first reaches `level` (None if never).

    200 experiences per target; the median runs over `window` targets.
    """
    m = np.asarray(median_per_target)
    for t in range(window - 1, len(m)):
        if np.median(m[t - window + 1 : t + 1]) <= level:
            return (t + 1) * 200
    return None


def run(cfg: PassiveBenchConfig, progress: Progress = no_progress) -> dict[str, Any]:
    """All conditions -> a JSON-ready dict."""
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="wfnn-passive-") as tmp:
        recorded = record_logs(cfg, Path(tmp))
        sources = [Path(p) for p in recorded["logs"]]
        summary = {p.name: logs.summarise(p).experiences for p in sources}
        arrays = logs.to_arrays(sources)
    progress(1)
    pull = pulled(cfg)
    learners: dict[str, tuple[str, dict[str, Any]]] = {
        "passive": (cfg.learner, pull), "passive_no_bc": (cfg.learner, {**pull, "bc_weight": 0.0}),
        "passive_thesis": ("thesis", {"reference": True}),
    }  # fmt: skip
    passives = {key: passive(cfg, arrays, False, progress, kind, **setting)
                for key, (kind, setting) in learners.items()}  # fmt: skip
    passive_phantom = passive(cfg, arrays, True, progress, cfg.learner, **pull)
    plain, mirrored, phantom_online = (online(cfg, kind, progress) for kind in ("plain", "mirror", "phantom"))
    level = plain["score_last10"]
    plain_n = experiences_to_reach(plain["median_per_target"], level)
    mirror_n = experiences_to_reach(mirrored["median_per_target"], level)
    policies: dict[str, Callable[[FloatArray], FloatArray]] = {
        "handcoded": handcoded_boat, "zero_thrust": lambda x: np.zeros((x.shape[0], 2)),
    }  # fmt: skip
    # On as many boats as each condition has controllers: boat i meets the targets controller i of
    # every condition meets (one boat met targets of its own), and the figure is their median.
    references = {name: evaluate(policy, cfg.controllers, cfg)._asdict() for name, policy in policies.items()}
    ref = {name: {k: float(np.median(v)) for k, v in figures.items()} for name, figures in references.items()}
    handcoded = ref["handcoded"]
    best = passives["passive"]
    return {
        "benchmark": "passive",
        "config": asdict(cfg),
        "machine": machine_info(),
        "logs": {
            "experiences": summary,
            "policy_scores": recorded["policy_scores"],
            "learned": best["experiences"],
        },
        "references": references,
        "handcoded_score": handcoded["scores"],
        "handcoded_reward": handcoded["rewards"],
        "handcoded_return": handcoded["returns"],
        "zero_thrust_score": ref["zero_thrust"]["scores"],
        "zero_thrust_reward": ref["zero_thrust"]["rewards"],
        "zero_thrust_return": ref["zero_thrust"]["returns"],
        **passives,
        "passive_score": best["score"],
        "passive_reward": best["reward"],
        "passive_return": best["return"],
        "passive_no_bc_score": passives["passive_no_bc"]["score"],
        "passive_thesis_score": passives["passive_thesis"]["score"],
        "passive_phantom_only": passive_phantom,
        "passive_phantom_only_score": passive_phantom["score"],
        "passive_phantom_only_reward": passive_phantom["reward"],
        "criteria": {
            "passive_score_within_20pct_of_handcoded": best["score"] <= 1.2 * handcoded["scores"],
            "passive_reward_above_handcoded": best["reward"] > handcoded["rewards"],
            "phantom_only_passive_within_20pct": passive_phantom["score"] <= 1.2 * handcoded["scores"],
        },
        "online": plain,
        "online_mirror": mirrored,
        "online_phantom_only": phantom_online,
        "phantom_only_score": phantom_online["score_last10"],
        "mirror_level": level,
        "mirror_experiences": {"plain": plain_n, "mirror": mirror_n},
        "mirror_experience_ratio": (mirror_n / plain_n) if plain_n and mirror_n else None,
        "wall_s": time.perf_counter() - t0,
    }


def steps(cfg: PassiveBenchConfig) -> int:
    """Progress units: logs, passive checks (four learners), online targets (three conditions)."""
    return 1 + (len(PASSIVE_LEARNERS) + 1) * cfg.passive_checks + 3 * cfg.online_targets


PASSIVE_LABELS = {
    "passive": "best wire pulled to the logged actions",
    "passive_no_bc": "no pull",
    "passive_thesis": "the thesis' learner",
    "passive_phantom_only": "pulled, from phantom targets only",
}


def label(result: dict[str, Any], key: str) -> str:
    """A passive condition's name with the learner settings it ran with."""
    c = result[key]
    kind = c.get("learner", "thesis")  # results from before the deep learner name none
    step = "alpha" if kind == "thesis" else "lr"
    return (f"{PASSIVE_LABELS[key]} ({kind}, k {c['advantage_k']:g}, {step} {c['alpha']:g}, "
            f"pull {c['bc_weight']:g})")  # fmt: skip


def plot(result: dict[str, Any], path: Path) -> None:
    """Passive curves, each controller's score against its reward, and the online conditions."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(19, 5))
    refs = {"handcoded": ("k", "--", "hand-coded controller"), "zero_thrust": ("grey", ":", "zero thrust")}
    ax = axes[0]
    for key in PASSIVE_LABELS:
        curve = result[key]["curve"]
        thinks = [c["thinks"] for c in curve]
        scores = np.array([c["scores"] for c in curve])
        ax.plot(thinks, np.median(scores, axis=1), marker="o", label=f"{label(result, key)} (median)")
        ax.fill_between(thinks, *np.percentile(scores, [25, 75], axis=1), alpha=0.2)
    for name, (colour, style, text) in refs.items():
        ax.axhline(result[f"{name}_score"], color=colour, ls=style, label=text)
    ax.set(xlabel="thinks per learner", ylabel="greedy score (mean distance to target)", yscale="log",
           title="passive learning from the hand-coded controller's logs")  # fmt: skip
    ax.legend(fontsize=7)
    ax = axes[1]
    for key in PASSIVE_LABELS:
        last = result[key]["curve"][-1]
        ax.scatter(last["rewards"], last["scores"], s=18, label=label(result, key))
    for name, (colour, _, text) in refs.items():
        ax.scatter([result[f"{name}_reward"]], [result[f"{name}_score"]], color=colour, marker="*", s=160,
                   label=text)  # fmt: skip
    ax.set(xlabel="mean squashed reward per action (what the thesis' learner maximises)", yscale="log",
           ylabel="score (mean distance to target)",
           title="each controller: score against reward")  # fmt: skip
    ax.legend(fontsize=7)
    ax = axes[2]
    for key, text in (("online", "online"), ("online_mirror", "online + mirror images"),
                       ("online_phantom_only", "online, phantom targets only")):  # fmt: skip
        m = np.asarray(result[key]["median_per_target"])
        ax.plot(np.arange(1, len(m) + 1) * 200, m, label=text)
    ax.axhline(result["handcoded_score"], color="k", ls="--", label="hand-coded controller")
    ax.set(xlabel="real experiences", ylabel="median score per target", yscale="log",
           title=f"learning while acting, {result['online'].get('learner', 'thesis')} learner "
                 "(Section 4.2 protocol)")  # fmt: skip
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    plt.close(fig)


def rows(result: dict[str, Any], cfg: PassiveBenchConfig) -> list[tuple[str, Any]]:
    """The figures of `wfnn-bench passive`'s table: (name, value) rows."""
    rows: list[tuple[str, Any]] = [
        (f"log policy {k}: score", v) for k, v in result["logs"]["policy_scores"].items()
    ]
    rows.append(("experiences learned from the logs", result["logs"]["learned"]))
    for name in ("handcoded", "zero_thrust"):
        rows.append((f"{name}: score / reward per action / return per target",
                     f"{result[f'{name}_score']:.3f} / {result[f'{name}_reward']:.4f} / "
                     f"{result[f'{name}_return']:.1f}"))  # fmt: skip
    for key in PASSIVE_LABELS:
        name_of = label(result, key)
        for c in result[key]["curve"]:
            rows.append((f"passive, {name_of}: greedy score / reward / return after {c['thinks']:,} thinks "
                         "(median)", f"{np.median(c['scores']):.3f} / {np.median(c['rewards']):.4f} / "
                         f"{np.median(c['returns']):.1f}"))  # fmt: skip
        d = result[key]["diagnosis"]
        rows.append((f"passive, {name_of}: value of the greedy / logged action (median over logged states)",
                     f"{d['greedy_value']:.3f} / {d['logged_action_value']:.3f}"))  # fmt: skip
    ratio = result["mirror_experience_ratio"]
    rows += [
        ("handcoded_score", result["handcoded_score"]),
        ("passive_score", result["passive_score"]),
        ("passive_phantom_only_score", result["passive_phantom_only_score"]),
        *((f"criterion {k}", str(v)) for k, v in result["criteria"].items()),
        (f"online ({result['online']['learner']}): last-10 median / greedy; return last-10 / greedy",
         f"{result['online']['score_last10']:.3f} / {result['online']['greedy']:.3f}; "
         f"{result['online']['return_last10']:.1f} / {result['online']['greedy_return']:.1f}"),
        ("online + mirror: last-10 median / greedy",
         f"{result['online_mirror']['score_last10']:.3f} / {result['online_mirror']['greedy']:.3f}"),
        ("phantom_only_score (online, last-10 median)", result["phantom_only_score"]),
        ("mirror_experience_ratio (experiences to reach the plain learners' last-10 score)",
         "-" if ratio is None else f"{ratio:.2f}"),
        ("wall_s", result["wall_s"]),
    ]  # fmt: skip
    return rows
