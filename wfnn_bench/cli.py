"""`wfnn-bench`: one subcommand per benchmark; each prints a table and writes JSON/PNG."""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer
from rich.console import Console
from rich.logging import RichHandler
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table

from wfnn_bench import boat as boat_bench
from wfnn_bench import cartpole as cartpole_bench
from wfnn_bench import dashboard as dashboard_bench
from wfnn_bench import faults as faults_bench
from wfnn_bench import hydra as hydra_bench
from wfnn_bench import nomad as nomad_bench
from wfnn_bench import passive as passive_bench
from wfnn_bench import relearn as relearn_bench
from wfnn_bench import safety as safety_bench
from wfnn_bench import speed as speed_bench
from wfnn_bench import transport as transport_bench
from wfnn_bench import vs_sb3 as vs_sb3_bench
from wfnn_bench.common import write_json
from wfnn_bench.hosts import unavailable as hosts_unavailable
from wfnn_io.cli_errors import guarded

app = typer.Typer(
    help="Benchmarks of the WFNN learner (thesis Chapters 3-4) and its speed.", no_args_is_help=True
)
console = Console()

JsonOpt = Annotated[Path | None, typer.Option("--json", help="Write the full result as JSON here.")]
PlotOpt = Annotated[Path | None, typer.Option("--plot", help="Write the figure as PNG here.")]


def _logging(verbose: bool, *outputs: Path | None) -> None:
    """Set up logging, and check before any work that each output file can be written."""
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(message)s",
        handlers=[RichHandler(console=console, show_path=False)],
    )
    for path in outputs:
        if path is not None:
            writable(path)


