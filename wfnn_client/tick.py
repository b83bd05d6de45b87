"""The control tick: an absolute schedule against a monotonic clock, with its timing figures.

Tick k is due at start + k * period (never `sleep(period)`, which drifts). A tick that starts
more than one period late has overrun: the schedule skips the missed ticks (keeping its phase)
and counts them, rather than firing a burst of late ticks.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np


@dataclass
class TickStats:
    """Timing of the control loop (seconds)."""

    latency_s: list[float] = field(default_factory=list)
    """Sense-to-act time per tick."""
    lateness_s: list[float] = field(default_factory=list)
    """How late each tick started against its absolute deadline (the jitter)."""
    due_unix: list[float] = field(default_factory=list)
    """When each tick was due, in Unix time (to line ticks up with events outside the process)."""
    overruns: int = 0
    """Ticks missed because a tick started more than one period late."""

    def summary(self, prefix: str = "", last: int | None = None) -> dict[str, float]:
        """Percentiles in milliseconds over every tick, or the `last` ticks (NaN when none)."""
        latency = self.latency_s[-last:] if last else self.latency_s
        lateness = self.lateness_s[-last:] if last else self.lateness_s

        def pct(values: list[float], q: float) -> float:
            return float(np.percentile(np.asarray(values) * 1e3, q)) if values else float("nan")

        return {
            f"{prefix}act_latency_ms_p50": pct(latency, 50),
            f"{prefix}act_latency_ms_p99": pct(latency, 99),
            f"{prefix}tick_jitter_ms_p50": pct(lateness, 50),
            f"{prefix}tick_jitter_ms_p99": pct(lateness, 99),
            f"{prefix}tick_jitter_ms_max": pct(lateness, 100),
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
        self.stats.lateness_s.append(late)
        self.stats.due_unix.append(self._start_unix + (deadline - self._start))
        return late

    def late_now(self) -> float:
        """Seconds since the current tick's deadline."""
        return time.perf_counter() - self.deadline
