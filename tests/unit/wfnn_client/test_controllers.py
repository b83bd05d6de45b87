"""Behaviour policies other than the learner: parsing a mix, drawing per episode, off-policy runs."""

from pathlib import Path

import numpy as np
import pytest

from sims.boat import BoatVec, handcoded_boat
from sims.cartpole import CartPoleVec
from wfnn_client.config import ClientConfig
from wfnn_client.controllers import Controllers, PolicyShare, parse_mix, source_names
from wfnn_client.run import SetupError, learner_config, run
from wfnn_common.learner import WFNN
from wfnn_common.learners import make_learner
from wfnn_io import logs
from wfnn_io.persist import save_weights


def test_a_mix_is_parsed_with_shares_and_bad_ones_are_named():
    assert parse_mix("wfnn=0.5, handcoded=0.3,random") == (
        PolicyShare("wfnn", 0.5), PolicyShare("handcoded", 0.3), PolicyShare("random", 1.0),
    )  # fmt: skip
    assert parse_mix("weights:runs/a=b/weights.npz=2") == (PolicyShare("weights:runs/a=b/weights.npz", 2.0),)
    for text, message in (("pid", "unknown behaviour policy"), ("wfnn=x", "must be a number"),
                          ("wfnn=0", "must be > 0"), ("", "empty"), ("random,random=2", "twice"),
                          ("weights:", "unknown"), ("wfnn=1e308,random=1e308", "sum beyond")):  # fmt: skip
        with pytest.raises(ValueError, match=message):
            parse_mix(text)
    for two_ways in (
        "weights:runs/a/w.npz,weights:./runs/a/w.npz",
        f"weights:x.npz,weights:{Path.cwd() / 'x.npz'}",
    ):
        with pytest.raises(ValueError, match="twice"):  # one file, written two ways
            parse_mix(two_ways)


def test_saved_policies_are_recorded_by_names_that_tell_them_apart():
    """Every run saves weights.npz: two runs' policies were both recorded as weights:weights.npz."""
    assert source_names(["random", "weights:/tmp/x/w.npz"]) == {
        "random": "random",
        "weights:/tmp/x/w.npz": "weights:w.npz",
    }
    assert source_names(["weights:runs/a/weights.npz", "weights:runs/b/weights.npz", "weights:c.npz"]) == {
        "weights:runs/a/weights.npz": "weights:a/weights.npz",
        "weights:runs/b/weights.npz": "weights:b/weights.npz",
        "weights:c.npz": "weights:c.npz",
    }  # fmt: skip
    assert source_names(["weights:x/a/w.npz", "weights:y/a/w.npz"]) == {
        "weights:x/a/w.npz": "weights:x/a/w.npz", "weights:y/a/w.npz": "weights:y/a/w.npz"
    }  # fmt: skip


def _controllers(mix, tmp_path=None, handcoded=None, seed=0):
    cfg = learner_config(BoatVec(1), ClientConfig(sim="boat"))
    low, high = np.array(cfg.action_low), np.array(cfg.action_high)
    return Controllers(parse_mix(mix), cfg, low, high, handcoded, np.random.default_rng(seed)), cfg


def test_episodes_are_drawn_by_share_and_each_controller_acts_as_itself(tmp_path):
    boat = BoatVec(1)
    handcoded = lambda s: handcoded_boat(s[None])[0]  # noqa: E731
    cfg = learner_config(boat, ClientConfig(sim="boat"))
    saved = WFNN(cfg)
    save_weights(tmp_path / "w.npz", cfg, saved.params, {})
    mix, _ = _controllers(f"wfnn=1,handcoded=2,random=1,weights:{tmp_path / 'w.npz'}=4", handcoded=handcoded)
    drawn = [mix.choose() for _ in range(4000)]
    for name, share in (("wfnn", 1 / 8), ("handcoded", 2 / 8), ("random", 1 / 8)):
        assert abs(drawn.count(name) / 4000 - share) < 0.03
    x = np.array([1.0, -0.5, 0.1, 0.0, 0.2, 0.0, 0.0])
    acted = mix.act("handcoded", x)
    np.testing.assert_array_equal(acted.result.action, handcoded_boat(x[None])[0])
    assert acted.source == "handcoded" and acted.version == 0 and not acted.result.explored
    greedy = mix.act(f"weights:{tmp_path / 'w.npz'}", x)
    np.testing.assert_array_equal(greedy.result.action, saved.act(x, explore=False).action)
    assert greedy.source == "weights:w.npz"
    randoms = np.array([mix.act("random", x).result.action for _ in range(200)])
    assert (np.abs(randoms) <= 1.0).all() and randoms.std() > 0.4


