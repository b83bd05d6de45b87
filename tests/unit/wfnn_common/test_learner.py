from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from sims.boat import BoatVec
from tests.fakes import random_experiences, small_config
from wfnn_common import replay as replay_module
from wfnn_common.config import ExplorationConfig, LearnerConfig, with_options
from wfnn_common.exploration import Explorer
from wfnn_common.learner import WFNN, DivergenceMonitor
from wfnn_common.learners import make_learner
from wfnn_common.network import forward, split_wires
from wfnn_common.replay import Experiences, ReplayBuffer
from wfnn_io.persist import (
    PersistError,
    load_checkpoint,
    load_experiences,
    load_weights,
    save_experiences,
    save_weights,
)


def test_act_is_the_best_wire_in_physical_units():
    cfg = small_config(
        state_low=(0.0, 0.0, 0.0),
        state_high=(10.0, 10.0, 10.0),
        action_low=(-2.0, 0.0),
        action_high=(2.0, 1.0),
    )
    for pop in (1, 4):
        learner = WFNN(cfg, population=pop)
        s = np.random.default_rng(0).uniform(0, 10, (pop, 3))
        res = learner.act(s if pop > 1 else s[0], explore=False)
        x = learner.state_scaler.to_unit(s)
        wu, wq = split_wires(forward(learner.params, x[:, None])[1][:, 0], cfg.n_wires, cfg.action_dim)
        best = wq.argmax(axis=1)
        expected_u = learner.action_scaler.from_unit(wu[np.arange(pop), best])
        expected_q = wq[np.arange(pop), best]
        np.testing.assert_allclose(np.reshape(res.action, (pop, 2)), expected_u)
        np.testing.assert_allclose(np.reshape(res.value, pop), expected_q)
        assert np.all(res.valid) and not np.any(res.explored)


def test_q_value_interpolates_and_peaks_at_the_chosen_action():
    learner = WFNN(small_config())
    x = np.array([0.2, -0.4, 0.1])
    res = learner.act(x, explore=False)
    q_best = learner.q_value(x, res.action)
    assert q_best <= res.value + 1e-12 and q_best == pytest.approx(res.value, abs=2e-2)
    others = np.random.default_rng(0).uniform(-1, 1, (50, 2))
    assert all(learner.q_value(x, u) <= q_best + 1e-9 for u in others)


def test_invalid_states_are_acted_on_but_never_learned():
    cfg = small_config(valid_margin=0.5)
    learner = WFNN(cfg)
    good = np.array([0.1, -0.2, 0.3])
    assert learner.act(good).valid
    for bad in (np.array([np.nan, 0.0, 0.0]), np.array([0.0, np.inf, 0.0]), np.array([0.0, 0.0, 2.5])):
        res = learner.act(bad, explore=False)
        assert not res.valid and np.all(np.isfinite(res.action))
        assert not learner.learn(bad, [0, 0], good, -0.1)
        assert not learner.learn(good, [0, 0], bad, -0.1)
    assert learner.learn(good, [0, 0], good, -0.1)
    assert not learner.learn(good, [np.nan, 0], good, -0.1)
    assert not learner.learn(good, [0, 0], good, np.nan)
    # A terminal experience needs no valid next state.
    assert learner.learn(good, [0, 0], np.full(3, np.nan), -1.0, terminal=True)
    # Irrelevant transitions (valid=False) are not stored and not counted as rejected.
    assert not learner.learn(good, [0, 0], good, -0.1, valid=False)
    assert learner.buffer.count[0] == 2
    assert learner.rejected[0] == 8
    # The best estimate of a non-finite reading is the last valid value.
    a_bad = learner.act(np.array([np.nan, -0.2, 0.3]), explore=False).action
    np.testing.assert_allclose(a_bad, learner.act(np.array([0.1, -0.2, 0.3]), explore=False).action)


@pytest.mark.parametrize("learner", ["thesis", "deep"])
def test_states_on_their_declared_bounds_are_valid_with_no_margin(learner):
    """Scaling rounds a bound to 1 plus a few ulps, more where the range lies far off centre
    (its midpoint's rounding, relative to the half-width): with valid_margin 0 that was refused."""
    ranges = [(-4.604265724722594, -2.0594087286058795), (5.27, 5.44), (-84.4, -79.8),
              (132638.20679028725, 132638.20679070702)]  # fmt: skip
    for lo, hi in ranges:
        cfg = small_config(1, 1, learner=learner, state_low=(lo,), state_high=(hi,), valid_margin=0.0)
        model = make_learner(cfg)
        for s in (lo, hi):
            assert model.act(np.array([s]), explore=False).valid and model.learn([s], [0.0], [s], -1.0)
        outside = hi + 1e-3 * (hi - lo)
        assert not model.act(np.array([outside]), explore=False).valid
        assert not model.learn([outside], [0.0], [hi], -1.0)


@pytest.mark.parametrize("learner", ["thesis", "deep"])
def test_a_state_of_the_wrong_shape_is_a_clear_error(learner):
    model = make_learner(small_config(state_dim=1, action_dim=1, learner=learner))
    for state in (0.5, np.float32(0.5), np.array(0.5), np.zeros(2), np.zeros((2, 1))):
        with pytest.raises(ValueError, match="expected state shape"):
            model.act(state)


def test_actions_outside_the_range_are_learned_clipped():
    learner = WFNN(small_config())
    learner.learn(np.zeros(3), [5.0, -5.0], np.zeros(3), -0.1)
    np.testing.assert_allclose(learner.buffer.action[0, 0], [1.0, -1.0])


def test_divergence_monitor_needs_a_persistent_run():
    mon = DivergenceMonitor(2, threshold=0.5, patience=3)
    seq = [[0.6, 0.6], [0.6, 0.1], [0.6, 0.6], [0.6, 0.6]]
    fired = [mon.observe(np.array(v)).tolist() for v in seq]
    assert fired == [[False, False], [False, False], [True, False], [False, False]]


