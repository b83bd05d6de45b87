"""Compiled incremental think: many one-experience WFNN updates per call, per learner.

The per-experience update is dominated by interpreter overhead in numpy (tens of
microseconds for a few thousand flops), so the loop over thinks runs compiled. Learners of a
population are independent and run in parallel; the GIL is released, so a background think
thread never stalls `act`. The arithmetic is `wfnn_common.update.wfnn_update` with B = 1.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

from wfnn_common.config import LearnerConfig
from wfnn_common.network import layer_rates

FloatArray = NDArray[np.float64]


class Hyperparameters(NamedTuple):
    """What the compiled think reads of a learner's config: one record, built once per learner.

    Its fields are always a Python float, int or bool whatever the config holds (an int
    `advantage_k`, a numpy float), so numba compiles the think kernels once: a record typed
    differently would compile and cache another version. The conversion changes no number:
    the kernels' float64 arithmetic widens an int or a float32 exactly so.

    Attributes:
        lr1, lr2: per-layer learning rates (`network.layer_rates`).
        n_wires, gamma, advantage_k, smoothing_c, eps, squash_reward, bc_weight: as in
            `LearnerConfig`.
        exact: `LearnerConfig.derivatives == "exact"`.
    """

    lr1: float
    lr2: float
    n_wires: int
    gamma: float
    advantage_k: float
    smoothing_c: float
    eps: float
    exact: bool
    squash_reward: bool
    bc_weight: float

    @classmethod
    def of(cls, config: LearnerConfig) -> Hyperparameters:
        """The record of a (frozen) config."""
        lr1, lr2 = layer_rates(config)
        return cls(
            float(lr1), float(lr2), int(config.n_wires), float(config.gamma), float(config.advantage_k),
            float(config.smoothing_c), float(config.eps), config.derivatives == "exact",
            bool(config.squash_reward), float(config.bc_weight),
        )  # fmt: skip


@njit(cache=True, nogil=True, fastmath=False, inline="always")
def _tanh(a):  # type: ignore[no-untyped-def]
    # libm's tanh costs about twice exp here and tanh is most of a small network's forward
    # pass. Both branches are accurate to a few ulp; expm1 avoids cancellation near zero.
    b = abs(a)
    if b < 0.125:
        e = math.expm1(-2.0 * b)
        t = -e / (2.0 + e)
    else:
        e = math.exp(-2.0 * b)
        t = (1.0 - e) / (1.0 + e)
    return t if a >= 0.0 else -t


@njit(cache=True, nogil=True, fastmath=False)
def _forward(W1, b1, W2, b2, x, hidden, out):  # type: ignore[no-untyped-def]
    n_hidden, n_in = W1.shape
    for j in range(n_hidden):
        a = b1[j]
        for i in range(n_in):
            a += W1[j, i] * x[i]
        hidden[j] = _tanh(a)
    for o in range(W2.shape[0]):
        a = b2[o]
        for j in range(n_hidden):
            a += W2[o, j] * hidden[j]
        out[o] = _tanh(a)


@njit(cache=True, nogil=True, fastmath=False)
def _think_learner(W1, b1, W2, b2, xs, us, xns, rs, terms, idx, hyper):  # type: ignore[no-untyped-def]
    lr1, lr2, n_wires, gamma = hyper.lr1, hyper.lr2, hyper.n_wires, hyper.gamma
    k, c, eps, bc = hyper.advantage_k, hyper.smoothing_c, hyper.eps, hyper.bc_weight
    n_hidden = W1.shape[0]
    n_out = W2.shape[0]
    action_dim = us.shape[1]
    n_act = n_wires * action_dim
    hidden = np.empty(n_hidden)
    out = np.empty(n_out)
    hidden_next = np.empty(n_hidden)
    out_next = np.empty(n_out)
    w = np.empty(n_wires)
    err = np.empty(n_out)
    delta_hidden = np.empty(n_hidden)
    q_sum = 0.0
    td_sum = 0.0
    for n in range(idx.shape[0]):
        t = idx[n]
        x = xs[t]
        u = us[t]
        r = rs[t]
        if hyper.squash_reward:  # Eq 3.6
            r = (1.0 - gamma) * math.tanh(r)
        # Part 2: best wire value of the next state.
        value_next = 0.0
        if not terms[t]:
            _forward(W1, b1, W2, b2, xns[t], hidden_next, out_next)
            value_next = out_next[n_act]
            for i in range(1, n_wires):
                value_next = max(value_next, out_next[n_act + i])
        # Part 3a: wires for the current state and Q(x, u) by wire fitting.
        _forward(W1, b1, W2, b2, x, hidden, out)
        top = 0
        q_max = out[n_act]
        for i in range(1, n_wires):
            if out[n_act + i] > q_max:
                q_max = out[n_act + i]
                top = i
        norm = 0.0
        wsum = 0.0
        for i in range(n_wires):
            d = c * (q_max - out[n_act + i]) + eps
            for j in range(action_dim):
                diff = out[i * action_dim + j] - u[j]
                d += diff * diff
            w[i] = 1.0 / d
            norm += w[i]
            wsum += w[i] * out[n_act + i]
        q = wsum / norm
        # Part 2 (advantage learning, Eq 4.1) and 3b: change in Q and in every wire.
        target = q_max + (r + gamma * value_next - q_max) / k
        delta_q = target - q
        correction = 0.0
        for i in range(n_wires):
            rho = w[i] / norm
            spread = out[n_act + i] - q
            rho_w = rho * w[i]
            err[n_act + i] = (rho + c * rho_w * spread) * delta_q
            g = -2.0 * rho_w * spread * delta_q
            for j in range(action_dim):
                err[i * action_dim + j] = g * (out[i * action_dim + j] - u[j])
            correction += rho_w * spread
        if hyper.exact:
            err[n_act + top] -= c * correction * delta_q
        if bc != 0.0:  # behaviour-cloning pull: the best wire's action toward the action taken
            for j in range(action_dim):
                err[top * action_dim + j] += bc * (u[j] - out[top * action_dim + j])
        # Part 3c: incremental backpropagation toward the new wires.
        for o in range(n_out):
            err[o] *= 1.0 - out[o] * out[o]
        for j in range(n_hidden):
            a = 0.0
            for o in range(n_out):
                a += W2[o, j] * err[o]
            delta_hidden[j] = a * (1.0 - hidden[j] * hidden[j])
        for o in range(n_out):
            g = lr2 * err[o]
            for j in range(n_hidden):
                W2[o, j] += g * hidden[j]
            b2[o] += g
        for j in range(n_hidden):
            g = lr1 * delta_hidden[j]
            for i in range(x.shape[0]):
                W1[j, i] += g * x[i]
            b1[j] += g
        q_sum += q
        td_sum += abs(delta_q)
    return q_sum, td_sum


@njit(cache=True, nogil=True, parallel=True)
def think_incremental(W1, b1, W2, b2, xs, us, xns, rs, terms, idx, active, hyper):  # type: ignore[no-untyped-def]
    """Replay T experiences per learner, one update each, in order; weights change in place.

    Args:
        W1 [P,H,S], b1 [P,H], W2 [P,O,H], b2 [P,O]: the population's weights.
        xs, xns [P,N,S]; us [P,N,A]; rs [P,N] raw rewards; terms [P,N] bool: experiences
            (a replay buffer's arrays, read in place: no gather copy).
        idx [P,T]: which experiences each learner replays, in order.
        active [P] bool: learners to update.
        hyper: the learners' `Hyperparameters` (learning rates and the config's update fields).

    Returns:
        (q_mean [P], td_abs_mean [P]) over the replayed experiences.
    """
    n_pop = W1.shape[0]
    n_thinks = idx.shape[1]
    q_mean = np.zeros(n_pop)
    td_mean = np.zeros(n_pop)
    for p in prange(n_pop):
        if active[p] and n_thinks > 0:
            q_sum, td_sum = _think_learner(
                W1[p], b1[p], W2[p], b2[p], xs[p], us[p], xns[p], rs[p], terms[p], idx[p], hyper
            )
            q_mean[p] = q_sum / n_thinks
            td_mean[p] = td_sum / n_thinks
    return q_mean, td_mean


@njit(cache=True, nogil=True)
def think_incremental_one(W1, b1, W2, b2, xs, us, xns, rs, terms, idx, active, hyper):  # type: ignore[no-untyped-def]
    """`think_incremental` for a population of one learner, outside a parallel region.

    Same arguments and results. A parallel region hands its work to numba's thread pool on
    every call; for one learner that buys nothing and, on a busy machine, costs a wait for a
    worker thread to be scheduled (about 15 ms per call measured with both cores loaded).
    """
    q_mean = np.zeros(1)
    td_mean = np.zeros(1)
    n_thinks = idx.shape[1]
    if active[0] and n_thinks > 0:
        q_sum, td_sum = _think_learner(
            W1[0], b1[0], W2[0], b2[0], xs[0], us[0], xns[0], rs[0], terms[0], idx[0], hyper
        )
        q_mean[0] = q_sum / n_thinks
        td_mean[0] = td_sum / n_thinks
    return q_mean, td_mean


@njit(cache=True, nogil=True, fastmath=False, inline="always")
def _best_wire(out, n_act, n_wires):  # type: ignore[no-untyped-def]
    # The first wire of the highest value (outputs: wire actions, then the n_wires values).
    best = 0
    for w in range(1, n_wires):
        if out[n_act + w] > out[n_act + best]:
            best = w
    return best


@njit(cache=True, nogil=True, fastmath=False)
def act_one(W1, b1, W2, b2, s, mid, half, limit, n_wires, action_dim, x, hidden, out):  # type: ignore[no-untyped-def]
    """One learner's greedy wire for one state, compiled: the robot's `act` hot path.

    Scales the state s [S] by (mid, half) into x [S], flags it invalid when an entry is not
    finite or beyond +-limit (then x holds the scaled values and the caller substitutes its best
    estimate), runs the network into hidden [H] and out [O], and returns (valid, best wire,
    its value). Numpy's per-call overhead was most of `act` (6.6 us for a 3-10-18 network).
    """
    valid = True
    for i in range(s.shape[0]):
        v = (s[i] - mid[i]) / half[i]
        x[i] = v
        if not abs(v) <= limit:  # NaN fails the comparison too
            valid = False
    if not valid:
        return False, -1, 0.0
    _forward(W1, b1, W2, b2, x, hidden, out)
    best = _best_wire(out, n_wires * action_dim, n_wires)
    return True, best, out[n_wires * action_dim + best]


@njit(cache=True, nogil=True, fastmath=False)
def surface_q(  # type: ignore[no-untyped-def]
    W1, b1, W2, b2, s, mid, half, limit, grid_u, on_axis, n_wires, action_dim, c, eps, x, hidden, out, q
):
    """Wire-fitted Q (Eq 3.1) at state s [S] over actions grid_u [G, A] into q [G] -> best wire.

    The state is scaled by (mid, half) into x [S] and clipped to +-limit (not finite: 0), as
    `act` sees it.
    Action variables not `on_axis` [A] take the best wire's action (grid_u's values there are
    ignored). `out` [O] receives the network's outputs (wire actions, then values); `hidden` [H]
    is scratch. One call instead of some fifty numpy calls: a live view draws this several times
    a second next to a think server's own work.
    """
    for i in range(s.shape[0]):
        v = (s[i] - mid[i]) / half[i]
        x[i] = min(max(v, -limit), limit) if math.isfinite(v) else 0.0
    _forward(W1, b1, W2, b2, x, hidden, out)
    n_act = n_wires * action_dim
    best = _best_wire(out, n_act, n_wires)
    qmax = out[n_act + best]
    for g in range(grid_u.shape[0]):
        num = 0.0
        den = 0.0
        for w in range(n_wires):
            d = c * (qmax - out[n_act + w]) + eps
            for a in range(action_dim):
                u = grid_u[g, a] if on_axis[a] else out[best * action_dim + a]
                diff = out[w * action_dim + a] - u
                d += diff * diff
            num += out[n_act + w] / d
            den += 1.0 / d
        q[g] = num / den
    return best
