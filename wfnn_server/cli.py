"""`wfnn-server`: a think server for robots running `wfnn-client` (act-learn-think-C/S)."""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.logging import RichHandler
from rich.markup import escape
from rich.status import Status

from wfnn_io.bus import SHARED_MEMORY_HELP, NetConfig
from wfnn_io.cli_errors import STATUS_LINE_EVERY_S, Every, guarded, log_printably, one_line, path_given
from wfnn_io.persist import to_jsonable
from wfnn_io.protocol import ServerStatus
from wfnn_server.config import DashboardConfig, ServerConfig
from wfnn_server.server import ThinkServer, run

app = typer.Typer(help="Think server: stores robots' experiences, replays them, publishes weights.")
console = Console(stderr=True)


def status_line(status: ServerStatus) -> str:
    """One line of the server's figures."""
    m = status.metrics
    parts = [
        f"[bold]{status.server}[/] v{status.weights_version}",
        f"thinks/s {m.get('think/thinks_per_s', 0):,.0f}",
        f"stored {m.get('store/experiences', 0):,.0f}",
        f"Q {m.get('learn/q_chosen_mean', float('nan')):+.3f}",
        f"resets {m.get('learn/divergence_resets', 0):.0f}",
        f"rejected {sum(status.rejected.values())}",
        f"clients {len(status.stored_through)}",
    ]
    return " | ".join(parts)


def _dashboard(port: int | None, host: str | None, hz: float | None) -> DashboardConfig | None:
    """The dashboard's config from its options (None without a port: then the others are refused)."""
    if port is None:
        if host is not None or hz is not None:  # else silently ignored
            raise typer.BadParameter(
                "serves no dashboard without --dashboard PORT",
                param_hint="--dashboard-host" if host is not None else "--dashboard-hz",
            )
        return None
    config = DashboardConfig(port=port)
    if host is not None:
        config = dataclasses.replace(config, host=host)
    return config if hz is None else dataclasses.replace(config, update_hz=hz)


