"""Minibatch WFNN updates with torch (the server-side throughput path).

The same arithmetic as `wfnn_common.update.wfnn_update` (which stays the readable numpy
reference), written with torch tensors so large batches use vectorised transcendental
functions and all cores. Imported only when a learner is configured for minibatch updates:
acting and incremental thinking never need torch.
"""

from __future__ import annotations

import numpy as np
import torch
from numpy.typing import NDArray

from wfnn_common.network import Params
from wfnn_common.replay import Experiences

DTYPES = {"float32": torch.float32, "float64": torch.float64}


def _forward(
    w1: torch.Tensor, b1: torch.Tensor, w2: torch.Tensor, b2: torch.Tensor, x: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    hidden = torch.tanh(torch.baddbmm(b1.unsqueeze(1), x, w1.transpose(1, 2)))
    out = torch.tanh(torch.baddbmm(b2.unsqueeze(1), hidden, w2.transpose(1, 2)))
    return hidden, out


@torch.no_grad()
def minibatch_think(
    params: Params,
    rates: tuple[float, float],
    buffer: Experiences,
    idx: NDArray[np.int64],
    active: NDArray[np.bool_],
    *,
    n_wires: int,
    gamma: float,
    advantage_k: float,
    c: float,
    eps: float,
    exact: bool,
    squash: bool,
    bc_weight: float = 0.0,
    dtype: str = "float32",
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Run len(idx) minibatch updates; params are updated in place.

    Args:
        params: P networks (numpy, float64; copied in and out once per call).
        rates: per-layer learning rates (applied to the batch-mean gradient).
        buffer: experience arrays [P, N, ...] (scaled units, raw rewards).
        idx: [U, P, B] experience indices of U updates of B experiences per learner.
        active: [P] learners to update.
        bc_weight: `LearnerConfig.bc_weight` (the best wire's action pulled toward the action taken).
        dtype: "float32" (fast) or "float64" (matches the numpy reference to rounding).

    Returns:
        (mean Q(x, u) [P], mean |Q_new - Q| [P]) over all experiences used.
    """
    tdt = DTYPES[dtype]
    w1, b1, w2, b2 = (torch.tensor(a, dtype=tdt) for a in (params.W1, params.b1, params.W2, params.b2))
    states, actions, next_states = (
        torch.from_numpy(a) for a in (buffer.state, buffer.action, buffer.next_state)
    )
    rewards, terminal = torch.from_numpy(buffer.reward), torch.from_numpy(np.asarray(buffer.terminal))
    mask = torch.from_numpy(active.astype(np.float64)).to(tdt)[:, None, None]
    n_pop, action_dim = params.population, buffer.action.shape[-1]
    n_act = n_wires * action_dim
    rows = torch.arange(n_pop)[:, None]
    lr1, lr2 = rates
    q_sum = torch.zeros(n_pop, dtype=torch.float64)
    td_sum = torch.zeros(n_pop, dtype=torch.float64)
    for batch in torch.from_numpy(np.ascontiguousarray(idx)):
        x = states[rows, batch].to(tdt)
        u = actions[rows, batch].to(tdt)
        xn = next_states[rows, batch].to(tdt)
        r = rewards[rows, batch].to(tdt)
        term = terminal[rows, batch] != 0
        if squash:
            r = (1.0 - gamma) * torch.tanh(r)
        # Part 2: value of the next state = its best wire's value.
        value_next = _forward(w1, b1, w2, b2, xn)[1][..., n_act:].amax(dim=-1)
        # Part 3: wires, Q(x, u) by Eq 3.1, and Eq 3.4-3.5 derivatives.
        hidden, out = _forward(w1, b1, w2, b2, x)
        wire_u = out[..., :n_act].unflatten(-1, (n_wires, action_dim))
        wire_q = out[..., n_act:]
        q_max, top = wire_q.max(dim=-1)
        diff = wire_u - u.unsqueeze(-2)
        w = 1.0 / ((diff * diff).sum(-1) + c * (q_max.unsqueeze(-1) - wire_q) + eps)
        rho = w / w.sum(-1, keepdim=True)
        q = (rho * wire_q).sum(-1)
        spread = wire_q - q.unsqueeze(-1)
        rho_w = rho * w
        dq = rho + c * rho_w * spread
        if exact:
            dq.scatter_add_(-1, top.unsqueeze(-1), -(c * (rho_w * spread).sum(-1, keepdim=True)))
        backed_up = r + torch.where(term, 0.0, gamma * value_next)
        delta_q = q_max + (backed_up - q_max) / advantage_k - q
        err_u = (-2.0 * rho_w * spread * delta_q.unsqueeze(-1)).unsqueeze(-1) * diff
        if bc_weight:
            best = torch.nn.functional.one_hot(top, n_wires).to(tdt).unsqueeze(-1)  # [P, B, W, 1]
            err_u = err_u - bc_weight * best * diff  # diff of the best wire = its action - u
        err = torch.cat([err_u.flatten(-2), dq * delta_q.unsqueeze(-1)], dim=-1) * mask
        # Backpropagation of the batch-mean error through both tanh layers.
        delta_out = err * (1.0 - out * out)
        delta_hidden = torch.bmm(delta_out, w2) * (1.0 - hidden * hidden)
        scale2, scale1 = lr2 / x.shape[1], lr1 / x.shape[1]
        w2.baddbmm_(delta_out.transpose(1, 2), hidden, alpha=scale2)
        b2.add_(delta_out.sum(1), alpha=scale2)
        w1.baddbmm_(delta_hidden.transpose(1, 2), x, alpha=scale1)
        b1.add_(delta_hidden.sum(1), alpha=scale1)
        q_sum += q.mean(1).double()
        td_sum += delta_q.abs().mean(1).double()
    for dst, src in ((params.W1, w1), (params.b1, b1), (params.W2, w2), (params.b2, b2)):
        dst[...] = src.double().numpy()
    n = max(len(idx), 1)
    return (q_sum / n).numpy(), (td_sum / n).numpy()
