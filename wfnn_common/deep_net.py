"""The deep wire-fitting critic in numpy: its parameter layout, forward pass and greedy wire.

This is what the robot side needs to `act` with the deep learner (no torch; `act_one` is the
same forward pass for one state, compiled with numba): the weights of one
critic travel in a snapshot as one flat float64 vector, and `DeepShapes.of(config)` lays it out.

One critic over a scaled state x [S]:

    h = trunk(x)                       ReLU layers `hidden`
    u_i = tanh(W_w h + b_w)_i          n_wires wire actions [N, A], in [-1, 1]
    g_i = relu(V_h h + V_u u_i + b_v)              the value head's first layer, per wire
    g_i = relu(V_k g_i + b_k), k = 1 .. value_layers - 1
    q_i = v . g_i + b_o                             wire values [N], conditioned on the action

With `layer_norm`, the trunk's ReLU inputs are normalised first (LayerNorm without learned
scale). Normalising the value head's too kept its units alive on a one-step task but lost
Pendulum's swing-up (tuning seed 100: -1100 to -1440 against -122 without, 5,000 steps), so
the value head is left plain.

The greedy action is the wire with the largest value; Q(x, u) for any u is Eq 3.1's wire-fitting
interpolation, with the smoothing term on values min-max normalised over the state's wires:

    d_i = |u - u_i|^2 + c (q_max - q_i) / (q_max - q_min + tiny) + eps
    Q(x, u) = sum_i (q_i / d_i) / sum_i (1 / d_i)
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from wfnn_common.config import LearnerConfig

FloatArray = NDArray[np.float64]
LN_EPS = 1e-5
"""Variance floor of the layer normalisation."""
SPAN_FLOOR = 1e-6
"""Smallest value span used to normalise a state's wire values (equal values: no smoothing)."""
POPART_MIN_STD = 1e-2
POPART_RELATIVE_STD = 1e-3
POPART_MAX_STD = 1e36
"""Bounds of the scale by which `deep.popart_rate` normalises values: at least POPART_MIN_STD
and POPART_RELATIVE_STD of the mean's magnitude, at most POPART_MAX_STD (within float32's range,
in which the update runs). The absolute floor is not smaller because a task paying nothing for
long (a sparse reward) shrinks its targets' spread to the critics' own noise: below it, the
first reward would be a normalised target of thousands, the very scale the normalisation is
there to spare the network. The relative floor keeps targets of one large value (a task paying
1e19 every step: no spread) within float32 once normalised (they overflowed its square)."""


@dataclass(frozen=True)
class DeepShapes:
    """The layout of one critic's parameters in a flat vector (offsets in order)."""

    state_dim: int
    action_dim: int
    hidden: tuple[int, ...]
    value_hidden: int
    n_wires: int
    layer_norm: bool
    value_layers: int = 1

    @classmethod
    def of(cls, config: LearnerConfig) -> DeepShapes:
        """The layout a deep learner config implies."""
        d = config.deep
        return cls(config.state_dim, config.action_dim, d.hidden, d.value_hidden, config.n_wires,
                   d.layer_norm, d.value_layers)  # fmt: skip

    def blocks(self) -> list[tuple[str, tuple[int, ...]]]:
        """(name, shape) of each parameter block, in the flat vector's order."""
        out: list[tuple[str, tuple[int, ...]]] = []
        fan_in = self.state_dim
        for k, width in enumerate(self.hidden):
            out += [(f"W{k}", (width, fan_in)), (f"b{k}", (width,))]
            fan_in = width
        na, hv = self.n_wires * self.action_dim, self.value_hidden
        out += [("Ww", (na, fan_in)), ("bw", (na,))]
        out += [
            ("Vh", (hv, fan_in)),
            ("Vu", (hv, self.action_dim)),
            ("bv", (hv,)),
        ]
        for k in range(1, self.value_layers):
            out += [(f"V{k}", (hv, hv)), (f"bv{k}", (hv,))]
        out += [("vo", (hv,)), ("bo", (1,))]
        return out

    def slices(self) -> dict[str, tuple[int, int, tuple[int, ...]]]:
        """Each block's (start, end, shape) in the flat vector (the same dict each call: read only)."""
        return self._slices

    @functools.cached_property
    def _slices(self) -> dict[str, tuple[int, int, tuple[int, ...]]]:
        out, a = {}, 0
        for name, shape in self.blocks():
            size = int(np.prod(shape))
            out[name] = (a, a + size, shape)
            a += size
        return out

    @property
    def n_params(self) -> int:
        """Parameters of one critic (where the last block ends)."""
        return max(end for _, end, _ in self._slices.values())

    def fan_ins(self) -> dict[str, int]:
        """Inputs feeding each block (its initial weights are uniform in +-1/sqrt(fan-in))."""
        fan: dict[str, int] = {}
        prev = self.state_dim
        for k, width in enumerate(self.hidden):
            fan[f"W{k}"] = fan[f"b{k}"] = prev
            prev = width
        fan["Ww"] = fan["bw"] = prev
        for name in ("Vh", "Vu", "bv"):
            fan[name] = prev + self.action_dim
        for k in range(1, self.value_layers):
            fan[f"V{k}"] = fan[f"bv{k}"] = self.value_hidden
        fan["vo"] = fan["bo"] = self.value_hidden
        return fan