@app.command()
def serve(
    controller: Annotated[
        str, typer.Option(help="Controller name (keys wfnn/<controller>/...).")
    ] = "default",
    server_id: Annotated[str, typer.Option("--id", help="This server's id.")] = "server",
    mode: Annotated[str, typer.Option(help="Zenoh mode: router, peer or client.")] = "router",
    listen: Annotated[list[str] | None, typer.Option(help="Endpoint to listen on (repeatable).")] = None,
    connect: Annotated[list[str] | None, typer.Option(help="Endpoint to connect to (repeatable).")] = None,
    zenoh_config: Annotated[
        Path | None, typer.Option(parser=path_given, help="Zenoh JSON5 config (TLS, auth...).")
    ] = None,
    shared_memory: Annotated[bool, typer.Option(help=SHARED_MEMORY_HELP)] = NetConfig.shared_memory,
    data_dir: Annotated[
        Path, typer.Option(parser=path_given, help="Store, checkpoint and config directory.")
    ] = Path("wfnn-data"),
    learner_config: Annotated[
        Path | None,
        typer.Option(parser=path_given, help="LearnerConfig JSON (default: adopt the first client's)."),
    ] = None,
    key_file: Annotated[
        Path | None, typer.Option(parser=path_given, help="Shared key: frames are HMAC-authenticated.")
    ] = None,
    insecure: Annotated[
        bool,
        typer.Option(
            help="Allow a non-loopback endpoint without --key-file (anyone reaching it can feed this server)."
        ),
    ] = False,
    allow_client: Annotated[
        list[str] | None,
        typer.Option(help="Take experiences, status and pictures only from this client id (repeatable)."),
    ] = None,
    seed: Annotated[int | None, typer.Option(help="Override the learner's seed.")] = None,
    device: Annotated[str, typer.Option(help="Where a deep learner trains: cpu, cuda or cuda:N.")] = "cpu",
    compile_update: Annotated[
        bool,
        typer.Option(
            "--compile/--no-compile",
            help="Compile a deep learner's update (torch.compile): faster after a first update of 5-30 s.",
        ),
    ] = False,
    bc_weight: Annotated[
        float | None,
        typer.Option(
            min=0.0,
            help="Override the learner's bc_weight: pull the best wire toward the actions "
            "taken (passive learning from other controllers' logs; thesis 0).",
        ),
    ] = None,
    alpha: Annotated[
        float | None,
        typer.Option(min=1e-9, help="Override the learner's learning rate (passive: 0.05; thesis 0.25)."),
    ] = None,
    publish_period: Annotated[float, typer.Option(help="Snapshot period (s).")] = 0.25,
    checkpoint_period: Annotated[float, typer.Option(help="Checkpoint period (s).")] = 30.0,
    think: Annotated[str, typer.Option(help="budget (thinks per action) or continuous.")] = "budget",
    fsync: Annotated[
        str,
        typer.Option(
            help=(
                "When acknowledged experiences are fsynced: always, interval (an acknowledgement waits at "
                "most 20 ms for its fsync) or never (acknowledged once the OS has them: they survive a "
                "server crash, not a power cut)."
            )
        ),
    ] = "interval",
    replay_only: Annotated[
        list[Path] | None,
        typer.Option(
            parser=path_given,
            help="Learn from these experience logs (client --record DIR/journal, server DATA_DIR/store; "
            "repeatable) with no robot: import them into the store, think until each experience has had "
            "its thinks, checkpoint, stop. Rerun without it to go on learning online.",
        ),
    ] = None,
    dashboard: Annotated[
        int | None,
        typer.Option(
            min=0, max=65535, help="Serve a live read-only web view on this port (0: any free port)."
        ),
    ] = None,
    dashboard_host: Annotated[
        str | None,
        typer.Option(
            help="Interface the dashboard binds (loopback unless you mean to share it) (default 127.0.0.1)."
        ),
    ] = None,
    dashboard_hz: Annotated[
        float | None, typer.Option(min=0.1, max=30.0, help="Dashboard updates per second (default 4).")
    ] = None,
    quiet: Annotated[bool, typer.Option(help="No live status line.")] = False,
    verbose: bool = False,
) -> None:
    """Serve a controller's robots until SIGTERM/SIGINT (checkpointing on the way out)."""
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING, format="%(message)s",
        handlers=[RichHandler(console=console, show_path=False)],
    )  # fmt: skip
    log_printably()
    # A config that does not hold (a ValueError), a data directory, key or endpoint that cannot be
    # used, or logs that cannot be replayed end in one `error:` line and exit 2 (`main`).
    # A Zenoh file's own endpoints are kept (the bus listens on loopback where it names none).
    default_listen = ("tcp/127.0.0.1:7447",) if mode == "router" and zenoh_config is None else ()
    net = NetConfig(
        mode=mode,  # type: ignore[arg-type]  # checked by NetConfig
        listen=tuple(listen) if listen is not None else default_listen,
        connect=tuple(connect or ()), zenoh_config=str(zenoh_config) if zenoh_config else None,
        shared_memory=shared_memory,
    )  # fmt: skip
    config = ServerConfig(
        controller=controller, server_id=server_id, net=net, data_dir=data_dir,
        learner_config=learner_config, key_file=key_file, insecure=insecure,
        allow_clients=tuple(allow_client or ()), seed=seed, device=device, compile=compile_update,
        bc_weight=bc_weight, alpha=alpha,
        publish_period_s=publish_period,
        checkpoint_period_s=checkpoint_period, think=think, fsync=fsync,  # type: ignore[arg-type]
        replay=tuple(replay_only or ()), replay_only=bool(replay_only),
        # Logs alone need no network: without an endpoint named, none is joined (no port taken).
        offline=bool(replay_only) and listen is None and not connect and zenoh_config is None,
        dashboard=_dashboard(dashboard, dashboard_host, dashboard_hz),
    )  # fmt: skip
    console.print(f"[bold]wfnn-server[/] {escape(one_line(config.summary()))}", soft_wrap=True)
    if verbose:  # the whole config (also in the data directory's server_config.json)
        console.print_json(json.dumps(to_jsonable(dataclasses.asdict(config))))

    def started(server: ThinkServer) -> None:  # the dashboard's address once it is bound (port 0 too)
        if server.dashboard is not None:
            console.print(f"live dashboard (read-only): {server.dashboard.url}")

    if quiet:
        figures = run(config, on_started=started)
    elif not console.is_terminal:  # a log file or a pipe: a line now and then, not a spinner it never sees
        every = Every(STATUS_LINE_EVERY_S)

        def in_a_file(status: ServerStatus) -> None:
            every(lambda: console.print(status_line(status), soft_wrap=True, highlight=False))

        figures = run(config, in_a_file, started)
    else:
        with Status("starting", console=console) as line:
            figures = run(config, lambda status: line.update(status_line(status)), started)
    if config.replay_only:
        weights = escape(one_line(str(config.data_dir / "checkpoint.npz")))
        console.print(
            f"replay-only: {figures['imported']} experiences imported, {figures['experiences']} stored, "
            f"{figures['thinks']} thinks in all (earlier runs' too); weights in {weights}",
            soft_wrap=True,
        )


main = guarded(app)
"""The console entry point: bad input ends in one line and a nonzero exit (`wfnn_io.cli_errors`)."""

if __name__ == "__main__":
    main()
