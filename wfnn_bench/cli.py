"""`wfnn-bench`: one subcommand per benchmark; each prints a table and writes JSON/PNG."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Annotated, Any

import numpy as np
import typer
from rich.console import Console
from rich.logging import RichHandler
from rich.markup import escape
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TaskID,
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
from wfnn_io.cli_errors import file_given, guarded, log_printably, path_given
from wfnn_io.persist import to_jsonable, writable

MAX_POPULATION = 100_000
"""Most learners, runs or controllers a benchmark option asks for (beyond: refused naming it,
not by numpy's array limits once the run has started)."""
MAX_BUDGET = 10_000_000
"""Most of any other count a benchmark option asks for (targets, steps, episodes, calls,
experiences, thinks), for the same reason: 1e11 targets ended in numpy's "Unable to allocate
14.6 TiB" after the run had begun, a server already started and stopped."""


def _count(least: int, help: str | None = None) -> Any:
    """The option of a count a benchmark takes: at least `least`, at most MAX_BUDGET."""
    return typer.Option(min=least, max=MAX_BUDGET, help=help)


app = typer.Typer(
    help="Benchmarks of the WFNN learner (thesis Chapters 3-4) and its speed.", no_args_is_help=True
)
console = Console()

JsonOpt = Annotated[
    Path | None, typer.Option("--json", parser=file_given, help="Write the full result as JSON here.")
]
PlotOpt = Annotated[
    Path | None, typer.Option("--plot", parser=file_given, help="Write the figure as PNG here.")
]


def _logging(verbose: bool, json_path: Path | None, plot_path: Path | None, *more: Path) -> None:
    """Set up logging, and check before any work that each output file can be written.

    The figure is a PNG: another suffix (matplotlib would write JPEG or PDF, or fail after the run)
    is refused now, and so are two outputs in one file (the last written would replace the
    other). `more`: further files the benchmark writes beside its plot.
    """
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(message)s",
        handlers=[RichHandler(console=console, show_path=False)],
    )
    log_printably()
    if plot_path is not None and plot_path.suffix.lower() != ".png":
        raise ValueError(f"--plot {plot_path}: the figure is a PNG; name a .png file")
    outputs = [p for p in (json_path, plot_path, *more) if p is not None]
    resolved = [p.resolve() for p in outputs]
    for i, path in enumerate(resolved):
        if path in resolved[:i]:
            raise ValueError(f"{outputs[i]}: two of the benchmark's outputs would be written to one file")
    for path in outputs:
        writable(path)


def _started(name: str, cfg: Any) -> None:
    """The one line at start: the benchmark and the options that differ from its defaults.

    With --verbose the whole config follows (the JSON holds it too).
    """
    fields = dataclasses.asdict(cfg)
    try:
        defaults = dataclasses.asdict(type(cfg)())
    except TypeError:  # a config with required fields: all of them are news
        defaults = {}
    changed = [f"{k}={v}" for k, v in fields.items() if k not in defaults or defaults[k] != v]
    console.print(f"[bold]wfnn-bench {escape(name)}[/] {escape(', '.join(changed) or 'defaults')}",
                  soft_wrap=True, highlight=False)  # fmt: skip
    logging.getLogger(__name__).info("config: %s", json.dumps(to_jsonable(fields)))


