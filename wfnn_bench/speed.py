"""Speed of act and think for a 16-state, 4-action, 9-wire, 32-hidden WFNN.

- act latency: one greedy `act` (the robot's hot path), p50/p99 over many calls, for the
  thesis' network and for the deep learner's default network on the same task (no torch).
- incremental thinks/s: one learner, one experience per update, one core.
- minibatch experience-updates/s: experiences processed per second in minibatch mode.
- population thinks/s: a population of learners thinking incrementally in parallel.
"""

from __future__ import annotations

import gc
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from wfnn_bench.common import Progress, check_seed, machine_info, no_progress
from wfnn_common.config import LearnerConfig, check_fields
from wfnn_common.learner import WFNN, FloatArray
from wfnn_common.learners import Learner, make_learner
from wfnn_common.replay import Experiences
from wfnn_io.persist import save_figure


@dataclass(frozen=True, kw_only=True)
class SpeedBenchConfig:
    """Options of `wfnn-bench speed`."""

    state_dim: int = 16
    action_dim: int = 4
    n_wires: int = 9
    n_hidden: int = 32
    act_calls: int = 20_000
    thinks: int = 200_000
    batch_sizes: tuple[int, ...] = (256, 1024, 4096)
    minibatch_updates: int = 40
    population: int = 64
    population_thinks: int = 2_000
    buffer: int = 20_000
    seed: int = 0

    def __post_init__(self) -> None:
        check_fields(self)
        check_seed(self.seed)
        if not 1 <= self.population <= 4096 or not self.batch_sizes:
            raise ValueError(f"population must be in [1, 4096] and batch sizes given, got {self.population}")
        for batch in self.batch_sizes:  # the network's sizes, checked now by the learner config's own rules
            _config(self, batch_size=batch)


def _config(bench: SpeedBenchConfig, **kw: Any) -> LearnerConfig:
    return LearnerConfig(
        state_low=(-1.0,) * bench.state_dim,
        state_high=(1.0,) * bench.state_dim,
        action_low=(-1.0,) * bench.action_dim,
        action_high=(1.0,) * bench.action_dim,
        n_wires=bench.n_wires,
        n_hidden=bench.n_hidden,
        replay_capacity=bench.buffer,
        seed=bench.seed,
        **kw,
    )


def _fill(learner: WFNN, n: int, rng: np.random.Generator) -> None:
    s, a = learner.config.state_dim, learner.config.action_dim
    for i in range(learner.population):
        learner.buffer.extend(
            i,
            Experiences(
                rng.uniform(-1, 1, (n, s)), rng.uniform(-1, 1, (n, a)), rng.uniform(-1, 1, (n, s)),
                -rng.random(n), rng.random(n) < 0.02,
            ),
        )  # fmt: skip


def _act_latency(learner: Learner, states: FloatArray, suffix: str) -> dict[str, float]:
    """p50, p99 and max microseconds of one greedy `act`, with the collector running and paused."""
    for st in states[:500]:
        learner.act(st, explore=False)
    out: dict[str, float] = {}
    for key, pause_gc in (("", False), ("_gc_paused", True)):
        lat = np.empty(len(states))
        gc_was = gc.isenabled()
        if pause_gc:  # a control loop may run with the collector paused (gc.freeze/disable)
            gc.disable()
        try:
            for i, st in enumerate(states):
                t0 = time.perf_counter()
                learner.act(st, explore=False)
                lat[i] = time.perf_counter() - t0
        finally:
            if gc_was:
                gc.enable()
        for name, value in (
            ("p50", np.percentile(lat, 50)),
            ("p99", np.percentile(lat, 99)),
            ("max", lat.max()),
        ):
            out[f"act_{name}_us{suffix}{key}"] = float(value * 1e6)
    return out