def test_a_controller_the_task_lacks_or_weights_of_another_task_are_refused(tmp_path):
    with pytest.raises(ValueError, match="no hand-coded controller"):
        _controllers("handcoded")
    other = learner_config(CartPoleVec(1), ClientConfig(sim="cartpole"))
    save_weights(tmp_path / "other.npz", other, WFNN(other).params, {})
    with pytest.raises(ValueError, match="another task's ranges"):
        _controllers(f"weights:{tmp_path / 'other.npz'}")
    # Another network for this task drives (a deep controller for the thesis learner, a smaller
    # network): it is made from its own config (it was refused as of another learner spec).
    boat = learner_config(BoatVec(1), ClientConfig(sim="boat"))
    deep = learner_config(BoatVec(1), ClientConfig(sim="boat", learner="deep"))
    for name, cfg in (("small", type(boat).from_dict({**boat.to_dict(), "n_hidden": 3})), ("deep", deep)):
        saved, policy = make_learner(cfg), f"weights:{tmp_path / name}.npz"
        save_weights(tmp_path / f"{name}.npz", cfg, saved.params, {})
        x = np.linspace(-0.5, 0.5, cfg.state_dim)
        acted = _controllers(policy)[0].act(policy, x)
        np.testing.assert_array_equal(acted.result.action, saved.act(x, explore=False).action)
    with pytest.raises(ValueError, match="cannot load"):
        _controllers(f"weights:{tmp_path / 'missing.npz'}")
    boat = learner_config(BoatVec(1), ClientConfig(sim="boat"))
    save_weights(tmp_path / "three.npz", boat, WFNN(boat, population=3).params, {})
    with pytest.raises(ValueError, match=r"weights:.*three\.npz: params hold 3 networks"):
        _controllers(f"weights:{tmp_path / 'three.npz'}")
    with pytest.raises(SetupError, match="no hand-coded"):
        run(ClientConfig(sim="cartpole", rate_hz=0, episodes=1, behaviour_policy=parse_mix("handcoded"),
                         out=tmp_path / "c"))  # fmt: skip


def test_the_learner_learns_off_policy_from_a_mix_and_the_log_names_who_drove(tmp_path):
    out = tmp_path / "run"
    metrics = run(ClientConfig(
        sim="boat", rate_hz=0, episodes=6, thinks_per_action=2, out=out, seed=3,
        behaviour_policy=parse_mix("wfnn=1,handcoded=1,random=1"),
    ))  # fmt: skip
    drove = metrics["episode_policies"]
    assert len(drove) == 6 and set(drove) <= {"wfnn", "handcoded", "random"} and len(set(drove)) >= 2
    summary = logs.summarise(out / "journal")
    steps = 200
    for name in ("handcoded", "random"):
        assert summary.behaviour.get(name, 0) == steps * drove.count(name)
    assert summary.behaviour.get("local", 0) == steps * drove.count("wfnn")
    assert metrics["experiences_learned"] == 6 * steps
    # The hand-coded controller steers the boat to its targets; random thrusts do not (seed 3
    # draws both).
    by = {
        name: [s for d, s in zip(drove, metrics["scores"], strict=True) if d == name] for name in set(drove)
    }
    assert max(by["handcoded"]) < 0.5 < min(by["random"])


def test_a_deep_learners_saved_weights_drive_as_a_behaviour_policy(tmp_path):
    cfg = learner_config(BoatVec(1), ClientConfig(sim="boat", learner="deep"))
    saved = make_learner(cfg)
    save_weights(tmp_path / "deep.npz", cfg, saved.params, {})
    low, high = np.array(cfg.action_low), np.array(cfg.action_high)
    mix = Controllers(parse_mix(f"weights:{tmp_path / 'deep.npz'}"), cfg, low, high, None,
                      np.random.default_rng(0))  # fmt: skip
    x = np.array([1.0, -0.5, 0.1, 0.0, 0.2, 0.0, 0.0])
    acted = mix.act(f"weights:{tmp_path / 'deep.npz'}", x)
    np.testing.assert_array_equal(acted.result.action, saved.act(x, explore=False).action)
    # The thesis' learner's spec is another, the task the same: they drive for it too.
    policy = f"weights:{tmp_path / 'deep.npz'}"
    for_thesis = _controllers(policy)[0].act(policy, x)
    np.testing.assert_array_equal(for_thesis.result.action, acted.result.action)