def test_a_non_finite_value_is_divergence_at_once():
    mon = DivergenceMonitor(3, threshold=0.5, patience=50)
    assert mon.observe(np.array([np.nan, 0.1, np.inf])).tolist() == [True, False, True]
    assert mon.observe(np.array([np.nan, 0.1, 0.1]), np.array([False, True, True])).tolist() == [False] * 3
    assert not DivergenceMonitor(1, threshold=0.5, patience=0).observe(np.array([np.nan])).any()  # disabled


def test_a_sequence_of_values_observed_in_one_pass_is_judged_as_one_by_one():
    """The server observes a batch's values in one pass (a call per value cost most of a batch)."""
    rng = np.random.default_rng(0)
    pool = np.array([0.1, 0.4, 0.6, 0.9, np.nan, np.inf, -np.inf])
    for trial in range(400):
        patience = int(rng.integers(0, 6))
        one, many = (DivergenceMonitor(1, threshold=0.5, patience=patience) for _ in range(2))
        start = int(rng.integers(0, 4))
        one.run[0] = many.run[0] = start
        values = rng.choice(pool, size=int(rng.integers(0, 12)), p=[0.2, 0.2, 0.25, 0.25, 0.04, 0.03, 0.03])
        expected = -1
        for i, v in enumerate(values):
            if one.observe(np.array([v]))[0]:
                expected = i
                break
        assert many.first_diverged(values) == expected, (trial, patience, start, values)
        assert many.run[0] == one.run[0], (trial, patience, start, values)


@pytest.mark.parametrize("learner", ["thesis", "deep"])
def test_a_reward_too_large_for_float32_training_is_refused(learner):
    cfg = small_config(state_dim=1, action_dim=1, learner=learner)
    model = make_learner(cfg)
    stored = [
        bool(model.learn(np.zeros(1), np.zeros(1), np.zeros(1), r)) for r in (1e30, 2e38, 1e39, -1e39, np.nan)
    ]
    assert stored == [True, False, False, False, False] and int(model.rejected[0]) == 4


def test_the_deep_learner_stays_finite_on_the_largest_rewards_it_takes():
    """Rewards of 2e38 (below float32's largest) were taken: the gradient 2(q - y) overflowed, the
    weights turned NaN and the divergence monitor reset them at every act, for good."""
    from wfnn_common.config import DeepConfig
    from wfnn_common.learner import MAX_REWARD

    cfg = small_config(state_dim=2, action_dim=1, learner="deep", batch_size=16, gamma=0.99,
                       squash_reward=False, divergence_threshold=1e4,
                       deep=DeepConfig(hidden=(16,), value_hidden=8, warmup=10), n_wires=3)  # fmt: skip
    model = make_learner(cfg)
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, 2)
    for _ in range(120):
        a = model.act(x).action
        x_next = rng.uniform(-1, 1, 2)
        model.learn(x, a, x_next, MAX_REWARD * rng.uniform(-1, 1))
        model.think(1)
        x = x_next
    assert np.isfinite(model.params.flat).all() and int(model.resets[0]) == 0


def test_divergence_resets_weights_and_keeps_experiences():
    cfg = small_config(divergence_threshold=-2.0, divergence_patience=5)  # any value counts as "high"
    learner = WFNN(cfg, population=2)
    rng = np.random.default_rng(1)
    exp = random_experiences(rng, 50, 3, 2)
    learner.buffer.extend(0, exp)
    before = learner.params.flat.copy()
    for _ in range(4):
        learner.act(np.zeros((2, 3)), explore=False)
    assert learner.resets.sum() == 0
    res = learner.act(np.zeros((2, 3)), explore=False)
    assert res.diverged.all() and learner.resets.tolist() == [1, 1]
    assert not np.allclose(learner.params.flat, before)
    assert learner.buffer.count[0] == 50
    learner.think(10)  # learning goes on from the kept experiences


def test_exploration_strategies():
    rng = np.random.default_rng(0)
    greedy = np.zeros((20000, 2))
    uniform = Explorer(ExplorationConfig(kind="uniform", p=0.1), 20000, 2, rng)(greedy)
    changed = np.any(uniform != 0, axis=1)
    assert 0.09 < changed.mean() < 0.11 and np.abs(uniform).max() <= 1
    gauss = Explorer(ExplorationConfig(kind="gaussian", sigma=0.1), 20000, 2, rng)(greedy)
    assert 0.095 < gauss.std() < 0.105
    smooth = Explorer(ExplorationConfig(kind="smooth", sigma=0.2, tau_steps=20.0), 500, 1, rng)
    trace = np.array([smooth(np.zeros((500, 1)))[:, 0] for _ in range(300)])
    steps = np.diff(trace, axis=0)
    assert steps.std() < 0.5 * trace[100:].std()  # consecutive actions close: smooth
    assert 0.15 < trace[100:].std() < 0.25
    assert np.array_equal(Explorer(ExplorationConfig(kind="none"), 3, 2, rng)(greedy[:3]), greedy[:3])


