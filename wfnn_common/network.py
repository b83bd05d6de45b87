"""The WFNN's tanh multilayer perceptron, its parameter layout, and state/action scaling.

A population of P independent networks is stored as one flat float64 array of shape
[P, n_params]; `Params` exposes the per-layer views. Per learner the layout is
W1 [H, S], b1 [H], W2 [O, H], b2 [O] with O = n_wires * (A + 1): first n_wires actions of
A components (wire-major), then n_wires values.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from wfnn_common.config import LearnerConfig

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Shapes:
    """Sizes of one network."""

    n_in: int
    n_hidden: int
    n_out: int

    @classmethod
    def of(cls, config: LearnerConfig) -> Shapes:
        """Shapes implied by a learner config."""
        return cls(config.state_dim, config.n_hidden, config.n_outputs)

    @property
    def n_params(self) -> int:
        """Parameters per network."""
        return self.n_hidden * (self.n_in + 1) + self.n_out * (self.n_hidden + 1)


class Params:
    """Weights of a population of networks over one flat array (views, no copies)."""

    def __init__(self, flat: FloatArray, shapes: Shapes) -> None:
        if flat.ndim != 2 or flat.shape[1] != shapes.n_params:
            raise ValueError(f"flat params must be [P, {shapes.n_params}], got {flat.shape}")
        if flat.dtype != np.float64 or not flat.flags.c_contiguous:
            raise ValueError("flat params must be C-contiguous float64")
        self.flat = flat
        self.shapes = shapes
        s, h, o = shapes.n_in, shapes.n_hidden, shapes.n_out
        p = flat.shape[0]
        a = 0
        self.W1 = flat[:, a : a + h * s].reshape(p, h, s)
        a += h * s
        self.b1 = flat[:, a : a + h]
        a += h
        self.W2 = flat[:, a : a + o * h].reshape(p, o, h)
        a += o * h
        self.b2 = flat[:, a : a + o]
        self.single = (self.W1[0], self.b1[0], self.W2[0], self.b2[0])
        """The first network's (W1, b1, W2, b2) views: the single-learner hot path."""

    @property
    def population(self) -> int:
        """Number of networks."""
        return int(self.flat.shape[0])

    def copy(self) -> Params:
        """Deep copy (used for snapshots that `act` reads while thinking goes on)."""
        return Params(self.flat.copy(), self.shapes)


def layer_rates(config: LearnerConfig) -> tuple[float, float]:
    """Per-layer learning rates alpha / sqrt(fan-in), the bias counted as an input weight."""
    return (
        config.alpha / np.sqrt(config.state_dim + 1),
        config.alpha / np.sqrt(config.n_hidden + 1),
    )


def init_params(config: LearnerConfig, population: int, rng: np.random.Generator) -> Params:
    """Small random weights, uniform in +-init_scale / sqrt(fan-in) per layer."""
    shapes = Shapes.of(config)
    params = Params(np.empty((population, shapes.n_params)), shapes)
    reinit(params, config, rng, np.arange(population))
    return params


def reinit(params: Params, config: LearnerConfig, rng: np.random.Generator, which: NDArray[np.int64]) -> None:
    """Reset the networks `which` to fresh small random weights, in place."""
    s, h, o = params.shapes.n_in, params.shapes.n_hidden, params.shapes.n_out
    k = len(which)
    r1 = config.init_scale / np.sqrt(s + 1)
    r2 = config.init_scale / np.sqrt(h + 1)
    params.W1[which] = rng.uniform(-r1, r1, size=(k, h, s))
    params.b1[which] = rng.uniform(-r1, r1, size=(k, h))
    params.W2[which] = rng.uniform(-r2, r2, size=(k, o, h))
    params.b2[which] = rng.uniform(-r2, r2, size=(k, o))


def forward(params: Params, x: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Propagate scaled states through every network.

    Args:
        params: P networks.
        x: scaled states, [P, B, S].

    Returns:
        (hidden [P, B, H], outputs [P, B, O]), both tanh activations.
    """
    if params.population == 1:  # one BLAS call per layer instead of a stacked matmul
        hidden = x[0] @ params.W1[0].T
        hidden += params.b1[0]
        np.tanh(hidden, out=hidden)
        out = hidden @ params.W2[0].T
        out += params.b2[0]
        np.tanh(out, out=out)
        return hidden[None], out[None]
    hidden = np.tanh(np.matmul(x, params.W1.transpose(0, 2, 1)) + params.b1[:, None, :])
    out = np.tanh(np.matmul(hidden, params.W2.transpose(0, 2, 1)) + params.b2[:, None, :])
    return hidden, out


def split_wires(out: FloatArray, n_wires: int, action_dim: int) -> tuple[FloatArray, FloatArray]:
    """Views of the network outputs as wires: actions [..., W, A] and values [..., W]."""
    n_act = n_wires * action_dim
    return out[..., :n_act].reshape(*out.shape[:-1], n_wires, action_dim), out[..., n_act:]


class Scaler:
    """Affine map between physical units and the learner's [-1, 1] ranges."""

    def __init__(self, low: tuple[float, ...], high: tuple[float, ...]) -> None:
        self.low = np.asarray(low, dtype=np.float64)
        self.high = np.asarray(high, dtype=np.float64)
        self.mid = 0.5 * (self.high + self.low)
        self.half = 0.5 * (self.high - self.low)

    def to_unit(self, value: FloatArray) -> FloatArray:
        """Physical -> scaled ([-1, 1] over the declared range)."""
        return (np.asarray(value, dtype=np.float64) - self.mid) / self.half

    def from_unit(self, scaled: FloatArray) -> FloatArray:
        """Scaled -> physical."""
        return np.asarray(scaled, dtype=np.float64) * self.half + self.mid