def test_a_learner_that_cannot_think_here_is_refused_before_its_journal_is_made(tmp_path):
    import torch

    if torch.cuda.is_available():
        pytest.skip("torch sees a CUDA device here: the refusal needs a machine without one")
    options = '{"deep": {"device": "cuda"}}'
    with pytest.raises(SetupError, match="no such CUDA device"):
        run(ClientConfig(sim="cartpole", rate_hz=0, episodes=1, learner="deep", learner_options=options,
                         out=tmp_path / "c"))  # fmt: skip
    assert not list((tmp_path / "c").glob("journal*"))
    run(
        ClientConfig(sim="cartpole", rate_hz=0, episodes=1, duration_s=0.2, out=tmp_path / "c")
    )  # the run dir is usable


@pytest.mark.parametrize("signum", ["SIGTERM", "SIGINT"])
def test_a_signal_while_the_run_stops_ends_it_as_that_signal_with_the_journal_closed(
    tmp_path, monkeypatch, signum
):
    """A second Ctrl-C, or a supervisor's SIGTERM while the servers are silent, arrived while the
    client waited for acks: stopping was cut short, the journal stayed open and the process hung."""
    import os
    import signal
    import time

    from wfnn_client.brain import LocalBrain
    from wfnn_io import logs, segments
    from wfnn_io.cli_errors import Terminated

    real_stop = LocalBrain.stop

    def stop_under_a_signal(self):
        os.kill(os.getpid(), getattr(signal, signum))
        time.sleep(0.05)  # the handler runs here
        real_stop(self)

    monkeypatch.setattr(LocalBrain, "stop", stop_under_a_signal)
    out = tmp_path / "run"
    # Python's own SIGINT handler, as in a terminal: a test run started in the background (&)
    # inherits SIGINT ignored, which the run rightly leaves ignored.
    inherited = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(Terminated if signum == "SIGTERM" else KeyboardInterrupt):
            run(ClientConfig(sim="boat", rate_hz=0, episodes=1, out=out))
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # handlers as they were
    finally:
        signal.signal(signal.SIGINT, inherited)
    segments.check_free(out / "journal")  # closed: no writer holds it
    assert logs.summarise(out / "journal").experiences > 0


def test_an_ignored_sigint_stays_ignored_while_the_run_stops(tmp_path, monkeypatch):
    """A job started with & inherits SIGINT ignored: noting it while stopping ended the run as 130."""
    import os
    import signal
    import time

    from wfnn_client.brain import LocalBrain

    real_stop = LocalBrain.stop

    def stop_under_sigint(self):
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
        real_stop(self)

    monkeypatch.setattr(LocalBrain, "stop", stop_under_sigint)
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        metrics = run(ClientConfig(sim="boat", rate_hz=0, episodes=1, out=tmp_path / "run"))
        assert len(metrics["scores"]) == 1 and (tmp_path / "run" / "metrics.json").exists()
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)


def test_a_local_deep_run_saves_its_training_and_weights_resume_it(tmp_path):
    """A local run's weights.npz held the network only: --weights restarted Adam, the targets
    and the warm-up (counted as done), with no word of it."""
    from wfnn_io.persist import load_checkpoint

    options = '{"deep": {"hidden": [16, 16], "value_hidden": 8, "warmup": 300}, "batch_size": 32}'
    common = {"sim": "boat", "rate_hz": 0, "lockstep": True, "episodes": 1, "learner": "deep",
              "learner_options": options, "thinks_per_action": 1}  # fmt: skip
    run(ClientConfig(**common, out=tmp_path / "a"))  # one episode: 200 actions, within the warm-up
    _, params, _, first = load_checkpoint(tmp_path / "a" / "weights.npz")
    assert int(first["acted"]) == 200 and float(first["adam_step"]) == 200
    run(ClientConfig(**common, weights=tmp_path / "a" / "weights.npz", out=tmp_path / "b"))
    _, _, _, second = load_checkpoint(tmp_path / "b" / "weights.npz")
    assert int(second["acted"]) == 400 and float(second["adam_step"]) == 400
    assert float(second["reward_scale"]) >= float(first["reward_scale"]) > 0
    # Acting on them alone reads the network and leaves the training state be.
    run(ClientConfig(**{**common, "learner_options": options}, weights=tmp_path / "b" / "weights.npz",
                     learn=False, out=tmp_path / "c"))  # fmt: skip
    _, greedy, _, none = load_checkpoint(tmp_path / "c" / "weights.npz")
    assert none == {} and np.array_equal(greedy.flat, load_checkpoint(tmp_path / "b" / "weights.npz")[1].flat)
    assert params.flat.shape == greedy.flat.shape


