"""`wfnn-router`: a standalone Zenoh router between robots and think servers.

Where no `zenohd` is installed, this is the router of a multi-host deployment: a Zenoh session
in router mode that listens (and optionally connects to other routers) and routes every wfnn
key between the sessions that reach it. It holds no wfnn state and reads no frame: with
`--key-file` on the robot and servers, every frame is authenticated end to end, so a router
cannot forge or alter one unnoticed. TLS on its links comes from `--zenoh-config`
(`deploy/zenoh-tls.json5`).
"""

from __future__ import annotations

import logging
import signal
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import typer

from wfnn_common.config import check_fields
from wfnn_io.bus import NetConfig, ZenohBus, endpoints, is_loopback
from wfnn_io.cli_errors import guarded, log_printably, path_given

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class RouterConfig:
    """A standalone router: its Zenoh settings only."""

    net: NetConfig

    def __post_init__(self) -> None:
        check_fields(self)


def run(config: RouterConfig, stop: threading.Event) -> None:
    """Route until `stop` is set."""
    listen, connect = endpoints(config.net)
    exposed = [e for e in (*listen, *connect) if not is_loopback(e)]
    if exposed:  # a router reads no frame; the key on robots and servers authenticates them
        log.warning(
            "router on %s: give robots and servers --key-file, and TLS on untrusted links", ", ".join(exposed)
        )
    bus = ZenohBus(config.net)
    try:
        log.info("routing on %s", ", ".join(listen) or "(no listen endpoint)")
        stop.wait()
    finally:
        bus.close()


app = typer.Typer(help="A standalone Zenoh router for robots and think servers on several hosts.")


@app.command()
def route(
    listen: Annotated[list[str] | None, typer.Option(help="Endpoint to listen on (repeatable).")] = None,
    connect: Annotated[
        list[str] | None, typer.Option(help="Another router to connect to (repeatable).")
    ] = None,
    zenoh_config: Annotated[
        Path | None, typer.Option(parser=path_given, help="Zenoh JSON5 config (TLS, auth...).")
    ] = None,
    verbose: bool = False,
) -> None:
    """Route until SIGTERM/SIGINT."""
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(message)s")
    log_printably()
    net = NetConfig(
        mode="router",
        listen=tuple(listen or ()),
        connect=tuple(connect or ()),
        zenoh_config=str(zenoh_config) if zenoh_config else None,
        shared_memory=False,
    )
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    typer.echo(
        f"wfnn-router listen={','.join(net.listen) or '(config)'} connect={','.join(net.connect)}", err=True
    )
    run(RouterConfig(net=net), stop)


main = guarded(app)
"""The console entry point: bad input ends in one line and a nonzero exit."""

if __name__ == "__main__":
    main()
