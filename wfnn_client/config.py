"""The options of `wfnn-client`: `ClientConfig` (the CLI only builds it and calls `run.run`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sims.boat import BoatConfig
from sims.hydra import HydraConfig
from sims.hydra.task import AXES, JOINTS
from sims.nomad import ForageConfig, NomadConfig
from wfnn_client.controllers import PolicyShare
from wfnn_client.safety import SafetyConfig
from wfnn_client.sims import SIMS, SimOptions
from wfnn_common.config import LEARNERS, MAX_SEED, ExplorationConfig, LearnerOverrides, check_fields
from wfnn_io.bus import NetConfig

MAX_RATE_HZ = 1000.0
"""Fastest control tick a client keeps (a robot's is tens of hertz; a tick above this is a mistake)."""
MIN_RATE_HZ = 1e-3
"""The slowest real-time tick (one every 1,000 s): below it a tick's wait overflows the clock."""


@dataclass(frozen=True, kw_only=True)
class ClientConfig:
    """Options of `wfnn-client`; the CLI only builds this and calls `run`."""

    sim: str = "boat"
    episodes: int = 40
    """Episodes (boat: targets) to run."""
    duration_s: float | None = None
    """Stop after this much wall time (whichever comes first)."""
    rate_hz: float | None = None
    """Control rate; 0 runs as fast as possible; None: the sim's own (0 in lock-step)."""
    lockstep: bool = False
    """As fast as possible, each action waiting for the previous experiences' thinks (the
    single-process act-learn-think order, for reproducible benchmarks); needs rate_hz 0."""
    lockstep_timeout_s: float = 30.0
    boat_dt: float = 0.1
    """Boat time per action (see sims.boat)."""
    env: str | None = None
    """`sim` gym: the Gymnasium task id (1-D Box observations and actions), e.g. Pendulum-v1."""
    hydra: HydraConfig = field(default_factory=HydraConfig)
    """HyDrA's joints, image axes and target regime (`sim` hydra)."""
    nomad: NomadConfig = field(default_factory=NomadConfig)
    """The Nomad's behaviour and camera (`sim` nomad)."""
    forage: ForageConfig | None = None
    """nomad: forage instead (learned wandering and learned servoing, Fig 6.3; `nomad.behaviour`
    must be wander): one learner per behaviour; weights and journals per behaviour, and in C/S
    mode the controllers `<controller>-servo` and `<controller>-wander`."""
    thinks_per_action: int | None = None
    """Override the learner's thinks per action (local thinking and the announced config)."""
    advantage_k: float | None = None
    """Override the advantage-learning constant (1: plain Q-learning); None: the sim's default."""
    bc_weight: float | None = None
    """Override the learner's `bc_weight` (the best wire pulled toward the actions taken, for
    learning from other controllers); None: the thesis' 0."""
    explicit: tuple[str, ...] = ()
    """Which of `seed`, `symmetries` and `exploration` were given (on the command line, its flags):
    a run resumed from `weights` sets only these over the learner config saved with them."""
    symmetries: bool = False
    """Learn each experience also as its images under the task's declared symmetries (the
    boat's mirror; `wfnn_common.symmetry`); they travel in the learner config to the servers."""
    behaviour_policy: tuple[PolicyShare, ...] = ()
    """Which controller drives each episode, drawn by share (`wfnn_client.controllers`): the
    learner, the task's hand-coded controller, random actions or a saved WFNN; the learner
    learns off-policy from whatever drove. Empty: the learner always."""
    think_batch: int = 50
    """Thinks per call of the think thread (not lock-step), at least 1."""
    exploration: ExplorationConfig | None = None
    """How `act` explores; None: the learner's default."""
    learner: str = "thesis"
    """Which learner: "thesis" (the thesis' WFNN) or "deep" (deep wire fitting)."""
    learner_options: str = ""
    """Learner config fields over the learner's defaults, as a JSON object (the deep learner's
    own fields under "deep"), e.g. '{"gamma": 0.95, "deep": {"hidden": [64, 64]}}'."""
    learn: bool = True
    """False: act greedily only (no exploration), send and learn nothing."""
    weights: Path | None = None
    """Start from these saved weights (local: the learner, resuming the training state saved beside
    them where there is one: the deep learner's second critic, targets, optimiser and warm-up; the
    replay memory starts empty. C/S: until a server's snapshot)."""
    server: tuple[str, ...] = ("local",)
    """`local` thinks in-process; otherwise Zenoh endpoints of think servers (or routers). Empty,
    with `net.listen` set: the servers connect to this client."""
    controller: str = "default"
    client_id: str | None = None
    follow: str | None = None
    """Pin a server id (C/S)."""
    net: NetConfig = field(default_factory=NetConfig)
    """Zenoh settings (C/S); `connect` is filled from `server`."""
    key_file: Path | None = None
    insecure: bool = False
    """Allow a non-loopback endpoint without a key (anyone reaching it could drive the robot)."""
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    out: Path = Path("runs/latest")
    json_stats: Path | None = None
    """Also write the final figures here."""
    camera_every: int = 0
    """Save what the cameras see every this many ticks to `out/cameras/` (0: never; sims with
    cameras only)."""
    timing_trace: bool = False
    """Put every tick's lateness and every snapshot's latency in the metrics (benchmarks)."""
    seed: int = 0

    def __post_init__(self) -> None:
        check_fields(self)
        if not set(self.explicit) <= {"seed", "symmetries", "exploration"}:
            raise ValueError(f"explicit names only seed, symmetries and exploration, got {self.explicit}")
        if self.sim not in SIMS:
            raise ValueError(f"unknown sim {self.sim!r}; choose from {', '.join(SIMS)}")
        if (self.sim == "gym") != (self.env is not None):
            raise ValueError("a Gymnasium task needs sim gym and an env id (wfnn-client --env ID)")
        if self.lockstep and self.tick_hz != 0:
            raise ValueError("lock-step runs as fast as possible: set rate_hz to 0")
        simulated = self.simulated_hz
        if simulated is not None and self.tick_hz > 0 and self.tick_hz != simulated:
            # A robot's tick is real time: a simulated robot ticking faster than it is simulated
            # would run in fast motion (as dm_control ties a control step to whole physics steps).
            raise ValueError(
                f"rate_hz {self.tick_hz:g} but {self.sim} is simulated at {simulated:g} actions per "
                f"simulated second ({self.tick_hz / simulated:g} x real time): set {self.sim}.rate_hz "
                "to the tick rate (wfnn-client --rate-hz sets both)"
            )
        if self.episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {self.episodes}")
        if not 0 <= self.seed <= MAX_SEED:
            raise ValueError(f"seed must be in [0, {MAX_SEED}], got {self.seed}")
        if self.rate_hz is not None and not (self.rate_hz == 0 or MIN_RATE_HZ <= self.rate_hz <= MAX_RATE_HZ):
            raise ValueError(
                f"rate_hz must be 0 (as fast as possible) or in [{MIN_RATE_HZ:g}, {MAX_RATE_HZ:g}], "
                f"got {self.rate_hz}"
            )
        if self.duration_s is not None and not self.duration_s > 0:
            raise ValueError(f"duration_s must be > 0 where given, got {self.duration_s}")
        if self.think_batch < 1:  # 0 never thought, and a negative batch grew what was owed
            raise ValueError(f"think_batch must be >= 1, got {self.think_batch}")
        BoatConfig(dt=self.boat_dt)  # checked now, not when the boat is first made
        if self.sim == "hydra" and not (self.hydra.joints and self.hydra.axes):
            # The task itself has every subset (its sizes are checked for all 256); a run with no
            # joint has nothing to learn, and with no image axis no error: a perfect score of 0.
            raise ValueError(f"a HyDrA run needs a joint and an image axis, got {self.hydra.joints}, "
                             f"{self.hydra.axes}")  # fmt: skip
        if not self.server and not self.net.listen:
            raise ValueError("server needs `local`, an endpoint, or a listen endpoint servers connect to")
        if "local" in self.server and len(self.server) > 1:
            raise ValueError("server is either `local` or endpoints, not both")
        if self.net.mode == "client" and len(self.server) > 1:
            # A client-mode session has one link (the first endpoint that answers): the other
            # servers would hear nothing, and the run would say nothing of it.
            raise ValueError(
                "in client mode a session links to one endpoint only: give one router (the servers "
                "connect to it), or use peer mode to reach several servers"
            )
        if self.camera_every < 0:
            raise ValueError(f"camera_every must be >= 0, got {self.camera_every}")
        if self.camera_every and SIMS[self.sim].views is None:
            raise ValueError(f"camera_every: sim {self.sim!r} has no cameras")
        if self.forage is not None and (self.sim != "nomad" or self.nomad.behaviour != "wander"):
            raise ValueError("forage: the nomad sim, configured to wander, only")
        if self.behaviour_policy and self.forage is not None:
            raise ValueError("behaviour_policy: one learned behaviour only (not forage)")
        if self.learner not in LEARNERS:
            raise ValueError(f"unknown learner {self.learner!r}; choose from {', '.join(LEARNERS)}")
        self.overrides  # noqa: B018  # checks the overrides by the learner config's rules

    @property
    def simulated_hz(self) -> float | None:
        """Actions per simulated second of a simulated robot (HyDrA, the Nomad); None for the others."""
        return {"hydra": self.hydra.rate_hz, "nomad": self.nomad.rate_hz}.get(self.sim)

    @property
    def tick_hz(self) -> float:
        """The control rate the client runs at (0: as fast as possible)."""
        if self.rate_hz is not None:
            return self.rate_hz
        return 0.0 if self.lockstep else (self.simulated_hz or SIMS[self.sim].rate_hz)

    @property
    def local(self) -> bool:
        """Whether thinking happens in this process."""
        return self.server == ("local",)

    @property
    def remote_net(self) -> NetConfig:
        """The Zenoh settings of a C/S run: `net`, connecting also to the `server` endpoints."""
        return dataclasses.replace(self.net, connect=tuple(self.net.connect) + tuple(self.server))

    @property
    def overrides(self) -> LearnerOverrides:
        """The learner fields this client sets (`--thinks`, `--advantage-k`, `--bc-weight`, options)."""
        return LearnerOverrides(thinks_per_action=self.thinks_per_action, advantage_k=self.advantage_k,
                                bc_weight=self.bc_weight, options=self.learner_options)  # fmt: skip

    @property
    def sim_options(self) -> SimOptions:
        """What building the simulated task needs of these options."""
        return SimOptions(boat_dt=self.boat_dt, env=self.env, hydra=self.hydra, nomad=self.nomad,
                          forage=self.forage, seed=self.seed, weights=self.weights)  # fmt: skip

    def _task_summary(self) -> str:
        """The task in a few words (the run's line)."""
        return {
            "hydra": f"hydra ({','.join(self.hydra.joints)}; {','.join(self.hydra.axes)}; "
                     f"{self.hydra.regime})",
            "nomad": f"nomad ({'forage' if self.forage else self.nomad.behaviour})",
            "gym": f"gym {self.env}", "boat": f"boat (dt {self.boat_dt:g})",
        }.get(self.sim, self.sim)  # fmt: skip

    @property
    def task(self) -> dict[str, Any]:
        """The task: {"sim": name, "options": every option that differs from its default}.

        A journal records it (`Journal`). Nested options are named with dots ("vision.source");
        HyDrA's joints and axes in the model's order, as its states are, whatever order given in.
        """
        options: dict[str, Any] = {}
        if self.sim == "boat":
            options = _differing({"boat_dt": self.boat_dt}, {"boat_dt": ClientConfig.boat_dt})
        elif self.sim == "gym":
            options = {"env": self.env}
        elif self.sim == "hydra":
            h = self.hydra
            canonical = dataclasses.replace(h, joints=tuple(JOINTS[i] for i in h.joint_index),
                                            axes=tuple(AXES[i] for i in h.axis_index))  # fmt: skip
            options = _dataclass_differing(canonical, HydraConfig())
        elif self.sim == "nomad":
            options = _dataclass_differing(self.nomad, NomadConfig())
            if self.forage is not None:
                options["forage"] = True
                options.update(_dataclass_differing(self.forage, ForageConfig(), "forage."))
        return {"sim": self.sim, "options": options}

    def summary(self) -> str:
        """One line: the task, where it thinks, the learner's overrides and the run directory."""
        task = self._task_summary()
        where = "thinking locally" if self.local else f"servers {', '.join(self.server) or '(they connect)'}"
        rate = (
            "lock-step"
            if self.lockstep
            else (f"{self.tick_hz:g} Hz" if self.tick_hz else "as fast as possible")
        )
        saved = f"as saved with {self.weights}" if self.weights is not None else None
        learner = ", ".join(f"{name} {value}" if name else str(value) for name, value in (
            ("", saved),
            ("k", self.advantage_k), ("thinks", self.thinks_per_action), ("bc_weight", self.bc_weight),
            ("options", _shortened(self.learner_options) or None),
        ) if value is not None) or "defaults"  # fmt: skip
        keyed = ", key" if self.key_file else ""
        kind = "" if self.learner == "thesis" else f"{self.learner} "  # the thesis' learner: as before
        return f"{task}, {rate}, {where}{keyed}; {kind}learner {learner}; run directory {self.out}"


def _plain(value: Any) -> Any:
    """A task option's value as JSON keeps it (tuples as lists, numbers as floats, -0.0 as 0.0)."""
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    if isinstance(value, int | float) and not isinstance(value, bool):
        return float(value) + 0.0
    return value


def _differing(values: dict[str, Any], defaults: dict[str, Any]) -> dict[str, Any]:
    """The entries of `values` that differ from `defaults`, as plain values."""
    return {k: _plain(v) for k, v in values.items() if _plain(v) != _plain(defaults.get(k))}


def _dataclass_differing(obj: Any, default: Any, prefix: str = "") -> dict[str, Any]:
    """The fields of dataclass `obj` that differ from `default`'s, nested ones named with dots."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(obj):
        mine, theirs = getattr(obj, f.name), getattr(default, f.name)
        if dataclasses.is_dataclass(mine) and dataclasses.is_dataclass(theirs):
            out.update(_dataclass_differing(mine, theirs, f"{prefix}{f.name}."))
        else:
            out.update(_differing({f"{prefix}{f.name}": mine}, {f"{prefix}{f.name}": theirs}))
    return out


def _shortened(text: str, most: int = 200) -> str:
    """`text` cut to `most` characters for the run's one line (options of any length are refused later)."""
    return text if len(text) <= most else text[: most - 3] + "..."