def test_a_saved_policy_keeps_its_weights_whatever_values_it_sees(tmp_path):
    """Acting on its own weights, its divergence monitor replaced them with random ones after 50
    high values, and the episodes were still recorded as the file's."""
    cfg = learner_config(BoatVec(1), ClientConfig(sim="boat"))
    learner = make_learner(cfg)
    learner.params.b2[:] += 1.0  # greedy values above the divergence threshold (0.5), every tick
    save_weights(tmp_path / "w.npz", cfg, learner.params)
    mix, _ = _controllers(f"weights:{tmp_path / 'w.npz'}")
    x = BoatVec(1).reset(np.random.default_rng(1))[0]
    first = mix.act(f"weights:{tmp_path / 'w.npz'}", x).result.action
    for _ in range(3 * cfg.divergence_patience):
        acted = mix.act(f"weights:{tmp_path / 'w.npz'}", x)
    np.testing.assert_array_equal(acted.result.action, first)


@pytest.mark.parametrize("lockstep", [False, True])
def test_a_run_that_learns_nothing_keeps_and_saves_the_weights_it_was_given(tmp_path, lockstep):
    """Its divergence monitor reset them to random ones, which the run then saved over them."""
    from wfnn_io.persist import load_weights

    cfg = learner_config(BoatVec(1), ClientConfig(sim="boat"))
    learner = make_learner(cfg)
    learner.params.b2[:] += 1.0  # greedy values above the divergence threshold, every tick
    save_weights(tmp_path / "w.npz", cfg, learner.params)
    metrics = run(ClientConfig(sim="boat", episodes=3, rate_hz=0, learn=False, lockstep=lockstep,
                               weights=tmp_path / "w.npz", out=tmp_path / "run"))  # fmt: skip
    assert metrics["experiences_learned"] == 0
    _, saved, _ = load_weights(tmp_path / "run" / "weights.npz")
    np.testing.assert_array_equal(np.asarray(saved.flat), np.asarray(learner.params.flat))


def _hashes(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_an_evaluation_never_replaces_what_a_learning_run_saved(tmp_path):
    """`--no-learn --weights RUN/weights.npz --out RUN` replaced the run's config.json, metrics and
    curve, and rewrote its weights without the training state saved beside them (a deep learner's
    second critic, targets and optimiser: 1.1 MB became 0.2 MB)."""
    options = '{"deep": {"warmup": 20}}'
    trained = tmp_path / "trained"
    run(ClientConfig(sim="boat", episodes=1, rate_hz=0, learner="deep", learner_options=options, out=trained))
    before = _hashes(trained)
    evaluation = dict(sim="boat", episodes=1, rate_hz=0, learn=False, learner="deep", learner_options=options)
    with pytest.raises(ValueError, match="holds the outputs of a run that learned"):
        run(ClientConfig(**evaluation, weights=trained / "weights.npz", out=trained))
    assert _hashes(trained) == before
    # The weights alone in a folder of their own: the evaluation's outputs go beside them, and the
    # file it was given is kept as it was, training state and all.
    alone = tmp_path / "alone"
    alone.mkdir()
    (alone / "weights.npz").write_bytes(before["weights.npz"])
    run(ClientConfig(**evaluation, weights=alone / "weights.npz", out=alone))
    assert (alone / "weights.npz").read_bytes() == before["weights.npz"]
    assert (alone / "metrics.json").exists()
    # An evaluation's own folder is an evaluation's to replace.
    run(ClientConfig(**evaluation, weights=alone / "weights.npz", out=alone))
    assert (alone / "weights.npz").read_bytes() == before["weights.npz"]
