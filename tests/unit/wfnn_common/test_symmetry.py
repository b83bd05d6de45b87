"""Declared symmetries: data in the learner config, applied by every learner to what it learns."""

import json

import numpy as np
import pytest

from sims.boat import MIRROR, BoatVec, mirror
from tests.fakes import Hub, small_config
from tests.unit.wfnn_server.test_server import Listener, batch, make_server, send
from wfnn_client.config import ClientConfig
from wfnn_client.run import learner_config
from wfnn_common.config import ConfigError, LearnerConfig
from wfnn_common.learner import WFNN
from wfnn_common.symmetry import Symmetry

SWAP = Symmetry(name="swap", state_index=(1, 0, 2), state_sign=(1.0, -1.0, 1.0),
                action_index=(1, 0), action_sign=(-1.0, 1.0))  # fmt: skip


def test_a_symmetry_is_a_signed_permutation():
    with pytest.raises(ValueError, match="permutation"):
        Symmetry(name="x", state_index=(0, 0), state_sign=(1.0, 1.0), action_index=(0,), action_sign=(1.0,))
    with pytest.raises(ValueError, match="sign"):
        Symmetry(name="x", state_index=(1, 0), state_sign=(1.0, 0.5), action_index=(0,), action_sign=(1.0,))
    s = np.array([[1.0, 2.0, 3.0]])
    np.testing.assert_array_equal(SWAP.states(s), [[2.0, -1.0, 3.0]])
    np.testing.assert_array_equal(SWAP.actions(np.array([[0.5, 0.25]])), [[-0.25, 0.5]])


@pytest.mark.parametrize("field, value", [
    ("state_index", [0.9, 1.7, 2]), ("state_index", [True, False, 2]), ("state_index", ["1", "0", "2"]),
    ("state_sign", ["-1", 1, 1]), ("state_sign", [True, True, True]), ("action_index", 10),
    ("name", 7), ("state_sign", [10**400, 1, 1]), ("action_sign", [float("nan"), 1.0]),
])  # fmt: skip
def test_a_symmetry_from_json_is_taken_as_written_or_refused(field, value):
    """Entries of the wrong type were converted (index 1.7 became 1, true 1, the sign "-1" -1):
    another symmetry than the one written, or, through the Python API, an error only at learn."""
    data = {"name": "swap", "state_index": [1, 0, 2], "state_sign": [1, -1, 1], "action_index": [1, 0],
            "action_sign": [-1.0, 1.0], field: value}  # fmt: skip
    with pytest.raises(ConfigError, match="not a symmetry"):
        LearnerConfig.from_dict({**small_config().to_dict(), "symmetries": [data]})
    with pytest.raises(ConfigError, match=field.split("_")[-1]) as caught:  # and through the API, at once
        Symmetry(**{**data, field: tuple(value) if isinstance(value, list) else value})
    assert "\n" not in str(caught.value) and len(str(caught.value)) < 400  # one short line


def test_a_symmetrys_whole_numbers_are_kept_as_plain_ints_and_floats():
    taken = Symmetry(name="swap", state_index=(np.int64(1), 0, 2), state_sign=(1, -1, np.float32(1.0)),
                     action_index=[1, 0], action_sign=(-1.0, 1.0))  # fmt: skip
    assert taken == SWAP.__class__(name="swap", state_index=(1, 0, 2), state_sign=(1.0, -1.0, 1.0),
                                   action_index=(1, 0), action_sign=(-1.0, 1.0))  # fmt: skip
    assert {type(i) for i in taken.state_index + taken.action_index} == {int}
    assert {type(x) for x in taken.state_sign + taken.action_sign} == {float}