def run(bench: SpeedBenchConfig, progress: Progress = no_progress) -> dict[str, Any]:
    """All speed figures -> JSON-ready dict."""
    rng = np.random.default_rng(bench.seed)
    out: dict[str, Any] = {"benchmark": "speed", "config": bench.__dict__, "machine": machine_info()}

    # act latency (greedy, single learner, no torch): the thesis' network, then the deep default's.
    learner = WFNN(_config(bench))
    states = rng.uniform(-1, 1, (bench.act_calls, bench.state_dim))
    out.update(_act_latency(learner, states, ""))
    deep = make_learner(LearnerConfig.for_task(learner.config, learner="deep", seed=bench.seed))
    out.update(_act_latency(deep, states, "_deep"))
    d = deep.config.deep
    out["deep_network"] = {"hidden": list(d.hidden), "value_hidden": d.value_hidden,
                           "value_layers": d.value_layers, "n_wires": deep.config.n_wires,
                           "layer_norm": d.layer_norm}  # fmt: skip
    progress(1)

    # incremental thinks/s, one learner (one core).
    _fill(learner, bench.buffer, rng)
    learner.think(1000)  # compile / load the kernel
    t0 = time.perf_counter()
    learner.think(bench.thinks)
    out["incremental_thinks_per_s"] = bench.thinks / (time.perf_counter() - t0)
    progress(1)

    # minibatch experience-updates/s.
    per_batch = {}
    for b in bench.batch_sizes:
        mb = WFNN(_config(bench, update="minibatch", batch_size=b))
        _fill(mb, bench.buffer, rng)
        mb.think(2)
        t0 = time.perf_counter()
        mb.think(bench.minibatch_updates)
        per_batch[str(b)] = bench.minibatch_updates * b / (time.perf_counter() - t0)
        progress(1)
    out["minibatch_updates_per_s_by_batch"] = per_batch
    out["minibatch_updates_per_s"] = max(per_batch.values())

    # population: many learners thinking incrementally at once.
    pop = WFNN(_config(bench), population=bench.population)
    _fill(pop, 2000, rng)
    pop.think(10)
    t0 = time.perf_counter()
    pop.think(bench.population_thinks)
    out["population"] = bench.population
    out["population_thinks_per_s"] = bench.population * bench.population_thinks / (time.perf_counter() - t0)
    progress(1)
    return out


def steps(bench: SpeedBenchConfig) -> int:
    """Progress units of `run`."""
    return 3 + len(bench.batch_sizes)


def rows(result: dict[str, Any], cfg: SpeedBenchConfig) -> list[tuple[str, Any]]:
    """The figures of `wfnn-bench speed`'s table: (name, value) rows."""
    keys = [
        "act_p50_us", "act_p99_us", "act_p50_us_gc_paused", "act_p99_us_gc_paused",
        "act_p50_us_deep", "act_p99_us_deep", "act_p50_us_deep_gc_paused", "act_p99_us_deep_gc_paused",
        "incremental_thinks_per_s", "minibatch_updates_per_s", "population_thinks_per_s",
    ]  # fmt: skip
    rows: list[tuple[str, Any]] = [(k, result[k]) for k in keys]
    rows += [
        (f"minibatch_updates_per_s (batch {b})", v)
        for b, v in result["minibatch_updates_per_s_by_batch"].items()
    ]
    return rows


def plot(result: dict[str, Any], path: Path) -> None:
    """Act latency (p50 and p99, both networks) beside the think rates (log scale)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    networks = [("thesis", ""), ("deep default", "_deep")]
    x = np.arange(len(networks))
    for k, (quantile, paused) in enumerate([("p50", ""), ("p99", ""), ("p99", "_gc_paused")]):
        values = [result[f"act_{quantile}_us{suffix}{paused}"] for _, suffix in networks]
        label = f"{quantile}" + (" (gc paused)" if paused else "")
        a.bar(x + (k - 1) * 0.27, values, width=0.27, label=label)
    a.set_xticks(x, [name for name, _ in networks])
    a.set_ylabel("greedy act (us, one core, numpy/numba)")
    a.axhline(50.0, color="grey", ls=":", lw=0.8, label="50 us")
    a.set_title("act latency")
    a.legend(fontsize=8)
    rates = {"incremental": result["incremental_thinks_per_s"],
             **{f"minibatch {n}": v for n, v in result["minibatch_updates_per_s_by_batch"].items()},
             f"population {result['population']}": result["population_thinks_per_s"]}  # fmt: skip
    b.bar(range(len(rates)), list(rates.values()), color="tab:green")
    b.set_xticks(range(len(rates)), list(rates), rotation=20, fontsize=8)
    b.set_yscale("log")
    b.set_ylabel("experience updates per second")
    b.set_title("thinking (the thesis' network)")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)