def test_pink_exploration_has_deviation_sigma_from_the_first_action_and_power_falling_as_one_over_f():
    """Eberhard et al.'s pink noise: its power spectrum's log-log slope is -1 between periods of
    a few actions and tau_steps (white noise's is 0, the smooth noise's -2 above its corner)."""
    from wfnn_common.exploration import pink_taus

    assert pink_taus(1.0).tolist() == [1.0] and pink_taus(4.0).tolist() == [1.0, 4.0]
    taus = pink_taus(1000.0)
    assert taus[0] == 1.0 and taus[-1] == pytest.approx(1000.0) and (taus[1:] / taus[:-1] <= 4.0 + 1e-9).all()
    pink_config = ExplorationConfig(kind="pink", sigma=0.1, tau_steps=1000.0)
    pink = Explorer(pink_config, 64, 2, np.random.default_rng(3))
    trace = np.array([pink(np.zeros((64, 2))) for _ in range(4096)])  # [T, P, A]
    assert 0.08 < trace[:10].std() < 0.12 and 0.09 < trace.std() < 0.11  # no ramp up from 0
    segments = trace.reshape(4096, -1).T  # one per learner and action dimension
    power = (np.abs(np.fft.rfft(segments * np.hanning(4096), axis=1)) ** 2).mean(axis=0)
    freq = np.fft.rfftfreq(4096)
    band = (freq > 1 / 1000) & (freq < 1 / 10)
    slope = np.polyfit(np.log(freq[band]), np.log(power[band]), 1)[0]
    assert -1.15 < slope < -0.85
    rows = np.array([True] + [False] * 63)
    before = pink.noise.copy()
    pink.reset(rows)  # drawn anew where asked, where it stands elsewhere
    assert not np.array_equal(pink.noise[0], before[0]) and np.array_equal(pink.noise[1:], before[1:])
    assert 0.0 < np.abs(pink.noise[0]).max() < 0.5
    near_bound = pink(np.full((64, 2), 0.99))
    assert (near_bound <= 1.0).all() and (near_bound < 0.99).any()


def test_replay_buffer_is_a_bounded_ring_per_learner():
    buf = ReplayBuffer(2, 5, 1, 1)
    rng = np.random.default_rng(0)
    exp = random_experiences(rng, 7, 1, 1)
    buf.extend(0, exp)
    assert buf.count.tolist() == [5, 0]
    np.testing.assert_allclose(buf.contents(0).reward, exp.reward[2:])
    idx = buf.sample_indices(rng, 100)
    assert idx[0].max() <= 4 and idx[0].min() >= 0 and np.all(idx[1] == 0)
    one = random_experiences(rng, 2, 1, 1)
    buf.add(one, np.array([False, True]))  # one experience per learner; learner 0 skips
    assert buf.count.tolist() == [5, 1]
    np.testing.assert_allclose(buf.contents(1).reward, one.reward[1:])


def test_replay_links_each_experience_to_its_first_stored_successor_within_bounds(monkeypatch):
    monkeypatch.setattr(replay_module, "OPEN_LINKS", 3)
    buf = ReplayBuffer(1, 8, 1, 1)
    buf.link_successors()

    def one(s, sn, terminal=False):
        buf.extend(0, Experiences(np.array([[s]]), np.zeros((1, 1)), np.array([[sn]]), np.zeros(1),
                                  np.array([terminal])))  # fmt: skip

    one(0.0, 1.0)  # 0
    one(5.0, 6.0, terminal=True)  # 1: terminal, so nothing continues it
    one(6.0, 7.0)  # 2
    one(1.0, 2.0)  # 3 continues 0
    one(1.0, 9.0)  # 4 starts where 0 ended too, but 0 already has its successor
    one(2.0, 3.0)  # 5 continues 3
    one(10.0, 11.0)  # 6: four would wait (2, 4, 5, 6): the oldest, 2, gives up
    one(12.0, 13.0)  # 7: and 4 gives up
    one(7.0, 8.0)  # 8, in slot 0 (overwriting 0, whose link goes): starts where 2 ended, too late
    slots, has = buf.continuation(0, np.arange(8))
    assert has.tolist() == [False, False, False, True, False, False, False, False]
    assert slots[3] == 5
    one(13.0, 14.0)  # 9, in slot 1, continues 7
    slots, has = buf.continuation(0, np.array([7, 1]))
    assert has.tolist() == [True, False] and slots.tolist() == [1, 1]


def test_weights_that_are_not_finite_are_never_saved(tmp_path):
    """Every reader refuses such a file: it is not written, and the one there is kept."""
    cfg = small_config()
    learner = WFNN(cfg)
    save_weights(tmp_path / "w.npz", cfg, learner.params)
    kept = (tmp_path / "w.npz").read_bytes()
    learner.params.flat[0, 5] = np.inf
    with pytest.raises(PersistError, match="not finite"):
        save_weights(tmp_path / "w.npz", cfg, learner.params)
    assert (tmp_path / "w.npz").read_bytes() == kept
    assert sorted(p.name for p in tmp_path.iterdir()) == ["w.npz"]


