"""Behaviour policies other than the learner: what may drive the robot while the learner watches.

Q-learning is off-policy: the learner learns from executed actions whatever chose them
(thesis Sections 2.5, 6.6). `wfnn-client --behaviour-policy` draws, for each episode, which
controller drives: the learner (`wfnn`), the task's hand-coded controller (`handcoded`), uniform
random actions (`random`, a scripted exploration policy) or a saved WFNN acting greedily
(`weights:PATH`). Their actions still pass the safety layer, and every experience is recorded
with the controller's name as its behaviour policy (`weights_source` in the logs).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path, PurePath

import numpy as np
from numpy.typing import NDArray

from wfnn_client.brain import Acted
from wfnn_client.sims import Policy
from wfnn_common.config import LearnerConfig
from wfnn_common.learner import ActResult
from wfnn_common.learners import make_learner
from wfnn_io.persist import load_weights

FloatArray = NDArray[np.float64]

LEARNER = "wfnn"
KINDS = (LEARNER, "handcoded", "random", "weights:PATH")


@dataclass(frozen=True)
class PolicyShare:
    """One controller of the mix and its share of the episodes."""

    name: str
    """`wfnn`, `handcoded`, `random` or `weights:PATH`."""
    share: float


def parse_mix(text: str) -> tuple[PolicyShare, ...]:
    """`"wfnn=0.5,handcoded=0.3,random=0.2"` (a name without `=` has share 1) -> shares.

    Raises ValueError naming what is wrong.
    """
    mix: list[PolicyShare] = []
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        name, _, share_text = part.rpartition("=") if "=" in part else (part, "", "1")
        try:
            share = float(share_text)
        except ValueError:
            raise ValueError(f"behaviour policy {part!r}: the share must be a number") from None
        if not (name in KINDS[:3] or (name.startswith("weights:") and len(name) > len("weights:"))):
            raise ValueError(f"unknown behaviour policy {name!r}; choose from {', '.join(KINDS)}")
        if not (share > 0 and np.isfinite(share)):
            raise ValueError(f"behaviour policy {name!r}: the share must be > 0, got {share_text}")
        mix.append(PolicyShare(name, share))
    if not mix:
        raise ValueError("an empty behaviour-policy mix")
    if len({_same(m.name, os.path.realpath) for m in mix}) != len(mix):  # one file, however written
        raise ValueError(f"behaviour policy named twice in {text!r}")
    if not np.isfinite(sum(m.share for m in mix)):  # each share is divided by the total
        raise ValueError(f"behaviour-policy shares {text!r} sum beyond the largest number")
    return tuple(mix)


def _same(name: str, way: Callable[[str], str] = os.path.normpath) -> str:
    """A policy's name with its path written one way (`runs/a/w.npz` is `./runs/a/w.npz`)."""
    return f"weights:{way(name[len('weights:') :])}" if name.startswith("weights:") else name


def source_names(names: Iterable[str]) -> dict[str, str]:
    """Each behaviour policy's name as recorded with its experiences.

    A saved WFNN is `weights:` and the fewest last parts of its path that tell it from the other
    saved ones of the mix: every run saves `weights.npz`, and two runs' policies recorded as one
    name could not be told apart in the logs.
    """
    names = list(names)
    saved = {n: PurePath(_same(n)[len("weights:") :]).parts for n in names if n.startswith("weights:")}
    out = {n: n for n in names if n not in saved}
    for n, parts in saved.items():
        k = 1
        while k < len(parts) and any(o != n and q[-k:] == parts[-k:] for o, q in saved.items()):
            k += 1
        out[n] = f"weights:{PurePath(*parts[-k:])}"
    return out


class Controllers:
    """The policies of a mix, built once for a task; `choose` draws one per episode.

    `handcoded` is the task's hand-coded controller (None where the task has none: refused).
    """

    def __init__(
        self, mix: tuple[PolicyShare, ...], learner: LearnerConfig, action_low: FloatArray,
        action_high: FloatArray, handcoded: Policy | None, rng: np.random.Generator,
    ) -> None:  # fmt: skip
        self.mix = mix
        self.rng = rng
        self.recorded = source_names(m.name for m in mix)
        """Each controller's name as recorded with its experiences (`source_names`)."""
        self.policies: dict[str, Policy] = {}
        low, high = np.asarray(action_low, dtype=np.float64), np.asarray(action_high, dtype=np.float64)
        for m in mix:
            if m.name == "handcoded":
                if handcoded is None:
                    raise ValueError("this task has no hand-coded controller (behaviour policy handcoded)")
                self.policies[m.name] = handcoded
            elif m.name == "random":
                self.policies[m.name] = lambda _state: rng.uniform(low, high)
            elif m.name.startswith("weights:"):
                self.policies[m.name] = _saved(Path(m.name[len("weights:") :]), learner)
        shares = np.array([m.share for m in mix])
        self._p = shares / shares.sum()

    def choose(self) -> str:
        """The controller that drives the next episode."""
        return self.mix[int(self.rng.choice(len(self.mix), p=self._p))].name

    def act(self, name: str, state: FloatArray) -> Acted:
        """The action of controller `name` (not the learner) for `state` [S]."""
        action = np.asarray(self.policies[name](state), dtype=np.float64)
        result = ActResult(action, np.float64(np.nan), np.bool_(True), np.bool_(False), np.bool_(False))
        return Acted(result, self.recorded[name], 0)


def _saved(path: Path, learner: LearnerConfig) -> Policy:
    """A saved WFNN acting greedily (numpy, like the learner's own act)."""
    try:
        cfg, params, _ = load_weights(path)
    except (OSError, ValueError, KeyError) as exc:
        raise ValueError(f"behaviour policy weights:{path}: cannot load ({exc})") from exc
    # Made from its own config, it needs only the task's ranges: a deep controller may drive for
    # a thesis learner, or another network for this one.
    ranges = ("state_low", "state_high", "action_low", "action_high")
    if any(getattr(cfg, name) != getattr(learner, name) for name in ranges):
        raise ValueError(
            f"behaviour policy weights:{path} is for another task's ranges (learner spec {cfg.spec_hash()}, "
            f"not {learner.spec_hash()}: {cfg.spec_difference(learner)})"
        )
    try:
        saved = make_learner(cfg, params=params)
    except ValueError as exc:  # weights that make no learner of their config (several networks, say)
        raise ValueError(f"behaviour policy weights:{path}: {exc}") from exc
    # On a copy of its weights: acting on its own, the learner's divergence monitor could reset
    # them to random ones, and the episodes would still be recorded as this file's.
    frozen = saved.snapshot()
    return lambda state: saved.act(state, explore=False, params=frozen).action