def value_scale(moments: FloatArray) -> tuple[float, float]:
    """The (mean, standard deviation) of the targets from their running moments [3].

    moments are the exponential averages of y and y^2 and the averages' total weight (their
    bias correction, as Adam's): (0, 0, 0) before any target, which gives (0, 1), the values as
    they are. The deviation is kept within [max(POPART_MIN_STD, POPART_RELATIVE_STD |mean|),
    POPART_MAX_STD].
    """
    m1, m2, weight = (float(v) for v in moments)
    if weight <= 0.0:
        return 0.0, 1.0
    mean = m1 / weight
    std = math.sqrt(max(m2 / weight - mean * mean, 0.0))
    return mean, min(max(std, POPART_MIN_STD, POPART_RELATIVE_STD * abs(mean)), POPART_MAX_STD)


def in_task_units(flat: FloatArray, shapes: DeepShapes, mean: float, std: float) -> FloatArray:
    """One critic's weights [n_params] that give values in the task's units: a float64 copy.

    A critic that learns values normalised by (mean, std) scores q~ = v . g + b_o; its values
    are q = std q~ + mean, which the same network gives with v and b_o replaced by std v and
    std b_o + mean. The wires' actions and their order by value do not change.
    """
    out = np.array(flat, dtype=np.float64)
    a, b, _ = shapes.slices()["vo"]
    out[a:b] *= std
    a, b, _ = shapes.slices()["bo"]
    out[a:b] = out[a:b] * std + mean
    return out


def init_critic(shapes: DeepShapes, rng: np.random.Generator, scale: float = 1.0) -> FloatArray:
    """Fresh weights of one critic [n_params]: uniform in +-scale/sqrt(fan-in) per block."""
    fan = shapes.fan_ins()
    parts = [rng.uniform(-scale, scale, int(np.prod(s))) / np.sqrt(fan[name]) for name, s in shapes.blocks()]
    return np.concatenate(parts)


class DeepParams:
    """Weights of one critic (the part `act` needs) over a flat [1, n_params] float64 array.

    Immutable: `flat` is made read-only, because `act`'s arrays are derived from it here (new
    weights are a new DeepParams); see `_act_layout` for what they hold.
    """

    def __init__(self, flat: FloatArray, shapes: DeepShapes) -> None:
        if flat.ndim != 2 or flat.shape != (1, shapes.n_params):
            raise ValueError(f"flat params must be [1, {shapes.n_params}], got {flat.shape}")
        if flat.dtype != np.float64 or not flat.flags.c_contiguous:
            raise ValueError("flat params must be C-contiguous float64")
        flat.flags.writeable = False
        self.flat = flat
        self.shapes = shapes
        self.blocks = {name: flat[0, a:b].reshape(shape) for name, (a, b, shape) in shapes.slices().items()}
        self.trunk = [(self.blocks[f"W{k}"], self.blocks[f"b{k}"]) for k in range(len(shapes.hidden))]
        self.value_layers = [
            (self.blocks[f"V{k}"], self.blocks[f"bv{k}"]) for k in range(1, shapes.value_layers)
        ]

    @functools.cached_property
    def act_layout(self) -> tuple[FloatArray, NDArray[np.int64]]:
        """`act_one`'s weights in one read-only vector, and the widths that lay it out.

        Made when first acted on (a think server makes new weights at every think and acts on
        few of them); two threads that both make it get the same arrays.
        """
        return _act_layout(self.blocks, self.shapes)

    @property
    def population(self) -> int:
        """Always 1: a deep learner is one network."""
        return 1

    def copy(self) -> DeepParams:
        """Deep copy (a snapshot that `act` reads while thinking goes on)."""
        return DeepParams(self.flat.copy(), self.shapes)


