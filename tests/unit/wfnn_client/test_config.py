import dataclasses
import re
import threading
import time

import gymnasium
import numpy as np
import pytest

from sims.hydra import HydraConfig
from wfnn_client.config import ClientConfig
from wfnn_io.bus import NetConfig


def test_local_and_remote_configs():
    assert ClientConfig().local
    assert not ClientConfig(server=("tcp/127.0.0.1:7447",)).local
    listening = ClientConfig(server=(), net=NetConfig(mode="router", listen=("tcp/127.0.0.1:7447",)))
    assert not listening.local  # servers connect to this client


@pytest.mark.parametrize(
    "kw, message",
    [
        ({"server": ()}, "listen"),
        ({"server": ("local", "tcp/127.0.0.1:7447")}, "not both"),
        ({"lockstep": True, "rate_hz": 15.0}, "lock-step"),
        ({"sim": "submarine"}, "unknown sim"),
        ({"episodes": 0}, "episodes"),
        ({"sim": "boat", "camera_every": 10}, "no cameras"),
        ({"sim": "hydra", "camera_every": -1}, "camera_every"),
        ({"rate_hz": 1e18}, "rate_hz"),
        ({"rate_hz": 1e-300}, "rate_hz"),  # a tick's wait would overflow the clock
        ({"duration_s": 0.0}, "duration_s"),
        ({"think_batch": 0}, "think_batch"),  # never thought
        ({"think_batch": -5}, "think_batch"),  # grew what was owed
        ({"boat_dt": 1e18}, "dt must be"),
        ({"boat_dt": 0.0}, "dt must be"),
    ],
)
def test_bad_client_configs_are_refused(kw, message):
    with pytest.raises(ValueError, match=message):
        ClientConfig(**kw)


def test_net_config_is_checked():
    with pytest.raises(ValueError, match="mode"):
        NetConfig(mode="star")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="lease"):
        NetConfig(lease_ms=10)


def test_the_learner_config_takes_the_sims_default_and_the_clients_override():
    from sims.boat import BoatVec
    from sims.hydra import HydraVec
    from wfnn_client.run import learner_config

    hydra = HydraVec(1)
    assert learner_config(hydra, ClientConfig(sim="hydra")).advantage_k == 1.0  # measured: see README
    assert learner_config(hydra, ClientConfig(sim="hydra", advantage_k=0.2)).advantage_k == 0.2
    assert learner_config(BoatVec(1), ClientConfig(sim="boat")).advantage_k == 0.2  # the thesis' default
    assert learner_config(BoatVec(1), ClientConfig(sim="boat")).bc_weight == 0.0  # the thesis' learner
    assert learner_config(BoatVec(1), ClientConfig(sim="boat", bc_weight=0.5)).bc_weight == 0.5


@pytest.mark.parametrize("sim", ["hydra", "nomad"])
def test_a_simulated_robot_ticks_at_the_rate_it_is_simulated_at(sim):
    from sims.hydra import HydraConfig
    from sims.nomad import NomadConfig

    own = {"hydra": HydraConfig().rate_hz, "nomad": NomadConfig().rate_hz}[sim]
    assert ClientConfig(sim=sim, rate_hz=own).rate_hz == own and ClientConfig(sim=sim, rate_hz=0).rate_hz == 0
    with pytest.raises(ValueError, match=r"x real time"):
        ClientConfig(sim=sim, rate_hz=2 * own)
    faster = {"hydra": HydraConfig(rate_hz=2 * own), "nomad": NomadConfig(rate_hz=2 * own)}[sim]
    assert ClientConfig(sim=sim, rate_hz=2 * own, **{sim: faster}).tick_hz == 2 * own
    assert ClientConfig(sim=sim, **{sim: faster}).tick_hz == 2 * own  # None: the rate it is simulated at
    assert ClientConfig(sim="boat").tick_hz == 50 and ClientConfig(sim="boat", lockstep=True).tick_hz == 0


