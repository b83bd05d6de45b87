"""The action-value surface of one state: Q(x, u) over one or two action variables (Figs 3.5, 3.14, 4.1).

The thesis judged convergence by looking at these: the wires (action, value) the network output
for a state, and the wire-fitted Q between them. Pure numpy, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from wfnn_common import deep_net
from wfnn_common.config import LearnerConfig
from wfnn_common.deep_net import DeepParams
from wfnn_common.kernels import surface_q
from wfnn_common.network import Params, Scaler, split_wires

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


class SurfaceGrid:
    """Q(x, u) over `points` values of each action variable in `dims`, for any state and weights.

    The grid, the scalers and the work arrays are made once, and each surface is one compiled
    call (`kernels.surface_q`): a live view draws it several times a second.
    """

    def __init__(self, config: LearnerConfig, dims: tuple[int, ...] = (0,), points: int = 41) -> None:
        if (
            not 1 <= len(dims) <= 2
            or len(set(dims)) != len(dims)
            or not all(0 <= d < config.action_dim for d in dims)
        ):
            raise ValueError(
                f"dims must be one or two distinct action indices < {config.action_dim}, got {dims}"
            )
        self.config, self.dims = config, tuple(dims)
        self.states = Scaler(config.state_low, config.state_high)
        self.actions = Scaler(config.action_low, config.action_high)
        self.limit = config.sanity_limit
        grid = np.linspace(-1.0, 1.0, points)
        mesh = np.meshgrid(*([grid] * len(dims)), indexing="xy")
        self.shape = mesh[0].shape
        self.grid_u = np.zeros((mesh[0].size, config.action_dim))
        self.on_axis = np.zeros(config.action_dim, dtype=np.bool_)
        for k, d in enumerate(dims):
            self.grid_u[:, d] = mesh[k].ravel()
            self.on_axis[d] = True
        self.axes = tuple(grid * self.actions.half[d] + self.actions.mid[d] for d in dims)
        self._x = np.empty(config.state_dim)
        self._hidden = np.empty(config.n_hidden)
        self._out = np.empty(config.n_outputs)
        self._q = np.empty(self.grid_u.shape[0])

    def __call__(self, params: Params | DeepParams, state: FloatArray) -> Surface:
        """The surface of the first network of `params` at `state` [S], physical units.

        The state is clipped to the sanity limits, as `act` sees it.
        """
        cfg, st = self.config, self.states
        if isinstance(params, DeepParams):
            return self._deep(params, state)
        W1, b1, W2, b2 = params.single
        best = surface_q(W1, b1, W2, b2, np.asarray(state, dtype=np.float64), st.mid, st.half, self.limit,
                         self.grid_u, self.on_axis, cfg.n_wires, cfg.action_dim, cfg.smoothing_c, cfg.eps,
                         self._x, self._hidden, self._out, self._q)  # fmt: skip
        wire_u, wire_q = split_wires(self._out, cfg.n_wires, cfg.action_dim)
        wires = self.actions.from_unit(wire_u)
        return Surface(
            self.dims, self.axes, self._q.reshape(self.shape).copy(), wires, wire_q.copy(), int(best)
        )

    def _deep(self, params: DeepParams, state: FloatArray) -> Surface:
        """The deep learner's surface: its wires and their interpolation (numpy)."""
        cfg = self.config
        x = np.clip(np.nan_to_num(self.states.to_unit(np.asarray(state, dtype=np.float64)[None])),
                    -self.limit, self.limit)  # fmt: skip
        wire_u, wire_q = deep_net.wires(params, x)
        best = int(wire_q[0].argmax())
        # Off the surface's axes every point sits at the best wire: that part of each point's
        # squared distance to a wire is one figure per wire, so the work is points x wires x
        # (one or two axes), not x every action variable (1024 wires of 64 actions made one
        # surface of 1681 points 0.9 s and 850 MB).
        off = ((wire_u[0, best] - wire_u[0]) ** 2)[:, ~self.on_axis].sum(axis=-1)  # [N]
        on = self.grid_u[:, self.on_axis]  # [P, len(dims)]
        dist2 = ((on[:, None, :] - wire_u[0][None][..., self.on_axis]) ** 2).sum(axis=-1) + off
        q = deep_net.wirefit_from_distances(dist2, wire_q[0], cfg.smoothing_c, cfg.eps, cfg.deep.top_k)
        wires = self.actions.from_unit(wire_u[0])
        return Surface(self.dims, self.axes, q.reshape(self.shape), wires, wire_q[0].copy(), best)


def action_value_surface(
    config: LearnerConfig,
    params: Params | DeepParams,
    state: FloatArray,
    dims: tuple[int, ...] = (0,),
    points: int = 41,
) -> Surface:
    """Q(state, u) over `points` values of each action variable in `dims` (first network of `params`)."""
    return SurfaceGrid(config, dims, points)(params, state)