def _layer_norm(h: FloatArray) -> FloatArray:
    mean = h.mean(axis=-1, keepdims=True)
    centred = h - mean
    return centred / np.sqrt((centred * centred).mean(axis=-1, keepdims=True) + LN_EPS)


def wires(params: DeepParams, x: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Wires of scaled states x [B, S] -> (actions [B, N, A] in [-1, 1], values [B, N])."""
    b = params.blocks
    h = x
    for W, bias in params.trunk:
        h = h @ W.T + bias
        if params.shapes.layer_norm:
            h = _layer_norm(h)
        h = np.maximum(h, 0.0)
    n, a = params.shapes.n_wires, params.shapes.action_dim
    u = np.tanh(h @ b["Ww"].T + b["bw"]).reshape(x.shape[0], n, a)
    g = np.maximum((h @ b["Vh"].T + b["bv"])[:, None, :] + u @ b["Vu"].T, 0.0)  # [B, N, Hv]
    for V, bias in params.value_layers:
        g = np.maximum(g @ V.T + bias, 0.0)
    q = g @ b["vo"] + b["bo"][0]
    return u, q


def _act_layout(blocks: dict[str, FloatArray], shapes: DeepShapes) -> tuple[FloatArray, NDArray[np.int64]]:
    """`act_one`'s weights as one vector, each matrix transposed ([fan-in, units], read by rows).

    In order: per trunk layer its weights and bias, with a LayerNorm layer's mean over units
    taken out, so that its output arrives centred ((W - mean W) h + (b - mean b) = W h + b -
    mean(W h + b)); the wire head and the value head's state part side by side, their biases;
    the value head's action part [A, Hv]; each further value layer's weights [Hv, Hv] and bias;
    its output weights [Hv] and bias [1]. dims: state, action, wires, value units, layer_norm
    (0/1), value layers, then the trunk's widths.
    """
    fan = shapes.hidden[-1]
    na = shapes.n_wires * shapes.action_dim
    pack = np.empty(shapes.n_params)  # the same numbers as the weights, rearranged
    at = 0

    def put(rows: int, cols: int) -> FloatArray:  # the next [rows, cols] of the pack
        nonlocal at
        at += rows * cols
        return pack[at - rows * cols : at].reshape(rows, cols)

    for k in range(len(shapes.hidden)):  # each matrix written transposed in one strided copy
        W, b = blocks[f"W{k}"], blocks[f"b{k}"]
        if shapes.layer_norm:
            np.subtract(W.T, (W.sum(axis=0) / W.shape[0])[:, None], out=put(W.shape[1], W.shape[0]))
            np.subtract(b, b.sum() / b.shape[0], out=put(1, b.shape[0])[0])
        else:
            put(W.shape[1], W.shape[0])[...] = W.T
            put(1, b.shape[0])[0] = b
    head = put(fan, na + shapes.value_hidden)
    head[:, :na] = blocks["Ww"].T
    head[:, na:] = blocks["Vh"].T
    put(1, na)[0] = blocks["bw"]
    put(1, shapes.value_hidden)[0] = blocks["bv"]
    put(shapes.action_dim, shapes.value_hidden)[...] = blocks["Vu"].T
    for k in range(1, shapes.value_layers):
        put(shapes.value_hidden, shapes.value_hidden)[...] = blocks[f"V{k}"].T
        put(1, shapes.value_hidden)[0] = blocks[f"bv{k}"]
    put(1, shapes.value_hidden)[0] = blocks["vo"]
    put(1, 1)[0] = blocks["bo"]
    pack.flags.writeable = False
    dims = np.array(
        [shapes.state_dim, shapes.action_dim, shapes.n_wires, shapes.value_hidden, int(shapes.layer_norm),
         shapes.value_layers, *shapes.hidden], dtype=np.int64,
    )  # fmt: skip
    return pack, dims


@njit(cache=True, nogil=True, fastmath=False)
def _affine(pack, at, h, n_out):  # type: ignore[no-untyped-def]
    # out = W h + b with W stored transposed from `at` ([len(h), n_out], then b [n_out]): each
    # input adds its row, a loop without a running sum that the compiler vectorises in order
    # (through a 2-D view: indexing the flat vector instead ran three times as long).
    # ReLU zeros are skipped (0 * w adds nothing: the weights are finite).
    n_in = h.shape[0]
    bias = at + n_in * n_out
    W = pack[at:bias].reshape((n_in, n_out))
    out = pack[bias : bias + n_out].copy()
    for j in range(n_in):
        hj = h[j]
        if hj != 0.0:
            row = W[j]
            for i in range(n_out):
                out[i] += row[i] * hj
    return out, bias + n_out


@njit(cache=True, nogil=True, fastmath=False)
def act_one(pack, dims, s, mid, half, limit):  # type: ignore[no-untyped-def]
    """All wires of one state, compiled: the robot's `act` hot path (see `_act_layout`).

    Scales the state s [S] by (mid, half) into x [S] and flags it invalid when an entry is not
    finite or beyond +-limit (then no wires: the caller acts on its best estimate instead).
    Returns (valid, x [S], wire actions [N, A], wire values [N], the best wire). In numpy,
    each call's overhead and OpenBLAS's threads (two of them doubled a matrix-vector product
    here) made most of `act`'s time.
    """
    n_state, n_action, n_wires, n_value = dims[0], dims[1], dims[2], dims[3]
    layer_norm, n_layers = dims[4], dims[5]
    x = np.empty(n_state)
    u = np.empty((n_wires, n_action))
    q = np.empty(n_wires)
    valid = True
    for i in range(n_state):
        x[i] = (s[i] - mid[i]) / half[i]
        if not abs(x[i]) <= limit:  # NaN fails the comparison too
            valid = False
    if not valid:
        return False, x, u, q, -1
    h, at = x, 0
    for k in range(6, dims.shape[0]):
        h, at = _affine(pack, at, h, dims[k])
        if layer_norm:  # already centred: only the scale is left
            ss = 0.0
            for i in range(h.shape[0]):
                ss += h[i] * h[i]
            scale = 1.0 / math.sqrt(ss / h.shape[0] + LN_EPS)
            for i in range(h.shape[0]):
                h[i] *= scale
        for i in range(h.shape[0]):
            h[i] = max(h[i], 0.0)
    na = n_wires * n_action
    y, at = _affine(pack, at, h, na + n_value)
    Vu = pack[at : at + n_action * n_value].reshape((n_action, n_value))
    deeper = at + n_action * n_value  # where the value head's further layers start
    at = deeper + (n_layers - 1) * (n_value + 1) * n_value
    vo = pack[at : at + n_value]
    bo = pack[at + n_value]
    best = 0
    g = np.empty(n_value)
    for w in range(n_wires):
        g[:] = y[na:]
        for a in range(n_action):
            u[w, a] = math.tanh(y[w * n_action + a])
            row, uwa = Vu[a], u[w, a]
            for i in range(n_value):
                g[i] += row[i] * uwa
        for i in range(n_value):
            g[i] = max(g[i], 0.0)
        z, layer_at = g, deeper
        for _ in range(n_layers - 1):
            z, layer_at = _affine(pack, layer_at, z, n_value)
            for i in range(n_value):
                z[i] = max(z[i], 0.0)
        value = bo
        for i in range(n_value):
            value += z[i] * vo[i]
        q[w] = value
        if value > q[best]:  # the first wire of the highest value
            best = w
    return True, x, u, q, best


def greedy(params: DeepParams, x: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Best wire for scaled states x [B, S] -> (action [B, A], value [B])."""
    u, q = wires(params, x)
    best = q.argmax(axis=1)
    rows = np.arange(x.shape[0])
    return u[rows, best], q[rows, best]


def wirefit_normalised(
    wire_u: FloatArray, wire_q: FloatArray, u: FloatArray, c: float, eps: float, top_k: int = 0
) -> FloatArray:
    """Q at actions u [..., A] from wires ([..., N, A], [..., N]), smoothing on normalised values.

    With 0 < top_k < N only the top_k largest weights count (ties at the k-th weight all count).
    """
    return wirefit_from_distances(((u[..., None, :] - wire_u) ** 2).sum(axis=-1), wire_q, c, eps, top_k)


def wirefit_from_distances(
    dist2: FloatArray, wire_q: FloatArray, c: float, eps: float, top_k: int = 0
) -> FloatArray:
    """`wirefit_normalised` from the squared distances dist2 [..., N] of each action to the wires.

    For callers that know the distances more cheaply than from the actions (a surface over one
    or two action variables, the others held at the best wire's: `SurfaceGrid`).
    """
    q_max = wire_q.max(axis=-1, keepdims=True)
    span = np.maximum(q_max - wire_q.min(axis=-1, keepdims=True), SPAN_FLOOR)
    d = dist2 + c * (q_max - wire_q) / span + eps
    w = 1.0 / d
    n = w.shape[-1]
    if 0 < top_k < n:
        kth = np.partition(w, n - top_k, axis=-1)[..., n - top_k : n - top_k + 1]
        w = np.where(w >= kth, w, 0.0)
    return np.asarray((w * wire_q).sum(axis=-1) / w.sum(axis=-1))
