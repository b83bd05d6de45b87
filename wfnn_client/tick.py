"""The control tick: an absolute schedule against a monotonic clock, with its timing figures.

Tick k is due at start + k * period (never `sleep(period)`, which drifts). A tick that starts
more than one period late has overrun: the schedule skips the missed ticks (keeping its phase)
and counts them, rather than firing a burst of late ticks.
"""

from __future__ import annotations

import random
import time
from collections import deque

import numpy as np

RECENT_KEPT = 10_000
"""Ticks whose timing is kept in order for `summary(last=...)`."""
SAMPLE_KEPT = 1 << 16
"""Ticks a whole run's percentiles are computed from, drawn uniformly at random once a run has
more (a reservoir sample: exact below it, within a small fraction of a percentile above)."""


class _Series:
    """One timing figure per tick, in bounded memory unless every value is to be kept."""

    def __init__(self, keep_all: bool, seed: int) -> None:
        self.all: list[float] | None = [] if keep_all else None
        self.recent: deque[float] = deque(maxlen=RECENT_KEPT)
        self.sample: list[float] = []
        self.count = 0
        self.max = float("nan")
        self._rng = random.Random(seed)

    def add(self, value: float) -> None:
        self.count += 1
        if self.count == 1 or value > self.max:
            self.max = value
        self.recent.append(value)
        if self.all is not None:
            self.all.append(value)
        if len(self.sample) < SAMPLE_KEPT:
            self.sample.append(value)
        else:
            k = self._rng.randrange(self.count)
            if k < SAMPLE_KEPT:
                self.sample[k] = value

    def values(self, last: int | None) -> list[float]:
        """The last `last` values (at most RECENT_KEPT), or the whole run's (or its sample)."""
        if last:
            return list(self.recent)[-last:]
        return self.all if self.all is not None else self.sample


class TickStats:
    """Timing of the control loop (seconds), in bounded memory: a robot runs for days.

    With `keep_all` (a timing trace), every tick's figures are kept as well (`latency_s`,
    `lateness_s`, `due_unix`).
    """

    def __init__(self, keep_all: bool = False) -> None:
        self._latency = _Series(keep_all, 1)
        """Sense-to-act time per tick."""
        self._lateness = _Series(keep_all, 2)
        """How late each tick started against its absolute deadline (the jitter)."""
        self.due_unix: list[float] = []
        """With keep_all: when each tick was due, in Unix time (to line ticks up with events outside
        the process)."""
        self.keep_all = keep_all
        self.overruns = 0
        """Ticks missed because a tick started more than one period late."""

    @property
    def count(self) -> int:
        """Ticks whose latency was recorded."""
        return self._latency.count

    @property
    def ticks(self) -> int:
        """Ticks whose lateness was recorded."""
        return self._lateness.count

    @property
    def latency_s(self) -> list[float]:
        """Every tick's latency (keep_all), else the recent ones."""
        return self._latency.all if self._latency.all is not None else list(self._latency.recent)

    @property
    def lateness_s(self) -> list[float]:
        """Every tick's lateness (keep_all), else the recent ones."""
        return self._lateness.all if self._lateness.all is not None else list(self._lateness.recent)

    def add_latency(self, seconds: float) -> None:
        """One tick's sense-to-act time."""
        self._latency.add(seconds)

    def add_lateness(self, seconds: float, due_unix: float) -> None:
        """How late one tick started, and when it was due (Unix time)."""
        self._lateness.add(seconds)
        if self.keep_all:
            self.due_unix.append(due_unix)

    def summary(self, prefix: str = "", last: int | None = None) -> dict[str, float]:
        """Percentiles in milliseconds over every tick, or the `last` ticks (NaN when none)."""
        latency = self._latency.values(last)
        lateness = self._lateness.values(last)

        def pct(values: list[float], q: float) -> float:
            return float(np.percentile(np.asarray(values) * 1e3, q)) if values else float("nan")

        most = self._lateness.max * 1e3 if not last else pct(lateness, 100)
        return {
            f"{prefix}act_latency_ms_p50": pct(latency, 50),
            f"{prefix}act_latency_ms_p99": pct(latency, 99),
            f"{prefix}tick_jitter_ms_p50": pct(lateness, 50),
            f"{prefix}tick_jitter_ms_p99": pct(lateness, 99),
            f"{prefix}tick_jitter_ms_max": most,
            f"{prefix}overruns": float(self.overruns),
        }


class Ticker:
    """Waits for each tick's absolute deadline; period 0 means as fast as possible (no waiting)."""

    def __init__(self, period_s: float, stats: TickStats | None = None) -> None:
        if period_s < 0:
            raise ValueError(f"period must be >= 0, got {period_s}")
        self.period_s = period_s
        self.stats = stats if stats is not None else TickStats()
        self._start: float | None = None
        self._start_unix = 0.0
        self._k = 0
        self.deadline = 0.0
        """Scheduled start of the current tick (perf_counter seconds)."""

    def next_due(self) -> float:
        """When the next tick is due (perf_counter seconds): now, where none is scheduled yet."""
        now = time.perf_counter()
        if self._start is None or self.period_s == 0.0:
            return now
        return max(now, self._start + self._k * self.period_s)

    def wait(self) -> float:
        """Sleep until the next tick is due; returns how late it starts (s)."""
        now = time.perf_counter()
        if self._start is None:
            self._start, self._start_unix = now, time.time()
        if self.period_s == 0.0:
            self.deadline = now
            return 0.0
        deadline = self._start + self._k * self.period_s
        if now < deadline:
            time.sleep(deadline - now)
            now = time.perf_counter()
        elif now - deadline > self.period_s:
            missed = int((now - deadline) // self.period_s)
            self.stats.overruns += missed
            self._k += missed
            deadline = self._start + self._k * self.period_s
        self._k += 1
        self.deadline = deadline
        late = now - deadline
        self.stats.add_lateness(late, self._start_unix + (deadline - self._start))
        return late

    def late_now(self) -> float:
        """Seconds since the current tick's deadline."""
        return time.perf_counter() - self.deadline
