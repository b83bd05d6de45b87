"""`wfnn-client`: run a simulated robot that learns while it acts."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

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

from wfnn_client.local import SIMS, ClientConfig, run
from wfnn_common.config import ExplorationConfig

app = typer.Typer(help="Simulated robot learning by WFNN Q-learning (act-learn-think-MT).")
console = Console()


@app.command()
def main(
    sim: Annotated[str, typer.Option(help=f"Simulated task: {', '.join(SIMS)}.")] = "boat",
    episodes: Annotated[int, typer.Option(min=1, help="Episodes (boat: targets).")] = 40,
    rate_hz: Annotated[float, typer.Option(min=0.0, help="Control rate; 0 = as fast as possible.")] = 50.0,
    boat_dt: Annotated[float, typer.Option(min=1e-6, help="Boat time per action.")] = 0.1,
    exploration: Annotated[str, typer.Option(help="uniform, gaussian, smooth or none.")] = "uniform",
    out: Annotated[Path, typer.Option(help="Run directory for weights, experiences, metrics, plot.")] = Path(
        "runs/latest"
    ),
    seed: int = 0,
    verbose: bool = False,
) -> None:
    """Learn a simulated task with thinking in a background thread; save the results."""
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING, format="%(message)s",
        handlers=[RichHandler(console=console, show_path=False)],
    )  # fmt: skip
    if sim not in SIMS:
        raise typer.BadParameter(f"unknown sim {sim!r}; choose from {', '.join(SIMS)}", param_hint="--sim")
    if exploration not in ("uniform", "gaussian", "smooth", "none"):
        raise typer.BadParameter(f"unknown exploration {exploration!r}", param_hint="--exploration")
    config = ClientConfig(
        sim=sim, episodes=episodes, rate_hz=rate_hz, boat_dt=boat_dt, out=out, seed=seed,  # type: ignore[arg-type]
        exploration=ExplorationConfig(kind=exploration),  # type: ignore[arg-type]
    )  # fmt: skip
    console.print(f"[bold]wfnn-client[/] {config}")
    with Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
        TextColumn("score {task.fields[score]:.3f}"), TimeElapsedColumn(), TimeRemainingColumn(),
        console=console,
    ) as bar:  # fmt: skip
        task = bar.add_task(f"{sim} episodes", total=episodes, score=float("nan"))
        metrics = run(config, lambda done, score: bar.update(task, completed=done, score=score))
    console.print(
        f"first-10 median {metrics['first10_median']:.3f} -> last-10 median {metrics['last10_median']:.3f} "
        f"({metrics['metric']}); {metrics['thinks']} thinks, {metrics['snapshots']} snapshots, "
        f"act p99 {metrics['act_latency_ms_p99']:.3f} ms, overruns {metrics['overruns']}"
    )
    console.print(f"saved weights, experiences, metrics.json and learning_curve.png in {out}/")


if __name__ == "__main__":
    app()