def test_symmetries_travel_in_the_learner_config_and_must_fit_the_task():
    cfg = small_config(symmetries=(SWAP,))
    again = LearnerConfig.from_dict(json.loads(cfg.to_json()))
    assert again.symmetries == (SWAP,) and again == cfg
    assert again.spec_hash() == small_config().spec_hash()  # the same network, the same experiences
    with pytest.raises(ConfigError, match="task has 4"):
        small_config(state_dim=4, symmetries=(SWAP,))
    with pytest.raises(ConfigError, match="not a symmetry"):
        LearnerConfig.from_dict({**cfg.to_dict(), "symmetries": [{"name": "broken"}]})


def test_the_learner_also_learns_the_transformed_experiences():
    cfg = small_config(symmetries=(SWAP,), replay_capacity=100)
    rng = np.random.default_rng(0)
    s, a, sn = rng.uniform(-0.9, 0.9, (5, 3)), rng.uniform(-1, 1, (5, 2)), rng.uniform(-0.9, 0.9, (5, 3))
    r = rng.uniform(-1, 0, 5)
    s[2, 0] = 50.0  # beyond the sanity limits: neither it nor its image is learned
    learner = WFNN(cfg)
    ok = learner.learn_many(s, a, sn, r, np.zeros(5, dtype=np.bool_))
    assert ok.tolist() == [True, True, False, True, True]
    assert learner.buffer.count[0] == 8
    stored = learner.buffer.contents(0)  # each experience followed by its image, as `learn` stores them
    np.testing.assert_allclose(stored.state[0::2], s[ok])
    np.testing.assert_allclose(stored.state[1::2], SWAP.states(s[ok]))
    np.testing.assert_allclose(stored.action[1::2], SWAP.actions(a[ok]))
    np.testing.assert_allclose(stored.next_state[1::2], SWAP.states(sn[ok]))
    np.testing.assert_allclose(stored.reward[1::2], stored.reward[0::2])
    # One experience at a time (learn) stores the pair too; without symmetries only the real one.
    one = WFNN(cfg)
    one.learn(s[0], a[0], sn[0], r[0])
    plain = WFNN(small_config())
    plain.learn(s[0], a[0], sn[0], r[0])
    assert one.buffer.count[0] == 2 and plain.buffer.count[0] == 1
    np.testing.assert_allclose(one.buffer.contents(0).state[1], SWAP.states(s[0]))


def test_the_boat_declares_its_mirror_and_the_client_uses_it_when_asked():
    assert BoatVec.symmetries == (MIRROR,)
    rng = np.random.default_rng(2)
    x, u, xn, r = (
        rng.uniform(-1, 1, (4, 7)),
        rng.uniform(-1, 1, (4, 2)),
        rng.uniform(-1, 1, (4, 7)),
        rng.uniform(-1, 0, 4),
    )
    for got, expected in zip(MIRROR(x, u, xn, r), mirror(x, u, xn, r), strict=True):
        np.testing.assert_array_equal(got, expected)
    boat = BoatVec(1)
    assert learner_config(boat, ClientConfig(sim="boat", symmetries=True)).symmetries == (MIRROR,)
    assert learner_config(boat, ClientConfig(sim="boat")).symmetries == ()
    from sims.cartpole import CartPoleVec

    with pytest.raises(ValueError, match="declares no symmetries"):
        learner_config(CartPoleVec(1), ClientConfig(sim="cartpole", symmetries=True))


def test_a_server_adopting_a_config_with_symmetries_learns_them_and_stores_only_real_experiences(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=2, symmetries=(SWAP,))
    listener = Listener(hub)
    with make_server(tmp_path, hub, cfg) as server:
        send(hub, batch(cfg, 0, 6))
        assert listener.wait(lambda: listener.acked() == 5)
        assert listener.wait(lambda: any(s.learned_through.get("c1") == 5 for s in listener.snapshots))
        assert server.store.count == 6 and server.learner.buffer.count[0] == 12
        snap = next(s for s in listener.snapshots if s.learned_through.get("c1") == 5)
        assert snap.thinks == 12  # thinks are owed per real experience
