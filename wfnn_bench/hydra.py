"""HyDrA experiments of thesis Chapter 7 on the MuJoCo head.

- Table 7.1: 1-DOF controllers (right verge-axis joint, right camera x) are trained with static
  targets (moved by steps) and with the swinging target, then evaluated with learning off and no
  exploration on both: RMS pixel error while tracked (and the fraction of time lost), lag
  (the delay that best aligns the joint's motion with the target's bearing, by
  cross-correlation) and roughness of the commanded action (mean |change| per tick).
- Controller analysis (Figs 7.19, 7.22): synthetic states fed to each trained controller; the
  implied joint acceleration (commanded velocity from rest, over one tick) against joint
  position, with the pendulum model of Eq 7.1 and the static model, and against target position.
- 4-DOF with both cameras (Section 7.6), target on elastic: learning curve, divergence resets,
  and how the joints share the work (pan against verge-axis redundancy).
- Time series like Figs 7.12-7.18 for one controller per Table 7.1 cell.
- The cost of a control tick (physics + vision + act) at the default settings.
- Rendered vision (`VisionConfig.source="render"`): template matching in MuJoCo's images against
  the camera model, per target regime, while a simple proportional follower keeps the target in
  view; the tick cost with rendering; a sheet of what the cameras see.

Several controllers (a population of learners, one simulated head each) learn at once.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sims.hydra import REGIMES, HydraConfig, HydraVec
from sims.hydra.vision import VisionConfig, VisionSource
from wfnn_bench.common import (
    Progress,
    check_seed,
    finite_median,
    fmt2,
    machine_info,
    nan_mean,
    no_progress,
    tick_learner,
)
from wfnn_client.step import Decided, Pupil, robot_step
from wfnn_common.config import LEARNERS, ExplorationConfig, LearnerConfig, check_fields
from wfnn_common.learners import make_population
from wfnn_io.persist import save_figure

FloatArray = np.ndarray
REGIMES_71 = ("static", "swing")
EPISODE = 450
"""Ticks per episode (30 s at 15 Hz)."""


@dataclass(frozen=True, kw_only=True)
class HydraBenchConfig:
    """Options of `wfnn-bench hydra`."""

    controllers: int = 4
    """Controllers trained per regime (1-DOF)."""
    train_episodes: int = 30
    """30 s episodes of training (1-DOF)."""
    eval_episodes: int = 4
    thinks: int = 200
    """The thesis' learner's replays per action (the deep learner's updates per action are its
    own default, `thinks_per_action` 1)."""
    learner: str = "thesis"
    """Which learner the heads learn with: "thesis" or "deep"."""
    sigma: float = 0.1
    """Gaussian exploration (scaled action units) while training."""
    advantage_k: float = 1.0
    """Advantage learning's k: 1 is plain Q-learning, the HyDrA default here (with the thesis'
    0.2 the controllers diverged and were reset 23 times in 1-DOF training, with 1 never; but only
    k 0.2 learned 4-DOF in the benchmark's budget)."""
    velocity_weight: float = 0.25
    """The 1-DOF task's image velocity penalty (`HydraConfig.velocity_weight`); 3.75 weighs a
    pixel per second as much as a pixel of error, as Fig 7.6 writes the reward in raw units."""
    four_dof_controllers: int = 2
    four_dof_episodes: int = 40
    tick_samples: int = 2000
    render: bool = True
    """Also check rendered vision (needs off-screen GL; reported unavailable otherwise)."""
    render_ticks: int = 450
    """Ticks per regime of the rendered-vision check."""
    seed: int = 0

    def __post_init__(self) -> None:
        check_fields(self)
        check_seed(self.seed)
        if self.learner not in LEARNERS:
            raise ValueError(f"learner must be one of {LEARNERS}, got {self.learner!r}")


NOT_IN_JSON = ("render_views",)
"""Rendered pictures: in the PNG, not in the JSON."""


def steps(cfg: HydraBenchConfig) -> int:
    """Progress units: episodes trained or evaluated, and the regimes of the rendering check."""
    one = len(REGIMES_71) * (cfg.train_episodes + len(REGIMES_71) * cfg.eval_episodes)
    return one + cfg.four_dof_episodes + 1 + (len(REGIMES) if cfg.render else 0)


