import numpy as np

from tests.fakes import small_config
from wfnn_common.network import Params, Scaler, Shapes, forward, init_params, layer_rates, split_wires


def test_params_are_views_of_the_flat_array():
    cfg = small_config()
    params = init_params(cfg, 3, np.random.default_rng(0))
    shapes = Shapes.of(cfg)
    assert params.flat.shape == (3, shapes.n_params)
    params.W1[1, 2, 0] = 7.0
    params.b2[2, -1] = -3.0
    assert (params.flat == 7.0).sum() == 1 and (params.flat == -3.0).sum() == 1
    assert params.single[0] is not None and np.shares_memory(params.single[0], params.flat)
    copy = params.copy()
    copy.W2[:] = 0
    assert np.abs(params.W2).sum() > 0


def test_initial_weights_small_and_bounded():
    cfg = small_config(init_scale=1.0)
    params = init_params(cfg, 5, np.random.default_rng(1))
    assert np.abs(params.W1).max() <= 1 / np.sqrt(cfg.state_dim + 1)
    assert np.abs(params.W2).max() <= 1 / np.sqrt(cfg.n_hidden + 1)


def test_forward_matches_per_network_formula_and_outputs_are_tanh_bounded():
    cfg = small_config()
    params = init_params(cfg, 2, np.random.default_rng(2))
    x = np.random.default_rng(3).uniform(-1, 1, (2, 5, cfg.state_dim))
    hidden, out = forward(params, x)
    for p in range(2):
        h = np.tanh(x[p] @ params.W1[p].T + params.b1[p])
        np.testing.assert_allclose(hidden[p], h)
        np.testing.assert_allclose(out[p], np.tanh(h @ params.W2[p].T + params.b2[p]))
    assert np.abs(out).max() < 1
    wire_u, wire_q = split_wires(out, cfg.n_wires, cfg.action_dim)
    assert wire_u.shape == (2, 5, cfg.n_wires, cfg.action_dim) and wire_q.shape == (2, 5, cfg.n_wires)
    single = Params(params.flat[:1].copy(), params.shapes)
    np.testing.assert_allclose(forward(single, x[:1])[1], out[:1])


def test_layer_rates_are_alpha_over_sqrt_fan_in():
    cfg = small_config(alpha=0.5)
    r1, r2 = layer_rates(cfg)
    assert r1 == 0.5 / np.sqrt(cfg.state_dim + 1) and r2 == 0.5 / np.sqrt(cfg.n_hidden + 1)


def test_scaler_maps_declared_range_to_unit():
    s = Scaler((0.0, -10.0), (2.0, 10.0))
    np.testing.assert_allclose(
        s.to_unit(np.array([[0.0, -10.0], [2.0, 10.0], [1.0, 0.0]])), [[-1, -1], [1, 1], [0, 0]]
    )
    v = np.array([0.3, 4.0])
    np.testing.assert_allclose(s.from_unit(s.to_unit(v)), v)