def test_the_command_line_simulates_a_robot_at_its_tick_rate(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from wfnn_client import cli

    seen = []

    def built(config):  # stop once the config is made: nothing is run
        seen.append(config)
        raise SystemExit(0)

    monkeypatch.setattr(cli, "prepare", built)
    result = CliRunner().invoke(cli.app, ["--sim", "hydra", "--rate-hz", "30", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert seen[0].rate_hz == seen[0].hydra.rate_hz == 30
    CliRunner().invoke(cli.app, ["--sim", "nomad", "--rate-hz", "0", "--out", str(tmp_path)])
    assert seen[1].nomad.rate_hz == 10  # as fast as possible: simulated at its own rate
    result = CliRunner().invoke(cli.app, ["--env", "Pendulum-v1", "--rate-hz", "900", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert seen[2].rate_hz == 900 and seen[2].hydra.rate_hz == HydraConfig().rate_hz
    # A Gymnasium task's rate is checked as the client's, not by a robot's limits (HyDrA's substeps).
    args = ["--env", "Pendulum-v1", "--rate-hz", "5000", "--out", str(tmp_path)]
    result = CliRunner().invoke(cli.app, args)
    assert result.exit_code != 0 and "rate_hz must be 0 (as fast as possible)" in str(result.exception)


def test_sim_configs_refuse_what_no_run_could_use():
    from sims.hydra import HydraConfig
    from sims.nomad import NomadConfig
    from wfnn_bench.transport import TransportBenchConfig

    refused = (
        (lambda: ClientConfig(sim="hydra", hydra=HydraConfig(axes=())), "image axis"),
        (lambda: ClientConfig(sim="hydra", hydra=HydraConfig(joints=())), "image axis"),
        (lambda: HydraConfig(rate_hz=1e18), "rate_hz"),
        (lambda: NomadConfig(balls=10**6), "balls"),
        (lambda: NomadConfig(rate_hz=1e18), "rate_hz"),
        (lambda: TransportBenchConfig(rate_hz=1e18), "rate_hz"),
    )
    for make, message in refused:
        with pytest.raises(ValueError, match=message):
            make()


def test_a_refused_client_start_leaves_the_last_runs_record_and_an_unwritable_json_stats_is_refused_first(
    tmp_path,
):
    from wfnn_client.run import prepare

    prepare(ClientConfig(out=tmp_path / "run"))
    assert not (tmp_path / "run" / "config.json").exists()  # written by `run`, once the start holds
    (tmp_path / "run" / "config.json").write_text('{"client": {"seed": 0}}')  # the last run's
    before = (tmp_path / "run" / "config.json").read_bytes()
    (tmp_path / "empty.key").write_bytes(b"")
    with pytest.raises(ValueError):
        prepare(ClientConfig(out=tmp_path / "run", seed=7, key_file=tmp_path / "empty.key"))
    assert (tmp_path / "run" / "config.json").read_bytes() == before
    with pytest.raises(IsADirectoryError):
        prepare(ClientConfig(out=tmp_path / "run", json_stats=tmp_path))
    from wfnn_io.segments import LogError, SegmentLog

    with SegmentLog(tmp_path / "run" / "journal"), pytest.raises(LogError, match="in use"):  # a run on it
        prepare(ClientConfig(out=tmp_path / "run", seed=8))
    assert (tmp_path / "run" / "config.json").read_bytes() == before


@pytest.mark.parametrize("learner", ["thesis", "deep"])
def test_a_gymnasium_task_gets_the_same_learner_config_through_the_client_as_alone(learner):
    """`wfnn-client --env` keeps what the task declares beyond its ranges: the margin its measured
    ranges need and its unknown largest reward (the thesis' learner's divergence threshold)."""
    from sims.gym import GymVec
    from wfnn_client.run import learner_config
    from wfnn_client.sims import OneBehaviour
    from wfnn_common.config import LearnerConfig

    task = GymVec("InvertedPendulum-v5", seed=0)  # unbounded observations: ranges measured
    try:
        client = ClientConfig(sim="gym", env="InvertedPendulum-v5", learner=learner)
        got = learner_config(OneBehaviour(task, None).ranges(""), client)
        alone = LearnerConfig.for_task(task, learner=learner, seed=ClientConfig().seed)
    finally:
        task.close()
    assert got.valid_margin == task.valid_margin > 1.0
    if learner == "thesis":
        assert got.divergence_threshold == alone.divergence_threshold > LearnerConfig.divergence_threshold
    assert got == alone


@pytest.mark.parametrize("seed", [-3, 1 << 62])
def test_a_seed_out_of_range_is_refused_before_the_run(seed):
    with pytest.raises(ValueError, match="seed must be in"):
        ClientConfig(seed=seed)


@pytest.mark.parametrize("kind", ["fifo", "directory", "missing"])
def test_a_zenoh_config_that_is_not_a_regular_file_is_refused_without_waiting(tmp_path, kind):
    """A FIFO given as --zenoh-config held both tools for good (opened for reading, no writer)."""
    import os

    from wfnn_io.bus import NetError, zenoh_config

    path = tmp_path / "zenoh.json5"
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "directory":
        path.mkdir()
    with pytest.raises(NetError, match="Zenoh config"):
        zenoh_config(NetConfig(zenoh_config=str(path)))


@pytest.mark.parametrize(
    ("text", "reason"),
    [("{a:" * 50000 + "1" + "}" * 50000, "nested 50000 deep"), ("[" * 100 + "]" * 100, "nested 100 deep"),
     ('{x:"' + "a" * (2 << 20) + '"}', "larger than")],
)  # fmt: skip
def test_a_zenoh_config_too_deep_or_too_large_is_refused_before_zenoh_reads_it(tmp_path, text, reason):
    """50,000 levels crashed Zenoh's parser (the process died without a word), and 50 MB took 4 GB."""
    from wfnn_io.bus import NetError, nesting, zenoh_config

    (tmp_path / "zenoh.json5").write_text(text)
    with pytest.raises(NetError, match=reason):
        zenoh_config(NetConfig(zenoh_config=str(tmp_path / "zenoh.json5")))
    (tmp_path / "include.json5").write_text('{plugins: {rest: {__config__: "deep.json5"}}}')
    with pytest.raises(NetError, match="includes"):  # an included file would go unchecked
        zenoh_config(NetConfig(zenoh_config=str(tmp_path / "include.json5")))
    assert nesting('{a: ["}", {b: 1}], // [[[\n c: /* {{{ */ 2, d: "\\"["}') == 3


@pytest.mark.parametrize("blocked", ["weights.npz", "experiences.npz", "metrics.json"])
def test_a_run_whose_end_cannot_be_written_is_refused_before_it_starts(tmp_path, blocked):
    """A folder where the run writes at its end: the run learned every episode, then lost its
    weights and metrics, with config.json already the new run's."""
    from wfnn_client.run import run

    out = tmp_path / "run"
    (out / blocked).mkdir(parents=True)
    with pytest.raises(IsADirectoryError, match=re.escape(blocked)):
        run(ClientConfig(sim="positioning", episodes=1, rate_hz=0.0, out=out))
    assert sorted(p.name for p in out.iterdir()) == [blocked]  # nothing written, no journal opened


def test_weights_that_make_no_learner_are_refused_naming_their_file(tmp_path):
    import numpy as np

    from wfnn_client.run import run
    from wfnn_common.learners import make_learner
    from wfnn_io.persist import save_weights

    run(ClientConfig(sim="positioning", episodes=1, rate_hz=0.0, out=tmp_path / "a"))
    with np.load(tmp_path / "a" / "weights.npz", allow_pickle=False) as npz:
        saved = {k: npz[k] for k in npz.files}
    from wfnn_common.config import LearnerConfig

    config = LearnerConfig.from_json(str(saved["config"]))
    several = make_learner(config, population=3) if config.learner == "thesis" else None
    assert several is not None
    save_weights(tmp_path / "three.npz", config, several.params)
    with pytest.raises(ValueError, match=r"three\.npz"):
        run(ClientConfig(sim="positioning", episodes=1, rate_hz=0.0, out=tmp_path / "b", learn=False,
                         weights=tmp_path / "three.npz"))  # fmt: skip


def test_learner_options_of_other_widths_than_the_task_are_refused_before_the_run(tmp_path):
    """The boat's 2 actions given 1 range: the think thread failed an episode in, with a traceback."""
    from wfnn_client.run import run

    options = '{"action_low": [-1], "action_high": [1]}'
    with pytest.raises(ValueError, match="give 1 action variables; boat has 2"):
        run(ClientConfig(sim="boat", episodes=1, rate_hz=0.0, out=tmp_path / "run", learner_options=options))
    assert not (tmp_path / "run" / "journal").exists()


def test_json_stats_naming_one_of_the_runs_own_files_is_refused_before_the_run(tmp_path):
    """--json-stats r/journal/00000000.seg wrote JSON over the journal (its experiences gone), and
    --json-stats r/weights.npz over the weights the run had just said it saved."""
    from wfnn_client.run import prepare

    out = tmp_path / "r"
    (out / "journal").mkdir(parents=True)
    (tmp_path / "link").symlink_to(out)
    for own in ("journal/00000000.seg", "journal", "weights.npz", "weights_servo.npz", "experiences.npz",
                "metrics.json", "config.json", "learning_curve.png", "cameras/x.json", "."):  # fmt: skip
        for base in (out, tmp_path / "link"):
            with pytest.raises(ValueError, match="one of the run's own"):
                prepare(ClientConfig(sim="boat", out=out, json_stats=base / own))
    for fine in (out / "stats.json", tmp_path / "stats.json", out / "weights.json"):
        prepare(ClientConfig(sim="boat", out=out, json_stats=fine))
    # A journal kept on another disk, linked from the run directory: the run's own there too.
    linked = tmp_path / "linked"
    (tmp_path / "disk" / "journal").mkdir(parents=True)
    linked.mkdir()
    (linked / "journal").symlink_to(tmp_path / "disk" / "journal")
    for spelled in (linked / "journal" / "00000000.seg", tmp_path / "disk" / "journal" / "00000000.seg"):
        with pytest.raises(ValueError, match="one of the run's own"):
            prepare(ClientConfig(sim="boat", out=linked, json_stats=spelled))
    prepare(ClientConfig(sim="boat", out=linked, json_stats=tmp_path / "disk" / "stats.json"))


@pytest.mark.parametrize("args, option", [
    (["--sim", "boat", "--behaviour", "forage"], "--behaviour"),
    (["--sim", "hydra", "--boat-dt", "1"], "--boat-dt"),
    (["--sim", "boat", "--regime", "static"], "--regime"),
    (["--sim", "nomad", "--every-second-target"], "--every-second-target"),
    (["--sim", "boat", "--follow", "s2"], "--follow"),
    (["--server", "local", "--listen", "tcp/127.0.0.1:7999"], "--listen"),
    (["--sim", "boat", "--controller", "x"], "--controller"),
    (["--sim", "boat", "--mode", "router"], "--mode"),
])  # fmt: skip
def test_options_this_run_would_not_read_are_refused(tmp_path, monkeypatch, args, option):
    """They were dropped without a word: a nomad forage option on the boat, a C/S option thinking
    locally (a run the user believed was following s2)."""
    from typer.testing import CliRunner

    from wfnn_client import cli

    monkeypatch.setattr(cli, "prepare", lambda config: pytest.fail("a run started"))
    result = CliRunner().invoke(cli.app, [*args, "--out", str(tmp_path)])
    assert result.exit_code != 0 and option in result.output and not (tmp_path / "config.json").exists()


def built_configs(monkeypatch, out, *command_lines):
    """The ClientConfig `wfnn-client` builds from each command line (run with --out `out`; not started)."""
    from typer.testing import CliRunner

    from wfnn_client import cli

    seen = []

    def built(config):
        seen.append(config)
        raise SystemExit(0)

    monkeypatch.setattr(cli, "prepare", built)
    for args in command_lines:
        result = CliRunner().invoke(cli.app, [*args, "--out", str(out)])
        assert result.exit_code == 0, result.output
    return seen


def test_options_of_the_run_given_are_taken(tmp_path, monkeypatch):
    seen = built_configs(
        monkeypatch, tmp_path,
        ["--sim", "nomad", "--behaviour", "forage", "--every-second-target"],
        ["--sim", "boat", "--boat-dt", "1"],
        ["--sim", "boat", "--server", "tcp/127.0.0.1:7447", "--follow", "s2", "--controller", "x"],
    )  # fmt: skip
    assert seen[0].forage is not None and seen[0].forage.pursue == "every_second"
    assert seen[1].boat_dt == 1.0 and seen[2].follow == "s2" and seen[2].controller == "x"


def test_a_start_refused_after_its_journals_opened_leaves_no_journal_of_its_making(tmp_path, monkeypatch):
    """Its client id would be picked up by the next run in the directory; a journal that was there
    before the start stays as it was."""
    from wfnn_client import run as run_module
    from wfnn_client.run import run

    (tmp_path / "run" / "config.json").mkdir(parents=True)  # refused before any journal opens
    with pytest.raises(OSError, match=r"config\.json"):
        run(ClientConfig(sim="boat", episodes=1, rate_hz=0.0, out=tmp_path / "run"))
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == ["config.json"]

    def full_disk(path, *args, **kwargs):
        raise OSError(28, "No space left on device", str(path))

    monkeypatch.setattr(run_module, "write_json", full_disk)  # refused once the journals are open
    from sims.nomad import ForageConfig, NomadConfig

    boat = ClientConfig(sim="boat", episodes=1, rate_hz=0.0, out=tmp_path / "boat")
    forage = ClientConfig(
        sim="nomad",
        episodes=1,
        rate_hz=0.0,
        out=tmp_path / "forage",
        nomad=NomadConfig(behaviour="wander"),
        forage=ForageConfig(),
    )  # one journal each
    for config in (boat, forage):
        with pytest.raises(OSError, match="No space"):
            run(config)
        assert not config.out.exists()  # nor the folder it made
    monkeypatch.undo()
    run(ClientConfig(sim="boat", episodes=1, rate_hz=0.0, out=tmp_path / "kept"))
    before = {p.name: p.read_bytes() for p in (tmp_path / "kept" / "journal").iterdir() if p.is_file()}
    monkeypatch.setattr(run_module, "write_json", full_disk)
    with pytest.raises(OSError, match="No space"):
        run(ClientConfig(sim="boat", episodes=1, rate_hz=0.0, out=tmp_path / "kept"))
    after = {p.name: p.read_bytes() for p in (tmp_path / "kept" / "journal").iterdir() if p.is_file()}
    assert after == before


@pytest.mark.parametrize("learner", ["thesis", "deep"])
def test_a_local_run_ended_by_ctrl_c_keeps_what_its_learner_learned(tmp_path, learner):
    """Ctrl-C or SIGTERM, how a long run is ended, left only the journal: no weights to resume."""
    from wfnn_client.run import run as run_client
    from wfnn_io.persist import load_checkpoint

    heard = []

    def interrupt(fields):
        heard.append(fields)
        if len(heard) == 2:  # after the first episode
            raise KeyboardInterrupt

    out = tmp_path / "run"
    options = '{"deep": {"warmup": 20}}' if learner == "deep" else ""
    cfg = ClientConfig(sim="boat", rate_hz=0, episodes=50, thinks_per_action=1, out=out, learner=learner,
                       learner_options=options)  # fmt: skip
    with pytest.raises(KeyboardInterrupt):
        run_client(cfg, on_status=interrupt)
    _, params, meta, training = load_checkpoint(out / "weights.npz")
    assert meta["episodes"] >= 1 and params.flat.shape[0] == 1
    if learner == "deep":
        assert int(training["adam_step"]) > 0 and int(training["acted"]) > 20
    resumed = run_client(ClientConfig(sim="boat", rate_hz=0, episodes=1, thinks_per_action=1,
                                      out=tmp_path / "resumed", learner=learner, learner_options=options,
                                      weights=out / "weights.npz"))  # fmt: skip
    assert resumed["experiences_learned"] > 0


def _meta_after_an_interrupted_lock_step_run(out):
    """Run the boat in lock-step until something interrupts it; -> the meta of the weights it saved."""
    from wfnn_client.run import run as run_client
    from wfnn_io.persist import load_checkpoint

    with pytest.raises(KeyboardInterrupt):
        run_client(ClientConfig(sim="boat", rate_hz=0, lockstep=True, episodes=50, thinks_per_action=1,
                                out=out))  # fmt: skip
    return load_checkpoint(out / "weights.npz")[2]


def test_ctrl_c_inside_a_compiled_act_keeps_what_the_learner_learned_and_ends_as_an_interrupt(
    tmp_path, monkeypatch
):
    """Raised inside a numba kernel's call, the interrupt came back as a SystemError: the run was
    taken for a failed learner, saved nothing and ended in that error (exit 1)."""
    from wfnn_common.learner import WFNN

    acts, original = [0], WFNN.act

    def act(self, *args, **kwargs):
        acts[0] += 1
        if acts[0] == 450:  # in the third episode
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt as exc:
                raise SystemError("CPUDispatcher returned a result with an exception set") from exc
        return original(self, *args, **kwargs)

    monkeypatch.setattr(WFNN, "act", act)
    assert _meta_after_an_interrupted_lock_step_run(tmp_path / "run")["episodes"] == 2


def test_a_stop_during_a_lock_step_think_waits_for_it_so_the_learner_is_saved_whole(tmp_path, monkeypatch):
    """The interrupt landed inside the update: the learner was saved with the update half-made
    (here: the think not counted), or inside a numba kernel's call, not saved at all."""
    import signal

    from wfnn_common.learner import WFNN

    calls, original = [0], WFNN.think

    def think(self, *args, **kwargs):
        calls[0] += 1
        if calls[0] == 300:  # SIGTERM, as a supervisor stops a run (SIGINT is ignored in a job run with &)
            signal.raise_signal(signal.SIGTERM)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(WFNN, "think", think)
    meta = _meta_after_an_interrupted_lock_step_run(tmp_path / "run")
    assert calls[0] == 300 and meta["thinks"] == 300


class _FailsLate(gymnasium.Env):
    """A task whose step fails (a simulation going unstable) after 250 steps."""

    observation_space = gymnasium.spaces.Box(-1.0, 1.0, (2,), np.float64)
    action_space = gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(2), {}

    def step(self, action):
        _FailsLate.steps += 1
        if _FailsLate.steps > 250:
            raise RuntimeError("simulation unstable")
        return np.full(2, 0.5 * float(action[0])), -1.0, False, _FailsLate.steps % 100 == 0, {}


@pytest.mark.parametrize("learner", ["thesis", "deep"])
def test_a_local_run_whose_robot_fails_keeps_what_its_learner_learned(tmp_path, learner):
    """A task failing in a step (the learner whole, as at Ctrl-C) left only the journal."""
    from wfnn_client.run import run as run_client
    from wfnn_io.persist import load_checkpoint

    gymnasium.register(f"WfnnTestFailsLate{learner}-v0", entry_point=_FailsLate, max_episode_steps=100)
    options = '{"deep": {"warmup": 20}}' if learner == "deep" else ""
    cfg = ClientConfig(sim="gym", env=f"WfnnTestFailsLate{learner}-v0", rate_hz=0, episodes=5,
                       thinks_per_action=1, out=tmp_path / "run", learner=learner,
                       learner_options=options)  # fmt: skip
    _FailsLate.steps = 0
    with pytest.raises(RuntimeError, match="failed in step: RuntimeError: simulation unstable"):
        run_client(cfg)
    _, _, meta, training = load_checkpoint(tmp_path / "run" / "weights.npz")
    assert meta["episodes"] == 2  # saved where it failed, in its third episode
    if learner == "deep":
        assert int(training["adam_step"]) > 0 and int(training["acted"]) >= 250


def test_a_learner_that_failed_itself_is_not_saved_when_its_robot_fails_too(tmp_path, monkeypatch):
    """Its think thread failed half-way through an update, and the robot failed before the run's
    check of the brains saw it: the half-made learner was saved as whole."""
    from wfnn_client.run import run as run_client
    from wfnn_common.learner import WFNN

    think, in_step, failed = WFNN.think, threading.Event(), threading.Event()

    def fails_in_the_robots_step(self, *args, **kwargs):
        if in_step.is_set() and not failed.is_set():  # no check of the brains can run meanwhile
            self.params.flat[:] += 1000.0  # half an update, finite
            failed.set()
            raise FloatingPointError("the update blew up half-way")
        return think(self, *args, **kwargs)

    class FailsAfterTheLearner(_FailsLate):
        def step(self, action):
            if _FailsLate.steps >= 250:
                in_step.set()
                failed.wait(30.0)  # the think thread owes thousands of thinks: it thinks on
            return super().step(action)

    monkeypatch.setattr(WFNN, "think", fails_in_the_robots_step)
    gymnasium.register("WfnnTestFailsLateThink-v0", entry_point=FailsAfterTheLearner, max_episode_steps=1000)
    _FailsLate.steps = 0
    with pytest.raises(RuntimeError, match="simulation unstable"):
        run_client(ClientConfig(sim="gym", env="WfnnTestFailsLateThink-v0", rate_hz=0, episodes=1,
                                thinks_per_action=200, out=tmp_path / "run"))  # fmt: skip
    assert failed.is_set() and not (tmp_path / "run" / "weights.npz").exists()


@pytest.mark.parametrize("grace_s", [300.0, 0.05])
def test_a_run_that_ends_while_its_learner_is_in_an_update_saves_it_whole(tmp_path, monkeypatch, grace_s):
    """A think thread still in a long update (a first compiled one) after its stop's wait was
    saved at the run's normal end as it stood: half an update. The run now waits for it, and
    one that outlives that wait too is not saved."""
    from wfnn_client import run as run_module
    from wfnn_client.run import run as run_client
    from wfnn_client.think_thread import ActLearnThinkMT
    from wfnn_common.learner import WFNN
    from wfnn_io.persist import load_checkpoint

    think, stop = WFNN.think, ActLearnThinkMT.stop
    ending, in_update = threading.Event(), threading.Event()

    def long_update(self, *args, **kwargs):
        if ending.is_set() and not in_update.is_set():
            self.params.flat[:] += 1000.0  # the first half of an update
            in_update.set()
            time.sleep(1.0)
            self.params.flat[:] -= 1000.0  # the second
        return think(self, *args, **kwargs)

    def stop_while_it_updates(self, timeout=5.0):
        if not ending.is_set():  # the first stop's wait runs out in the middle of the update
            ending.set()
            self.schedule.owe(1)  # a think to do, however far the thread had got
            in_update.wait(30.0)
            timeout = 0.05
        stop(self, timeout)

    monkeypatch.setattr(WFNN, "think", long_update)
    monkeypatch.setattr(ActLearnThinkMT, "stop", stop_while_it_updates)
    monkeypatch.setattr(run_module, "THINKING_GRACE_S", grace_s)
    cfg = ClientConfig(sim="positioning", rate_hz=0, episodes=2, thinks_per_action=1, out=tmp_path / "run")
    if grace_s < 1.0:
        with pytest.raises(RuntimeError, match=r"still thinking 0\.05 s after the run ended: not saved"):
            run_client(cfg)
        assert in_update.is_set() and not (tmp_path / "run" / "weights.npz").exists()
        return
    metrics = run_client(cfg)
    _, params, _, _ = load_checkpoint(tmp_path / "run" / "weights.npz")
    assert in_update.is_set() and np.abs(params.flat).max() < 100.0
    assert metrics["think/thinks"] > 0


def test_a_local_run_whose_tasks_reward_fails_keeps_what_its_learner_learned(tmp_path, monkeypatch):
    """Only the task's step and new episode counted as the robot's: its reward of a vetoed proposal
    (learning twice), failing in a step, left only the journal."""
    import dataclasses

    from wfnn_client.run import run as run_client
    from wfnn_client.sims import SIMS

    calls = []

    def reward_of(task):
        def reward(state, action, next_state):
            calls.append(1)
            if len(calls) > 300:
                raise RuntimeError("the reward model failed")
            return -abs(next_state[..., 0])

        return reward

    def always_veto(task):
        return lambda state, action: np.zeros_like(action)

    monkeypatch.setitem(SIMS, "positioning", dataclasses.replace(SIMS["positioning"], reward_of=reward_of,
                                                                 veto=always_veto))  # fmt: skip
    with pytest.raises(RuntimeError, match="the reward model failed"):
        run_client(ClientConfig(sim="positioning", rate_hz=0, episodes=3, thinks_per_action=1,
                                out=tmp_path / "run"))  # fmt: skip
    assert (tmp_path / "run" / "weights.npz").exists()


def test_a_local_run_whose_tasks_own_controller_fails_keeps_what_its_learner_learned(tmp_path, monkeypatch):
    """The task's hand-coded controller, driving as a behaviour policy, is the robot's code too."""
    import dataclasses

    from wfnn_client.controllers import parse_mix
    from wfnn_client.run import run as run_client
    from wfnn_client.sims import SIMS

    calls = []

    def handcoded(task):
        def policy(state):
            calls.append(1)
            if len(calls) > 300:
                raise RuntimeError("the hand-coded controller failed")
            return np.zeros(1)

        return policy

    monkeypatch.setitem(SIMS, "positioning", dataclasses.replace(SIMS["positioning"], handcoded=handcoded))
    with pytest.raises(RuntimeError, match="the hand-coded controller failed"):
        run_client(ClientConfig(sim="positioning", rate_hz=0, episodes=3, thinks_per_action=1,
                                behaviour_policy=parse_mix("handcoded"), out=tmp_path / "run"))  # fmt: skip
    assert (tmp_path / "run" / "weights.npz").exists()


@pytest.mark.parametrize("learner", ["thesis", "deep"])
def test_a_local_learner_resumed_from_its_weights_counts_its_thinks_on(tmp_path, learner):
    """Its thinks (a local learner's weights version) began again at 0: versions recorded in a
    continued journal went backwards."""
    from wfnn_client.run import run as run_client
    from wfnn_io.persist import load_checkpoint

    def client(out, **kw):
        return ClientConfig(sim="boat", rate_hz=0, lockstep=True, episodes=1, thinks_per_action=2, out=out,
                            learner=learner, **kw)  # fmt: skip

    first = run_client(client(tmp_path / "a"))
    _, _, meta, _ = load_checkpoint(tmp_path / "a" / "weights.npz")
    assert meta["thinks"] == first["think/thinks"] > 0
    second = run_client(client(tmp_path / "a", weights=tmp_path / "a" / "weights.npz"))
    assert second["think/thinks"] == 2 * first["think/thinks"]
    _, _, meta, _ = load_checkpoint(tmp_path / "a" / "weights.npz")
    assert meta["thinks"] == second["think/thinks"]


def test_local_runs_resumed_from_their_weights_number_their_weights_on_whatever_their_mode(tmp_path):
    """A threaded run's weights versions (snapshots published) began again at 0 while its thinks
    went on; a lock-step run after a threaded one numbered by its thinks, below the snapshots'
    count; a run that learned nothing saved no count, and one resumed from its weights began at
    0: journals the runs continued named other weights by versions already used."""
    from wfnn_client.run import run as run_client
    from wfnn_io import logs
    from wfnn_io.persist import load_checkpoint, save_weights

    def client(out="a", **kw):
        return ClientConfig(sim="boat", rate_hz=0, episodes=1, thinks_per_action=2, out=tmp_path / out, **kw)

    def versions(out="a"):
        return np.concatenate([b.weights_version for b in logs.read_batches(tmp_path / out / "journal")])

    weights = tmp_path / "a" / "weights.npz"
    run_client(client())
    seen = versions()
    # Threaded, lock-step, one that learns nothing (its own --out: it may not replace a learning
    # run's outputs) whose weights the next run resumes, then threaded and lock-step again.
    runs = [("a", {}), ("a", {"lockstep": True}), ("b", {"learn": False}),
            ("a", {"weights": tmp_path / "b" / "weights.npz"}), ("a", {"lockstep": True})]  # fmt: skip
    for out, kw in runs:
        given = kw.setdefault("weights", weights)
        _, _, meta, _ = load_checkpoint(given)
        run_client(client(out, **kw))
        if out == "b":  # the weights it was given, as they were: their counts
            _, _, saved, _ = load_checkpoint(tmp_path / "b" / "weights.npz")
            assert (saved["version"], saved["thinks"]) == (meta["version"], meta["thinks"])
            continue
        now = versions(out)
        assert len(now) > len(seen) and (np.diff(now.astype(np.int64)) >= 0).all(), kw
        assert now[len(seen) :].min() > meta["version"] >= seen.max(), kw
        seen = now
    cfg, params, meta, training = load_checkpoint(weights)
    save_weights(tmp_path / "bad.npz", cfg, params, {**meta, "version": -1}, training=training)
    with pytest.raises(ValueError, match=r"bad\.npz: its saved weights version is not a count: -1"):
        run_client(client(weights=tmp_path / "bad.npz"))


@pytest.mark.parametrize("lockstep", [False, True])
def test_a_run_continuing_a_journal_numbers_its_weights_past_every_version_the_journal_names(
    tmp_path, lockstep
):
    """Given another run's weights (or none), a run continuing a journal numbered its snapshots
    on from those weights' version: the journal's versions went back, and named two snapshots
    by one version."""
    from wfnn_client.run import run as run_client
    from wfnn_io import logs

    def client(out, **kw):
        return ClientConfig(sim="boat", rate_hz=0, episodes=1, thinks_per_action=2, out=tmp_path / out,
                            lockstep=lockstep, **kw)  # fmt: skip

    def versions():
        return np.concatenate([b.weights_version for b in logs.read_batches(tmp_path / "a" / "journal")])

    run_client(client("a"))
    run_client(client("b"))  # a run elsewhere: its weights are numbered apart from this journal
    first = versions()
    assert first.max() > 0
    run_client(client("a", weights=tmp_path / "b" / "weights.npz"))
    second = versions()
    run_client(client("a"))  # no weights given: a fresh learner, in the same record
    both = versions()
    for before, after in ((first, second), (second, both)):
        assert len(after) > len(before) and after[len(before) :].min() > before.max()
    assert (np.diff(both.astype(np.int64)) >= 0).all()


def test_a_journal_version_near_the_saved_counts_limit_is_refused(tmp_path):
    """One record of a version near the saved counts' limit (forged, or odd): the run numbered on
    from it and saved weights whose version its own resume then refused."""
    from wfnn_client.brain import Experience, Recorder
    from wfnn_client.run import SetupError
    from wfnn_client.run import run as run_client
    from wfnn_common.config import MAX_SAVED_COUNT
    from wfnn_io.persist import load_checkpoint

    first = ClientConfig(sim="boat", rate_hz=0, lockstep=True, episodes=1, thinks_per_action=1,
                         out=tmp_path / "a")  # fmt: skip
    run_client(first)
    lcfg = load_checkpoint(tmp_path / "a" / "weights.npz")[0]
    record = Recorder(tmp_path / "a" / "journal", lcfg, task=first.task)
    x, u = np.zeros(lcfg.state_dim), np.zeros(lcfg.action_dim)
    record.add(Experience(x, u, x, 0.0, False, 0), "local", MAX_SAVED_COUNT - 1)
    record.close()
    before = (tmp_path / "a" / "weights.npz").read_bytes()
    with pytest.raises(SetupError, match="names weights versions up to 999999999999999, too near the last"):
        run_client(dataclasses.replace(first, weights=tmp_path / "a" / "weights.npz"))
    assert (tmp_path / "a" / "weights.npz").read_bytes() == before


def test_the_task_a_journal_records_covers_every_option_of_a_robots_task(tmp_path):
    """A nomad's camera yaw or balls (or a robot's simulated rate) made no other task: such runs
    continued each other's journals; a task that cannot be read was replaced, the journal continued."""
    import json

    from sims.nomad import NomadConfig
    from wfnn_client.journal import Journal

    nomad = ClientConfig(sim="nomad")
    assert nomad.task == ClientConfig(sim="nomad", seed=3, rate_hz=0, lockstep=True).task  # no other task
    assert nomad.task == {"sim": "nomad", "options": {}}
    for other in (NomadConfig(camera_yaw_deg=90.0), NomadConfig(balls=1), NomadConfig(rate_hz=20.0)):
        assert dataclasses.replace(nomad, nomad=other).task != nomad.task
    assert ClientConfig(sim="nomad", nomad=NomadConfig(camera_yaw_deg=-0.0)).task == nomad.task
    hydra = ClientConfig(sim="hydra")
    assert dataclasses.replace(hydra, hydra=HydraConfig(rate_hz=30.0)).task["options"] == {"rate_hz": 30.0}
    assert dataclasses.replace(hydra, hydra=HydraConfig(rate_hz=15)).task == hydra.task  # 15 is 15.0
    both = [
        dataclasses.replace(hydra, hydra=HydraConfig(joints=j)).task
        for j in (("right", "pan"), ("pan", "right"))
    ]
    assert both[0] == both[1]  # the states are in the model's order either way
    boat = ClientConfig(sim="boat", boat_dt=1.0).task
    Journal(tmp_path / "j", "c1", task=ClientConfig(sim="boat").task).close()
    with pytest.raises(ValueError, match=r"another task \(boat_dt default there, 1 here\)"):
        Journal(tmp_path / "j", task=boat)
    meta = json.loads((tmp_path / "j" / "client.json").read_text())
    for damaged in (5, "", "x" * 2000, ["boat"], {"sim": "boat", "options": {"dt": {"nested": 1}}}):
        (tmp_path / "j" / "client.json").write_text(json.dumps({**meta, "task": damaged}))
        with pytest.raises(ValueError, match="records a task that cannot be read"):
            Journal(tmp_path / "j", task=boat)
        assert json.loads((tmp_path / "j" / "client.json").read_text())["task"] == damaged  # not rewritten
    # A boolean is not the number 1 (True == 1.0 in Python); a hostile record is told on one short line.
    (tmp_path / "j" / "client.json").write_text(
        json.dumps({**meta, "task": {"sim": "boat", "options": {"boat_dt": True}}})
    )
    with pytest.raises(ValueError, match="boat_dt true there, 1 here"):
        Journal(tmp_path / "j", task=boat)
    hostile = {
        "sim": "b\nINJECTED" + "b" * 1000,
        "options": {f"{'k' * 1000}{i}": "v" * 1000 for i in range(200)},
    }
    (tmp_path / "j" / "client.json").write_text(json.dumps({**meta, "task": hostile}))
    with pytest.raises(ValueError) as refused:
        Journal(tmp_path / "j", task=boat)
    assert (
        "\n" not in str(refused.value)
        and len(str(refused.value)) < 1500
        and "and 195 more" in str(refused.value)
    )


def test_a_journal_is_continued_only_by_runs_of_the_task_it_records(tmp_path, caplog):
    """The boat at another time step (or two Gymnasium tasks of the same spaces) has the same
    learner spec: a run of it continued another task's journal, which then mixed the two."""
    import json
    import logging

    from wfnn_client.run import run as run_client
    from wfnn_io import logs

    def client(dt, out="a", **kw):
        return ClientConfig(sim="boat", boat_dt=dt, rate_hz=0, lockstep=True, episodes=1, thinks_per_action=1,
                            out=tmp_path / out, **kw)  # fmt: skip

    run_client(client(0.2))
    meta = json.loads((tmp_path / "a" / "journal" / "client.json").read_text())
    assert meta["task"] == {"sim": "boat", "options": {"boat_dt": 0.2}}
    assert logs.summarise(tmp_path / "a" / "journal").task == "boat (boat_dt 0.2)"  # as inspect says it
    before = logs.summarise(tmp_path / "a" / "journal").experiences
    with pytest.raises(ValueError, match=r"another task \(boat_dt 0.2 there, 1 here\)"):
        run_client(client(1.0))
    assert logs.summarise(tmp_path / "a" / "journal").experiences == before
    run_client(client(0.2))  # the same task goes on
    assert logs.summarise(tmp_path / "a" / "journal").experiences > before
    assert logs.summarise(tmp_path / "a" / "journal").task_record == {
        "sim": "boat",
        "options": {"boat_dt": 0.2},
    }
    # A journal from before tasks were recorded is continued, and records the task from then on.
    del meta["task"]
    (tmp_path / "a" / "journal" / "client.json").write_text(json.dumps(meta))
    run_client(client(0.2))
    assert json.loads((tmp_path / "a" / "journal" / "client.json").read_text())["task"]["options"] == {
        "boat_dt": 0.2
    }
    # Weights may go to another task of the same spaces (a simulation's to the robot): said, not refused.
    with caplog.at_level(logging.WARNING, logger="wfnn_client.run"):
        run_client(client(1.0, out="b", weights=tmp_path / "a" / "weights.npz"))
    assert any(
        "learned on another task (boat_dt 0.2 there, 1 here)" in r.getMessage() for r in caplog.records
    )
    # A client.json that cannot be read: its records' task is unknown, and no run's is written as theirs.
    (tmp_path / "a" / "journal" / "client.json").write_text('{"client": "c1", "task": {"sim": "bo')
    run_client(client(1.0))
    assert "task" not in json.loads((tmp_path / "a" / "journal" / "client.json").read_text())


@pytest.mark.parametrize("learner", ["thesis", "deep"])
def test_a_learner_resumed_from_its_weights_keeps_its_saved_config_under_the_options_given(
    tmp_path, learner, caplog
):
    """A resume built the config from the command line: its defaults replaced the saved discount,
    rates and warm-up without a word, though the training state went on."""
    import json

    from wfnn_client.run import run as run_client
    from wfnn_common.config import ExplorationConfig
    from wfnn_io.persist import load_checkpoint

    def client(out, options, **kw):
        return ClientConfig(sim="boat", rate_hz=0, lockstep=True, episodes=1, thinks_per_action=1, out=out,
                            learner=learner, learner_options=json.dumps(options), **kw)  # fmt: skip

    # Another network than the defaults' too: the defaults' refused the saved one.
    own = (
        {"deep": {"warmup": 50, "lr": 1e-3, "hidden": [16, 16]}}
        if learner == "deep"
        else {"alpha": 0.05, "n_hidden": 7}
    )
    run_client(client(tmp_path / "a", {"gamma": 0.95, **own}))
    weights = tmp_path / "a" / "weights.npz"
    run_client(client(tmp_path / "b", {}, weights=weights, advantage_k=0.5))  # nothing else said
    saved, _, _, _ = load_checkpoint(tmp_path / "b" / "weights.npz")
    assert saved.gamma == 0.95 and saved.advantage_k == 0.5  # kept, and the option given applied
    if learner == "deep":
        assert saved.deep.warmup == 50 and saved.deep.lr == 1e-3 and saved.deep.hidden == (16, 16)
    else:
        assert saved.alpha == 0.05 and saved.n_hidden == 7
    other = {"deep": {"hidden": [8]}} if learner == "deep" else {"n_hidden": 5}
    caplog.clear()
    with pytest.raises(ValueError, match=r"the options given make .*another network"):
        run_client(client(tmp_path / "g", other, weights=weights))
    assert "resuming its learner config" not in caplog.text  # no word of a change then refused
    run_client(client(tmp_path / "c", {"gamma": 0.9}, weights=weights))
    assert load_checkpoint(tmp_path / "c" / "weights.npz")[0].gamma == 0.9
    # The seed, symmetries and exploration apply where given (the CLI names them), else as saved.
    mirror = ExplorationConfig(kind="gaussian", sigma=0.3)
    run_client(client(tmp_path / "d", {}, exploration=mirror, symmetries=True, seed=3))
    given = tmp_path / "d" / "weights.npz"
    default = ExplorationConfig(kind="uniform")  # what the CLI fills in for the thesis' learner
    run_client(client(tmp_path / "e", {}, weights=given, exploration=default))
    kept = load_checkpoint(tmp_path / "e" / "weights.npz")[0]
    assert kept.exploration == mirror and kept.symmetries and kept.seed == 3
    run_client(client(tmp_path / "f", {}, weights=given, exploration=default, seed=7,
                      explicit=("seed", "symmetries", "exploration")))  # fmt: skip
    changed = load_checkpoint(tmp_path / "f" / "weights.npz")[0]
    assert changed.exploration == default and not changed.symmetries and changed.seed == 7


def test_the_command_line_says_which_of_seed_symmetries_and_exploration_it_gave(tmp_path, monkeypatch):
    seen = built_configs(
        monkeypatch, tmp_path / "run",
        ["--sim", "boat"],
        ["--sim", "boat", "--no-symmetries", "--seed", "0"],
        ["--sim", "boat", "--exploration", "gaussian"],
    )  # fmt: skip
    assert [c.explicit for c in seen] == [(), ("seed", "symmetries"), ("exploration",)]
    assert all(c.seed == 0 and not c.symmetries for c in seen)


def test_huge_figures_print_in_powers_of_ten_and_usual_ones_with_their_places():
    """A diverging task's score of 1e300 printed 300 digits in the status and summary lines."""
    from wfnn_client.cli import status_line

    fields = {"client/score": 1e300, "client/tick_jitter_ms_p99": float("nan"), "client/overruns": 0.0,
              "client/safe_actions": 0.0, "client/reward_mean": -3e200, "client/q_mean": 0.25,
              "following": "local"}  # fmt: skip
    line = status_line(fields)
    assert len(line) < 150 and "score 1.000e+300" in line and "r -3.000e+200" in line and "Q +0.250" in line
    usual = status_line({**fields, "client/score": 1.0204, "client/reward_mean": -0.645})
    assert (
        "score 1.020 |" in usual
        and "r -0.645 |" in usual
        and "score nan" in status_line({**fields, "client/score": float("nan")})
    )


def test_a_run_some_of_whose_experiences_no_server_acknowledged_says_so():
    """Only a run of which no server acknowledged any was flagged: one whose server went away
    half-way printed "N experiences" as if a learner had them all."""
    from wfnn_client.cli import _unacknowledged

    assert _unacknowledged({}) == ""  # thinking locally
    assert _unacknowledged({"uplink/acked_by_any": -1.0, "uplink/produced_through": 99.0}) == (
        " (none acknowledged by a server)"
    )
    partly = _unacknowledged({"uplink/acked_by_any": 59.0, "uplink/produced_through": 99.0})
    assert "through #59 of #99" in partly and "the next run sends" in partly
    assert _unacknowledged({"uplink/acked_by_any": 99.0, "uplink/produced_through": 99.0}) == ""
    figures = {"servo/uplink/acked_by_any": -1.0, "servo/uplink/produced_through": 99.0,
               "wander/uplink/acked_by_any": 40.0, "wander/uplink/produced_through": 99.0}  # fmt: skip
    several = _unacknowledged(figures)
    assert several.startswith(
        " (servo: none acknowledged by a server; wander: acknowledged by a server through #40"
    )


def test_the_status_line_of_several_behaviours_shows_each_ones_weights_version():
    """With each behaviour's figures under its name, it showed v0 and no thinks/s."""
    from wfnn_client.cli import status_line

    fields = {"client/score": 1.0, "client/tick_jitter_ms_p99": float("nan"), "client/overruns": 0.0,
              "client/safe_actions": 0.0, "client/reward_mean": 0.0, "client/q_mean": 0.0,
              "following": "servo:s1 wander:s2", "servo/weights/version": 238.0,
              "wander/weights/version": 1220.0, "servo/server/think/thinks_per_s": 1000.0,
              "wander/server/think/thinks_per_s": 500.0}  # fmt: skip
    line = status_line(fields)
    assert "v238/1220 from servo:s1 wander:s2" in line and "thinks/s 1,500" in line
    one = {
        **{k: v for k, v in fields.items() if "/" not in k or k.startswith("client/")},
        "following": "local",
    }
    assert "v0 from local" in status_line(one) and "thinks/s -" in status_line(one)
    assert "v7 from local" in status_line({**one, "weights/version": 7.0})


def test_options_that_would_be_ignored_or_taken_as_the_default_are_refused(tmp_path, monkeypatch):
    """An empty --exploration ran with the sim's default (and was taken as chosen); a server's
    --dashboard-host and --dashboard-hz without --dashboard started no dashboard without a word."""
    from typer.testing import CliRunner

    from wfnn_client import cli
    from wfnn_server import cli as server_cli

    result = CliRunner().invoke(cli.app, ["--sim", "boat", "--exploration", "", "--out", str(tmp_path / "r")])
    assert result.exit_code == 2 and "--exploration" in result.output and not (tmp_path / "r").exists()
    # An empty --learner-options ran with the defaults; --env dropped the --sim typed beside it.
    for args, option in ((["--sim", "boat", "--learner-options", " "], "--learner-options"),
                         (["--env", "Pendulum-v1", "--sim", "boat"], "--sim")):  # fmt: skip
        result = CliRunner().invoke(cli.app, [*args, "--out", str(tmp_path / "r")])
        assert result.exit_code == 2 and option in result.output and not (tmp_path / "r").exists()
    from wfnn_bench import cli as bench_cli

    for args in (["vs-sb3", "--deep-options", ""], ["boat", "--learner-options", ""],
                 ["passive", "--learner-options", ""]):  # fmt: skip
        result = CliRunner().invoke(bench_cli.app, args, env={"COLUMNS": "300"})
        assert result.exit_code == 2 and "not an empty string" in result.output, result.output
    monkeypatch.setattr(server_cli, "run", lambda *args, **kwargs: {})  # a server that would start ends
    for option in (["--dashboard-host", "0.0.0.0"], ["--dashboard-hz", "30"]):
        args = ["--listen", "tcp/127.0.0.1:0", "--data-dir", str(tmp_path / "d"), *option]
        result = CliRunner().invoke(server_cli.app, args)
        assert result.exit_code == 2 and "serves no dashboard without --dashboard" in result.output
    assert not (tmp_path / "d").exists()


def test_a_start_the_python_api_refuses_leaves_no_empty_folder_of_its_making(tmp_path):
    """As the command line's: a refused run() left its new, empty --out (and the folders above it)."""
    from wfnn_client.run import SetupError
    from wfnn_client.run import run as run_client

    (tmp_path / "kept").mkdir()
    for out in (tmp_path / "new" / "deeper" / "run", tmp_path / "kept"):
        with pytest.raises(SetupError, match="no such file"):
            run_client(ClientConfig(sim="boat", rate_hz=0, episodes=1, out=out, weights=tmp_path / "no.npz"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kept"] and not any((tmp_path / "kept").iterdir())
