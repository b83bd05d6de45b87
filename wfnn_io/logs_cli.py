"""`wfnn-logs`: inspect, merge, split and export experience logs (client records, server stores)."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.logging import RichHandler
from rich.markup import escape
from rich.table import Table

from wfnn_io import logs
from wfnn_io.cli_errors import describe, file_given, guarded, log_printably, one_line, path_given
from wfnn_io.persist import to_jsonable
from wfnn_io.protocol import load_key
from wfnn_io.segments import named_strays

app = typer.Typer(help="Experience logs: a client's --record DIR/journal, a server's DATA_DIR/store.",
                  no_args_is_help=True)  # fmt: skip
console = Console()
errors = Console(stderr=True)
KeyOpt = Annotated[
    Path | None, typer.Option(parser=path_given, help="Shared key file, where the frames carry HMAC tags.")
]


def _key(path: Path | None) -> bytes | None:
    return load_key(str(path)) if path is not None else None


def _shown(text: str) -> str:
    """Text from a log or the network as the console prints it: no markup, no control characters."""
    return escape(one_line(text))


def _fail(exc: Exception) -> typer.Exit:
    """Bad input (an unreadable log, a wrong option value): one line on stderr, exit 2, as every tool."""
    errors.print(f"[red]error:[/] {_shown(describe(exc))}", soft_wrap=True)
    return typer.Exit(2)


@app.callback()
def _setup(verbose: bool = False) -> None:
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING, format="%(message)s",
        handlers=[RichHandler(console=Console(stderr=True), show_path=False)],
    )  # fmt: skip
    log_printably()


@app.command()
def inspect(
    log_dir: Annotated[Path, typer.Argument(parser=path_given)],
    key_file: KeyOpt = None,
    json_out: Annotated[bool, typer.Option("--json", help="Print the summary as JSON.")] = False,
) -> None:
    """What a log holds: experiences per client and behaviour policy, flags, gaps, its learner spec."""
    try:
        summary = logs.summarise(log_dir, _key(key_file))
    except (logs.LogFormatError, ValueError, OSError) as exc:
        raise _fail(exc) from exc
    if json_out:
        print(json.dumps(to_jsonable(summary.to_dict()), indent=1, allow_nan=False))  # strict JSON: no NaN
        return
    where = _shown(str(log_dir))
    title = f"{where}: {summary.experiences:,} experiences in {summary.batches:,} batches"
    table = Table(title=title)
    table.add_column("")
    table.add_column("", justify="right")
    for client, run in summary.clients.items():
        table.add_row(f"client {_shown(client)}",
                      f"{run.experiences:,} (seq {run.first_seq}..{run.last_seq}, "
                      f"{run.gaps} gaps, {run.duplicates} duplicates)")  # fmt: skip
    for source, n in summary.behaviour.items():
        table.add_row(f"chosen by {_shown(source)}", f"{n:,}")
    for name, n in summary.flags.items():
        table.add_row(f"flag {_shown(name)}", f"{n:,}")
    table.add_row("terminal", f"{summary.terminal:,}")
    mean = summary.reward_mean  # rewards as large as 1e308 are not written out in 300 digits
    table.add_row("mean reward", f"{mean:.4f}" if abs(mean) < 1e6 else f"{mean:.4g}")
    table.add_row("learner spec", _shown(", ".join(summary.spec_hashes)) or "-")
    if summary.task:
        table.add_row("task", _shown(summary.task))
    table.add_row("learner config", "in the log" if summary.learner_config else "not recorded")
    if summary.description_error:
        table.add_row("[red]description[/]", _shown(summary.description_error))
    for why, n in summary.refused.most_common():
        table.add_row(f"[red]records refused ({escape(why)})[/]", f"{n:,}")
    for d in summary.damage:
        last = d.segment + d.segments - 1
        span = f"segment {d.segment}" if d.segments == 1 else f"segments {d.segment} to {last}"
        where = (f"{span}: not there, or empty" if d.kind == "missing"
                 else f"segment {d.segment}, offset {d.offset:,}: {d.length:,} bytes")  # fmt: skip
        table.add_row(f"[red]damaged, skipped ({escape(d.kind)})[/]", where)
    if summary.strays:
        table.add_row("[red]named like segments, not read[/]", escape(named_strays(summary.strays)))
    console.print(table)


@app.command()
def merge(
    sources: Annotated[
        list[Path],
        typer.Argument(parser=path_given, help="Logs to merge (each client's experiences kept once)."),
    ],
    out: Annotated[
        Path, typer.Option(parser=path_given, help="The new log's directory (must not hold a log).")
    ],
    key_file: KeyOpt = None,
) -> None:
    """Merge logs into a new one."""
    try:
        n = logs.merge(sources, out, _key(key_file))
    except (logs.LogFormatError, ValueError, OSError) as exc:
        raise _fail(exc) from exc
    console.print(f"{n:,} experiences merged into {_shown(str(out))}")


@app.command()
def split(
    source: Annotated[Path, typer.Argument(parser=path_given)],
    out: Annotated[
        Path, typer.Option(parser=path_given, help="Directory for the new logs (one subdirectory each).")
    ],
    by: Annotated[str, typer.Option(help="client, behaviour (weights source) or count.")] = "client",
    every: Annotated[
        int, typer.Option(help="by count: most experiences per part (whole batches: a larger one alone).")
    ] = 0,
    key_file: KeyOpt = None,
) -> None:
    """Split a log by client, by behaviour policy, or into parts."""
    try:
        parts = logs.split(source, out, by, every, _key(key_file))
    except (logs.LogFormatError, ValueError, OSError) as exc:
        raise _fail(exc) from exc
    for name, n in parts.items():
        console.print(f"{_shown(str(out / name))}: {n:,} experiences")


@app.command()
def export(
    sources: Annotated[list[Path], typer.Argument(parser=path_given, help="Logs to export (merged).")],
    out: Annotated[Path, typer.Option(parser=file_given, help="The .npz file to write (a new one).")],
    key_file: KeyOpt = None,
    replace: Annotated[bool, typer.Option(help="Write over a file already at --out.")] = False,
) -> None:
    """Write logs' experiences as plain numpy arrays in one .npz (np.load(..., allow_pickle=False))."""
    try:
        n = logs.export(sources, out, _key(key_file), replace)
    except (logs.LogFormatError, ValueError, OSError) as exc:
        raise _fail(exc) from exc
    console.print(f"{n:,} experiences exported to {_shown(str(out))}")


main = guarded(app)
"""The console entry point: bad input ends in one line and a nonzero exit (`wfnn_io.cli_errors`)."""

if __name__ == "__main__":
    main()
