"""When to think, and how far thinking has reached: the one think scheduler (thesis Section 5.4).

Every experience stored is owed `thinks_per_action` replays (more over-fit, Fig 4.9). The
scheduler keeps that budget against the learner's think counter, says how many thinks to do
next, and which experiences have had all of theirs (`learned_through`, which a snapshot
carries to the robot). After a divergence reset it asks for more thinks until the stored
experiences are relearned. It is bookkeeping only: no clock, thread or learner inside; the
think server and the client's think thread both schedule with it.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass, field


@dataclass(frozen=True)
class _Owed:
    """Thinks owed up to a client's experience: done when the think counter reaches `mark`."""

    mark: int
    client: str
    seq: int


@dataclass
class ThinkSchedule:
    """Thinks owed and done, over one learner's think counter (`thinks_done` below)."""

    budget: int = 0
    """Thinks still owed to the experiences stored."""
    learned_through: dict[str, int] = field(default_factory=dict)
    """Per client: every experience numbered up to this one has had its thinks."""
    recover_until: int = 0
    """After a divergence reset: the think count up to which the learner is relearning."""
    _owed: collections.deque[_Owed] = field(default_factory=collections.deque)
    _marked: int = 0
    """The think count at which everything owed so far is done."""

    def resume(self, thinks_done: int, budget: int, done_through: dict[str, int]) -> None:
        """Start from a learner that has done `thinks_done` thinks and owes `budget`.

        The experiences up to `done_through` (per client) are done when it has paid them.
        """
        self.budget = budget
        self._marked = thinks_done + budget
        for client, seq in done_through.items():
            self._owed.append(_Owed(self._marked, client, seq))

    def owe(self, thinks: int, client: str | None = None, seq: int = -1) -> None:
        """`thinks` more are owed; a client's experiences through `seq` are done once they are paid.

        Without a client nothing is followed to `learned_through` (a learner in the robot's own
        process, whose experiences are not numbered).
        """
        self.budget += thinks
        self._marked += thinks
        if client is not None:
            self._owed.append(_Owed(self._marked, client, seq))

    def next_thinks(self, batch: int, thinks_done: int, stored: bool, continuous: bool = False) -> int:
        """How many thinks to do now (0: none).

        Owed ones first, at most `batch`; then, with experiences `stored`, a batch more when
        thinking `continuous`ly or relearning.
        """
        if batch < 1:  # the configs refuse it; a smaller batch would never think, or grow what is owed
            raise ValueError(f"a think batch must be at least 1, got {batch}")
        if self.budget > 0:
            n = min(batch, self.budget)
            self.budget -= n
            return n
        if stored and (continuous or self.recovering(thinks_done)):
            self._marked += batch  # extra thinks: what is owed later waits behind them
            return batch
        return 0

    def advance(self, thinks_done: int) -> bool:
        """Move `learned_through` past the experiences whose thinks are done; True if it moved."""
        moved = False
        while self._owed and self._owed[0].mark <= thinks_done:
            owed = self._owed.popleft()
            if self.learned_through.get(owed.client, -1) < owed.seq:
                self.learned_through[owed.client] = owed.seq
                moved = True
        return moved

    def recover(self, thinks_done: int, thinks: int) -> None:
        """Weights were reset: relearn for `thinks` more thinks (flagged as diverged meanwhile)."""
        self.recover_until = thinks_done + thinks

    def recovering(self, thinks_done: int) -> bool:
        """Whether the learner is still relearning after a reset."""
        return thinks_done < self.recover_until

    def settled(self, thinks_done: int) -> bool:
        """Nothing owed, nothing waiting to be marked learned, no relearning."""
        return self.budget <= 0 and not self._owed and not self.recovering(thinks_done)