class LineProgress:
    """Progress as plain lines, for output that is not a terminal (a log file, a pipe).

    A progress bar redraws one line in place, which a file receives only when the work ends, so
    a benchmark run in the background said nothing for an hour. This writes a line when a task
    starts, at most one every `every_s` seconds as it advances, and one when the work ends.
    Only `add_task` and `advance` of rich's Progress, as the benchmarks use them.
    """

    def __init__(
        self, write: Callable[[str], None], every_s: float = 60.0, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self._write, self._every_s, self._clock = write, every_s, clock
        self._tasks: list[list[Any]] = []  # [description, total, done, started, last line's time]

    def __enter__(self) -> LineProgress:
        return self

    def __exit__(self, *_: object) -> None:
        for task in range(len(self._tasks)):
            self._line(task)

    def add_task(self, description: str, total: float | None = None) -> TaskID:
        """A new task, announced with a line."""
        now = self._clock()
        self._tasks.append([description, total, 0.0, now, now])
        self._line(len(self._tasks) - 1)
        return TaskID(len(self._tasks) - 1)

    def advance(self, task: TaskID, advance: float = 1.0) -> None:
        """`advance` more units of `task` done; a line if the last was `every_s` ago."""
        entry = self._tasks[task]
        entry[2] += advance
        if self._clock() - entry[4] >= self._every_s:
            self._line(task)

    def _line(self, task: int) -> None:
        description, total, done, started, _ = entry = self._tasks[task]
        now = entry[4] = self._clock()
        elapsed = now - started
        text = f"{description}: {done:g}" + (f"/{total:g} ({100 * done / total:.0f}%)" if total else "")
        text += f", {_duration(elapsed)} elapsed"
        if total and 0 < done < total:
            text += f", about {_duration(elapsed * (total - done) / done)} left"
        self._write(text)


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.0f} min"


def _progress() -> Progress | LineProgress:
    """A progress bar on a terminal; elsewhere (a log file), lines now and then."""
    if not console.is_terminal:
        return LineProgress(lambda text: console.out(text, highlight=False))
    return Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
        TimeElapsedColumn(), TimeRemainingColumn(), console=console, transient=False,
    )  # fmt: skip


def _measure(bench: ModuleType, cfg: Any, description: str, total: int, title: str, json_path: Path | None,
             plot_path: Path | None) -> dict[str, Any]:  # fmt: skip
    """What every benchmark does: run with a progress bar, print its table, write its PNG and JSON.

    `bench` is the benchmark's module: `run(cfg, progress)` measures, `rows(result, cfg)` are its
    table's figures, `plot(result, path)` (where it has one) draws them; keys listed in its
    `NOT_IN_JSON` (pictures) go to the PNG only.
    """
    _started(bench.__name__.rsplit(".", 1)[-1].replace("_", "-"), cfg)
    with _progress() as bar:
        task = bar.add_task(description, total=total)
        result = bench.run(cfg, lambda k: bar.advance(task, k))
    _table(title, bench.rows(result, cfg))
    if json_path:  # first: a figure that fails to draw must not lose the figures
        write_json(json_path, {k: v for k, v in result.items() if k not in getattr(bench, "NOT_IN_JSON", ())})
    plot = getattr(bench, "plot", None)
    if plot_path and plot is not None:
        plot(result, plot_path)
    return result


def _table(title: str, rows: list[tuple[str, Any]]) -> None:
    table = Table(title=title)
    table.add_column("figure")
    table.add_column("value", justify="right")
    for name, value in rows:
        table.add_row(escape(name), _cell(value))
    console.print(table)


def _cell(value: Any) -> str:
    """A figure as the table shows it: "-" where there is none (None or NaN), as elsewhere."""
    if value is None or (isinstance(value, float | np.floating) and math.isnan(value)):
        return "-"
    return f"{value:.4g}" if isinstance(value, float | np.floating) else escape(str(value))


@app.command()
def boat(
    controllers: Annotated[
        int, typer.Option(min=1, max=MAX_POPULATION, help="Controllers per condition.")
    ] = 20,
    mode: Annotated[str, typer.Option(help="advantage, q or both.")] = "both",
    targets: Annotated[int, _count(1)] = 40,
    thinks: Annotated[
        int | None,
        _count(0, "Replays (updates) per action (learner's: thesis 200, deep 1)."),
    ] = None,
    dt: Annotated[float, typer.Option(min=1e-6, help="Boat time per action.")] = 0.1,
    hold: Annotated[
        int,
        typer.Option(
            min=1,
            help="Steps each chosen action is held for (learned as one experience); "
            "warm-up and thinks then count held actions.",
        ),
    ] = 1,
    learner: Annotated[str, typer.Option(help="thesis or deep.")] = "thesis",
    learner_options: Annotated[
        str | None, typer.Option(help="Learner config fields over the learner's defaults (JSON).")
    ] = None,
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
            hold=hold,
            learner=learner,
            learner_options=_json_options(learner_options, "--learner-options"),
            seed=seed,
        )
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    n_cond = 2 if mode == "both" else 1
    _measure(boat_bench, cfg, f"boat ({controllers} controllers x {n_cond})", targets * n_cond,
             "boat (Section 4.2 protocol)", json_path, plot_path)  # fmt: skip