def writable(path: Path) -> None:
    """Raise OSError now if `path` cannot be written (its folder is made if missing)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.is_dir():
        raise IsADirectoryError(21, "is a directory, not a file", str(path))
    with tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{path.name}.", suffix=".probe"):
        pass


def _progress() -> Progress:
    return Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
        TimeElapsedColumn(), TimeRemainingColumn(), console=console, transient=False,
    )  # fmt: skip


def _table(title: str, rows: list[tuple[str, Any]]) -> None:
    table = Table(title=title)
    table.add_column("figure")
    table.add_column("value", justify="right")
    for name, value in rows:
        table.add_row(name, f"{value:.4g}" if isinstance(value, float) else str(value))
    console.print(table)


@app.command()
def boat(
    controllers: Annotated[int, typer.Option(min=1, help="Controllers per condition.")] = 20,
    mode: Annotated[str, typer.Option(help="advantage, q or both.")] = "both",
    targets: Annotated[int, typer.Option(min=1)] = 40,
    thinks: Annotated[
        int | None, typer.Option(min=0, help="Replays (updates) per action [learner's: thesis 200, deep 1].")
    ] = None,
    dt: Annotated[float, typer.Option(min=1e-6, help="Boat time per action.")] = 0.1,
    learner: Annotated[str, typer.Option(help="thesis or deep.")] = "thesis",
    learner_options: Annotated[
        str, typer.Option(help="Learner config fields over the learner's defaults (JSON).")
    ] = "",
    seed: int = 0,
    json_path: JsonOpt = None,
    plot_path: PlotOpt = None,
    verbose: bool = False,
) -> None:
    """Section 4.2 protocol, Q-learning vs advantage learning (Fig 4.2)."""
    _logging(verbose, json_path, plot_path)
    if mode not in ("advantage", "q", "both"):
        raise typer.BadParameter(f"mode must be advantage, q or both, got {mode!r}", param_hint="--mode")
    try:
        cfg = boat_bench.BoatBenchConfig(
            controllers=controllers,
            mode=mode,  # type: ignore[arg-type]  # checked just above
            targets=targets,
            thinks=thinks,
            dt=dt,
            learner=learner,
            learner_options=learner_options,
            seed=seed,
        )
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    n_cond = 2 if mode == "both" else 1
    with _progress() as bar:
        task = bar.add_task(f"boat ({controllers} controllers x {n_cond})", total=targets * n_cond)
        result = boat_bench.run(cfg, lambda k: bar.advance(task, k))
    rows: list[tuple[str, Any]] = [
        ("random_ref", result["random_ref"]),
        ("handcoded_ref", result["handcoded_ref"]),
        ("step1_random_ref (dt=1)", result["step1_random_ref"]),
        ("step1_handcoded_ref (dt=1)", result["step1_handcoded_ref"]),
    ]
    for res in result["results"]:
        c = res["condition"]
        rows += [
            (f"{c}: median_last10", res["median_last10"]),
            (f"{c}: frac_acceptable", res["frac_acceptable"]),
            (f"{c}: greedy_median", res["greedy_median"]),
            (f"{c}: divergence_resets", res["divergence_resets"]),
            (f"{c}: thinks_per_s", res["thinks_per_s"]),
        ]
    for name, p in result.get("tests", {}).items():
        rows.append((name, p))
    rows.append(("wall_s", result["wall_s"]))
    _table("boat (Section 4.2 protocol)", rows)
    if json_path:
        write_json(json_path, result)
    if plot_path:
        boat_bench.plot(result, plot_path)


@app.command()
def cartpole(
    runs: Annotated[int, typer.Option(min=1)] = 8,
    steps: Annotated[int, typer.Option(min=1, help="Control steps per run.")] = 30_000,
    thinks: Annotated[int, typer.Option(min=0)] = 100,
    max_attempt_steps: Annotated[int, typer.Option(min=1)] = 10_000,
    gamma: float = 0.8,
    advantage_k: float = 0.2,
    seed: int = 0,
    json_path: JsonOpt = None,
    plot_path: PlotOpt = None,
    verbose: bool = False,
) -> None:
    """Cart-pole, pure-delayed reward: steps balanced per attempt (Fig 4.12)."""
    _logging(verbose, json_path, plot_path)
    cfg = cartpole_bench.CartPoleBenchConfig(
        runs=runs, steps=steps, thinks=thinks, max_attempt_steps=max_attempt_steps,
        gamma=gamma, advantage_k=advantage_k, seed=seed,
    )  # fmt: skip
    with _progress() as bar:
        task = bar.add_task("cart-pole", total=steps)
        result = cartpole_bench.run(cfg, lambda k: bar.advance(task, k))
    med = np.asarray(result["median_per_attempt"], dtype=float)
    rows: list[tuple[str, Any]] = [
        ("attempts per run (min)", min(result["attempts_per_run"])),
        ("best attempt per run (median)", float(np.median(result["best_attempt"]))),
        ("median steps, first 10 attempts", float(np.median(med[:10])) if med.size else float("nan")),
        ("median steps, last 10 attempts", float(np.median(med[-10:])) if med.size else float("nan")),
        ("thinks_per_s", result["thinks_per_s"]),
        ("wall_s", result["wall_s"]),
    ]
    _table("cart-pole (Section 4.5)", rows)
    if json_path:
        write_json(json_path, result)
    if plot_path:
        cartpole_bench.plot(result, plot_path)


@app.command()
def speed(
    act_calls: Annotated[int, typer.Option(min=100)] = 20_000,
    thinks: Annotated[int, typer.Option(min=1000)] = 200_000,
    population: Annotated[int, typer.Option(min=1)] = 64,
    json_path: JsonOpt = None,
    verbose: bool = False,
) -> None:
    """Act latency, incremental / minibatch / population think rates (16-32-45 network)."""
    _logging(verbose, json_path)
    cfg = speed_bench.SpeedBenchConfig(act_calls=act_calls, thinks=thinks, population=population)
    with _progress() as bar:
        task = bar.add_task("speed", total=speed_bench.steps(cfg))
        result = speed_bench.run(cfg, lambda k: bar.advance(task, k))
    keys = [
        "act_p50_us", "act_p99_us", "act_p50_us_gc_paused", "act_p99_us_gc_paused",
        "incremental_thinks_per_s", "minibatch_updates_per_s", "population_thinks_per_s",
    ]  # fmt: skip
    rows: list[tuple[str, Any]] = [(k, result[k]) for k in keys]
    rows += [
        (f"minibatch_updates_per_s (batch {b})", v)
        for b, v in result["minibatch_updates_per_s_by_batch"].items()
    ]
    _table("speed (16 states, 4 actions, 9 wires, 32 hidden)", rows)
    if json_path:
        write_json(json_path, result)


def _num(value: float | None) -> str:
    return "-" if value is None or not np.isfinite(value) else f"{value:.2f}"


@app.command()
def hydra(
    controllers: Annotated[int, typer.Option(min=1, help="1-DOF controllers per training regime.")] = 4,
    episodes: Annotated[int, typer.Option(min=1, help="1-DOF training episodes (30 s each).")] = 30,
    eval_episodes: Annotated[int, typer.Option(min=1)] = 4,
    thinks: Annotated[int, typer.Option(min=0, help="Experience replays per action (thesis).")] = 200,
    learner: Annotated[str, typer.Option(help="thesis or deep.")] = "thesis",
    four_dof_controllers: Annotated[int, typer.Option(min=1)] = 2,
    four_dof_episodes: Annotated[int, typer.Option(min=1)] = 40,
    advantage_k: Annotated[
        float, typer.Option(min=0.0, help="Advantage learning k (1 = Q-learning; the thesis' 0.2).")
    ] = 1.0,
    velocity_weight: Annotated[
        float, typer.Option(min=0.0, help="1-DOF image velocity penalty (3.75: Fig 7.6's raw units).")
    ] = 0.25,
    render: Annotated[bool, typer.Option(help="Also check rendered vision (template matching).")] = True,
    render_ticks: Annotated[int, typer.Option(min=3, help="Ticks per regime of the rendering check.")] = 450,
    seed: int = 0,
    json_path: JsonOpt = None,
    plot_path: PlotOpt = None,
    verbose: bool = False,
) -> None:
    """HyDrA (Chapter 7): Table 7.1, controller analysis, 4-DOF, tick cost."""
    _logging(verbose, json_path, plot_path)
    cfg = hydra_bench.HydraBenchConfig(
        controllers=controllers, train_episodes=episodes, eval_episodes=eval_episodes, thinks=thinks,
        four_dof_controllers=four_dof_controllers, four_dof_episodes=four_dof_episodes, seed=seed,
        render=render, render_ticks=render_ticks, velocity_weight=velocity_weight, advantage_k=advantage_k,
        learner=learner,
    )  # fmt: skip
    with _progress() as bar:
        task = bar.add_task("hydra episodes", total=hydra_bench.steps(cfg))
        result = hydra_bench.run(cfg, lambda k: bar.advance(task, k))
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
                         f"{_num(r['error_px_p50'])}, {_num(r['error_px_p95'])}"))  # fmt: skip
        rows.append(("tick_ms_p50_render", rendering["tick_ms_p50_render"]))
    else:
        rows.append(("rendered vision", f"not checked: {rendering['reason']}"))
    rows += [
        ("wall_s", result["wall_s"]),
    ]  # fmt: skip
    _table("HyDrA (Chapter 7)", rows)
    if plot_path:
        hydra_bench.plot(result, plot_path)
    del result["render_views"]  # images: in the PNG, not in the JSON
    if json_path:
        write_json(json_path, result)


@app.command()
def nomad(
    controllers: Annotated[int, typer.Option(min=1, help="Servo controllers learning at once.")] = 8,
    episodes: Annotated[int, typer.Option(min=1, help="Servo training episodes (15 s each).")] = 30,
    eval_every: Annotated[int, typer.Option(min=1, help="Evaluate greedily every this many episodes.")] = 5,
    wander_episodes: Annotated[int, typer.Option(min=1, help="Learned wandering: 60 s episodes.")] = 15,
    forage_minutes: Annotated[
        int, typer.Option(min=1, help="Learning servoing while the hand-coded wandering forages: minutes.")
    ] = 20,
    forage_balls: Annotated[int, typer.Option(min=1, help="Balls in the room while foraging.")] = 24,
    forage_eval_minutes: Annotated[
        int, typer.Option(min=1, help="Evaluate foraging servoing every N min.")
    ] = 5,
    thinks: Annotated[int, typer.Option(min=0, help="Experience replays per action.")] = 200,
    advantage_k: Annotated[float, typer.Option(min=0.0, help="Advantage learning k (1 = Q-learning).")] = 0.2,
    watch_phantoms: Annotated[
        int, typer.Option(min=0, help="Passive watching: phantom-goal copies per watched experience.")
    ] = 4,
    watch_mirror: Annotated[
        bool, typer.Option(help="Passive watching: also learn each experience mirrored.")
    ] = True,
    watch_bc_weight: Annotated[
        float,
        typer.Option(min=0.0, help="Passive watching: pull of the best wire toward the watched action."),
    ] = 0.2,
    watch_alpha: Annotated[float, typer.Option(min=1e-6, help="Passive watching: learning rate.")] = 0.05,
    render: Annotated[bool, typer.Option(help="Also check vision from rendered images (needs GL).")] = True,
    render_ticks: Annotated[
        int, typer.Option(min=1, help="Rendered-vision check: ticks of hand-coded wandering (2 robots).")
    ] = 1200,
    learner: Annotated[
        str, typer.Option(help="The servo controllers learning from scratch: thesis or deep.")
    ] = "thesis",
    servo_only: Annotated[bool, typer.Option(help="Run servoing from scratch only.")] = False,
    seed: int = 0,
    json_path: JsonOpt = None,
    plot_path: PlotOpt = None,
    verbose: bool = False,
) -> None:
    """Nomad 200 (Chapter 6): servoing and wandering learned, servoing from the wandering, tick cost."""
    _logging(verbose, json_path, plot_path)
    try:
        cfg = nomad_bench.NomadBenchConfig(
            controllers=controllers, servo_episodes=episodes, eval_every=eval_every, thinks=thinks,
            wander_episodes=wander_episodes, forage_minutes=forage_minutes, forage_balls=forage_balls,
            forage_eval_minutes=min(forage_eval_minutes, forage_minutes),
            advantage_k=advantage_k, watch_phantoms=watch_phantoms, watch_mirror=watch_mirror,
            watch_bc_weight=watch_bc_weight, watch_alpha=watch_alpha,
            render=render, render_wander_ticks=render_ticks, learner=learner, servo_only=servo_only,
            seed=seed,
        )  # fmt: skip
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    with _progress() as bar:
        task = bar.add_task("nomad episodes", total=nomad_bench.steps(cfg))
        result = nomad_bench.run(cfg, lambda k: bar.advance(task, k))
    rows: list[tuple[str, Any]] = []
    for e in result["servo"]["evaluations"]:
        label = f"servo after {e['episode']} episodes ({np.median(e['experiences']):.0f} experiences)"
        to_goal = _num(float(np.nanmedian(e["time_to_goal_s"])))
        reached = float(np.median(e["reached_fraction"]))
        rows.append((f"{label}: final error px / time to goal s / reached",
                     f"{np.median(e['final_error_px']):.1f} / {to_goal} / {reached:.2f}"))  # fmt: skip
    ref = result["proportional"]
    ref_goal = _num(float(np.nanmedian(ref["time_to_goal_s"])))
    rows += [
        ("proportional controller: final error px / time to goal s",
         f"{float(np.median(ref['final_error_px'])):.1f} / {ref_goal}"),
        ("servo_final_error_px", result["servo_final_error_px"]),
        ("servo_time_to_goal_s", result["servo_time_to_goal_s"]),
    ]  # fmt: skip
    if not cfg.servo_only:
        rows += _nomad_rows(result)
    rows.append(("wall_s", result["wall_s"]))
    _table("Nomad 200 (Chapter 6)", rows)
    if json_path:
        write_json(json_path, result)
    if plot_path:
        nomad_bench.plot(result, plot_path)


def _nomad_rows(result: dict[str, Any]) -> list[tuple[str, Any]]:
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
            to_goal = _num(float(np.nanmedian(e["time_to_goal_s"])))
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
         " / ".join(_num(result["wander_m_per_collision"][k]) for k in ("early", "late", "handcoded"))),
        ("wander collisions early / late (all robots)",
         f"{w['collisions_early']:.0f} / {w['collisions_late']:.0f}"),
        ("without the veto: metres per collision early / late / hand-coded",
         " / ".join(_num(result["wander_m_per_collision"][k])
                    for k in ("no_veto_early", "no_veto_late", "no_veto_handcoded"))),
        ("without the veto: collisions early / late (all robots)",
         "{collisions_early:.0f} / {collisions_late:.0f}".format(**result["wander_no_veto"])),
        ("wander_m_per_veto early / late", " / ".join(_num(v) for v in result["wander_m_per_veto"].values())),
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
             f"{r['servo_final_error_px']:.1f} / {_num(r['servo_time_to_goal_s'])}"),
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


@app.command()
def safety(
    episodes: Annotated[int, typer.Option(min=1, help="Boat episodes recorded for the damaged logs.")] = 4,
    seconds: Annotated[
        float, typer.Option(min=6.0, help="Length of each real-time phase (restart, storm, frames).")
    ] = 10.0,
    json_path: JsonOpt = None,
    plot_path: PlotOpt = None,
    verbose: bool = False,
) -> None:
    """What survives damaged logs, a server restarted empty, a token storm and huge frames."""
    _logging(verbose, json_path, plot_path)
    cfg = safety_bench.SafetyBenchConfig(
        episodes=episodes, restart_seconds=max(seconds, 9.0), storm_seconds=seconds, frames_seconds=seconds
    )
    with _progress() as bar:
        task = bar.add_task("safety", total=safety_bench.steps(cfg))
        result = safety_bench.run(cfg, lambda k: bar.advance(task, k))
    d = result["damaged_logs"]
    rows: list[tuple[str, Any]] = [("experiences in the recorded log", d["experiences"])]
    for case in ("torn_tail", "middle"):
        c = d[case]
        rows += [
            (f"{case}: read by inspect / imported by replay-only",
             f"{c['inspect_experiences']} / {c['replay_experiences']}"),
            (f"{case}: bytes changed by inspect / replay-only",
             f"{c['inspect_bytes_changed']} / {c['replay_bytes_changed']}"),
        ]  # fmt: skip
    r, s = result["restart_empty"], result["token_storm"]
    rows += [
        (
            "restart empty: produced / stored by the new server",
            f"{r['produced']} / {r['stored_by_new_server']}",
        ),
        ("token storm: longest without new weights (s)", s["longest_without_weights_s"]),
        ("token storm: unsigned statuses refused", s["rejected_status_auth"]),
    ]
    for f in result["huge_frames"]:
        rows.append((f"{f['megabytes']} MB frames x{f['frames']} at 50 Hz: overruns, jitter p99 / max (ms)",
                     f"{f['overruns']:.0f}, {f['tick_jitter_p99_ms']:.2f} / "
                     f"{f['tick_jitter_max_ms']:.2f}"))  # fmt: skip
    rows += [(f"goal {k} {g['goal']}", "met" if g["met"] else "NOT met") for k, g in result["goals"].items()]
    rows.append(("wall_s", result["wall_s"]))
    _table("safety (real processes, loopback)", rows)
    if json_path:
        write_json(json_path, result)
    if plot_path:
        safety_bench.plot(result, plot_path)


@app.command()
def transport(
    experiences: Annotated[
        int, typer.Option(min=1000, help="Experiences in the throughput phase.")
    ] = 200_000,
    seconds: Annotated[float, typer.Option(min=1.0, help="Length of the real-time phase.")] = 30.0,
    rate_hz: Annotated[float, typer.Option(min=1.0, help="Tick rate of the real-time phase.")] = 15.0,
    busy: Annotated[bool, typer.Option(help="The server thinks continuously meanwhile.")] = True,
    outage_seconds: Annotated[
        float, typer.Option(min=0.0, help="Length of the outage phase (0: skip).")
    ] = 12.0,
    json_path: JsonOpt = None,
    plot_path: PlotOpt = None,
    verbose: bool = False,
) -> None:
    """C/S over Zenoh across processes: experiences/s, loss, snapshot latency, tick jitter."""
    _logging(verbose, json_path, plot_path)
    cfg = transport_bench.TransportBenchConfig(
        experiences=experiences, tick_seconds=seconds, rate_hz=rate_hz, busy_server=busy,
        outage_seconds=outage_seconds,
    )  # fmt: skip
    with _progress() as bar:
        task = bar.add_task("transport", total=transport_bench.steps(cfg))
        result = transport_bench.run(cfg, lambda k: bar.advance(task, k))
    rows: list[tuple[str, Any]] = [
        (k, result[k])
        for k in (
            "experiences_per_s",
            "experiences_lost",
            "snapshot_p50_ms",
            "snapshot_p99_ms",
            "tick_jitter_p99_ms",
        )
    ]
    rt = result["realtime"]
    rows += [
        ("experiences_per_s over TCP (no shared memory)", result["experiences_per_s_tcp"]),
        ("tick_jitter_p50_ms", rt["tick_jitter_p50_ms"]),
        ("tick_jitter_max_ms", rt["tick_jitter_max_ms"]),
        ("ticks / overruns / safe actions", f"{rt['ticks']} / {rt['overruns']} / {rt['safe_actions']}"),
        ("snapshots applied", rt["snapshots_applied"]),
        ("server thinks/s while ticking", rt["server_thinks_per_s"]),
        ("outage: tick jitter p99 ms (server dead)", result["outage_tick_jitter_p99_ms"]),
        ("outage: experiences missing after restart", result["outage_experiences_missing"]),
        ("wall_s", result["wall_s"]),
    ]
    rows += [(f"goal {k} {g['goal']}", "met" if g["met"] else "NOT met") for k, g in result["goals"].items()]
    _table("transport (act-learn-think-C/S, loopback)", rows)
    if json_path:
        write_json(json_path, result)
    if plot_path:
        transport_bench.plot(result, plot_path)


@app.command()
def dashboard(
    seconds: Annotated[float, typer.Option(min=1.0, help="Measured window per run.")] = 60.0,
    warmup: Annotated[float, typer.Option(min=1.0, help="Warm-up before each window (s).")] = 15.0,
    repeats: Annotated[int, typer.Option(min=1, help="Off/on pairs of runs.")] = 2,
    update_hz: Annotated[float, typer.Option(min=0.1, max=30.0, help="View updates per second.")] = 4.0,
    think: Annotated[
        str, typer.Option(help="The server's --think: budget (light) or continuous (busy).")
    ] = "budget",
    json_path: JsonOpt = None,
    plot_path: PlotOpt = None,
    verbose: bool = False,
) -> None:
    """What the dashboard costs a think server serving the HyDrA robot (CPU, off vs on)."""
    _logging(verbose, json_path, plot_path)
    if think not in ("budget", "continuous"):
        raise typer.BadParameter("budget or continuous", param_hint="--think")
    cfg = dashboard_bench.DashboardBenchConfig(seconds=seconds, warmup_s=warmup, repeats=repeats,
                                               update_hz=update_hz, think=think)  # fmt: skip
    with _progress() as bar:
        task = bar.add_task("dashboard", total=dashboard_bench.steps(cfg))
        result = dashboard_bench.run(cfg, lambda k: bar.advance(task, k))
    rows: list[tuple[str, Any]] = [
        ("dashboard CPU / server's other CPU (attributed, median)", result["added_fraction_attributed"]),
        ("server CPU per experience, on / off - 1 (A/B, medians)", result["added_fraction_ab"]),
        ("server CPU ms per experience, off", result["server_cpu_ms_per_experience_off"]),
        ("server CPU ms per experience, on", result["server_cpu_ms_per_experience_on"]),
        ("dashboard CPU ms per update", result["dashboard_cpu_ms_per_update"]),
        ("server CPU (fraction of a core), runs", " ".join(
            f"{r['server_cpu_fraction_of_a_core']:.3f}{'*' * r['dashboard']}" for r in result["runs"])),
        (f"goal {result['goal']['goal']}", "met" if result["goal"]["met"] else "NOT met"),
        ("wall_s", result["wall_s"]),
    ]  # fmt: skip
    _table(f"dashboard cost (think server, --think {think}, serving HyDrA at 15 Hz; * = dashboard on)", rows)
    if json_path:
        write_json(json_path, result)
    if plot_path:
        dashboard_bench.plot(result, plot_path)


@app.command()
def relearn(
    controllers: Annotated[int, typer.Option(min=1, help="Controllers learning at once.")] = 2,
    episodes: Annotated[int, typer.Option(min=1, help="30 s episodes of online learning.")] = 40,
    eval_every: Annotated[int, typer.Option(min=1, help="Episodes between greedy evaluations.")] = 5,
    thinks: Annotated[int, typer.Option(min=1, help="Thinks per action.")] = 200,
    advantage_k: Annotated[float, typer.Option(min=0.01, max=1.0, help="Advantage learning k.")] = 0.2,
    seed: int = 0,
    json_path: JsonOpt = None,
    plot_path: PlotOpt = None,
    verbose: bool = False,
) -> None:
    """HyDrA 4-DOF: relearning from the stored experiences after a divergence reset vs learning online."""
    _logging(verbose, json_path, plot_path)
    if episodes < eval_every:
        raise typer.BadParameter(
            "needs at least one evaluation: episodes >= eval-every", param_hint="--episodes"
        )
    cfg = relearn_bench.RelearnBenchConfig(controllers=controllers, episodes=episodes, eval_every=eval_every,
                                           thinks=thinks, advantage_k=advantage_k, seed=seed)  # fmt: skip
    with _progress() as bar:
        task = bar.add_task("relearn", total=relearn_bench.steps(cfg))
        result = relearn_bench.run(cfg, lambda k: bar.advance(task, k))
    rows: list[tuple[str, Any]] = [("relearn_fraction (robot time after a reset, store kept / from scratch)",
                                    result["relearn_fraction"])]  # fmt: skip
    for i, c in enumerate(result["controllers"]):
        rows += [
            (f"controller {i}: pre-divergence / untrained error px",
             f"{c['pre_divergence_error_px']:.1f} / {c['untrained_error_px']:.1f}"),
            (f"controller {i}: robot s to reach: from scratch / store kept",
             f"{c['online_robot_s_to_reach']} / {c['with_store_robot_s_to_reach']}"),
            (f"controller {i}: store alone: thinks to reach / best error px",
             f"{c['store_only_thinks_to_reach']} / {c['store_only_best_error_px']:.1f}"),
            (f"controller {i}: store alone, passive learner: thinks / wall s to reach / best error px",
             f"{c['store_only_passive_thinks_to_reach']} / "
             f"{_num(c['store_only_passive_wall_s_to_reach'])} / "
             f"{c['store_only_passive_best_error_px']:.1f}"),
        ]  # fmt: skip
    rows += [("competent controllers / relearned with the store kept / with the store alone / "
              "with the store alone by the passive learner",
              f"{result['competent_controllers']} / {result['relearned_with_store']} / "
              f"{result['relearned_store_only']} / {result['relearned_store_only_passive']}"),
             ("online divergence resets", str(result["online_divergence_resets"].tolist())),
             ("stored experiences", str(result["stored_experiences"].tolist())),
             ("online wall_s", result["online_wall_s"])]  # fmt: skip
    _table("relearning from stored experiences after a divergence reset (HyDrA 4-DOF)", rows)
    if json_path:
        write_json(json_path, result)
    if plot_path:
        relearn_bench.plot(result, plot_path)


@app.command()
def passive(
    controllers: Annotated[int, typer.Option(min=1, help="Learners per condition.")] = 8,
    dt: Annotated[float, typer.Option(min=1e-6, help="Boat time per action.")] = 0.1,
    log_targets: Annotated[int, typer.Option(min=1, help="Targets per logged boat and policy.")] = 10,
    passive_thinks: Annotated[
        int | None, typer.Option(min=1000, help="Replays per passive learner [thinks per logged experience].")
    ] = None,
    online_targets: Annotated[int, typer.Option(min=10, help="Targets of the online conditions.")] = 40,
    thinks: Annotated[int, typer.Option(min=0, help="Online replays per action.")] = 200,
    eval_targets: Annotated[int, typer.Option(min=1, help="Targets of each greedy evaluation.")] = 10,
    bc_weight: Annotated[
        float, typer.Option(min=0.0, help="Passive learners' pull of the best wire to the logged actions.")
    ] = 0.5,
    passive_advantage_k: Annotated[
        float, typer.Option(min=0.01, max=1.0, help="Passive learners' k (the thesis' learner keeps 0.2).")
    ] = 1.0,
    passive_alpha: Annotated[
        float, typer.Option(min=1e-6, help="Passive learners' learning rate (the thesis' keeps 0.25).")
    ] = 0.05,
    seed: int = 0,
    json_path: JsonOpt = None,
    plot_path: PlotOpt = None,
    verbose: bool = False,
) -> None:
    """Boat: passive learning from logs, phantom targets, mirror images (learning from data)."""
    _logging(verbose, json_path, plot_path)
    cfg = passive_bench.PassiveBenchConfig(
        controllers=controllers, dt=dt, log_targets=log_targets, passive_thinks=passive_thinks,
        online_targets=online_targets, thinks=thinks, eval_targets=eval_targets, bc_weight=bc_weight,
        passive_advantage_k=passive_advantage_k, passive_alpha=passive_alpha, seed=seed,
    )  # fmt: skip
    with _progress() as bar:
        task = bar.add_task("passive", total=passive_bench.steps(cfg))
        result = passive_bench.run(cfg, lambda k: bar.advance(task, k))
    rows: list[tuple[str, Any]] = [
        (f"log policy {k}: score", v) for k, v in result["logs"]["policy_scores"].items()
    ]
    rows.append(("experiences learned from the logs", result["logs"]["learned"]))
    for name in ("handcoded", "zero_thrust"):
        rows.append((f"{name}: score / reward per action",
                     f"{result[f'{name}_score']:.3f} / {result[f'{name}_reward']:.4f}"))  # fmt: skip
    for key in passive_bench.PASSIVE_LABELS:
        label = passive_bench.label(result, key)
        for c in result[key]["curve"]:
            rows.append((f"passive, {label}: greedy score / reward after {c['thinks']:,} thinks (median)",
                         f"{np.median(c['scores']):.3f} / {np.median(c['rewards']):.4f}"))  # fmt: skip
        d = result[key]["diagnosis"]
        rows.append((f"passive, {label}: value of the greedy / logged action (median over logged states)",
                     f"{d['greedy_value']:.3f} / {d['logged_action_value']:.3f}"))  # fmt: skip
    ratio = result["mirror_experience_ratio"]
    rows += [
        ("handcoded_score", result["handcoded_score"]),
        ("passive_score", result["passive_score"]),
        ("passive_phantom_only_score", result["passive_phantom_only_score"]),
        *((f"criterion {k}", str(v)) for k, v in result["criteria"].items()),
        ("online: last-10 median / greedy",
         f"{result['online']['score_last10']:.3f} / {result['online']['greedy']:.3f}"),
        ("online + mirror: last-10 median / greedy",
         f"{result['online_mirror']['score_last10']:.3f} / {result['online_mirror']['greedy']:.3f}"),
        ("phantom_only_score (online, last-10 median)", result["phantom_only_score"]),
        ("mirror_experience_ratio (experiences to reach the plain learners' last-10 score)",
         "-" if ratio is None else f"{ratio:.2f}"),
        ("wall_s", result["wall_s"]),
    ]  # fmt: skip
    _table("Passive and off-policy learning (boat)", rows)
    if json_path:
        write_json(json_path, result)
    if plot_path:
        passive_bench.plot(result, plot_path)


def _names(text: str) -> tuple[str, ...]:
    return tuple(v.strip() for v in text.split(",") if v.strip())


@app.command("vs-sb3")
def vs_sb3(
    tasks: Annotated[
        str, typer.Option(help="Gymnasium task ids, comma-separated.")
    ] = "wfnn/Boat-v0,Pendulum-v1",
    steps: Annotated[str, typer.Option(help="Environment steps per task, comma-separated.")] = "8000,15000",
    algorithms: Annotated[str, typer.Option(help="Of wfnn, sac, td3.")] = "wfnn,sac,td3",
    learners: Annotated[str, typer.Option(help="WFNN learners run for wfnn: thesis, deep.")] = "thesis",
    deep_options: Annotated[
        str, typer.Option(help="Deep learner config fields over its defaults (JSON).")
    ] = "",
    seeds: Annotated[int, typer.Option(min=1)] = 3,
    eval_every: Annotated[int, typer.Option(min=1, help="Steps between greedy evaluations.")] = 2000,
    eval_episodes: Annotated[int, typer.Option(min=1)] = 3,
    thinks: Annotated[int, typer.Option(min=0, help="WFNN replays per action.")] = 200,
    seed: int = 0,
    json_path: JsonOpt = None,
    plot_path: PlotOpt = None,
    verbose: bool = False,
) -> None:
    """WFNN beside Stable-Baselines3 SAC and TD3: return vs steps, seconds per step, act latency."""
    _logging(verbose, json_path, plot_path)
    try:
        cfg = vs_sb3_bench.VsSb3Config(
            tasks=_names(tasks), steps=tuple(int(v) for v in _names(steps)), algorithms=_names(algorithms),
            learners=_names(learners), deep_options=deep_options, seeds=seeds, eval_every=eval_every,
            eval_episodes=eval_episodes, thinks=thinks, seed=seed,
        )  # fmt: skip
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    with _progress() as bar:
        task = bar.add_task("vs-sb3 runs", total=vs_sb3_bench.steps_total(cfg))
        result = vs_sb3_bench.run(cfg, lambda k: bar.advance(task, k))
    rows: list[tuple[str, Any]] = []
    for env_id, algos in result["tasks"].items():
        for algorithm, r in algos.items():
            if not isinstance(r, dict):
                continue
            if "skipped" in r:
                rows.append((f"{env_id} {algorithm}", f"skipped: {r['skipped']}"))
                continue
            curve = " / ".join(f"{v:.0f}" for v in r["return_median"])
            rows.append((f"{env_id} {algorithm}: greedy return median at {r['steps']} steps", curve))
            rows.append((f"{env_id} {algorithm}: final return per seed",
                         " / ".join(f"{v:.0f}" for v in r["final_returns"])))  # fmt: skip
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
    _table("WFNN vs Stable-Baselines3", rows)
    if json_path:
        write_json(json_path, result)
    if plot_path:
        vs_sb3_bench.plot(result, plot_path)


@app.command()
def faults(
    cases: Annotated[str, typer.Option(help="Of a-f, comma-separated (see the list below).")] = "a,b,c,d,e,f",
    impair_s: Annotated[float, typer.Option(min=1.0, help="Loss and delay length (a, e).")] = 60.0,
    partition_s: Annotated[float, typer.Option(min=1.0, help="Partition length (b, d).")] = 10.0,
    router_down_s: Annotated[float, typer.Option(min=0.5, help="Router down time (c).")] = 5.0,
    rate_limit_s: Annotated[float, typer.Option(min=1.0, help="Rate limit length (f).")] = 30.0,
    warmup_s: Annotated[float, typer.Option(min=1.0, help="Learning before each fault.")] = 10.0,
    after_s: Annotated[float, typer.Option(min=1.0, help="Running on after each fault.")] = 20.0,
    keep: Annotated[Path | None, typer.Option(help="Keep every case's logs, stores and traces here.")] = None,
    seed: int = 0,
    json_path: JsonOpt = None,
    plot_path: PlotOpt = None,
    verbose: bool = False,
) -> None:
    """C/S across hosts (network namespaces) under faults; needs root, ip, iptables and tc.

    Cases: a 5% loss and 20 +- 10 ms delay on the robot's link, b robot partitioned, c router
    killed and restarted, d followed server partitioned, e as a with TLS, f 1 Mbit/s link while a
    late server catches up.
    """
    _logging(verbose, json_path, plot_path)
    why = hosts_unavailable()
    if why is not None:
        raise OSError(f"wfnn-bench faults cannot make hosts here: {why}")
    cfg = faults_bench.FaultsBenchConfig(
        cases=tuple(c.strip() for c in cases.split(",") if c.strip()), impair_s=impair_s,
        partition_s=partition_s, router_down_s=router_down_s, rate_limit_s=rate_limit_s, warmup_s=warmup_s,
        after_s=after_s, seed=seed,
    )  # fmt: skip
    with _progress() as bar:
        task = bar.add_task("faults (cases)", total=len(cfg.cases))
        result = faults_bench.run(cfg, lambda k: bar.advance(task, k), keep=keep)
    table = Table(title="act-learn-think-C/S across hosts, under faults (HyDrA 1-DOF, 15 Hz)")
    for name in faults_bench.TABLE_HEADER:
        table.add_column(name, justify="left" if name == "case" else "right")
    for row in faults_bench.table_rows(result):
        table.add_row(*row)
    console.print(table)
    missed = [f"{case}: {name}" for case, goals in result["goals"].items()
              for name, g in goals.items() if not g["met"]]  # fmt: skip
    console.print("goals: " + ("all met" if not missed else "NOT met: " + ", ".join(missed)))
    if json_path:
        write_json(json_path, result)
    if plot_path:
        faults_bench.plot(result, plot_path)


main = guarded(app)
"""The console entry point: bad input ends in one line and a nonzero exit (`wfnn_io.cli_errors`)."""

if __name__ == "__main__":
    main()
