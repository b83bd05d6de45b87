"""`wfnn-client`: a simulated robot that learns while it acts, thinking locally or on servers."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.logging import RichHandler
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from sims.gym import control_rate, make_env
from sims.hydra import HydraConfig
from sims.hydra.vision import VisionConfig
from sims.nomad import ForageConfig, NomadConfig
from sims.nomad.config import BEHAVIOURS as NOMAD_BEHAVIOURS
from sims.nomad.vision import NomadVisionConfig
from wfnn_client.config import MAX_RATE_HZ, MIN_RATE_HZ, ClientConfig
from wfnn_client.controllers import LEARNER, parse_mix
from wfnn_client.run import jsonable_config, prepare, run
from wfnn_client.safety import SafetyConfig
from wfnn_client.sims import SIMS
from wfnn_common.checks import cut_repr
from wfnn_common.config import ExplorationConfig
from wfnn_io.bus import SHARED_MEMORY_HELP, NetConfig
from wfnn_io.cli_errors import (
    STATUS_LINE_EVERY_S,
    Every,
    file_given,
    guarded,
    log_printably,
    one_line,
    path_given,
)
from wfnn_io.persist import folders_to_be_made, remove_empty_folders

app = typer.Typer(help="Simulated robot learning by WFNN Q-learning (act-learn-think-MT or -C/S).")
console = Console()


def _floats(text: str | None, what: str) -> tuple[float, ...] | None:
    if text is None:
        return None
    try:
        return tuple(float(v) for v in text.split(","))
    except ValueError:
        raise typer.BadParameter(f"expected comma-separated numbers, got {text!r}", param_hint=what) from None


def _names(text: str) -> tuple[str, ...]:
    return tuple(v.strip() for v in text.split(",") if v.strip())


def _shown(value: Any, spec: str) -> str:
    """A figure as `spec` formats it, or "-" where there is none (no ticks to time: --rate-hz 0)."""
    return "-" if value is None or not math.isfinite(value) else format(value, spec)


def _run_showing_progress(config: ClientConfig, sim: str, episodes: int) -> dict[str, Any]:
    """`prepare`, then `run` with a progress bar, or status lines where the output is no terminal."""
    prepare(config)
    if not console.is_terminal:  # a log file or a pipe: a line now and then, not a bar it never sees
        every = Every(STATUS_LINE_EVERY_S)

        def line(f: dict[str, Any]) -> None:
            done = f["episode"] >= episodes
            every(lambda: console.out(f"{sim} episodes: {f['episode']}/{episodes}, {status_line(f)}",
                                      highlight=False), now=done)  # fmt: skip

        return run(config, line, prepared=True)
    with Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
        TextColumn("{task.fields[line]}"), console=console,
    ) as bar:  # fmt: skip
        task = bar.add_task(f"{sim} episodes", total=episodes, line="")
        return run(config, lambda f: bar.update(task, completed=f["episode"], line=status_line(f)),
                   prepared=True)  # fmt: skip


def _figure(value: float, decimals: int = 3, sign: str = "") -> str:
    """A score, reward or value with `decimals` places, or in powers of ten where it is huge.

    A diverging task's 1e300 printed with places is 300 digits long.
    """
    return format(value, f"{sign}.{decimals}{'e' if math.isfinite(value) and abs(value) >= 1e9 else 'f'}")


def _unacknowledged(metrics: dict[str, Any]) -> str:
    """A C/S run's experiences no server acknowledged, for its summary line ("" where none).

    The journal holds them all, and the client's next run sends them; where no server took any
    (all of another task, say), nothing reached a learner. Several behaviours: each one's.
    """
    names = [""] if "uplink/acked_by_any" in metrics else [
        k.split("/", 1)[0] for k in metrics if k.endswith("/uplink/acked_by_any") and k.count("/") == 2
    ]  # fmt: skip
    said = []
    for name in names:
        prefix, who = (f"{name}/", f"{name}: ") if name else ("", "")
        acked, produced = (
            metrics[f"{prefix}uplink/acked_by_any"],
            metrics.get(f"{prefix}uplink/produced_through"),
        )
        if acked < 0:
            said.append(f"{who}none acknowledged by a server")
        elif produced is not None and acked < produced:
            said.append(f"{who}acknowledged by a server through #{acked:.0f} of #{produced:.0f}: the journal "
                        "keeps the rest, which the next run sends")  # fmt: skip
    return f" ({'; '.join(said)})" if said else ""


def _per_behaviour(f: dict[str, Any], name: str) -> list[float]:
    """A figure of several behaviours, each under `<behaviour>/name`, in their order."""
    return [v for k, v in f.items() if k.endswith("/" + name) and "/" not in k[: -len(name) - 1]]


def status_line(f: dict[str, Any]) -> str:
    """The live figures of a run (several behaviours: their thinks/s summed, their versions each)."""
    thinks = f.get("server/think/thinks_per_s", f.get("think/thinks_per_s"))
    if thinks is None:
        several = _per_behaviour(f, "server/think/thinks_per_s") or _per_behaviour(f, "think/thinks_per_s")
        thinks = sum(several) if several else None
    versions = _per_behaviour(f, "weights/version") if "weights/version" not in f else [f["weights/version"]]
    return (
        f"score {_figure(f['client/score'])} | "
        f"jitter p99 {_shown(f['client/tick_jitter_ms_p99'], '.2f')} ms | "
        f"overruns {f['client/overruns']:.0f} | safe {f['client/safe_actions']:.0f} | "
        f"thinks/s {_shown(thinks, ',.0f')} | "
        f"r {_figure(f['client/reward_mean'], sign='+')} | Q {_figure(f['client/q_mean'], sign='+')} | "
        f"v{'/'.join(f'{v:.0f}' for v in versions) or 0} from {f['following'] or '-'}"
    )


_FOR_SIMS = {
    "boat_dt": ("boat",), "joints": ("hydra",), "axes": ("hydra",), "regime": ("hydra",),
    "vision": ("hydra", "nomad"), "behaviour": ("nomad",), "balls": ("nomad",),
    "every_second_target": ("nomad",), "camera_yaw": ("nomad",),
}  # fmt: skip
"""Options only some sims read: given with another, they would be dropped without a word."""
_FOR_SERVERS = (
    "listen", "mode", "zenoh_config", "shared_memory", "controller", "follow", "key_file", "insecure",
)  # fmt: skip
"""Options only the C/S client reads: thinking locally, they would be dropped without a word."""


def _given(ctx: typer.Context, name: str) -> bool:
    """Whether option `name` was given (on the command line or by its environment variable)."""
    source = ctx.get_parameter_source(name)  # typer's own click: its enum is not public
    return source is not None and source.name in ("COMMANDLINE", "ENVIRONMENT", "PROMPT")


def _option(name: str) -> str:
    return "--" + name.replace("_", "-")


@app.command()
def client(
    ctx: typer.Context,
    sim: Annotated[str, typer.Option(help=f"Simulated task: {', '.join(SIMS)}.")] = "boat",
    episodes: Annotated[int, typer.Option(min=1, help="Episodes (boat: targets).")] = 40,
    duration: Annotated[float | None, typer.Option(min=0.0, help="Stop after this many seconds.")] = None,
    rate_hz: Annotated[
        float | None,
        typer.Option(
            min=0.0,
            help="Control rate; 0 = as fast as possible (sim's rate: 50, hydra 15, "
            "nomad 10, --env 1 / the task's time step). HyDrA and the Nomad are simulated at this rate.",
        ),
    ] = None,
    lockstep: Annotated[bool, typer.Option(help="As fast as possible, each act after the thinks.")] = False,
    server: Annotated[
        list[str] | None,
        typer.Option(
            help="`local`, or a think server's Zenoh endpoint (repeatable); default local, "
            "or none with --listen (servers connect to this client)."
        ),
    ] = None,
    listen: Annotated[
        list[str] | None, typer.Option(help="Zenoh endpoint to listen on (repeatable).")
    ] = None,
    mode: Annotated[str, typer.Option(help="Zenoh mode: peer, client or router.")] = "peer",
    zenoh_config: Annotated[
        Path | None, typer.Option(parser=path_given, help="Zenoh JSON5 config (TLS, auth...).")
    ] = None,
    shared_memory: Annotated[bool, typer.Option(help=SHARED_MEMORY_HELP)] = NetConfig.shared_memory,
    controller: Annotated[
        str, typer.Option(help="Controller name (keys wfnn/<controller>/...).")
    ] = "default",
    client_id: Annotated[str | None, typer.Option(help="Client id (default: from the journal).")] = None,
    follow: Annotated[str | None, typer.Option(help="Follow only this server id.")] = None,
    key_file: Annotated[
        Path | None, typer.Option(parser=path_given, help="Shared key: frames are HMAC-authenticated.")
    ] = None,
    insecure: Annotated[
        bool,
        typer.Option(
            help="Allow a non-loopback endpoint without --key-file (anyone reaching it can drive the robot)."
        ),
    ] = False,
    learn: Annotated[bool, typer.Option(help="--no-learn: act greedily, learn nothing.")] = True,
    weights: Annotated[
        Path | None,
        typer.Option(
            parser=path_given,
            help="Start from these saved weights (thinking locally: with the training saved).",
        ),
    ] = None,
    learner: Annotated[
        str,
        typer.Option(help="thesis (the thesis' WFNN) or deep (deep wire fitting, torch where it thinks)."),
    ] = "thesis",
    learner_options: Annotated[
        str,
        typer.Option(
            help='Learner config fields over its defaults (JSON), e.g. \'{"deep": {"warmup": 100}}\'.'
        ),
    ] = "",
    thinks: Annotated[int | None, typer.Option(min=0, help="Thinks per action.")] = None,
    advantage_k: Annotated[
        float | None, typer.Option(min=0.0, help="Advantage learning k (1 = Q-learning; thesis 0.2).")
    ] = None,
    bc_weight: Annotated[
        float | None,
        typer.Option(
            min=0.0,
            help="Pull the best wire toward each replayed experience's action (for learning from "
            "logged or other controllers' actions; thesis 0).",
        ),
    ] = None,
    behaviour_policy: Annotated[
        str,
        typer.Option(
            help="Who drives each episode, drawn by share: wfnn (the learner), handcoded, random, "
            "weights:PATH (a saved WFNN, greedy), e.g. 'wfnn=0.5,handcoded=0.3,random=0.2'. "
            "The learner learns off-policy from every episode.",
        ),
    ] = "wfnn",
    symmetries: Annotated[
        bool | None,
        typer.Option(
            help="Also learn each experience's images under the task's declared symmetries "
            "(default: no; with --weights, as saved)."
        ),
    ] = None,
    boat_dt: Annotated[float, typer.Option(min=1e-6, help="Boat time per action.")] = 0.1,
    env: Annotated[
        str | None,
        typer.Option(
            help="A Gymnasium task with 1-D Box observations and actions (e.g. Pendulum-v1); sets --sim gym."
        ),
    ] = None,
    joints: Annotated[str, typer.Option(help="hydra: included joints (pan,tilt,left,right).")] = "right",
    axes: Annotated[
        str, typer.Option(help="hydra: included image axes (left_x,left_y,right_x,right_y).")
    ] = "right_x",
    regime: Annotated[str, typer.Option(help="hydra: targets: static, swing, mixed or elastic.")] = "swing",
    vision: Annotated[
        str,
        typer.Option(
            help="hydra, nomad: `projection` (camera model + tracker faults) or `render` (images, "
            "template matching; slower)."
        ),
    ] = "projection",
    behaviour: Annotated[
        str,
        typer.Option(
            help="nomad: the learned behaviour: servo, wander, or forage (both, one learner each; "
            "C/S controllers <controller>-servo and <controller>-wander; --weights: their run directory)."
        ),
    ] = "servo",
    balls: Annotated[int, typer.Option(min=1, help="nomad: balls in the room (objects to pursue).")] = 6,
    every_second_target: Annotated[
        bool, typer.Option(help="nomad forage: pursue every second target only (the first is watched).")
    ] = False,
    camera_yaw: Annotated[
        float, typer.Option(help="nomad: camera turned from the direction of travel (degrees, Fig 6.14).")
    ] = 0.0,
    camera_every: Annotated[
        int,
        typer.Option(
            min=0, help="hydra, nomad: save what the cameras see every N ticks to OUT/cameras/ (0: off)."
        ),
    ] = 0,
    exploration: Annotated[
        str | None,
        typer.Option(help="uniform, gaussian, smooth, pink or none (sim's: uniform, hydra gaussian)."),
    ] = None,
    max_action_rate: Annotated[str | None, typer.Option(help="Max change per second, per action.")] = None,
    safe_action: Annotated[str | None, typer.Option(help="Safe action, comma-separated (default 0).")] = None,
    veto: Annotated[bool, typer.Option(help="Apply the robot's veto rules.")] = True,
    out: Annotated[
        Path,
        typer.Option("--out", "--record", parser=path_given, help="Run directory (journal, weights...)."),
    ] = Path("runs/latest"),
    json_stats: Annotated[
        Path | None, typer.Option(parser=file_given, help="Write the final figures as JSON here.")
    ] = None,
    timing_trace: Annotated[
        bool, typer.Option(help="Also write every tick's timing and every applied snapshot into the metrics.")
    ] = False,
    seed: Annotated[
        int | None,
        typer.Option(
            help="The run's seed: the task's and the learner's (with --weights: the task's, and "
            "the learner's only where given; default 0)."
        ),
    ] = None,
    verbose: bool = False,
) -> None:
    """Run a simulated robot learning at a fixed tick; save weights, experiences, metrics, plot."""
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING, format="%(message)s",
        handlers=[RichHandler(console=console, show_path=False)],
    )  # fmt: skip
    log_printably()
    if env is not None and _given(ctx, "sim") and sim != "gym":  # else the --sim typed was dropped unsaid
        raise typer.BadParameter(f"--env runs a Gymnasium task (--sim gym), not --sim {cut_repr(sim, 60)}",
                                 param_hint="--sim")  # fmt: skip
    if _given(ctx, "learner_options") and not learner_options.strip():
        raise typer.BadParameter("config fields as a JSON object, not an empty string",
                                 param_hint="--learner-options")  # fmt: skip
    if sim not in SIMS and env is None:
        raise typer.BadParameter(f"unknown sim {cut_repr(sim, 60)}; choose from {', '.join(SIMS)}",
                                 param_hint="--sim")  # fmt: skip
    own_rate = SIMS[sim].rate_hz if env is None else 0.0
    if env is not None:
        sim = "gym"
        try:
            made = make_env(env)
        except ValueError as exc:
            raise typer.BadParameter(str(exc), param_hint="--env") from exc
        own_rate = control_rate(made)  # a Gymnasium task's own time step sets its real-time tick
        made.close()
    if rate_hz is None and not lockstep and own_rate > MAX_RATE_HZ:
        raise typer.BadParameter(
            f"the task's own rate is {own_rate:g} Hz, above real time's limit of {MAX_RATE_HZ:g} Hz: give "
            "--rate-hz 0 (as fast as possible) or a lower rate", param_hint="--rate-hz",
        )  # fmt: skip
    if rate_hz is None and not lockstep and 0.0 < own_rate < MIN_RATE_HZ:  # else blamed on a flag not given
        raise typer.BadParameter(
            f"the task's own rate is {own_rate:g} Hz, below real time's limit of {MIN_RATE_HZ:g} Hz: give "
            "--rate-hz 0 (as fast as possible) or a higher rate", param_hint="--rate-hz",
        )  # fmt: skip
    rate = rate_hz if rate_hz is not None else (0.0 if lockstep else own_rate)
    if exploration is not None and not exploration.strip():
        raise typer.BadParameter("an exploration kind, not an empty string", param_hint="--exploration")
    explicit = exploration is not None
    exploration = exploration or SIMS[sim].exploration
    if exploration not in ("uniform", "gaussian", "smooth", "pink", "none"):
        raise typer.BadParameter(f"unknown exploration {cut_repr(exploration, 60)}",
                                 param_hint="--exploration")  # fmt: skip
    try:
        mix = parse_mix(behaviour_policy)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--behaviour-policy") from exc
    if [m.name for m in mix] == [LEARNER]:
        mix = ()  # the learner alone: the usual run
    # A config that does not hold (a ValueError), or a run directory, key or endpoint that cannot be
    # used ends in one `error:` line and exit 2 (`main`, `wfnn_io.cli_errors`).
    # A simulated robot is simulated at its tick rate (as fast as possible: at its own rate).
    # (Only the robot run is given the rate: another sim's limits must not refuse it.)
    simulated = {"rate_hz": rate} if rate > 0 else {}
    hydra = HydraConfig(
        joints=_names(joints), axes=_names(axes), regime=regime,  # type: ignore[arg-type]
        vision=VisionConfig(source=vision), **(simulated if sim == "hydra" else {}),  # type: ignore[arg-type]
    )  # fmt: skip
    for name, sims in _FOR_SIMS.items():
        if _given(ctx, name) and sim not in sims:
            raise typer.BadParameter(f"is for --sim {' or '.join(sims)}, not {sim}", param_hint=_option(name))
    foraging = behaviour == "forage"
    if every_second_target and not foraging:
        raise typer.BadParameter("needs --behaviour forage", param_hint="--every-second-target")
    if not foraging and behaviour not in NOMAD_BEHAVIOURS:  # the sim's own check knows no forage
        known = (*NOMAD_BEHAVIOURS, "forage")
        raise ValueError(f"--behaviour must be one of {known}, got {behaviour[:60]!r}")
    nomad = NomadConfig(
        behaviour="wander" if foraging else behaviour,  # type: ignore[arg-type]
        camera_yaw_deg=camera_yaw, balls=balls,
        vision=NomadVisionConfig(source=vision), **(simulated if sim == "nomad" else {}),  # type: ignore[arg-type]
    )  # fmt: skip
    forage = ForageConfig(pursue="every_second" if every_second_target else "every") if foraging else None
    config = ClientConfig(
        sim=sim, episodes=episodes, duration_s=duration, rate_hz=rate, lockstep=lockstep,
        hydra=hydra, nomad=nomad, forage=forage if sim == "nomad" else None,
        boat_dt=boat_dt, env=env, thinks_per_action=thinks, advantage_k=advantage_k, learn=learn,
        bc_weight=bc_weight, weights=weights, symmetries=bool(symmetries), behaviour_policy=mix,
        # The deep learner explores its own way unless told (the sims' defaults are the thesis').
        exploration=ExplorationConfig(kind=exploration) if explicit or learner == "thesis" else None,  # type: ignore[arg-type]
        learner=learner, learner_options=learner_options,
        server=tuple(server) if server else (() if listen else ("local",)),
        controller=controller, client_id=client_id, follow=follow,
        net=NetConfig(mode=mode, listen=tuple(listen or ()), shared_memory=shared_memory,  # type: ignore[arg-type]
                      zenoh_config=str(zenoh_config) if zenoh_config else None),
        key_file=key_file, insecure=insecure, out=out, json_stats=json_stats, seed=seed or 0,
        explicit=tuple(name for name, given in (
            ("seed", seed is not None), ("symmetries", symmetries is not None), ("exploration", explicit),
        ) if given),
        timing_trace=timing_trace, camera_every=camera_every,
        safety=SafetyConfig(safe_action=_floats(safe_action, "--safe-action"),
                            max_action_rate=_floats(max_action_rate, "--max-action-rate"), veto=veto),
    )  # fmt: skip
    if config.local:
        for name in _FOR_SERVERS:
            if _given(ctx, name):
                raise typer.BadParameter("is for the C/S client (--server ENDPOINT); this run thinks "
                                         "locally", param_hint=_option(name))  # fmt: skip
    console.print(f"[bold]wfnn-client[/] {escape(one_line(config.summary()))}", soft_wrap=True)
    if verbose:  # the whole config (also in the run directory's config.json)
        console.print_json(json.dumps(jsonable_config(config)))
    new_folders = folders_to_be_made(Path(out))
    try:
        metrics = _run_showing_progress(config, sim, episodes)
    except BaseException:
        remove_empty_folders(new_folders)  # a refused start leaves no empty folder of its own making
        raise
    scores = metrics["scores"]
    trend = (
        f"first-10 median {_figure(metrics['first10_median'])} -> "
        f"last-10 median {_figure(metrics['last10_median'])}"
        if len(scores) >= 20
        else f"episode 1 {_figure(scores[0])} -> episode {len(scores)} {_figure(scores[-1])}"
    )
    if metrics["metric_not_finite"]:  # a score is the mean over the steps whose metric was finite
        trend += (f" (over the finite steps: {metrics['metric_not_finite']} steps' metric was not finite; "
                  "nan: none was)")  # fmt: skip
    refused = int(metrics.get("learn/rejected", 0))  # in-process: what the learner's sanity checks refused
    unacked = _unacknowledged(metrics)
    console.print(
        f"{trend} ({metrics['metric']}); {metrics['experiences_learned']} experiences{unacked}"
        f"{f' ({refused} refused as not finite or out of range)' if refused else ''}, following "
        f"{metrics['following'] or '-'}, act p99 {metrics['client/act_latency_ms_p99']:.3f} ms, "
        f"jitter p99 {_shown(metrics['client/tick_jitter_ms_p99'], '.3f')} ms, "
        f"overruns {metrics['client/overruns']:.0f}",
        soft_wrap=True,
    )
    # No weights where no snapshot ever came (C/S), or they were not finite.
    saved = ("weights, " if metrics.get("weights_saved") else "") + "metrics.json"
    drawn = (Path(out) / "learning_curve.png").exists()  # this run's: a failed plot removes an older one
    saved += " and learning_curve.png" if drawn else " (no learning curve: see above)"
    if metrics.get("camera_frames"):
        saved += f", {metrics['camera_frames']['written']} camera frames (cameras/)"
    console.print(f"saved {saved} in {escape(one_line(str(out)))}/", soft_wrap=True)


main = guarded(app)
"""The console entry point: bad input ends in one line and a nonzero exit (`wfnn_io.cli_errors`)."""

if __name__ == "__main__":
    main()