@app.command()
def cartpole(
    runs: Annotated[int, typer.Option(min=1, max=MAX_POPULATION)] = 8,
    steps: Annotated[int, _count(1, "Control steps per run.")] = 30_000,
    thinks: Annotated[int, _count(0)] = 100,
    max_attempt_steps: Annotated[int, _count(1)] = 10_000,
    gamma: Annotated[float, typer.Option(min=0.0, max=0.9999, help="Discount factor.")] = 0.8,
    advantage_k: Annotated[float, typer.Option(min=0.01, max=1.0, help="Advantage learning k.")] = 0.2,
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
    _measure(cartpole_bench, cfg, "cart-pole", steps, "cart-pole (Section 4.5)", json_path, plot_path)


@app.command()
def speed(
    act_calls: Annotated[int, _count(100)] = 20_000,
    thinks: Annotated[int, _count(1000)] = 200_000,
    population: Annotated[int, typer.Option(min=1, max=MAX_POPULATION)] = 64,
    json_path: JsonOpt = None,
    plot_path: PlotOpt = None,
    verbose: bool = False,
) -> None:
    """Act latency, incremental / minibatch / population think rates (16-32-45 network)."""
    _logging(verbose, json_path, plot_path)
    cfg = speed_bench.SpeedBenchConfig(act_calls=act_calls, thinks=thinks, population=population)
    _measure(speed_bench, cfg, "speed", speed_bench.steps(cfg),
             "speed (16 states, 4 actions, 9 wires, 32 hidden)", json_path, plot_path)  # fmt: skip


@app.command()
def hydra(
    controllers: Annotated[
        int, typer.Option(min=1, max=MAX_POPULATION, help="1-DOF controllers per training regime.")
    ] = 4,
    episodes: Annotated[
        int,
        _count(1, "1-DOF training episodes (30 s each)."),
    ] = 30,
    eval_episodes: Annotated[int, _count(1)] = 4,
    thinks: Annotated[
        int,
        _count(0, "Experience replays per action (thesis)."),
    ] = 200,
    learner: Annotated[str, typer.Option(help="thesis or deep.")] = "thesis",
    four_dof_controllers: Annotated[int, typer.Option(min=1, max=MAX_POPULATION)] = 2,
    four_dof_episodes: Annotated[int, _count(1)] = 40,
    advantage_k: Annotated[
        float, typer.Option(min=0.01, max=1.0, help="Advantage learning k (1 = Q-learning; the thesis' 0.2).")
    ] = 1.0,
    velocity_weight: Annotated[
        float, typer.Option(min=0.0, help="1-DOF image velocity penalty (3.75: Fig 7.6's raw units).")
    ] = 0.25,
    render: Annotated[bool, typer.Option(help="Also check rendered vision (template matching).")] = True,
    render_ticks: Annotated[
        int,
        _count(3, "Ticks per regime of the rendering check."),
    ] = 450,
    seed: int = 0,
    json_path: JsonOpt = None,
    plot_path: PlotOpt = None,
    verbose: bool = False,
) -> None:
    """HyDrA (Chapter 7): Table 7.1, controller analysis, 4-DOF, tick cost."""
    cameras = [hydra_bench.cameras_path(plot_path)] if plot_path and render else []
    _logging(verbose, json_path, plot_path, *cameras)
    cfg = hydra_bench.HydraBenchConfig(
        controllers=controllers, train_episodes=episodes, eval_episodes=eval_episodes, thinks=thinks,
        four_dof_controllers=four_dof_controllers, four_dof_episodes=four_dof_episodes, seed=seed,
        render=render, render_ticks=render_ticks, velocity_weight=velocity_weight, advantage_k=advantage_k,
        learner=learner,
    )  # fmt: skip
    _measure(hydra_bench, cfg, "hydra episodes", hydra_bench.steps(cfg),
             "HyDrA (Chapter 7)", json_path, plot_path)  # fmt: skip


@app.command()
def nomad(
    controllers: Annotated[
        int, typer.Option(min=1, max=MAX_POPULATION, help="Servo controllers learning at once.")
    ] = 8,
    episodes: Annotated[
        int,
        _count(1, "Servo training episodes (15 s each)."),
    ] = 30,
    eval_every: Annotated[
        int,
        _count(1, "Evaluate greedily every this many episodes."),
    ] = 5,
    wander_episodes: Annotated[
        int,
        _count(1, "Learned wandering: 60 s episodes."),
    ] = 15,
    forage_minutes: Annotated[
        int,
        _count(1, "Learning servoing while the hand-coded wandering forages: minutes."),
    ] = 20,
    forage_balls: Annotated[
        int,
        _count(1, "Balls in the room while foraging."),
    ] = 24,
    forage_eval_minutes: Annotated[int, _count(1, "Evaluate foraging servoing every N min.")] = 5,
    thinks: Annotated[int, _count(0, "Experience replays per action.")] = 200,
    advantage_k: Annotated[
        float, typer.Option(min=0.01, max=1.0, help="Advantage learning k (1 = Q-learning).")
    ] = 0.2,
    watch_phantoms: Annotated[
        int,
        _count(0, "Passive watching: phantom-goal copies per watched experience."),
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
        int,
        _count(1, "Rendered-vision check: ticks of hand-coded wandering (2 robots)."),
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
    _measure(nomad_bench, cfg, "nomad episodes", nomad_bench.steps(cfg),
             "Nomad 200 (Chapter 6)", json_path, plot_path)  # fmt: skip


@app.command()
def safety(
    episodes: Annotated[
        int,
        _count(1, "Boat episodes recorded for the damaged logs."),
    ] = 4,
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
    _measure(safety_bench, cfg, "safety", safety_bench.steps(cfg),
             "safety (real processes, loopback)", json_path, plot_path)  # fmt: skip


@app.command()
def transport(
    experiences: Annotated[int, _count(1000, "Experiences in the throughput phase.")] = 200_000,
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
    _measure(transport_bench, cfg, "transport", transport_bench.steps(cfg),
             "transport (act-learn-think-C/S, loopback)", json_path, plot_path)  # fmt: skip


@app.command()
def dashboard(
    seconds: Annotated[float, typer.Option(min=1.0, help="Measured window per run.")] = 60.0,
    warmup: Annotated[float, typer.Option(min=1.0, help="Warm-up before each window (s).")] = 15.0,
    repeats: Annotated[int, _count(1, "Off/on pairs of runs.")] = 2,
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
    _measure(dashboard_bench, cfg, "dashboard", dashboard_bench.steps(cfg),
             f"dashboard cost (think server, --think {cfg.think}, serving HyDrA at 15 Hz; * = dashboard on)",
             json_path, plot_path)  # fmt: skip


@app.command()
def relearn(
    controllers: Annotated[
        int, typer.Option(min=1, max=MAX_POPULATION, help="Controllers learning at once.")
    ] = 2,
    episodes: Annotated[
        int,
        _count(1, "30 s episodes of online learning."),
    ] = 40,
    eval_every: Annotated[
        int,
        _count(1, "Episodes between greedy evaluations."),
    ] = 5,
    thinks: Annotated[int, _count(1, "Thinks per action.")] = 200,
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
    _measure(relearn_bench, cfg, "relearn", relearn_bench.steps(cfg),
             "relearning from stored experiences after a divergence reset (HyDrA 4-DOF)",
             json_path, plot_path)  # fmt: skip


@app.command()
def passive(
    controllers: Annotated[int, typer.Option(min=1, max=MAX_POPULATION, help="Learners per condition.")] = 8,
    learner: Annotated[
        str, typer.Option(help="thesis | deep: the learner of every condition but the thesis' passive one.")
    ] = "thesis",
    learner_options: Annotated[
        str | None,
        typer.Option(
            help="That learner's config fields over its defaults, a JSON object (the passive "
            "learners' k, pull and rate come from --passive-advantage-k, --bc-weight and "
            "--passive-alpha over it)."
        ),
    ] = None,
    dt: Annotated[float, typer.Option(min=1e-6, help="Boat time per action.")] = 0.1,
    log_targets: Annotated[
        int,
        _count(1, "Targets per logged boat and policy."),
    ] = 10,
    passive_thinks: Annotated[
        int | None,
        typer.Option(min=1000, help="Replays per passive learner (thinks per logged experience)."),
    ] = None,
    online_targets: Annotated[
        int,
        _count(10, "Targets of the online conditions."),
    ] = 40,
    thinks: Annotated[
        int | None,
        _count(0, "Online replays per action (the learner's: thesis 200, deep 1)."),
    ] = None,
    eval_targets: Annotated[
        int,
        _count(1, "Targets of each greedy evaluation."),
    ] = 10,
    bc_weight: Annotated[
        float, typer.Option(min=0.0, help="Passive learners' pull of the best wire to the logged actions.")
    ] = 0.5,
    passive_advantage_k: Annotated[
        float, typer.Option(min=0.01, max=1.0, help="Passive learners' k (the thesis' learner keeps 0.2).")
    ] = 1.0,
    passive_alpha: Annotated[
        float,
        typer.Option(min=1e-6, help="The thesis' learner's rate in the pulled and unpulled conditions."),
    ] = 0.05,
    seed: int = 0,
    json_path: JsonOpt = None,
    plot_path: PlotOpt = None,
    verbose: bool = False,
) -> None:
    """Boat: passive learning from logs, phantom targets, mirror images (learning from data)."""
    _logging(verbose, json_path, plot_path)
    try:
        cfg = passive_bench.PassiveBenchConfig(
            controllers=controllers, learner=learner,  # type: ignore[arg-type]
            learner_options=_json_options(learner_options, "--learner-options"),
            dt=dt, log_targets=log_targets, passive_thinks=passive_thinks, online_targets=online_targets,
            thinks=thinks, eval_targets=eval_targets, bc_weight=bc_weight,
            passive_advantage_k=passive_advantage_k, passive_alpha=passive_alpha, seed=seed,
        )  # fmt: skip
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    _measure(passive_bench, cfg, "passive", passive_bench.steps(cfg),
             "Passive and off-policy learning (boat)", json_path, plot_path)  # fmt: skip


def _json_options(text: str | None, option: str) -> str:
    """An options JSON text as given ("" where not given); an empty one given is refused."""
    if text is not None and not text.strip():
        raise typer.BadParameter("config fields as a JSON object, not an empty string", param_hint=option)
    return text or ""


def _names(text: str) -> tuple[str, ...]:
    return tuple(v.strip() for v in text.split(",") if v.strip())


def _counts(text: str, option: str) -> tuple[int, ...]:
    """Comma-separated whole numbers; a BadParameter naming the option otherwise."""
    try:
        return tuple(int(v) for v in _names(text))
    except ValueError:
        raise typer.BadParameter(f"whole numbers, comma-separated, expected: {text!r}",
                                 param_hint=option) from None  # fmt: skip


@app.command("vs-sb3")
def vs_sb3(
    tasks: Annotated[
        str, typer.Option(help="Gymnasium task ids, comma-separated.")
    ] = "wfnn/Boat-v0,Pendulum-v1",
    steps: Annotated[str, typer.Option(help="Environment steps per task, comma-separated.")] = "8000,15000",
    algorithms: Annotated[str, typer.Option(help="Of wfnn, sac, td3.")] = "wfnn,sac,td3",
    learners: Annotated[str, typer.Option(help="WFNN learners run for wfnn: thesis, deep.")] = "thesis",
    deep_options: Annotated[
        str | None, typer.Option(help="Deep learner config fields over its defaults (JSON).")
    ] = None,
    seeds: Annotated[int, _count(1)] = 3,
    eval_every: Annotated[
        int,
        _count(1, "Steps between greedy evaluations."),
    ] = 2000,
    eval_episodes: Annotated[int, _count(1)] = 3,
    thinks: Annotated[int, _count(0, "WFNN replays per action.")] = 200,
    reward_scale: Annotated[
        float, typer.Option(help="Rewards learnt from are multiplied by this (returns reported are not).")
    ] = 1.0,
    seed: int = 0,
    json_path: JsonOpt = None,
    plot_path: PlotOpt = None,
    verbose: bool = False,
) -> None:
    """WFNN beside Stable-Baselines3 SAC and TD3: return vs steps, seconds per step, act latency."""
    _logging(verbose, json_path, plot_path)
    try:
        cfg = vs_sb3_bench.VsSb3Config(
            tasks=_names(tasks), steps=_counts(steps, "--steps"), algorithms=_names(algorithms),
            learners=_names(learners), deep_options=_json_options(deep_options, "--deep-options"),
            seeds=seeds, eval_every=eval_every, eval_episodes=eval_episodes, thinks=thinks,
            reward_scale=reward_scale, seed=seed,
        )  # fmt: skip
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    _measure(vs_sb3_bench, cfg, "vs-sb3 environment steps", vs_sb3_bench.steps_total(cfg),
             "WFNN vs Stable-Baselines3", json_path, plot_path)  # fmt: skip


@app.command()
def faults(
    cases: Annotated[str, typer.Option(help="Of a-f, comma-separated (see the list below).")] = "a,b,c,d,e,f",
    impair_s: Annotated[float, typer.Option(min=1.0, help="Loss and delay length (a, e).")] = 60.0,
    partition_s: Annotated[float, typer.Option(min=1.0, help="Partition length (b, d).")] = 10.0,
    router_down_s: Annotated[float, typer.Option(min=0.5, help="Router down time (c).")] = 5.0,
    rate_limit_s: Annotated[float, typer.Option(min=1.0, help="Rate limit length (f).")] = 30.0,
    warmup_s: Annotated[float, typer.Option(min=1.0, help="Learning before each fault.")] = 10.0,
    after_s: Annotated[float, typer.Option(min=1.0, help="Running on after each fault.")] = 20.0,
    keep: Annotated[
        Path | None, typer.Option(parser=path_given, help="Keep every case's logs, stores and traces here.")
    ] = None,
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
    _started("faults", cfg)
    with _progress() as bar:
        task = bar.add_task("faults (cases)", total=len(cfg.cases))
        result = faults_bench.run(cfg, lambda k: bar.advance(task, k), keep=keep)
    table = Table(title="act-learn-think-C/S across hosts, under faults (HyDrA 1-DOF, 15 Hz)")
    for name in faults_bench.TABLE_HEADER:
        table.add_column(name, justify="left" if name == "case" else "right")
    for row in faults_bench.table_rows(result):
        table.add_row(*(_cell(cell) for cell in row))
    console.print(table)
    missed = [f"{case}: {name}" for case, goals in result["goals"].items()
              for name, g in goals.items() if not g["met"]]  # fmt: skip
    console.print("goals: " + ("all met" if not missed else "NOT met: " + escape(", ".join(missed))))
    if json_path:
        write_json(json_path, result)
    if plot_path:
        faults_bench.plot(result, plot_path)


main = guarded(app)
"""The console entry point: bad input ends in one line and a nonzero exit (`wfnn_io.cli_errors`)."""

if __name__ == "__main__":
    main()
