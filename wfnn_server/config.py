"""Typed configuration of a think server."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from wfnn_common.config import DeepConfig, LearnerOverrides, check_fields
from wfnn_io.bus import NetConfig
from wfnn_io.protocol import check_id
from wfnn_io.segments import MAX_SEGMENT_BYTES, FsyncPolicy

MIN_PERIOD_S = 1e-3
"""The shortest period of a server's loops (snapshots, statuses, checkpoints, fsyncs)."""
MAX_HOST = 253
"""The longest host name (DNS's limit); longer is no interface."""


@dataclass(frozen=True, kw_only=True)
class DashboardConfig:
    """Where the dashboard listens and what it keeps."""

    port: int
    """TCP port (0: any free port; `Dashboard.port` says which)."""
    host: str = "127.0.0.1"
    """Interface to bind; loopback unless a person asks for more. An IPv6 address may come in
    brackets, as a URL writes it ([::1]); it is kept without them."""
    update_hz: float = 4.0
    """How often the page asks for new figures (and the most the view is recomputed)."""
    history: int = 2400
    """Samples kept per series (one per server status: 20 minutes at the default 0.5 s)."""
    surface_points: int = 41
    """Grid points per action variable of the action-value surface."""

    def __post_init__(self) -> None:
        check_fields(self)
        if len(self.host) > 2 and self.host[0] == "[" and self.host[-1] == "]":  # as in a URL: [::1]
            object.__setattr__(self, "host", self.host[1:-1])
        if not 0 <= self.port <= 65535:
            raise ValueError(f"dashboard port must be in 0..65535, got {self.port}")
        if not 0.1 <= self.update_hz <= 30.0:
            raise ValueError(f"dashboard update_hz must be in [0.1, 30], got {self.update_hz}")
        if self.history < 10 or self.surface_points < 3:
            raise ValueError("dashboard history must be >= 10 and surface_points >= 3")
        if not self.host.strip() or self.host != self.host.strip():  # "" binds every interface, silently
            raise ValueError(
                f"dashboard host must name an interface (127.0.0.1 by default), got {self.host!r}"
            )
        if len(self.host) > MAX_HOST:  # logged in warnings, where 100 KB took a minute to wrap
            raise ValueError(
                f"dashboard host is {len(self.host)} characters, more than a name has ({MAX_HOST})"
            )

    @property
    def url(self) -> str:
        """The page's address (an IPv6 host in brackets, as URLs write it)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    @property
    def loopback(self) -> bool:
        """Whether only this machine can reach the dashboard."""
        import ipaddress

        if self.host == "localhost":
            return True
        try:
            return ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return False


@dataclass(frozen=True, kw_only=True)
class ServerConfig:
    """Everything a `wfnn-server` needs; the CLI only builds this and calls `run`."""

    controller: str = "default"
    """Controller name: the server serves keys under wfnn/<controller>/."""
    server_id: str = "server"
    """This server's id (1-16 of [A-Za-z0-9_.-]); unique among the controller's servers."""
    net: NetConfig = field(default_factory=lambda: NetConfig(mode="router", listen=("tcp/127.0.0.1:7447",)))
    data_dir: Path = Path("wfnn-data")
    """Experience store, checkpoint, learner config and incarnation counter."""
    learner_config: Path | None = None
    """A LearnerConfig JSON file; without one the server adopts the first client's config."""
    key_file: Path | None = None
    """Shared key: frames must carry a valid HMAC-SHA256 tag, and so will ours."""
    insecure: bool = False
    """Allow listening on or connecting to a non-loopback address without a key (anyone who
    reaches it can then feed this server experiences and configs)."""
    allow_clients: tuple[str, ...] = ()
    """Client ids whose experiences, status and pictures are taken; empty: any client."""
    seed: int | None = None
    """Overrides the learner config's seed (servers on the same data learn differently)."""
    device: str = "cpu"
    """Where a deep learner trains on this server ("cpu", "cuda", "cuda:N"): the server's own
    choice, whatever the config it adopts from a client says."""
    compile: bool = False
    """Compile a deep learner's update (`DeepConfig.compile`): about 1.4 times as fast on a CPU
    after a compile of 5 to 30 s in the first update, in which this server thinks of nothing else."""
    bc_weight: float | None = None
    """Overrides the learner config's `bc_weight` (the best wire pulled toward the actions taken:
    for passive learning from other controllers' logs, `wfnn-bench passive`)."""
    alpha: float | None = None
    """Overrides the learner config's learning rate: the thesis' learner's `alpha` (passive
    learning replays a fixed set millions of times; `wfnn-bench passive` measured 0.05 better
    than the thesis' 0.25 there), or the deep learner's Adam step size `deep.lr`."""
    publish_period_s: float = 0.25
    """Weight snapshot period (also published as soon as the think budget is spent)."""
    status_period_s: float = 0.5
    """Status heartbeat period."""
    checkpoint_period_s: float = 30.0
    """Checkpoint period (also on SIGTERM/SIGINT)."""
    think_batch: int = 50
    """Replays per think call (between checks for new experiences and publishing)."""
    think: Literal["budget", "continuous"] = "budget"
    """`budget`: thinks_per_action replays per stored experience, then idle (as
    act-learn-think); `continuous`: replay whenever there is nothing else to do."""
    think_nice: int = 10
    """Niceness of the thinking thread (Linux): thinking is any-time work and yields the CPU
    to real-time work on the same machine, as the thesis runs `think` at a lower priority."""
    fsync: FsyncPolicy = "interval"
    """When the store fsyncs, and so what an acknowledgement promises: `always` and `interval` acknowledge
    experiences once fsynced; `never` once written to the OS (they survive the server's crash, not a
    power cut)."""
    fsync_interval_s: float = 0.02
    """With fsync `interval`: acknowledgements wait at most this long for an fsync."""
    segment_bytes: int = 64 << 20
    """Where the store starts a new segment file (readers read at most this much of one, with a
    record more: `wfnn_io.segments.MAX_SEGMENT_BYTES`)."""
    replay: tuple[Path, ...] = ()
    """Experience logs (client records `DIR/journal`, other servers' `DATA_DIR/store`) imported
    into the store at start, each client's experiences once; they are owed their thinks like
    experiences that arrive from robots."""
    replay_only: bool = False
    """Serve no robot: learn from the store (with `replay`) until every stored experience has had
    its thinks, then checkpoint (`DATA_DIR/checkpoint.npz`, a weights file) and stop. Starting the
    server again on the same data directory without it continues online from there."""
    offline: bool = False
    """Join no network (a replay-only run that names no endpoint: it needs no port)."""
    dashboard: DashboardConfig | None = None
    """Serve a live, read-only web view of this server (`wfnn_server.dashboard`); None: off."""
    recovery_thinks_max: int = 2_000_000
    """After a divergence reset, snapshots are flagged diverged until the learner has replayed
    thinks_per_action per stored experience, at most this many thinks."""

    def summary(self) -> str:
        """One line: who, where it listens or connects, its data and where its learner comes from."""
        net = ", ".join(
            (*(f"listen {e}" for e in self.net.listen), *(f"connect {e}" for e in self.net.connect))
        )
        learner = (f"learner config {self.learner_config}" if self.learner_config
                   else "learner config from the data directory or the first client")  # fmt: skip
        replay = f"; replay-only {len(self.replay)} logs" if self.replay_only else ""
        keyed = ", key" if self.key_file else ""
        if self.offline:
            net = "no network"
        if self.net.zenoh_config:
            net = ", ".join((net, f"the rest as {self.net.zenoh_config} says")) if net else (
                f"endpoints as {self.net.zenoh_config} says")  # fmt: skip
        return (f"{self.server_id} (controller {self.controller}, {self.net.mode}{keyed}) "
                f"{net or 'no endpoints'}; data directory {self.data_dir}; {learner}{replay}")  # fmt: skip

    @property
    def overrides(self) -> LearnerOverrides:
        """This server's learner overrides (`seed`, `bc_weight`, `alpha`): the client's mechanism too."""
        return LearnerOverrides(seed=self.seed, bc_weight=self.bc_weight, learning_rate=self.alpha)

    def __post_init__(self) -> None:
        check_fields(self)
        DeepConfig(device=self.device)  # the same rule for a device name as a learner config's
        if self.device != "cpu":
            import torch

            index = int(self.device[5:]) if ":" in self.device else 0
            if not torch.cuda.is_available() or index >= torch.cuda.device_count():
                raise ValueError(f"device {self.device}: torch sees no such CUDA device here")
        check_id(self.controller, "controller name")
        check_id(self.server_id, "server id")
        for client in self.allow_clients:
            check_id(client, "allowed client id")
        for name in ("publish_period_s", "status_period_s", "checkpoint_period_s", "fsync_interval_s"):
            if not getattr(self, name) >= MIN_PERIOD_S:  # 1e-300 published without a pause, NaN too
                raise ValueError(f"{name} must be at least {MIN_PERIOD_S:g} s, got {getattr(self, name)}")
        if self.think_batch < 1:
            raise ValueError(f"think_batch must be >= 1, got {self.think_batch}")
        if not 1 <= self.segment_bytes <= MAX_SEGMENT_BYTES:
            raise ValueError(f"segment_bytes must be in [1, {MAX_SEGMENT_BYTES}], got {self.segment_bytes}")
        if self.fsync not in ("always", "interval", "never"):
            raise ValueError(f"fsync must be always, interval or never, got {self.fsync!r}")
        if self.think not in ("budget", "continuous"):
            raise ValueError(f"think must be budget or continuous, got {self.think!r}")
        self.overrides  # noqa: B018  # checks seed, bc_weight and alpha by the learner config's rules
        if self.offline and not self.replay_only:
            raise ValueError("offline: only a replay-only server joins no network")
        if self.replay_only and self.think != "budget":
            raise ValueError("replay_only learns the stored experiences' think budget: think must be budget")