def test_weights_and_experiences_roundtrip(tmp_path):
    cfg = small_config()
    learner = WFNN(cfg, population=2)
    save_weights(tmp_path / "w.npz", cfg, learner.params, {"note": "x"})
    cfg2, params, meta = load_weights(tmp_path / "w.npz")
    assert cfg2 == cfg and meta == {"note": "x"}
    np.testing.assert_array_equal(params.flat, learner.params.flat)
    exp = random_experiences(np.random.default_rng(0), 9, 3, 2)
    save_experiences(tmp_path / "e.npz", cfg, exp)
    back = load_experiences(tmp_path / "e.npz", cfg)
    for a, b in zip(exp, back, strict=True):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(PersistError, match="spec"):
        load_experiences(tmp_path / "e.npz", small_config(n_hidden=9))
    with pytest.raises(PersistError, match="format"):
        load_weights(tmp_path / "e.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(PersistError):
        load_weights(tmp_path / "junk.npz")
    assert not list(tmp_path.glob("*.tmp"))


@pytest.mark.parametrize(("learner", "population"), [("thesis", 1), ("thesis", 3), ("deep", 1)])
def test_explored_actions_never_leave_a_narrow_offset_range(learner, population):
    """Mapped back from [-1, 1], a clipped action rounded one float step past 0.9."""
    from wfnn_common.config import ExplorationConfig, with_options
    from wfnn_common.learners import make_learner

    cfg = with_options(small_config(state_dim=1, action_dim=1, learner=learner),
                       {"action_low": [0.7], "action_high": [0.9]})  # fmt: skip
    cfg = with_options(cfg, {"exploration": ExplorationConfig(kind="gaussian", sigma=1.0).__dict__})
    agent = make_learner(cfg) if population == 1 else WFNN(cfg, population=population)
    states = np.zeros(1) if population == 1 else np.zeros((population, 1))
    actions = np.array([agent.act(states).action for _ in range(400)])
    assert (actions >= 0.7).all() and (actions <= 0.9).all()
    assert (actions == 0.9).any() and (actions == 0.7).any()  # the bounds themselves are reached


def test_weights_whose_params_or_format_version_are_damaged_are_refused_naming_the_file(tmp_path):
    cfg = small_config()
    save_weights(tmp_path / "w.npz", cfg, WFNN(cfg).params)
    with np.load(tmp_path / "w.npz") as npz:
        arrays = {k: npz[k] for k in npz.files}
    for name, value in (("params", arrays["params"].astype(np.complex128) + 1j), ("params", np.str_("x")),
                        ("format_version", np.float64(np.inf)), ("format_version", np.array([1, 1])),
                        ("format_version", np.str_("one"))):  # fmt: skip
        with open(tmp_path / "bad.npz", "wb") as f:
            np.savez(f, **{**arrays, name: value})
        with pytest.raises(PersistError, match=r"bad\.npz"):
            load_weights(tmp_path / "bad.npz")


def test_an_archive_whose_members_would_unpack_to_far_more_than_they_hold_is_refused_unread(tmp_path):
    """A 100 KB file that inflates to 80 MiB (or gigabytes) is no file this project wrote; a small
    member it does not know, listed in its manifest (a later version's), is left unread, and one
    added after it was written is damage."""
    import zipfile

    from wfnn_io.persist import MANIFEST, MAX_INFLATION_BYTES, atomic_savez

    cfg = small_config()
    learner = WFNN(cfg)
    save_weights(tmp_path / "w.npz", cfg, learner.params)
    with np.load(tmp_path / "w.npz") as npz:
        members = {name: npz[name] for name in npz.files if name != MANIFEST}
    atomic_savez(tmp_path / "w.npz", {**members, "notes": np.str_("never unpacked")})
    assert np.array_equal(load_weights(tmp_path / "w.npz")[1].flat, learner.params.flat)
    with zipfile.ZipFile(tmp_path / "w.npz", "a") as archive:
        archive.writestr("added.npy", b"not an array")
    with pytest.raises(PersistError, match="not listed: added"):
        load_weights(tmp_path / "w.npz")
    with zipfile.ZipFile(tmp_path / "w.npz", "a", compression=zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("train/bomb.npy", bytes(MAX_INFLATION_BYTES + (16 << 20)))
    assert (tmp_path / "w.npz").stat().st_size < 1 << 20
    with pytest.raises(PersistError, match="would unpack"):
        load_weights(tmp_path / "w.npz")


def test_members_that_each_inflate_a_little_are_refused_together_and_weights_skip_the_training_state(
    tmp_path, monkeypatch
):
    """57 listed members each just under the per-member limit made a 3.7 MB weights file take
    4 GB; and loading weights unpacked the training state, only to drop it."""
    import zipfile

    from wfnn_io import persist
    from wfnn_io.persist import MANIFEST, atomic_savez

    cfg = small_config()
    learner = WFNN(cfg)
    save_weights(tmp_path / "w.npz", cfg, learner.params, training={"extra": np.zeros(3)})
    monkeypatch.setattr(persist, "MAX_INFLATION_BYTES", 1 << 20)  # the same rule, at a test's size
    unpacked = []
    real = persist.np.load

    class Recorded:  # np.load's archive, noting each member unpacked
        def __init__(self, data):
            self.data = data

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.data.close()

        def __getitem__(self, name):
            unpacked.append(name)
            return self.data[name]

    def load(f, **kwargs):
        return Recorded(real(f, **kwargs))

    monkeypatch.setattr(persist.np, "load", load)
    assert np.array_equal(load_weights(tmp_path / "w.npz")[1].flat, learner.params.flat)
    assert "train/extra" not in unpacked and "params" in unpacked
    monkeypatch.setattr(persist.np, "load", real)
    with np.load(tmp_path / "w.npz") as npz:
        members = {name: npz[name] for name in npz.files if name != MANIFEST}
    names = [f"train/x{i}" for i in range(4)]
    atomic_savez(tmp_path / "w.npz", {**members, **{n: np.zeros(1) for n in names}})
    with zipfile.ZipFile(tmp_path / "w.npz") as archive:
        kept = {i.filename: archive.read(i) for i in archive.infolist() if i.filename[:-4] not in names}
    with zipfile.ZipFile(tmp_path / "w.npz", "w") as archive:
        for name, data in kept.items():
            archive.writestr(name, data)
        for name in names:  # each inflates by 0.3 MiB, under the limit alone: 1.2 MiB together
            archive.writestr(name + ".npy", bytes(300 << 10), compress_type=zipfile.ZIP_DEFLATED)
    with pytest.raises(PersistError, match="would unpack"):
        load_weights(tmp_path / "w.npz")


def test_a_member_that_declares_a_huge_stored_size_lifts_no_limit(tmp_path, monkeypatch):
    """The allowance was the members' declared sizes: one member never unpacked that declared
    4 GB stored let a 0.6 MB file unpack 600 MB."""
    import struct
    import zipfile

    from wfnn_io import persist
    from wfnn_io.persist import MANIFEST, atomic_savez

    cfg = small_config()
    save_weights(tmp_path / "w.npz", cfg, WFNN(cfg).params)
    with np.load(tmp_path / "w.npz") as npz:
        members = {name: npz[name] for name in npz.files if name != MANIFEST}
    atomic_savez(tmp_path / "w.npz", {**members, "train/big": np.zeros(1), "train/pad": np.zeros(1)})
    with zipfile.ZipFile(tmp_path / "w.npz") as archive:
        kept = {i.filename: archive.read(i) for i in archive.infolist()}
    with zipfile.ZipFile(tmp_path / "w.npz", "w") as archive:
        for name, data in kept.items():
            if name == "train/big.npy":  # inflates by 2 MiB
                archive.writestr(name, data[:128] + bytes(2 << 20), compress_type=zipfile.ZIP_DEFLATED)
            else:
                archive.writestr(name, data)
    raw = bytearray((tmp_path / "w.npz").read_bytes())
    at = raw.rfind(b"train/pad.npy")  # its entry in the central directory, which zipfile believes
    assert raw[at - 46 : at - 42] == b"PK\x01\x02"
    struct.pack_into("<I", raw, at - 46 + 20, 0xF0000000)  # declares 3.75 GiB stored
    (tmp_path / "w.npz").write_bytes(bytes(raw))
    monkeypatch.setattr(persist, "MAX_INFLATION_BYTES", 1 << 20)
    with pytest.raises(PersistError, match="would unpack"):
        load_checkpoint(tmp_path / "w.npz")


@pytest.mark.slow
def test_learns_a_one_step_task_to_the_best_action():
    """Terminal experiences, reward -(u - 0.5 x)^2: the best wire must move to u = 0.5 x."""
    cfg = small_config(
        state_dim=1,
        action_dim=1,
        advantage_k=1.0,
        thinks_per_action=20,
        squash_reward=False,
        n_hidden=10,
        n_wires=9,
        replay_capacity=5000,
        seed=1,
    )
    learner = WFNN(cfg, population=4)
    rng = np.random.default_rng(0)
    for _ in range(3000):
        x, u = rng.uniform(-1, 1, (4, 1)), rng.uniform(-1, 1, (4, 1))
        learner.learn(x, u, x, -((u - 0.5 * x) ** 2)[:, 0], True)
        learner.think()
    for xv in (-0.8, 0.0, 0.8):
        a = learner.act(np.full((4, 1), xv), explore=False).action[:, 0]
        assert np.median(np.abs(a - 0.5 * xv)) < 0.15


def test_invalid_states_neither_extend_nor_end_a_run_of_high_values():
    mon = DivergenceMonitor(1, threshold=0.5, patience=3)
    valid, invalid = np.array([True]), np.array([False])
    assert not mon.observe(np.array([0.9]), valid)[0]
    assert not mon.observe(np.array([0.1]), invalid)[0]  # a best-estimate state: skipped
    assert not mon.observe(np.array([0.9]), valid)[0]
    assert mon.observe(np.array([0.9]), valid)[0]
    # The single-learner path of act agrees.
    cfg = small_config(divergence_threshold=-2.0, divergence_patience=3)
    learner = WFNN(cfg)
    learner.act(np.zeros(3), explore=False)
    learner.act(np.full(3, np.nan), explore=False)  # invalid: skipped
    learner.act(np.zeros(3), explore=False)
    assert learner.resets[0] == 0
    assert learner.act(np.zeros(3), explore=False).diverged and learner.resets[0] == 1


def test_a_population_of_one_thinks_exactly_as_the_population_kernel_does():
    from wfnn_common.kernels import think_incremental, think_incremental_one

    cfg = LearnerConfig.for_task(BoatVec, thinks_per_action=50, seed=3)
    learner = WFNN(cfg)
    rng = np.random.default_rng(0)
    for _ in range(300):
        learner.learn(rng.uniform(-1, 1, 7), rng.uniform(-1, 1, 2), rng.uniform(-1, 1, 7), rng.normal())
    exp, idx = learner.buffer.arrays(), learner.buffer.sample_indices(rng, 200)
    results = []
    for kernel in (think_incremental, think_incremental_one):
        p = learner.params.copy()
        q, td = kernel(p.W1, p.b1, p.W2, p.b2, exp.state, exp.action, exp.next_state, exp.reward,
                       exp.terminal, idx, np.ones(1, dtype=np.bool_), learner.hyperparameters)  # fmt: skip
        results.append((p.flat.copy(), q, td))
    np.testing.assert_array_equal(results[0][0], results[1][0])
    assert not np.array_equal(results[0][0], learner.params.flat)  # the weights did change
    np.testing.assert_array_equal(results[0][1], results[1][1])


def test_many_minibatch_thinks_draw_their_indices_in_parts_and_learn_the_same(monkeypatch):
    """All n x batch_size indices were drawn at once: gigabytes for an accepted config."""
    import wfnn_common.learner as learner_module

    cfg = small_config(update="minibatch", batch_size=16)
    exp = random_experiences(np.random.default_rng(4), 50, 3, 2)
    whole, parts = WFNN(cfg), WFNN(cfg)
    for model in (whole, parts):
        model.learn_many(exp.state, exp.action, exp.next_state, exp.reward, exp.terminal)
    drawn = []
    real = learner_module.ReplayBuffer.sample_indices
    monkeypatch.setattr(learner_module.ReplayBuffer, "sample_indices",
                        lambda self, r, n: drawn.append(n) or real(self, r, n))  # fmt: skip
    expected = whole.think(10)
    monkeypatch.setattr(learner_module, "MAX_INDICES", 64)  # 4 updates of 16 at a time
    stats = parts.think(10)
    assert drawn == [160, 64, 64, 32]
    np.testing.assert_array_equal(parts.params.flat, whole.params.flat)
    np.testing.assert_allclose(stats.q, expected.q, rtol=1e-12)
    np.testing.assert_allclose(stats.td_abs, expected.td_abs, rtol=1e-12)


def test_weights_made_for_another_network_are_refused_by_either_learner():
    thesis = small_config()
    wider = replace(thesis, n_wires=thesis.n_wires + 1)
    with pytest.raises(ValueError, match="do not fit this config"):
        make_learner(wider, params=make_learner(thesis).params)
    deep = LearnerConfig.for_task(BoatVec(1), learner="deep")
    narrower = with_options(deep, {"deep": {"hidden": [16]}})
    with pytest.raises(ValueError, match="do not fit this config"):
        make_learner(narrower, params=make_learner(deep).params)
    # The same network under another config's other fields is fine (a server adopting a config).
    make_learner(replace(thesis, gamma=0.5), params=make_learner(thesis).params)
    make_learner(replace(deep, gamma=0.5), params=make_learner(deep).params)


def test_replay_never_links_experiences_whose_states_only_share_a_hash(monkeypatch):
    """Waiting experiences are keyed by a hash of their next state: a collision must not link."""
    monkeypatch.setattr(replay_module, "hash", lambda data: 0, raising=False)  # every state collides
    buf = ReplayBuffer(1, 16, 1, 1)
    buf.link_successors()
    rng = np.random.default_rng(3)
    for k in range(12):  # two chains, a 0 -> 1 -> 2 ... and b 100 -> 101 ..., two steps at a time
        s = float((k // 4) * 2 + k % 2 + (100 if (k // 2) % 2 else 0))
        action, reward, terminal = rng.uniform(size=(1, 1)), np.zeros(1), np.array([False])
        buf.extend(0, Experiences(np.array([[s]]), action, np.array([[s + 1]]), reward, terminal))
    slots, has = buf.continuation(0, np.arange(12))
    assert has.any()  # where the newest waiting one is the right one, it is linked
    for slot in np.flatnonzero(has):
        assert buf.state[0, slots[slot], 0] == buf.next_state[0, slot, 0]


def test_replay_links_experiences_given_in_float32_as_it_stores_them():
    """The ring holds float64; states given in float32 are compared as stored, not as given."""
    buf = ReplayBuffer(1, 8, 1, 1)
    buf.link_successors()
    f = np.float32
    for s in (0.1, 0.2):
        buf.extend(0, Experiences(np.array([[s]], f), np.zeros((1, 1), f), np.array([[s + f(0.1)]], f),
                                  np.zeros(1, f), np.array([False])))  # fmt: skip
    slots, has = buf.continuation(0, np.array([0]))
    assert has.tolist() == [True] and slots.tolist() == [1]


@pytest.mark.parametrize("learner", ["thesis", "deep"])
def test_evaluating_leaves_the_learner_as_it_was(learner):
    """A benchmark's greedy evaluations changed training: acting set the last valid state (which
    later invalid states fall back on) and the divergence monitor's run, and acting on the
    learner's own weights could reset them."""
    from wfnn_common.learners import make_population

    cfg = small_config(learner=learner, divergence_threshold=-1e9, divergence_patience=2)
    model = make_population(cfg, 2)
    members = getattr(model, "members", [model])
    last_valid = [m._last_valid.copy() for m in members]
    run = [m.monitor.run.copy() for m in members]
    with model.evaluating() as frozen:
        for x in ([[0.1, 0.2, 0.3], [0.3, 0.2, 0.1]], [[0.5, -0.5, 0.0], [0.0, 0.5, -0.5]]):
            model.act(np.array(x), explore=False, params=frozen)  # every value "diverged"
    for m, lv, r in zip(members, last_valid, run, strict=True):
        np.testing.assert_array_equal(m._last_valid, lv)
        np.testing.assert_array_equal(m.monitor.run, r)
    assert int(np.sum(model.resets)) == 0
    for _ in range(2):  # the same, not evaluating:
        model.act(np.array([[0.1, 0.2, 0.3], [0.3, 0.2, 0.1]]), explore=False)
    assert any((m._last_valid != lv).any() for m, lv in zip(members, last_valid, strict=True))
    assert int(np.sum(model.resets)) > 0  # what evaluating keeps from happening


def _api_config(learner: str, **over) -> LearnerConfig:
    deep = {"learner": "deep"} if learner == "deep" else {}
    ranges = {
        "state_low": (-1.0, -1.0),
        "state_high": (1.0, 1.0),
        "action_low": (-1.0,),
        "action_high": (1.0,),
    }
    return LearnerConfig(**ranges, **deep, **over)


@pytest.mark.parametrize("learner", ["thesis", "deep"])
def test_act_refuses_a_snapshot_of_another_network(learner):
    """act's compiled kernels take their sizes from the weights: another network's were read past
    their ends (an empty action and a value of 3.9e287 from memory outside them)."""
    mine = make_learner(_api_config(learner, n_wires=9))
    for other in (_api_config(learner, n_wires=2), replace(_api_config(learner), state_low=(-1.0,) * 5,
                                                           state_high=(1.0,) * 5)):  # fmt: skip
        with pytest.raises(ValueError, match="another network"):
            mine.act(np.zeros(2), explore=False, params=make_learner(other).snapshot())
    assert mine.act(np.zeros(2), explore=False, params=mine.snapshot()).action.shape == (1,)
    if learner == "thesis":
        population = make_learner(_api_config(learner, n_wires=9), population=3).snapshot()
        with pytest.raises(ValueError, match="population of 3"):
            mine.act(np.zeros(2), explore=False, params=population)


@pytest.mark.parametrize("learner", ["thesis", "deep"])
def test_think_on_refuses_experiences_learn_would_refuse(learner):
    """One NaN reward given to think_on made every weight NaN, and no experience failed with
    numpy's reshape error."""
    lrn = make_learner(_api_config(learner, batch_size=4))
    before = lrn.params.flat.copy()
    exp = Experiences(np.zeros((1, 4, 2)), np.zeros((1, 4, 1)), np.zeros((1, 4, 2)),
                      np.array([[0.0, np.nan, 0.0, 0.0]]), np.zeros((1, 4), dtype=bool))  # fmt: skip
    with pytest.raises(ValueError, match="finite"):
        lrn.think_on(exp)
    empty = Experiences(np.zeros((1, 0, 2)), np.zeros((1, 0, 1)), np.zeros((1, 0, 2)), np.zeros((1, 0)),
                        np.zeros((1, 0), dtype=bool))  # fmt: skip
    with pytest.raises(ValueError, match="T >= 1"):
        lrn.think_on(empty)
    with pytest.raises(ValueError, match="action: expected shape"):
        lrn.think_on(exp._replace(reward=np.zeros((1, 4)), action=np.zeros((1, 4, 3))))
    np.testing.assert_array_equal(lrn.params.flat, before)
    with pytest.raises(ValueError, match="finite"):  # the update computes with it at a terminal too
        lrn.think_on(exp._replace(reward=np.zeros((1, 4)), next_state=np.full((1, 4, 2), np.nan),
                                  terminal=np.ones((1, 4), dtype=bool)))  # fmt: skip
    np.testing.assert_array_equal(lrn.params.flat, before)
    lrn.think_on(exp._replace(reward=np.zeros((1, 4)), terminal=np.ones((1, 4), dtype=bool)))
    assert np.isfinite(lrn.params.flat).all() and int(np.sum(lrn.thinks)) >= 1


@pytest.mark.parametrize("learner", ["thesis", "deep"])
def test_blocks_of_experiences_of_the_wrong_shape_are_refused_not_reshaped(learner):
    """[S, N] states given for [N, S] ones were reshaped into other states and stored."""
    lrn = make_learner(replace(_api_config(learner), state_low=(-1.0,) * 3, state_high=(1.0,) * 3))
    s = np.array([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]])
    with pytest.raises(ValueError, match=r"state: expected shape \[N, 3\], got \[3, 2\]"):
        lrn.learn_many(s.T, np.zeros((2, 1)), s.T, np.zeros(2), np.zeros(2))
    with pytest.raises(ValueError, match=r"action: expected shape \[2, 1\]"):
        lrn.learn_many(s, np.zeros(2), s, np.zeros(2), np.zeros(2))
    with pytest.raises(ValueError, match=r"state: expected shape"):
        lrn.greedy_values(s.T)
    assert int(lrn.buffer.count[0]) == 0
    assert lrn.learn_many(s, np.zeros((2, 1)), s, np.zeros(2), np.zeros(2)).tolist() == [True, True]
    assert lrn.greedy_values(s).shape == (1, 2)


@pytest.mark.parametrize("flag", ["False", "no", np.nan, 0.5, 2])
def test_flags_that_are_not_booleans_are_refused(flag):
    """numpy takes any non-empty text or non-zero number for True: "False" read from a log was
    stored as terminal, its next state dropped."""
    lrn = make_learner(_api_config("thesis"))
    with pytest.raises(ValueError, match="booleans or 0/1"):
        lrn.learn(np.zeros(2), np.zeros(1), np.full(2, 0.5), -1.0, flag)
    with pytest.raises(ValueError, match="booleans or 0/1"):
        lrn.learn(np.zeros(2), np.zeros(1), np.full(2, 0.5), -1.0, False, flag)
    with pytest.raises(ValueError, match="booleans or 0/1"):
        lrn.learn_many(np.zeros((1, 2)), np.zeros((1, 1)), np.zeros((1, 2)), np.zeros(1), [flag])
    assert int(lrn.buffer.count[0]) == 0
    assert lrn.learn(np.zeros(2), np.zeros(1), np.full(2, 0.5), -1.0, 0) and lrn.learn(
        np.zeros(2), np.zeros(1), np.full(2, 0.5), -1.0, np.float32(1.0)
    )


@pytest.mark.parametrize("learner", ["thesis", "deep"])
def test_a_large_block_is_learned_in_pieces_exactly_as_at_once(monkeypatch, learner):
    """A block of 100,000 experiences under hundreds of symmetries was made with all its images
    at once: gigabytes, and a think server stopped by the MemoryError."""
    from wfnn_common import learner as learner_module
    from wfnn_common.symmetry import Symmetry

    flip = Symmetry(
        name="flip", state_index=(1, 0), state_sign=(1.0, -1.0), action_index=(0,), action_sign=(-1.0,)
    )
    rng = np.random.default_rng(3)
    n = 500
    block = (rng.uniform(-1.2, 1.2, (n, 2)), rng.uniform(-1, 1, (n, 1)), rng.uniform(-1.2, 1.2, (n, 2)),
             rng.uniform(-1, 0, n), rng.random(n) < 0.1)  # fmt: skip
    block[3][::7] = np.nan  # refused, in every piece alike
    whole, pieces = (make_learner(_api_config(learner, symmetries=(flip,))) for _ in range(2))
    stored = whole.learn_many(*block)
    monkeypatch.setattr(learner_module, "LEARN_BLOCK_FLOATS", 40)  # pieces of 3 experiences
    assert (pieces.learn_many(*block) == stored).all() and 0 < stored.sum() < n
    for a, b in zip(whole.buffer.contents(0), pieces.buffer.contents(0), strict=True):
        np.testing.assert_array_equal(a, b)
    assert int(whole.rejected.sum()) == int(pieces.rejected.sum())


def test_a_deep_population_takes_its_members_rows_as_given_not_reshaped():
    """[S, P] states for [P, S] ones were reshaped into other states, one per member."""
    from wfnn_common.learners import make_population

    population = make_population(_api_config("deep"), 3)
    rows = np.array([[0.1, 0.2], [0.3, 0.4], [0.5, 0.6]])
    with pytest.raises(ValueError, match=r"state: expected shape \[3, 2\], got \[2, 3\]"):
        population.act(rows.T, explore=False)
    with pytest.raises(ValueError, match=r"action: expected shape \[3, 1\]"):
        population.learn(rows, np.zeros(3), rows, np.zeros(3))
    with pytest.raises(ValueError, match=r"state: expected shape"):
        population.q_value(rows.T, np.zeros((3, 1)))
    with pytest.raises(ValueError, match="population of 2"):
        population.act(rows, explore=False, params=make_population(_api_config("deep"), 2).snapshot())
    assert population.act(rows, explore=False).action.shape == (3, 1)
    assert population.learn(rows, np.zeros((3, 1)), rows, np.zeros(3)).tolist() == [True] * 3


RESUMED = [("thesis", "uniform"), ("deep", "uniform"), ("deep", "pink")]


@pytest.mark.parametrize(("learner", "exploration"), RESUMED)
def test_a_learner_resumed_from_its_training_state_goes_on_as_one_that_never_stopped(
    tmp_path, learner, exploration
):
    """Its random streams (replay sampling, exploration, the deep learner's smoothing noise and
    warm-up) are resumed where they stood: they started again from the seed, and a run stopped
    and resumed (a think server's restart) sampled, explored and learned otherwise."""
    from wfnn_io.persist import load_checkpoint, save_weights

    options: dict[str, Any] = {"deep": {"warmup": 30}} if learner == "deep" else {}
    options["exploration"] = {"kind": exploration, "tau_steps": 50.0}
    cfg = with_options(small_config(learner=learner, thinks_per_action=3, seed=4), options)
    exp = random_experiences(np.random.default_rng(1), 60, 3, 2)
    states = np.random.default_rng(2).uniform(-1, 1, (40, 3))

    def go_on(brain, rows):  # explore and learn (some of the warm-up), then think
        acted = [brain.act(states[i]).action for i in rows]
        for i in rows:
            brain.learn(exp.state[i], exp.action[i], exp.next_state[i], exp.reward[i], exp.terminal[i])
        brain.think(12)
        return np.array(acted)

    first = make_learner(cfg)
    go_on(first, range(20))
    save_weights(tmp_path / "ck.npz", cfg, first.params, {}, training=first.training_state())
    ck_cfg, params, _, training = load_checkpoint(tmp_path / "ck.npz")
    resumed = make_learner(ck_cfg, params=params)
    resumed.load_training_state(training)
    for i in range(20):  # the replay memory, as a server reloads it from its store
        resumed.learn(exp.state[i], exp.action[i], exp.next_state[i], exp.reward[i], exp.terminal[i])
    np.testing.assert_array_equal(go_on(resumed, range(20, 40)), go_on(first, range(20, 40)))
    np.testing.assert_array_equal(resumed.params.flat, first.params.flat)
    if learner == "deep":  # another device type's noise generator: the rest resumed all the same
        moved = make_learner(ck_cfg, params=params)
        moved.load_training_state({**training, "random_noise": np.zeros(16, dtype=np.uint8)})
        for key in ("random_weights", "random_replay", "random_exploration"):
            np.testing.assert_array_equal(moved.random_state()[key], training[key])
    # Resumed with another seed, the learner keeps that seed's own streams.
    reseeded = make_learner(replace(ck_cfg, seed=5), params=params)
    streams = {k: v.copy() for k, v in reseeded.random_state().items()}
    reseeded.load_training_state(training)
    for key in ("random_seed", "random_replay", "random_exploration", "exploration_noise"):
        np.testing.assert_array_equal(reseeded.random_state()[key], streams[key])
    assert int(streams["random_seed"]) == 5 and not np.array_equal(streams["random_replay"],
                                                                   training["random_replay"])  # fmt: skip
    # Damaged or partial random state is refused, and changes nothing.
    resumed = make_learner(ck_cfg, params=params)
    before = {k: v.copy() for k, v in resumed.training_state().items()}
    zeroed = np.zeros(6, dtype=np.uint64)  # state and increment 0: PCG64 then draws 0 for ever
    bad_states = [{**training, "random_replay": training["random_replay"][:5]},
                  {**training, "exploration_noise": np.full_like(training["exploration_noise"], np.nan)},
                  {k: v for k, v in training.items() if k != "random_weights"},
                  {**training, "random_exploration": zeroed}]  # fmt: skip
    if learner == "deep":  # bytes of no generator, and none from a learner that had trained
        bad_states += [{**training, "random_noise": training["random_noise"][:-1]},
                       {k: v for k, v in training.items() if k != "random_noise"}]  # fmt: skip
    for bad in bad_states:
        with pytest.raises(ValueError, match=r"random|noise"):
            resumed.load_training_state(bad)
        for key, value in resumed.training_state().items():
            np.testing.assert_array_equal(value, before[key])
    # Smooth noise no run reaches (1e300 held the actions at their limit for thousands of ticks)
    # restarts from 0, as at an episode's start.
    resumed.load_training_state(
        {**training, "exploration_noise": np.full_like(training["exploration_noise"], 1e300)}
    )
    restarted = resumed.random_state()["exploration_noise"]
    assert (0.0 < np.abs(restarted).max() < 1.0) if exploration == "pink" else not restarted.any()
    # Noise laid out for another exploration (smooth's [P, A], pink's [P, K, A], another K) is
    # a resume with another --exploration: the noise restarts, the rest resumes.
    for other in ("smooth", "pink"):
        again = make_learner(with_options(ck_cfg, {"exploration": {"kind": other, "tau_steps": 400.0}}),
                             params=params)  # fmt: skip
        again.load_training_state(training)
        np.testing.assert_array_equal(again.random_state()["random_replay"], training["random_replay"])
        assert again.random_state()["exploration_noise"].shape == again.explorer.noise.shape
    with pytest.raises(ValueError, match="exploration_noise"):
        resumed.load_training_state({**training, "exploration_noise": np.zeros((2, 3))})