def _learner(task: HydraVec, population: int, cfg: HydraBenchConfig, episodes: int) -> Any:
    thinks = {"thinks_per_action": cfg.thinks} if cfg.learner == "thesis" else {}
    lcfg = LearnerConfig.for_task(
        task, learner=cfg.learner, exploration=ExplorationConfig(kind="gaussian", sigma=cfg.sigma),
        replay_capacity=episodes * EPISODE, advantage_k=cfg.advantage_k, seed=cfg.seed, **thinks,
    )  # fmt: skip
    return make_population(lcfg, population)


def learn_episode(learner: Any, task: HydraVec, rng: np.random.Generator) -> FloatArray:
    """One 30 s episode with new targets, acting, learning and thinking every tick.

    Returns each head's mean |pixel error| over the episode [P].
    """
    error = np.zeros(task.n)
    x = task.new_targets(rng)
    for _ in range(EPISODE):
        tr = robot_step(Decided.unchanged(learner.act(x).action), task.step, [Pupil(x, learner.learn)])
        learner.think()
        error += task.pixel_error() / EPISODE
        x = tr.state
    return error


def train(
    hydra: HydraConfig, population: int, episodes: int, cfg: HydraBenchConfig, progress: Progress
) -> dict[str, Any]:
    """Learn in `population` heads at once -> learner, per-episode error [P, episodes], resets."""
    task = HydraVec(population, hydra, seed=cfg.seed)
    learner = _learner(task, population, cfg, episodes)
    rng = np.random.default_rng(cfg.seed)
    task.reset(rng)
    curve = np.zeros((population, episodes))
    t0 = time.perf_counter()
    for ep in range(episodes):
        curve[:, ep] = learn_episode(learner, task, rng)
        progress(1)
    return {
        "learner": learner,
        "curve": curve,
        "divergence_resets": learner.resets.copy(),
        "recentred": task.recentred.copy(),
        "experiences": learner.buffer.count.copy(),
        "wall_s": time.perf_counter() - t0,
    }


def _bearing(task: HydraVec) -> FloatArray:
    """Horizontal bearing of each head's first target from its right verge axis [n] (rad)."""
    out = np.zeros(task.n)
    for i, data in enumerate(task.data):
        target = data.geom_xpos[task._candidates[0]]
        axis = data.xpos[task.model.cam_bodyid[task.cameras[i]["right"].id]]
        out[i] = np.arctan2(target[1] - axis[1], target[0] - axis[0])
    return out


def evaluate(
    learner: Any, hydra: HydraConfig, episodes: int, seed: int, progress: Progress
) -> dict[str, Any]:
    """Greedy, learning off: traces and the Table 7.1 figures per controller.

    On a copy of the weights (a divergence seen while evaluating resets nothing), and what acting
    changed in the learner is put back after (`WFNN.evaluating`).
    """
    with learner.evaluating() as frozen:
        return _evaluate(learner, frozen, hydra, episodes, seed, progress)


def _evaluate(
    learner: Any, frozen: Any, hydra: HydraConfig, episodes: int, seed: int, progress: Progress
) -> dict[str, Any]:
    n = learner.population
    task = HydraVec(n, hydra, seed=seed)
    rng = np.random.default_rng(seed)
    task.reset(rng)
    traces: dict[str, list[FloatArray]] = {
        k: [] for k in ("pixel", "pixel_velocity", "joint", "action", "bearing")
    }
    errors, lags, rough, lost = [], [], [], []
    for _ in range(episodes):
        x = task.new_targets(rng)
        ep: dict[str, list[FloatArray]] = {k: [] for k in traces}
        for _ in range(EPISODE):
            u = learner.act(x, explore=False, params=frozen).action
            tr = task.step(u)
            angles = task.joint_angles()
            ep["pixel"].append(task.pixels[:, 2].copy())
            ep["pixel_velocity"].append(task.pixel_velocity[:, 2].copy())
            ep["joint"].append(angles[:, 0] + angles[:, 3])  # pan + right verge: the camera's heading
            ep["action"].append(u[:, 0].copy())
            ep["bearing"].append(_bearing(task))
            x = tr.state
        arrays = {k: np.stack(v, axis=1) for k, v in ep.items()}  # [n, T]
        for k in traces:
            traces[k].append(arrays[k])
        px = arrays["pixel"]
        found = ~np.isnan(px)
        errors.append(np.sqrt(nan_mean(np.where(found, px, np.nan) ** 2, axis=1)))
        lost.append(1.0 - found.mean(axis=1))
        lags.append(
            np.array([lag_s(arrays["bearing"][i], arrays["joint"][i], hydra.rate_hz) for i in range(n)])
        )
        rough.append(np.abs(np.diff(arrays["action"], axis=1)).mean(axis=1))
        progress(1)
    return {
        "rms_error_px": nan_mean(errors, axis=0),
        "lost_fraction": np.mean(lost, axis=0),
        "lag_s": nan_mean(lags, axis=0),
        "action_roughness": np.mean(rough, axis=0),
        "trace": {k: v[0][0].tolist() for k, v in traces.items()},
    }


