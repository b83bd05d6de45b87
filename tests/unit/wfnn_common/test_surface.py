"""The action-value surface agrees with the learner's own wire fitting."""

import numpy as np
import pytest

from tests.fakes import small_config
from wfnn_common.learners import make_learner
from wfnn_common.surface import SurfaceGrid, action_value_surface


@pytest.mark.parametrize("learner_name", ["thesis", "deep"])
@pytest.mark.parametrize("dims", [(0,), (1,), (0, 1), (1, 0), (2, 0)])
def test_the_surface_is_q_over_the_grid_with_other_actions_at_the_best_wire(dims, learner_name):
    """The deep learner's too, whose surface adds the distance off its axes once per wire."""
    cfg = small_config(action_dim=3, state_dim=3, action_low=(-2.0, 0.0, -1.0), action_high=(2.0, 1.0, 3.0),
                       learner=learner_name, n_wires=6)  # fmt: skip
    learner = make_learner(cfg)
    state = np.array([0.3, -0.7, 0.1])
    surface = action_value_surface(cfg, learner.params, state, dims, points=7)
    best = learner.act(state, explore=False)
    np.testing.assert_allclose(surface.wire_action[surface.best], best.action, atol=1e-9)
    assert surface.wire_value[surface.best] == pytest.approx(float(best.value))
    assert surface.q.shape == (7,) * len(dims)
    for index in np.ndindex(surface.q.shape):
        action = best.action.copy()
        for k, d in enumerate(dims):  # q[j, i]: axes[0][i], axes[1][j]
            action[d] = surface.axes[k][index[::-1][k] if len(dims) == 2 else index[0]]
        assert surface.q[index] == pytest.approx(float(learner.q_value(state, action)), abs=1e-12)
    np.testing.assert_allclose(surface.axes[0][[0, -1]], [cfg.action_low[dims[0]], cfg.action_high[dims[0]]])


def test_the_surface_refuses_impossible_dimensions():
    cfg = small_config(action_dim=1)
    for dims in ((1,), (0, 0), ()):
        with pytest.raises(ValueError, match="dims"):
            SurfaceGrid(cfg, dims)
