"""What a think server publishes for read-only views (the dashboard), and nothing else.

The server owns one `ViewModel` and replaces its fields whole (each from one thread), never
changing a published dict or array in place, so a reader in another thread never sees half an
update and never needs the server object itself.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from wfnn_common.config import LearnerConfig
from wfnn_common.learners import Weights
from wfnn_io.protocol import CameraView, ClientStatus, ServerStatus

CLIENT_SERIES = {
    "reward": "client/reward_mean",
    "q": "client/q_mean",
    "jitter_p99_ms": "client/tick_jitter_ms_p99",
    "overruns": "client/overruns",
}
"""The client figures views show: name on the page -> ClientStatus metric."""


def kept(status: ClientStatus) -> ClientStatus:
    """What views keep of a client's status: its figures they show, not its config or other metrics.

    A server keeps one per heard client (thousands, under forged ids without a key): whole, each
    could hold a megabyte of metrics and a config.
    """
    metrics = {k: status.metrics[k] for k in CLIENT_SERIES.values() if k in status.metrics}
    return dataclasses.replace(status, learner_config="", acked={}, metrics=metrics)


@dataclass
class ViewModel:
    """A think server's state as its views may read it."""

    server: str
    """The server's id."""
    incarnation: int
    controller: str
    learner_config: LearnerConfig | None = None
    """The config the server learns with (None until a client's config is adopted)."""
    weights_version: int = 0
    """The newest snapshot's version."""
    published: Weights | None = None
    """A copy of the weights of the newest snapshot (learner thread)."""
    last_status: ServerStatus | None = None
    """The newest status the server published (learner thread)."""
    clients: dict[str, ClientStatus] = field(default_factory=dict)
    """Per client: what views keep (`kept`) of its latest status heartbeat (ingest thread)."""
    camera_views: dict[str, CameraView] = field(default_factory=dict)
    """Per client: what its cameras saw last, when it sends pictures (ingest thread); newest last,
    for the 16 most recent heard clients."""
    latest_state: dict[str, NDArray[np.float64]] = field(default_factory=dict)
    """Per client: the newest learnable state it sent, physical units [S] (learner thread); the
    client heard from last comes last."""
    status_listeners: list[Callable[[ServerStatus], None]] = field(default_factory=list)
    """Called with every status published (learner thread): must be quick."""