def lag_s(target: FloatArray, joint: FloatArray, rate_hz: float, max_lag_s: float = 1.0) -> float:
    """Delay (s) of the joint's motion behind the target's.

    The lag at the peak cross-correlation of their changes, refined between ticks by a parabola;
    NaN when either does not move.
    """
    a, b = np.diff(target), np.diff(joint)
    if np.std(a) < 1e-9 or np.std(b) < 1e-9:
        return float("nan")
    a, b = (a - a.mean()) / a.std(), (b - b.mean()) / b.std()
    max_k = int(max_lag_s * rate_hz)
    corr = np.array([np.mean(a[: len(a) - k] * b[k:]) for k in range(max_k + 1)])
    k = int(np.argmax(corr))
    lag = float(k)
    if 0 < k < max_k:
        y0, y1, y2 = corr[k - 1], corr[k], corr[k + 1]
        denom = y0 - 2 * y1 + y2
        lag += 0.5 * (y0 - y2) / denom if denom != 0 else 0.0
    return lag / rate_hz


def analysis(learner: Any, task: HydraVec) -> dict[str, Any]:
    """Figs 7.19 and 7.22: implied joint acceleration from synthetic states, per controller."""
    rate = task.config.rate_hz
    limit = task.state_high[0]
    positions = np.linspace(-0.8 * limit, 0.8 * limit, 41)
    pixels = np.linspace(-0.8 * task.state_high[2], 0.8 * task.state_high[2], 41)
    n = learner.population

    def accel(states: FloatArray) -> FloatArray:
        out = np.array([learner.act(np.tile(s, (n, 1)), explore=False, params=learner.params).action[:, 0]
                        for s in states])  # fmt: skip
        return (out * rate).T  # from rest to the commanded velocity within one tick [n, K]

    zeros = np.zeros(len(positions))
    by_position = accel(np.stack([positions, zeros, zeros, zeros], axis=1))
    by_pixel = accel(np.stack([zeros, zeros, pixels, zeros], axis=1))
    # Eq 7.1 about the joint angle that looks at the weight at rest (the right camera sits
    # beside the string's plane), signed as a restoring acceleration: the thesis prints the
    # magnitude; a joint ahead of the rest bearing must accelerate back toward it.
    g, length, d = 9.81, 1.6, 0.64
    task.reset(np.random.default_rng(0))
    axis = task.data[0].xpos[task.model.cam_bodyid[task.cameras[0]["right"].id]]
    rest = float(np.arctan2(-axis[1], d - axis[0]))
    beta = positions - rest
    pendulum = -beta * g / length * np.sqrt(np.clip(1 - (beta * d / length) ** 2, 0, None))
    return {
        "joint_position_rad": positions.tolist(),
        "accel_by_position": by_position.tolist(),
        "pendulum_model": pendulum.tolist(),
        "rest_bearing_rad": rest,
        "target_position_px": pixels.tolist(),
        "accel_by_target": by_pixel.tolist(),
    }


def tick_cost(
    samples: int, seed: int, source: VisionSource = "projection", learner_kind: str = "thesis"
) -> dict[str, float]:
    """Milliseconds per control tick (physics + vision + act) at the default 1-DOF settings.

    The tick acts with a fresh learner of the kind the heads learned with.
    """
    task = HydraVec(1, HydraConfig(vision=VisionConfig(source=source)), seed=seed)
    learner = tick_learner(task, learner_kind)
    x = task.reset(np.random.default_rng(seed))
    times = np.zeros(samples)
    for k in range(samples):
        t0 = time.perf_counter()
        u = learner.act(x[0]).action
        x = task.step(u[None]).state
        times[k] = time.perf_counter() - t0
    task.close()
    return {
        "tick_ms_p50": float(np.median(times) * 1e3),
        "tick_ms_p99": float(np.percentile(times, 99) * 1e3),
    }


