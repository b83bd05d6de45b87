"""The action-value surface of one state: Q(x, u) over one or two action variables (Figs 3.5, 3.14, 4.1).

The thesis judged convergence by looking at these: the wires (action, value) the network output
for a state, and the wire-fitted Q between them. Pure numpy, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from wfnn_common.config import LearnerConfig
from wfnn_common.network import Params, Scaler, forward, split_wires
from wfnn_common.wirefit import wirefit_q

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Surface:
    """Q over a grid of one or two action variables, the others fixed at the best wire's action.

    Attributes:
        dims: the action variables on the axes (one or two indices).
        axes: grid values of each, physical units ([G] each).
        q: Q on the grid, [G] (one variable) or [G, G] (two: q[j, i] at axes[0][i], axes[1][j]).
        wire_action: every wire's action, physical units [W, A].
        wire_value: every wire's value [W].
        best: index of the best wire (the action `act` would choose without exploration).
    """

    dims: tuple[int, ...]
    axes: tuple[FloatArray, ...]
    q: FloatArray
    wire_action: FloatArray
    wire_value: FloatArray
    best: int


def action_value_surface(
    config: LearnerConfig, params: Params, state: FloatArray, dims: tuple[int, ...] = (0,), points: int = 41
) -> Surface:
    """Q(state, u) over `points` values of each action variable in `dims` (first network of `params`).

    `state` [S] in physical units (clipped to the sanity limits as `act` sees it).
    """
    if (
        not 1 <= len(dims) <= 2
        or len(set(dims)) != len(dims)
        or not all(0 <= d < config.action_dim for d in dims)
    ):
        raise ValueError(f"dims must be one or two distinct action indices < {config.action_dim}, got {dims}")
    x = Scaler(config.state_low, config.state_high).to_unit(np.asarray(state, dtype=np.float64))
    limit = 1.0 + 2.0 * config.valid_margin
    x = np.nan_to_num(np.clip(x, -limit, limit))
    single = Params(params.flat[:1], params.shapes)
    _, out = forward(single, x[None, None, :])
    wire_u, wire_q = split_wires(out[0, 0], config.n_wires, config.action_dim)  # [W, A], [W]
    best = int(np.argmax(wire_q))
    grid = np.linspace(-1.0, 1.0, points)
    mesh = np.meshgrid(*([grid] * len(dims)), indexing="xy")
    u = np.broadcast_to(wire_u[best], (*mesh[0].shape, config.action_dim)).copy()
    for k, d in enumerate(dims):
        u[..., d] = mesh[k]
    q = wirefit_q(wire_u, wire_q, u, config.smoothing_c, config.eps)
    actions = Scaler(config.action_low, config.action_high)
    axes = tuple(grid * actions.half[d] + actions.mid[d] for d in dims)
    return Surface(tuple(dims), axes, q, actions.from_unit(wire_u), wire_q.copy(), best)
