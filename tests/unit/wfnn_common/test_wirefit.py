import numpy as np
import pytest

from wfnn_common.wirefit import wirefit_grad, wirefit_q

C, EPS = 0.01, 1e-4


def random_wires(rng, batch=(4,), n_wires=5, action_dim=2):
    u = rng.uniform(-1, 1, (*batch, n_wires, action_dim))
    q = rng.uniform(-1, 1, (*batch, n_wires))
    return u, q


def numeric_grad(fn, arr, h=1e-6):
    grad = np.zeros_like(arr)
    it = np.nditer(arr, flags=["multi_index"])
    for _ in it:
        i = it.multi_index
        plus, minus = arr.copy(), arr.copy()
        plus[i] += h
        minus[i] -= h
        grad[i] = (fn(plus) - fn(minus)) / (2 * h)
    return grad


def test_eq31_matches_direct_formula():
    rng = np.random.default_rng(0)
    wu, wq = random_wires(rng, batch=(), n_wires=4, action_dim=3)
    u = rng.uniform(-1, 1, 3)
    dist = ((u - wu) ** 2).sum(axis=1) + C * (wq.max() - wq) + EPS
    expected = (wq / dist).sum() / (1 / dist).sum()
    assert wirefit_q(wu, wq, u, C, EPS) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("action_dim", [1, 2, 4])
def test_derivatives_match_finite_differences_away_from_top_wire(action_dim):
    rng = np.random.default_rng(action_dim)
    for _ in range(20):
        wu, wq = random_wires(rng, batch=(), n_wires=6, action_dim=action_dim)
        u = rng.uniform(-1, 1, action_dim)
        top = int(np.argmax(wq))
        fit = wirefit_grad(wu, wq, u, C, EPS, "approx")
        num_q = numeric_grad(lambda q, wu=wu, u=u: wirefit_q(wu, q, u, C, EPS), wq)
        num_u = numeric_grad(lambda a, wq=wq, u=u: wirefit_q(a, wq, u, C, EPS), wu)
        others = np.arange(6) != top
        np.testing.assert_allclose(fit.dq[others], num_q[others], rtol=1e-5, atol=1e-8)
        # Eq 3.5 does not depend on the max, so it is exact for every wire.
        np.testing.assert_allclose(fit.du, num_u, rtol=1e-5, atol=1e-8)


def test_exact_mode_is_exact_for_the_top_wire_and_approx_is_not():
    rng = np.random.default_rng(3)
    wu, wq = random_wires(rng, batch=(), n_wires=5, action_dim=2)
    u = rng.uniform(-1, 1, 2)
    top = int(np.argmax(wq))
    num_q = numeric_grad(lambda q: wirefit_q(wu, q, u, C, EPS), wq)
    exact = wirefit_grad(wu, wq, u, C, EPS, "exact")
    approx = wirefit_grad(wu, wq, u, C, EPS, "approx")
    np.testing.assert_allclose(exact.dq, num_q, rtol=1e-5, atol=1e-8)
    assert abs(approx.dq[top] - num_q[top]) > 1e-4  # the thesis' noted inexactness
    np.testing.assert_allclose(exact.du, approx.du)


def test_batched_equals_per_item():
    rng = np.random.default_rng(4)
    wu, wq = random_wires(rng, batch=(3, 5), n_wires=4, action_dim=2)
    u = rng.uniform(-1, 1, (3, 5, 2))
    fit = wirefit_grad(wu, wq, u, C, EPS, "exact")
    for i in range(3):
        for j in range(5):
            one = wirefit_grad(wu[i, j], wq[i, j], u[i, j], C, EPS, "exact")
            assert fit.q[i, j] == pytest.approx(float(one.q))
            np.testing.assert_allclose(fit.dq[i, j], one.dq)
            np.testing.assert_allclose(fit.du[i, j], one.du)


def test_maximum_is_the_top_wire_value_at_its_action():
    rng = np.random.default_rng(5)
    for _ in range(10):
        wu, wq = random_wires(rng, batch=(), n_wires=5, action_dim=2)
        top = int(np.argmax(wq))
        grid = np.stack(np.meshgrid(np.linspace(-1.5, 1.5, 151), np.linspace(-1.5, 1.5, 151)), -1)
        candidates = np.concatenate([grid.reshape(-1, 2), wu])
        q = wirefit_q(
            np.broadcast_to(wu, (len(candidates), 5, 2)),
            np.broadcast_to(wq, (len(candidates), 5)),
            candidates,
            C,
            EPS,
        )
        best = int(np.argmax(q))
        np.testing.assert_allclose(candidates[best], wu[top])
        # eps makes the peak a hair below q_top, never above it.
        assert q[best] <= wq[top] + 1e-12
        assert q[best] == pytest.approx(wq[top], abs=1e-2)


def test_far_from_every_wire_q_tends_to_mean_of_q():
    rng = np.random.default_rng(6)
    wu, wq = random_wires(rng, batch=(), n_wires=7, action_dim=3)
    direction = rng.normal(size=3)
    errors = [abs(wirefit_q(wu, wq, r * direction, C, EPS) - wq.mean()) for r in (1e1, 1e3, 1e5, 1e7)]
    assert errors[0] > errors[1] > errors[2] > errors[3]
    assert errors[3] < 1e-6


def test_coincident_wires_and_huge_inputs_are_finite():
    wu = np.zeros((4, 2))
    wq = np.array([0.3, 0.3, -0.2, 0.3])
    for u in (np.zeros(2), np.array([1e30, -1e30]), np.array([1e300, 1e300]), np.array([-1e308, 0.0])):
        for mode in ("approx", "exact"):
            fit = wirefit_grad(wu, wq, u, C, EPS, mode)
            assert np.isfinite(fit.q) and np.isfinite(fit.dq).all() and np.isfinite(fit.du).all()
    huge_q = np.array([1e300, -1e300, 0.0, 5.0])
    fit = wirefit_grad(
        rng_u := np.random.default_rng(0).uniform(-1, 1, (4, 2)), huge_q, np.zeros(2), C, EPS, "exact"
    )
    assert rng_u.shape == (4, 2)
    assert np.isfinite(fit.q) and np.isfinite(fit.dq).all() and np.isfinite(fit.du).all()
    # Coincident wires at the evaluated action: Q is their (equal) value.
    assert wirefit_q(wu, wq, np.zeros(2), C, EPS) == pytest.approx(0.3, abs=5e-3)


def test_zero_smoothing_still_finite_with_eps():
    rng = np.random.default_rng(7)
    wu, wq = random_wires(rng, batch=(), n_wires=3, action_dim=1)
    fit = wirefit_grad(wu, wq, wu[0], 0.0, EPS, "exact")
    assert np.isfinite(fit.dq).all()
