"""One WFNN learning step (thesis Fig 3.8-3.9) in numpy, for a population and a batch.

This is the readable reference of the update and the minibatch mode. The incremental mode's
hot loop (`wfnn_common.kernels`) computes exactly the same numbers one experience at a time.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import numpy as np
from numpy.typing import NDArray

from wfnn_common.network import Params, forward, split_wires
from wfnn_common.wirefit import wirefit_grad

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


def squash_reward(raw: FloatArray, gamma: float) -> FloatArray:
    """Eq 3.6: r = (1 - gamma) tanh(raw), so action-values stay inside tanh's range."""
    return (1.0 - gamma) * np.tanh(raw)


def q_target(
    reward: FloatArray,
    value_next: FloatArray,
    value_now: FloatArray,
    terminal: BoolArray,
    gamma: float,
    advantage_k: float,
) -> FloatArray:
    """New estimate of Q(x_t, u_t) by advantage learning, Eq 4.1 (k = 1: Q-learning, Eq 2.4).

        Q_new = max_u A(x_t, u) + (r + gamma max_u A(x_t+1, u) - max_u A(x_t, u)) / k

    with the next-state term dropped for terminal experiences. All arrays share one shape.
    """
    backed_up = reward + np.where(terminal, 0.0, gamma * value_next)
    return value_now + (backed_up - value_now) / advantage_k


class UpdateStats(NamedTuple):
    """Per-learner means over the experiences of one update: Q(x_t, u_t) before, |Q_new - Q|."""

    q: FloatArray
    td_abs: FloatArray


def wfnn_update(
    params: Params,
    rates: tuple[float, float],
    x: FloatArray,
    u: FloatArray,
    x_next: FloatArray,
    reward: FloatArray,
    terminal: BoolArray,
    *,
    n_wires: int,
    gamma: float,
    advantage_k: float,
    c: float,
    eps: float,
    derivatives: Literal["approx", "exact"],
    active: BoolArray | None = None,
    bc_weight: float = 0.0,
) -> UpdateStats:
    """Move every network's output toward the wire-fitter targets of a batch, in place.

    One gradient step on the batch mean; with B = 1 this is the thesis' incremental rule.

    Args:
        params: P networks, updated in place.
        rates: learning rates of the hidden and output layers.
        x, x_next: scaled states, [P, B, S].
        u: scaled actions taken, [P, B, A].
        reward: squashed rewards, [P, B].
        terminal: [P, B]; no next state is used where True.
        n_wires, gamma, advantage_k, c, eps, derivatives, bc_weight: as in `LearnerConfig`.
        active: [P]; learners where False are left unchanged.

    Returns:
        `UpdateStats` of shape [P].
    """
    action_dim = u.shape[-1]
    batch = x.shape[1]
    # Part 2: the value of the next state is its best wire's value (no wire fitting needed).
    _, out_next = forward(params, x_next)
    value_next = split_wires(out_next, n_wires, action_dim)[1].max(axis=-1)
    # Part 3: current wires, interpolated Q of the action taken, and its derivatives.
    hidden, out = forward(params, x)
    wire_u, wire_q = split_wires(out, n_wires, action_dim)
    fit = wirefit_grad(wire_u, wire_q, u, c, eps, derivatives)
    target = q_target(reward, value_next, wire_q.max(axis=-1), terminal, gamma, advantage_k)
    delta_q = target - fit.q  # [P, B]
    # Eq 3.2-3.3: the change in each wire, which becomes the network's output error.
    err_u = fit.du * delta_q[..., None, None]  # [P, B, W, A]
    if bc_weight:  # the best wire's action is also pulled toward the action taken
        best = np.arange(n_wires) == np.argmax(wire_q, axis=-1)[..., None]  # [P, B, W] one-hot
        best_u = np.einsum("pbw,pbwa->pba", best, wire_u)
        err_u = err_u + bc_weight * best[..., None] * (u - best_u)[..., None, :]
    err = np.concatenate([err_u.reshape(*delta_q.shape, -1), fit.dq * delta_q[..., None]], axis=-1)
    if active is not None:
        err = err * active[:, None, None]
    # Backpropagation through the two tanh layers.
    delta_out = err * (1.0 - out * out)  # [P, B, O]
    delta_hidden = np.matmul(delta_out, params.W2) * (1.0 - hidden * hidden)  # [P, B, H]
    lr1, lr2 = rates[0] / batch, rates[1] / batch
    params.W2 += lr2 * np.matmul(delta_out.transpose(0, 2, 1), hidden)
    params.b2 += lr2 * delta_out.sum(axis=1)
    params.W1 += lr1 * np.matmul(delta_hidden.transpose(0, 2, 1), x)
    params.b1 += lr1 * delta_hidden.sum(axis=1)
    return UpdateStats(fit.q.mean(axis=1), np.abs(delta_q).mean(axis=1))