def follow_target(
    regime: str, source: VisionSource, ticks: int, seed: int = 0, views_every: int = 0
) -> dict[str, Any]:
    """The right verge axis follows the right camera's target by a proportional rule.

    Returns the tracker's error against the camera model's exact projection of the nearest
    target (pixels, max of x and y, per frame it reported a target), the fraction of ticks it
    tracked one, and (every `views_every` ticks) what the cameras saw.
    """
    hydra = HydraConfig(regime=regime, vision=VisionConfig(source=source))  # type: ignore[arg-type]
    task = HydraVec(1, hydra, seed=seed)
    task.reset(np.random.default_rng(seed))
    cam = task.cameras[0]["right"]
    errors, found, views = [], [], []
    try:
        for k in range(ticks):
            px = task.pixels[0, 2]
            u = 0.0 if np.isnan(px) else -float(np.clip(px / 120.0, -1.0, 1.0))
            task.step(np.array([[u]]))
            found.append(bool(task.found[0, 1]))
            if task.found[0, 1]:
                data = task.data[0]
                truth = [cam.project(data, data.geom_xpos[g])[0] for g in task._candidates]
                errors.append(min(float(np.abs(p - task.pixels[0, 2:]).max()) for p in truth))
            if views_every and k % views_every == views_every - 1:
                views.append(task.camera_images(0))
    finally:
        task.close()
    return {"errors": np.asarray(errors), "found": np.asarray(found), "views": views}


