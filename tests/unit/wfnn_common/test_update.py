import numpy as np
import pytest

from tests.fakes import random_experiences, small_config
from wfnn_common.learner import WFNN
from wfnn_common.network import Params, forward, init_params, layer_rates, split_wires
from wfnn_common.replay import Experiences
from wfnn_common.update import q_target, squash_reward, wfnn_update
from wfnn_common.wirefit import wirefit_q


def test_squash_eq36_bounds_values():
    raw = np.array([-1e6, -2.0, 0.0, 0.5, 1e6])
    r = squash_reward(raw, 0.8)
    np.testing.assert_allclose(r, 0.2 * np.tanh(raw))
    assert np.all(np.abs(r) <= 0.2)


def test_q_learning_target_is_eq24_and_advantage_is_eq41():
    r, vn, v, term = (
        np.array([-0.1, -0.1]),
        np.array([0.3, 0.3]),
        np.array([0.5, 0.5]),
        np.array([False, True]),
    )
    np.testing.assert_allclose(q_target(r, vn, v, term, 0.8, 1.0), [-0.1 + 0.8 * 0.3, -0.1])
    k = 0.2
    expected = (1 / k) * (r + 0.8 * np.where(term, 0, vn)) + (1 - 1 / k) * v  # Eq 4.1 with alpha = 1
    np.testing.assert_allclose(q_target(r, vn, v, term, 0.8, k), expected)


def _exp_block(rng, cfg, p, t):
    blocks = [random_experiences(rng, t, cfg.state_dim, cfg.action_dim, 0.2) for _ in range(p)]
    return Experiences(*(np.stack(parts) for parts in zip(*blocks, strict=True)))


@pytest.mark.parametrize("derivatives", ["approx", "exact"])
@pytest.mark.parametrize(("advantage_k", "bc_weight"), [(1.0, 0.0), (0.2, 0.0), (0.2, 0.5)])
def test_compiled_incremental_think_equals_numpy_reference(derivatives, advantage_k, bc_weight):
    cfg = small_config(derivatives=derivatives, advantage_k=advantage_k, bc_weight=bc_weight)
    rng = np.random.default_rng(0)
    learner = WFNN(cfg, population=3)
    ref = learner.params.copy()
    exp = _exp_block(rng, cfg, 3, 25)
    learner.think_on(exp)
    for t in range(25):
        one = Experiences(*(a[:, t : t + 1] for a in exp))
        wfnn_update(
            ref,
            learner.rates,
            one.state,
            one.action,
            one.next_state,
            squash_reward(one.reward, cfg.gamma),
            one.terminal,
            n_wires=cfg.n_wires,
            gamma=cfg.gamma,
            advantage_k=advantage_k,
            c=cfg.smoothing_c,
            eps=cfg.eps,
            derivatives=derivatives,
            bc_weight=bc_weight,
        )
    np.testing.assert_allclose(learner.params.flat, ref.flat, atol=1e-12)
    assert np.abs(learner.params.flat - WFNN(cfg, population=3).params.flat).max() > 1e-4  # it moved


@pytest.mark.parametrize("bc_weight", [0.0, 0.3])
def test_torch_minibatch_float64_equals_numpy_reference(bc_weight):
    pytest.importorskip("torch")
    from wfnn_common.torch_update import minibatch_think

    cfg = small_config(derivatives="exact", update="minibatch", batch_size=16)
    rng = np.random.default_rng(1)
    params = init_params(cfg, 2, rng)
    ref = params.copy()
    buf = _exp_block(rng, cfg, 2, 40)
    idx = rng.integers(0, 40, size=(3, 2, 16))
    active = np.array([True, False])
    minibatch_think(
        params,
        layer_rates(cfg),
        buf,
        idx,
        active,
        n_wires=cfg.n_wires,
        gamma=cfg.gamma,
        advantage_k=cfg.advantage_k,
        c=cfg.smoothing_c,
        eps=cfg.eps,
        exact=True,
        squash=True,
        bc_weight=bc_weight,
        dtype="float64",
    )
    rows = np.arange(2)[:, None]
    for batch in idx:
        b = Experiences(*(a[rows, batch] for a in buf))
        wfnn_update(
            ref,
            layer_rates(cfg),
            b.state,
            b.action,
            b.next_state,
            squash_reward(b.reward, cfg.gamma),
            b.terminal,
            n_wires=cfg.n_wires,
            gamma=cfg.gamma,
            advantage_k=cfg.advantage_k,
            c=cfg.smoothing_c,
            eps=cfg.eps,
            derivatives="exact",
            active=active,
            bc_weight=bc_weight,
        )
    np.testing.assert_allclose(params.flat, ref.flat, atol=1e-10)
    np.testing.assert_array_equal(params.flat[1], init_params(cfg, 2, np.random.default_rng(1)).flat[1])


def test_an_update_moves_q_toward_its_target():
    cfg = small_config(advantage_k=1.0, gamma=0.0, squash_reward=False)
    rng = np.random.default_rng(2)
    params = init_params(cfg, 1, rng)
    x = rng.uniform(-1, 1, (1, 1, cfg.state_dim))
    u = rng.uniform(-1, 1, (1, 1, cfg.action_dim))
    target = -0.6

    def q_now(p: Params) -> float:
        wu, wq = split_wires(forward(p, x)[1], cfg.n_wires, cfg.action_dim)
        return float(wirefit_q(wu, wq, u, cfg.smoothing_c, cfg.eps)[0, 0])

    errors = [abs(q_now(params) - target)]
    for _ in range(100):
        wfnn_update(
            params,
            layer_rates(cfg),
            x,
            u,
            x,
            np.array([[target]]),
            np.array([[True]]),
            n_wires=cfg.n_wires,
            gamma=0.0,
            advantage_k=1.0,
            c=cfg.smoothing_c,
            eps=cfg.eps,
            derivatives="approx",
        )
        errors.append(abs(q_now(params) - target))
    assert errors[1] < errors[0]
    assert errors[-1] < 0.1 * errors[0]


def test_the_bc_pull_draws_the_best_wire_to_the_action_taken():
    # With the pull, replaying one experience over and over brings the greedy action to the
    # action the experience took; without it the best wire is wherever the values put it.
    x = np.array([0.3, -0.2, 0.5])
    taken = np.array([0.7])
    gaps = {}
    for bc in (0.0, 0.5):
        learner = WFNN(small_config(action_dim=1, bc_weight=bc, gamma=0.0, seed=4))
        learner.learn(x, taken, x, 0.0, terminal=True)
        start = abs(learner.act(x, explore=False).action[0] - taken[0])
        learner.think(3000)
        gaps[bc] = (start, abs(learner.act(x, explore=False).action[0] - taken[0]))
    assert gaps[0.5][1] < 0.02 < gaps[0.5][0]
    assert gaps[0.0][1] > 0.1
