"""The wire-fitting interpolator (thesis Eq 3.1) and its partial derivatives (Eq 3.4, 3.5).

Shapes use `...` for any leading batch dimensions (population, batch), `W` for wires and
`A` for action dimensions. Everything here is pure numpy: arrays in, arrays out.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

# Differences and values are clipped to this magnitude so that squared distances stay finite.
# At |u| = 1e100 the interpolant already equals the mean of q to far below float resolution.
HUGE = 1e100


class WireFit(NamedTuple):
    """Interpolated value and its partial derivatives.

    Attributes:
        q: Q(x, u), shape [...].
        dq: dQ/dq_i, shape [..., W].
        du: dQ/du_ij (wire actions), shape [..., W, A].
    """

    q: FloatArray
    dq: FloatArray
    du: FloatArray


def _weights(
    wire_u: FloatArray, wire_q: FloatArray, u: FloatArray, c: float, eps: float
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Inverse distances of Eq 3.1 and the pieces the derivatives reuse.

    Returns (w [...,W], rho [...,W] = w / norm, diff [...,W,A] = u_i - u, q_clipped [...,W]).
    """
    q = np.clip(wire_q, -HUGE, HUGE)
    diff = np.clip(wire_u - u[..., None, :], -HUGE, HUGE)
    qmax = q.max(axis=-1, keepdims=True)
    distance = np.einsum("...wa,...wa->...w", diff, diff) + c * (qmax - q) + eps
    w = 1.0 / distance
    rho = w / w.sum(axis=-1, keepdims=True)
    return w, rho, diff, q


def wirefit_q(
    wire_u: FloatArray, wire_q: FloatArray, u: FloatArray, c: float = 0.01, eps: float = 1e-4
) -> FloatArray:
    """Q(x, u) by wire fitting, Eq 3.1.

    Args:
        wire_u: wire actions, [..., W, A].
        wire_q: wire values, [..., W].
        u: actions to evaluate, [..., A].
        c: smoothing factor.
        eps: keeps distances positive.

    Returns:
        Q, shape [...].
    """
    _, rho, _, q = _weights(wire_u, wire_q, u, c, eps)
    return np.einsum("...w,...w->...", rho, q)


def wirefit_grad(
    wire_u: FloatArray,
    wire_q: FloatArray,
    u: FloatArray,
    c: float = 0.01,
    eps: float = 1e-4,
    mode: Literal["approx", "exact"] = "approx",
) -> WireFit:
    """Q(x, u) and its partial derivatives with respect to every wire's value and action.

    `approx` is Eq 3.4 and 3.5 of the thesis, which ignore that max_i q_i moves when the top
    wire's value moves (inexact for that wire only). `exact` adds that term. Both are written
    with w_i = 1/distance_i and rho_i = w_i / norm, which is algebraically Eq 3.4-3.5:

        dQ/dq_i  = rho_i + c rho_i w_i (q_i - Q)      [- c sum_j rho_j w_j (q_j - Q) if i is top]
        dQ/du_ij = 2 rho_i w_i (Q - q_i) (u_ij - u_j)

    Shapes as in `wirefit_q`; returns a `WireFit`.
    """
    w, rho, diff, q = _weights(wire_u, wire_q, u, c, eps)
    big_q = np.einsum("...w,...w->...", rho, q)
    spread = q - big_q[..., None]  # q_i - Q
    rho_w = rho * w
    dq = rho + c * rho_w * spread
    if mode == "exact":
        top = np.argmax(q, axis=-1)[..., None]
        correction = c * np.einsum("...w,...w->...", rho_w, spread)
        np.put_along_axis(dq, top, np.take_along_axis(dq, top, axis=-1) - correction[..., None], axis=-1)
    elif mode != "approx":
        raise ValueError(f"mode must be 'approx' or 'exact', got {mode!r}")
    du = (-2.0 * rho_w * spread)[..., None] * diff
    return WireFit(big_q, dq, du)