def render_check(cfg: HydraBenchConfig, progress: Progress) -> dict[str, Any]:
    """Rendered vision against the camera model per regime, and the tick cost with rendering."""
    from sims.render import RenderUnavailable

    out: dict[str, Any] = {"available": True, "regimes": {}, "views": {}}
    try:
        for regime in REGIMES:
            rendered = follow_target(
                regime, "render", cfg.render_ticks, cfg.seed, views_every=cfg.render_ticks // 3
            )
            projected = follow_target(regime, "projection", cfg.render_ticks, cfg.seed)
            errors = rendered["errors"]
            out["regimes"][regime] = {
                "tracked_fraction": float(rendered["found"].mean()),
                "tracked_fraction_projection": float(projected["found"].mean()),
                "error_px_p50": float(np.median(errors)) if errors.size else None,
                "error_px_p95": float(np.percentile(errors, 95)) if errors.size else None,
            }
            out["views"][regime] = rendered["views"]
            progress(1)
        tick = tick_cost(max(cfg.tick_samples // 4, 50), cfg.seed, source="render", learner_kind=cfg.learner)
    except RenderUnavailable as exc:
        return {"available": False, "reason": str(exc)}
    out["tick_ms_p50_render"] = tick["tick_ms_p50"]
    out["tick_ms_p99_render"] = tick["tick_ms_p99"]
    return out


def four_dof(cfg: HydraBenchConfig, progress: Progress) -> dict[str, Any]:
    """All joints and image axes, target on elastic: curve, resets, how the joints share the work."""
    hydra = HydraConfig(
        joints=("pan", "tilt", "left", "right"),
        axes=("left_x", "left_y", "right_x", "right_y"),
        regime="elastic",
    )
    result = train(hydra, cfg.four_dof_controllers, cfg.four_dof_episodes, cfg, progress)
    learner: Any = result.pop("learner")
    task = HydraVec(learner.population, hydra, seed=cfg.seed + 7)
    rng = np.random.default_rng(cfg.seed + 7)
    x = task.reset(rng)
    motion = np.zeros((learner.population, 4))
    previous = task.joint_angles()
    for _ in range(EPISODE):
        x = task.step(learner.act(x, explore=False, params=learner.params).action).state
        angles = task.joint_angles()
        motion += np.abs(angles - previous)
        previous = angles
    share = motion / np.maximum(motion.sum(axis=1, keepdims=True), 1e-12)
    return {
        "curve": result["curve"],
        "divergence_resets": result["divergence_resets"],
        "recentred": result["recentred"],
        "joint_motion_share": {j: share[:, k] for k, j in enumerate(("pan", "tilt", "left", "right"))},
        "wall_s": result["wall_s"],
    }


def run(cfg: HydraBenchConfig, progress: Progress = no_progress) -> dict[str, Any]:
    """All experiments; Table 7.1 as `table71[trained][evaluated]`.

    `render_views` holds camera images (for `plot`, not for JSON).
    """
    t0 = time.perf_counter()
    table: dict[str, dict[str, Any]] = {}
    training: dict[str, Any] = {}
    analyses: dict[str, Any] = {}
    traces: dict[str, Any] = {}
    for trained in REGIMES_71:
        hydra = HydraConfig(regime=trained, velocity_weight=cfg.velocity_weight)  # type: ignore[arg-type]
        result = train(hydra, cfg.controllers, cfg.train_episodes, cfg, progress)
        learner: Any = result.pop("learner")
        training[trained] = result
        analyses[trained] = analysis(learner, HydraVec(1, hydra))
        table[trained] = {}
        for evaluated in REGIMES_71:
            hydra_eval = HydraConfig(regime=evaluated)  # type: ignore[arg-type]
            ev = evaluate(learner, hydra_eval, cfg.eval_episodes, cfg.seed + 1000, progress)
            traces[f"{trained}_on_{evaluated}"] = ev.pop("trace")
            table[trained][evaluated] = {
                **{k: finite_median(v) for k, v in ev.items()},
                "per_controller": {k: v for k, v in ev.items()},
            }
    dof4 = four_dof(cfg, progress)
    tick = tick_cost(cfg.tick_samples, cfg.seed, learner_kind=cfg.learner)
    progress(1)
    rendering = render_check(cfg, progress) if cfg.render else {"available": False, "reason": "not run"}
    return {
        "benchmark": "hydra",
        "config": asdict(cfg),
        "machine": machine_info(),
        "table71": table,
        "training": training,
        "analysis": analyses,
        "traces": traces,
        "four_dof": dof4,
        "render": {k: v for k, v in rendering.items() if k != "views"},
        "render_views": rendering.get("views", {}),
        **tick,
        "wall_s": time.perf_counter() - t0,
    }


def plot(result: dict[str, Any], path: Path) -> None:
    """Learning curves, Table 7.1 traces, controller analysis and the 4-DOF curve in one figure."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 3, figsize=(16, 12))
    ax = axes[0, 0]
    for trained, res in result["training"].items():
        curve = np.asarray(res["curve"])
        ax.plot(np.median(curve, axis=0), label=f"{trained}-trained (median of {curve.shape[0]})")
    ax.set(xlabel="episode (30 s)", ylabel="mean |pixel error| (lost: 160)", title="1-DOF learning")
    ax.legend()
    for k, (name, trace) in enumerate(result["traces"].items()):
        ax = axes.flat[1 + k]
        t = np.arange(len(trace["joint"])) / 15.0
        ax.plot(t, np.degrees(trace["bearing"]), label="target bearing (deg)", lw=1)
        ax.plot(t, np.degrees(trace["joint"]), label="camera heading (deg)", lw=1)
        ax.plot(t, np.degrees(trace["action"]), label="joint action (deg/s)", lw=0.8, alpha=0.7)
        ax.plot(t, np.asarray(trace["pixel"], dtype=float) / 20.0, label="target px / 20", lw=0.8, alpha=0.7)
        ax.set(xlabel="s", title=name.replace("_", " ") + " (Figs 7.12-7.18)")
        ax.legend(fontsize=7)
    an = result["analysis"]
    ax = axes[1, 2]
    for trained, a in an.items():
        ax.plot(
            a["joint_position_rad"], np.median(a["accel_by_position"], axis=0), label=f"{trained}-trained"
        )
    first = next(iter(an.values()))
    ax.plot(first["joint_position_rad"], first["pendulum_model"], "k--", label="pendulum model (Eq 7.1)")
    ax.axhline(0, color="gray", ls=":", label="static model")
    ax.set(xlabel="joint position (rad)", ylabel="implied acceleration (rad/s^2)", title="Fig 7.19")
    ax.legend(fontsize=8)
    ax = axes[2, 0]
    for trained, a in an.items():
        ax.plot(a["target_position_px"], np.median(a["accel_by_target"], axis=0), label=f"{trained}-trained")
    ax.set(xlabel="target position (px)", ylabel="implied acceleration (rad/s^2)", title="Fig 7.22")
    ax.legend(fontsize=8)
    ax = axes[2, 1]
    curve = np.asarray(result["four_dof"]["curve"])
    for c in curve:
        ax.plot(c, lw=1)
    ax.set(xlabel="episode (30 s)", ylabel="mean |pixel error|", title="4-DOF, both cameras, elastic target")
    ax = axes[2, 2]
    ax.axis("off")
    rows = [f"{tr} -> {ev}: rms {c['rms_error_px']:.1f} px, lag {c['lag_s']:.3f} s, "
            f"roughness {c['action_roughness']:.3f}, lost {c['lost_fraction']:.0%}"
            for tr, cells in result["table71"].items() for ev, c in cells.items()]  # fmt: skip
    ax.text(0, 1, "Table 7.1 (medians)\n" + "\n".join(rows) + f"\n\ntick {result['tick_ms_p50']:.3f} ms p50",
            va="top", family="monospace", fontsize=8)  # fmt: skip
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    plt.close(fig)
    if result.get("render_views"):
        plot_views(result["render_views"], cameras_path(path))


def cameras_path(plot: Path) -> Path:
    """Where the rendered-vision check's camera pictures go, beside the plot."""
    return plot.with_name(plot.stem + "_cameras.png")


def plot_views(views_by_regime: dict[str, list[dict[str, Any]]], path: Path) -> None:
    """What the cameras saw in the rendered-vision check: one row per regime, left | right."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    regimes = {k: v for k, v in views_by_regime.items() if v}
    columns = max(len(v) for v in regimes.values())
    fig, axes = plt.subplots(
        len(regimes), columns, figsize=(5.2 * columns, 2.2 * len(regimes)), squeeze=False
    )
    for row, (regime, seen) in enumerate(regimes.items()):
        for col in range(columns):
            ax = axes[row, col]
            ax.axis("off")
            if col < len(seen):
                views = seen[col]
                ax.imshow(np.concatenate([np.asarray(views["left"]), np.asarray(views["right"])], axis=1))
                ax.set_title(f"{regime}: left | right (right tracked)", fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    plt.close(fig)


def rows(result: dict[str, Any], cfg: HydraBenchConfig) -> list[tuple[str, Any]]:
    """The figures of `wfnn-bench hydra`'s table: (name, value) rows."""
    rows: list[tuple[str, Any]] = []
    for trained, cells in result["table71"].items():
        for evaluated, c in cells.items():
            rows += [
                (f"{trained}-trained on {evaluated}: rms_error_px", c["rms_error_px"]),
                (f"{trained}-trained on {evaluated}: lag_s", c["lag_s"]),
                (f"{trained}-trained on {evaluated}: action_roughness", c["action_roughness"]),
                (f"{trained}-trained on {evaluated}: lost_fraction", c["lost_fraction"]),
            ]
    for trained, res in result["training"].items():
        curve = np.asarray(res["curve"])
        rows.append((f"{trained} training: error first / last episode (median)",
                     f"{np.median(curve[:, 0]):.1f} / {np.median(curve[:, -1]):.1f}"))  # fmt: skip
        rows.append((f"{trained} training: divergence resets", int(np.sum(res["divergence_resets"]))))
    dof4 = result["four_dof"]
    curve4 = np.asarray(dof4["curve"])
    rows += [
        ("4-DOF error first / last episode (median)",
         f"{np.median(curve4[:, 0]):.1f} / {np.median(curve4[:, -1]):.1f}"),
        ("4-DOF divergence resets", int(np.sum(dof4["divergence_resets"]))),
        ("4-DOF joint motion share pan/tilt/left/right",
         " / ".join(f"{float(np.median(v)):.2f}" for v in dof4["joint_motion_share"].values())),
        ("tick_ms_p50", result["tick_ms_p50"]),
        ("tick_ms_p99", result["tick_ms_p99"]),
    ]  # fmt: skip
    rendering = result["render"]
    if rendering["available"]:
        for regime, r in rendering["regimes"].items():
            rows.append((f"rendered vision, {regime}: tracked (projection) / error p50, p95 px",
                         f"{r['tracked_fraction']:.2f} ({r['tracked_fraction_projection']:.2f}) / "
                         f"{fmt2(r['error_px_p50'])}, {fmt2(r['error_px_p95'])}"))  # fmt: skip
        rows.append(("tick_ms_p50_render", rendering["tick_ms_p50_render"]))
    else:
        rows.append(("rendered vision", f"not checked: {rendering['reason']}"))
    rows += [
        ("wall_s", result["wall_s"]),
    ]  # fmt: skip
    return rows
