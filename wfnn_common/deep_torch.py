"""The deep wire-fitting learner's update in torch (pure: no I/O, threads or clocks).

Two critics (each the network of `deep_net`: trunk, wire head, action-conditioned value head)
and their Polyak-averaged targets live in flat float32 vectors, so Adam, gradient clipping and
target averaging are one operation each. One update on a minibatch of B experiences
(x, u, R, x', discount), R the n-step return and discount gamma^n (0 after a terminal):

    u' = clip(best wire of target critic 1 at x' + clip(N(0, noise), +-noise_clip), -1, 1)
    y  = R + discount * min_j Q'_j(x', u')                       (twin critics, Fujimoto 2018)
    y  = V(x) + (y - V(x)) / k,  V(x) = min_j Q'_j(x, best wire)  (advantage learning, Eq 4.1)
    L  = sum_j mean (Q_j(x, u) - y)^2 + separation * sum_j mean_{i<l} 1 / (|u_i - u_l| + 0.1)
         (the best wire held still in its pairs unless deep.separate_best)
         + sum_j mean max(0, |z| - tanh_limit)^2   (z the wire head's inputs to tanh)
         + bc_weight * mean |best wire of critic 1 at x - u|^2

With `deep.popart_rate` the critics' outputs are normalised values: Q = std Q~ + mean, with
the running (mean, std) of the targets, and the first term is sum_j mean (Q~_j(x, u) - (y -
mean) / std)^2, and the separation, tanh-limit and bc terms are divided by std^2, so that they
keep the weight against the values that they have without the option (normalised, the values'
pull on the wires is 1 / std^2 of what it was, against the same push apart: the boat lost by
that). The interpolation commutes with that affine map (its smoothing term is on min-max
normalised values, its weights sum to 1), so Q~ interpolates the normalised wire values.
After each step the statistics take in the batch's targets, and both critics' and targets'
output layers are rescaled so that their values in the task's units stay as they were (van
Hasselt et al. 2016).

Q_j(x, u) is the wire-fitting interpolation (Eq 3.1) of critic j's wires (the deep.top_k of
largest weight, where set) with the smoothing term on normalised values
(`deep_net.wirefit_normalised`); the smoothing term's values are
held constant in the gradient (normalised by a small span, its derivative would dwarf the
rest). Shapes: x [B, S], u [B, A].

Adam (Kingma and Ba 2015) and gradient-norm clipping are written out over the flat vector;
with `deep.compile` the loss and its gradient go through torch.compile (the same arithmetic,
fused). The loss takes the weights as views of their vector, one per block, whose gradients are
views of one gradient vector that the backward pass adds into: differentiated through slices of
the weights' vector, the compiled backward pass spent about 8% of an update assembling its
gradient element by element.

Making a trainer has one effect outside it: glibc's malloc is asked to keep freed memory for
reuse (`keep_freed_memory`), which halves a small network's update. Importing this module
silences torch's one warning about the gradient's layout.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import dataclasses
import functools
import logging
import math
import warnings
from collections.abc import Callable
from typing import Any, cast

import numpy as np
import torch
import torch.nn.functional as tnf

from wfnn_common.config import LearnerConfig
from wfnn_common.deep_net import LN_EPS, SPAN_FLOOR, DeepShapes, in_task_units, value_scale

logger = logging.getLogger(__name__)

# A block's gradient is laid out as the block itself (a strided view of one vector), which
# torch's layout check for gradients flags once per process: the layout is deliberate (above).
warnings.filterwarnings("ignore", message="grad and param do not obey the gradient layout contract",
                        category=UserWarning)  # fmt: skip

Losses = tuple[torch.Tensor, torch.Tensor, torch.Tensor]
"""What `loss` gives: (loss, critic 1's Q(x, u) [B], targets y [B])."""

CUDA_GENERATOR_BYTES = 16
"""Length of a CUDA generator's state (Philox: its seed and offset), told from a CPU's (mt19937)."""
SEPARATION_EPS = 0.1
"""Distance added in the separation term, so that wires close together get a bounded push (wires
that coincide exactly have no direction apart: their pair adds nothing to the gradient)."""


class Critics:
    """Functional forward pass of both critics at once over a flat parameter vector [2 n].

    The two critics' blocks sit side by side ([2, n] viewed), so each layer of both is one
    batched matrix product: the update's cost is dominated by per-operation overhead on a CPU.
    """

    def __init__(self, shapes: DeepShapes) -> None:
        self.shapes = shapes
        self.n = shapes.n_params
        self.slices = shapes.slices()

    def blocks(self, theta: torch.Tensor) -> dict[str, torch.Tensor]:
        """Views [2, *shape] of each block of both critics in theta [2 n], in the vector's order.

        Views made once stay valid across in-place updates of theta, so the trainer makes them
        once per vector.
        """
        both = theta.view(2, self.n)
        return {name: both[:, a:b].reshape(2, *shape) for name, (a, b, shape) in self.slices.items()}

    def trunk(self, p: dict[str, torch.Tensor], x: torch.Tensor) -> torch.Tensor:
        """Both critics' trunk features at states x [B, S] -> [2, B, H]."""
        shapes = self.shapes
        h = x.unsqueeze(0).expand(2, x.shape[0], x.shape[1])
        for k in range(len(shapes.hidden)):
            h = torch.baddbmm(p[f"b{k}"].unsqueeze(1), h, p[f"W{k}"].transpose(1, 2))
            if shapes.layer_norm:
                h = tnf.layer_norm(h, h.shape[-1:], eps=LN_EPS)
            h = tnf.relu(h)
        return h

    def values(self, p: dict[str, torch.Tensor], h: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """The value head's scores of actions u [2, B, M, A] at trunk features h [2, B, H] -> [2, B, M]."""
        z = torch.baddbmm(p["bv"].unsqueeze(1), h, p["Vh"].transpose(1, 2))  # [2, B, Hv]
        # einsum and a broadcast product rather than bmm: with A or the output width 1 these
        # are outer and inner products, which a batched matrix product does several times slower.
        zu = torch.einsum("cbna,cha->cbnh", u, p["Vu"])
        g = tnf.relu(z.unsqueeze(2) + zu)
        for k in range(1, self.shapes.value_layers):  # [2, B M, Hv] through each further layer
            flat = g.reshape(2, -1, g.shape[-1])
            z = torch.baddbmm(p[f"bv{k}"].unsqueeze(1), flat, p[f"V{k}"].transpose(1, 2))
            g = tnf.relu(z).view(g.shape)
        q = (g * p["vo"].view(2, 1, 1, -1)).sum(dim=-1)
        return q + p["bo"].view(2, 1, 1)

    def wires(self, p: dict[str, torch.Tensor], x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Both critics' wires (blocks p) at states x [B, S] -> (actions [2, B, N, A], values [2, B, N])."""
        u, q, _ = self.wires_and_preactivations(p, x)
        return u, q

    def wires_and_preactivations(
        self, p: dict[str, torch.Tensor], x: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """`wires`, and the wire head's inputs to tanh that gave their actions ([2, B, N A])."""
        h = self.trunk(p, x)
        z = torch.baddbmm(p["bw"].unsqueeze(1), h, p["Ww"].transpose(1, 2))
        u = torch.tanh(z).view(2, x.shape[0], self.shapes.n_wires, self.shapes.action_dim)
        return u, self.values(p, h, u), z


def wirefit(
    wire_u: torch.Tensor, wire_q: torch.Tensor, u: torch.Tensor, c: float, eps: float, top_k: int = 0
) -> torch.Tensor:
    """Q at actions u [..., A] from wires ([..., N, A], [..., N]), smoothing on normalised values.

    With 0 < top_k < N only the top_k largest weights count (ties at the k-th weight all count).
    """
    q = wire_q.detach()
    q_max = q.max(dim=-1, keepdim=True).values
    span = (q_max - q.min(dim=-1, keepdim=True).values).clamp_min(SPAN_FLOOR)
    d = ((u.unsqueeze(-2) - wire_u) ** 2).sum(dim=-1) + (q_max - q) * (c / span) + eps
    w = 1.0 / d
    if 0 < top_k < w.shape[-1]:
        kth = torch.topk(w.detach(), top_k, dim=-1).values[..., -1:]
        w = torch.where(w >= kth, w, torch.zeros_like(w))
    return (w * wire_q).sum(dim=-1) / w.sum(dim=-1)


def best_wire(wire_u: torch.Tensor, wire_q: torch.Tensor) -> torch.Tensor:
    """The best wire's action [B, A] of wires ([B, N, A], [B, N])."""
    best = wire_q.argmax(dim=-1)
    return torch.gather(wire_u, 1, best.view(-1, 1, 1).expand(-1, 1, wire_u.shape[-1])).squeeze(1)


def separation(wire_u: torch.Tensor, wire_q: torch.Tensor | None = None) -> torch.Tensor:
    """Mean over states and wire pairs of 1 / (distance + SEPARATION_EPS); wire_u [..., N, A].

    Given the wires' values wire_q [..., N], each state's best wire is held where it is: the
    pairs it is in push only the other wire. The greedy action is then placed by the values
    alone, not driven toward the action range's corners by the push (where tanh's gradient
    vanishes: on Reacher-v5 that left the greedy action at full torque for thousands of steps).
    """
    if wire_q is not None:
        best = tnf.one_hot(wire_q.argmax(dim=-1), wire_q.shape[-1]).unsqueeze(-1).bool()
        wire_u = torch.where(best, wire_u.detach(), wire_u)
    n = wire_u.shape[-2]
    if n < 2:
        return wire_u.new_zeros(())
    # [..., N, N]; the diagonal (0) is left out below. Computed from the differences: above 25
    # points cdist by default takes |a|^2 + |b|^2 - 2 a.b, which in float32 cancels to 0 for
    # wires 1e-4 apart, and the push between them with it.
    dist = torch.cdist(wire_u, wire_u, compute_mode="donot_use_mm_for_euclid_dist")
    inverse = 1.0 / (dist + SEPARATION_EPS)
    diagonal = n / SEPARATION_EPS
    return (inverse.sum(dim=(-1, -2)) - diagonal).mean() / (n * (n - 1))


def loss(
    critics: Critics,
    config: LearnerConfig,
    blocks: dict[str, torch.Tensor],
    target: torch.Tensor,
    x: torch.Tensor,
    u: torch.Tensor,
    reward: torch.Tensor,
    next_state: torch.Tensor,
    discount: torch.Tensor,
    noise: torch.Tensor,
    scale: torch.Tensor,
) -> Losses:
    """The update's loss (module docstring) -> (loss, critic 1's Q(x, u) [B], targets y [B]).

    blocks are both critics' weights (`Critics.blocks`), target [2 n] their targets as one vector;
    x [B, S], u [B, A], reward and discount [B], next_state [B, S], noise [B, A] standard normal;
    scale [2] the (mean, std) that normalise the values (read only with deep.popart_rate). Q and
    y come back in the task's units. Pure in its arguments, so that torch.compile can take it whole.
    """
    cfg, d = config, config.deep
    c, eps, k = cfg.smoothing_c, cfg.eps, d.top_k
    popart = d.popart_rate > 0.0  # fixed per config: without it the graph is the one it always was
    mean, std = scale[0], scale[1]
    target_blocks = critics.blocks(target)
    with torch.no_grad():
        tu, tq = critics.wires(target_blocks, next_state)
        next_u = best_wire(tu[0], tq[0])
        if d.target_noise > 0.0:
            next_u = next_u + (noise * d.target_noise).clamp(-d.target_noise_clip, d.target_noise_clip)
            next_u = next_u.clamp(-1.0, 1.0)
        next_q = wirefit(tu, tq, next_u, c, eps, k).min(dim=0).values
        if popart:
            next_q = next_q * std + mean
        y = reward + discount * next_q
        if cfg.advantage_k < 1.0:
            nu, nq = critics.wires(target_blocks, x)
            v = wirefit(nu, nq, best_wire(nu[0], nq[0]), c, eps, k).min(dim=0).values
            if popart:
                v = v * std + mean
            y = v + (y - v) / cfg.advantage_k
        learnt = (y - mean) / std if popart else y
    wu, wq, z = critics.wires_and_preactivations(blocks, x)
    Q = wirefit(wu, wq, u, c, eps, k)  # [2, B]
    total = ((Q - learnt) ** 2).mean(dim=1).sum()
    aux = 1.0 / (std * std) if popart else 1.0  # their weight against the values in the task's units
    if d.separation > 0.0:
        total = total + aux * 2.0 * d.separation * separation(wu, None if d.separate_best else wq)
    if d.tanh_limit > 0.0:
        total = total + aux * (tnf.relu(z.abs() - d.tanh_limit) ** 2).mean(dim=(1, 2)).sum()
    if cfg.bc_weight > 0.0:
        total = total + aux * cfg.bc_weight * ((best_wire(wu[0], wq[0]) - u) ** 2).sum(dim=-1).mean()
    Q1 = Q[0].detach()
    return total, (Q1 * std + mean if popart else Q1), y


@functools.lru_cache(maxsize=8)
def compiled_loss(config: LearnerConfig) -> Callable[..., Losses]:
    """`loss` for this config, through torch.compile (compiled when first called).

    One per config in a process, so that learners with one config (a population's members,
    given seed 0 here) share one compiled graph: torch recompiles a function at most a few
    times before it gives up and runs it uncompiled.
    """
    critics = Critics(DeepShapes.of(config))

    def bound(blocks: dict[str, torch.Tensor], *args: torch.Tensor) -> Losses:
        return loss(critics, config, blocks, *args)

    return torch.compile(bound, dynamic=False)


ADAM_BETAS = (0.9, 0.999)
ADAM_EPS = 1e-8
"""Adam's moment decays and denominator term (Kingma and Ba 2015's defaults)."""
GRAD_NORM_LIMIT = 1e18
"""The largest gradient norm of an update where deep.grad_clip does not bound it (0, or a norm
beyond float32's range): Adam's second moment holds squares of the gradient's components in
float32 (largest 3.4e38), which a gradient beyond about 1.8e19 overflows, freezing the weights it
covers and leaving a training state that no load accepts (as a task paying 1e20 a step gives)."""


M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
"""glibc's mallopt parameter numbers (malloc.h)."""


@functools.cache  # once per process: every trainer calls it, and loading libc is not free
def keep_freed_memory() -> None:
    """Ask glibc's malloc to keep freed blocks for reuse instead of returning them to the system.

    An update allocates and frees the same few megabytes of temporaries each time. With glibc's
    default thresholds, blocks above 128 KiB go back to the system when freed, and every fresh one
    page-faults as it is written: that doubled a small network's update here. Process-wide and
    harmless where it does not apply (another C library: nothing happens).
    """
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.mallopt(M_MMAP_THRESHOLD, 64 << 20)
        libc.mallopt(M_TRIM_THRESHOLD, 128 << 20)
    except (OSError, AttributeError):
        pass


def check_device(name: str) -> torch.device:
    """The torch device `deep.device` names, where torch sees it (else a ValueError)."""
    device = torch.device(name)
    seen = torch.cuda.is_available() and (device.index or 0) < torch.cuda.device_count()
    if device.type == "cuda" and not seen:
        raise ValueError(f"deep.device {name}: torch sees no such CUDA device here")
    return device


class Trainer:
    """The critics' weights, targets and Adam state, and the minibatch update.

    Adam and gradient-norm clipping are written out over the one flat vector: a handful of
    in-place operations, where torch's optimiser and clipping utilities spend more time in
    their Python bookkeeping than a small network's whole backward pass.
    """

    def __init__(self, config: LearnerConfig, theta: np.ndarray, seed: int) -> None:
        d = config.deep
        self.config = config
        self.device = check_device(d.device)
        if self.device.type == "cpu":
            # One core: the result then does not depend on how many threads the process (or the
            # thread thinking in it) gets, so a server and an in-process learner agree exactly.
            torch.set_num_threads(1)
        keep_freed_memory()
        self.critics = Critics(DeepShapes.of(config))
        self.theta = torch.tensor(theta, dtype=torch.float32, device=self.device)
        """Both critics' weights [2 n], outside autograd: Adam updates them in place."""
        self.blocks = self.critics.blocks(self.theta)
        """theta's blocks (views), each a leaf of the loss's graph: the gradient is taken per block."""
        self._grad = torch.zeros_like(self.theta)
        """The loss's gradient [2 n], laid out as theta: each block's gradient is a view of it, into
        which the backward pass adds in place (no gradient vector assembled per update)."""
        for block, grad in zip(self.blocks.values(), self.critics.blocks(self._grad).values(), strict=True):
            block.requires_grad_(True)
            block.grad = grad
        self.target = self.theta.clone()
        self._outputs = [(b["vo"], b["bo"]) for b in map(self.critics.blocks, (self.theta, self.target))]
        """Both critics' output layers in theta and in target (views made once, not the loss's
        leaves), which `_rescale` moves."""
        self.adam_m = torch.zeros_like(self.target)
        self.adam_v = torch.zeros_like(self.target)
        self.adam_step = 0
        self._denominator = torch.empty_like(self.target)
        """Adam's denominator, rewritten in place by each step (no new vector per update)."""
        self._critic1 = self.theta[: self.critics.n].numpy() if self.device.type == "cpu" else None
        """Critic 1's float32 weights as a numpy view of theta (on a CPU), for `critic1`."""
        self.moments = np.zeros(3)
        """The targets' running moments (`deep_net.value_scale`), with deep.popart_rate."""
        self._identity = torch.tensor([0.0, 1.0], device=self.device)
        self.generator = torch.Generator(device=self.device).manual_seed(int(seed))
        self._compiled: Any = None
        """`loss` compiled (deep.compile), False where compiling failed, None until first used."""

    def reset(self, theta: np.ndarray) -> None:
        """Fresh weights (targets equal), and Adam's moments forgotten."""
        self.theta.copy_(torch.as_tensor(theta, dtype=torch.float32))
        self.target.copy_(self.theta)
        self.moments = np.zeros(3)
        self._forget_adam()

    def _forget_adam(self) -> None:
        self.adam_m.zero_()
        self.adam_v.zero_()
        self.adam_step = 0

    def _step(self, grad: torch.Tensor) -> None:
        """Clip the gradient's norm at deep.grad_clip (GRAD_NORM_LIMIT where 0), then one Adam step.

        The clipping factor is float32 arithmetic on the norm as a numpy scalar, with the roundings
        of the 0-dim tensor operations it replaces (norm + 1e-6; grad_clip / that, which torch
        computes as the reciprocal times grad_clip; min with 1) without their overhead. A factor
        of 1 (no clipping) leaves the gradient as it is, as multiplying by 1 would.
        """
        d = self.config.deep
        norm = torch.linalg.vector_norm(grad).item()
        if d.grad_clip > 0.0 and norm != math.inf:
            norm32 = np.float32(norm) + np.float32(1e-6)
            scale = np.minimum((np.float32(1.0) / norm32) * np.float32(d.grad_clip), np.float32(1.0))
            if scale != 1.0:  # NaN included: it spreads to the gradient as before
                grad.mul_(float(scale))
        else:  # no clipping asked for, or squares beyond float32: bounded in float64 all the same
            if norm == math.inf:
                norm = torch.linalg.vector_norm(grad, dtype=torch.float64).item()
            limit = d.grad_clip if d.grad_clip > 0.0 else GRAD_NORM_LIMIT
            if norm > limit:  # NaN is not: it spreads to the gradient as before
                grad.mul_(limit / norm)
        beta1, beta2 = ADAM_BETAS
        self.adam_step += 1
        self.adam_m.lerp_(grad, 1.0 - beta1)
        self.adam_v.mul_(beta2).addcmul_(grad, grad, value=1.0 - beta2)
        denominator = torch.div(self.adam_v, 1.0 - beta2**self.adam_step, out=self._denominator)
        denominator.sqrt_().add_(ADAM_EPS)
        self.theta.addcdiv_(self.adam_m, denominator, value=-d.lr / (1.0 - beta1**self.adam_step))

    def critic1(self) -> np.ndarray:
        """Critic 1's weights as float64 [n_params] (what `act` uses), values in the task's units."""
        if self._critic1 is not None:  # float32 to float64 is exact, in numpy as in torch
            raw = self._critic1.astype(np.float64)
        else:
            raw = self.theta[: self.critics.n].to("cpu", torch.float64).numpy()
        if self.moments[2] > 0.0:  # learnt normalised (deep.popart_rate)
            return in_task_units(raw, self.critics.shapes, *value_scale(self.moments))
        return raw

    def _tensors(self, batch: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
        """The minibatch's arrays as float32 tensors on the device, moved in one copy.

        The arrays are cast into one float32 block [B, columns] by one concatenation, in the
        batch's order, and the tensors are that block's columns (views).
        """
        names = list(batch)
        b = len(batch["reward"])
        columns = [np.asarray(batch[k]).reshape(b, -1) for k in names]
        widths = [c.shape[1] for c in columns]
        packed = np.concatenate(columns, axis=1, dtype=np.float32, casting="unsafe")  # as astype
        parts = torch.split(torch.from_numpy(packed).to(self.device), widths, dim=1)
        return {k: (p if w > 1 or k in ("state", "action", "next_state") else p.squeeze(1))
                for k, p, w in zip(names, parts, widths, strict=True)}  # fmt: skip

    def update(self, batch: dict[str, np.ndarray], stats: bool = True) -> tuple[float, float]:
        """One Adam step on a minibatch (arrays [B, ...]) -> (mean Q(x, u), mean |y - Q(x, u)|).

        With stats False the step is the same and (nan, nan) comes back: for all but the last
        of several updates, whose statistics nobody reads.
        """
        d = self.config.deep
        t = self._tensors(batch)
        noise = torch.randn(t["action"].shape, generator=self.generator, device=self.device)
        total, Q1, y = self._losses(t, noise)
        self._step(self.gradient(total))
        self.target.lerp_(self.theta, d.tau)
        if d.popart_rate > 0.0:
            self._track(y)
        if not stats:
            return float("nan"), float("nan")
        return float(Q1.mean()), float((y - Q1).abs_().mean())

    def _losses(self, t: dict[str, torch.Tensor], noise: torch.Tensor) -> Losses:
        """`loss` (compiled where deep.compile is set) on a minibatch's tensors (`_tensors`) and noise."""
        d = self.config.deep
        popart = d.popart_rate > 0.0
        scale = torch.tensor(value_scale(self.moments), device=self.device) if popart else self._identity
        args = (self.blocks, self.target, t["state"], t["action"], t["reward"], t["next_state"],
                t["discount"], noise, scale)  # fmt: skip
        return self._compiled_loss(args) if d.compile else loss(self.critics, self.config, *args)

    def _track(self, y: torch.Tensor) -> None:
        """The statistics take in targets y [B]; the output layers keep every value as it was.

        In float64: squares of targets beyond 1.8e19 would be infinite in float32.
        """
        before = value_scale(self.moments)
        y64 = y.detach().to(torch.float64)
        rate = self.config.deep.popart_rate
        batch = np.array([float(y64.mean()), float((y64 * y64).mean()), 1.0])
        self.moments = (1.0 - rate) * self.moments + rate * batch
        self._rescale(before, value_scale(self.moments))

    def _rescale(self, before: tuple[float, float], after: tuple[float, float]) -> None:
        """Both critics' and targets' output layers: values under `before` the same under `after`.

        std v~ + mean = std' v~' + mean' for v~' = (std v~ + mean - mean') / std'.
        """
        (mean, std), (mean2, std2) = before, after
        with torch.no_grad():
            for vo, bo in self._outputs:
                vo.mul_(std / std2)
                bo.mul_(std / std2).add_((mean - mean2) / std2)

    def gradient(self, total: torch.Tensor) -> torch.Tensor:
        """The gradient [2 n] of a loss computed from `blocks`, laid out as theta.

        One vector, rewritten by the next call: copy it to keep it.
        """
        self._grad.zero_()
        total.backward()
        return self._grad

    def warm(self) -> None:
        """Compile the update now (deep.compile), on a batch of zeros: no weight, moment or stream moves.

        Its first real update compiled it otherwise, for 5 to 30 s holding the interpreter lock
        much of the time: in a robot's own process, beside its control loop, ticks came late.
        """
        if not self.config.deep.compile or self._compiled is not None:
            return
        b, s, a = self.config.batch_size, self.config.state_dim, self.config.action_dim
        # Laid out as every update's minibatch (`_tensors`' views of one block, in `think`'s order):
        # torch.compile guards on strides too, and contiguous zeros were compiled again at the first update.
        zeros = {"state": np.zeros((b, s)), "action": np.zeros((b, a)), "reward": np.zeros(b),
                 "next_state": np.zeros((b, s)), "discount": np.zeros(b)}  # fmt: skip
        t = self._tensors(zeros)
        total, _, _ = self._losses(t, torch.zeros(t["action"].shape, device=self.device))
        try:
            self.gradient(total)  # the backward pass is compiled at its first call too
        except Exception as exc:  # as a failing forward compile: the uncompiled loss is the same arithmetic
            logger.warning("deep.compile: torch.compile failed (%s); training uncompiled", exc)
            self._compiled = False
        self._grad.zero_()

    def _compiled_loss(self, args: tuple[Any, ...]) -> Losses:
        """`loss` through torch.compile (compiled in its first call); uncompiled where that fails."""
        if self._compiled is None:
            self._compiled = compiled_loss(dataclasses.replace(self.config, seed=0))
        if self._compiled is not False:
            try:
                return cast(Losses, self._compiled(*args))
            except Exception as exc:  # a compiler fault: the uncompiled loss is the same arithmetic
                logger.warning("deep.compile: torch.compile failed (%s); training uncompiled", exc)
                self._compiled = False
        return loss(self.critics, self.config, *args)

    def generator_state(self) -> np.ndarray:
        """Where the smoothing noise's generator stands, as bytes [n] uint8 (n fixed per device type)."""
        return self.generator.get_state().numpy().copy()

    # ------------------------------------------------------------------ state
    def state(self) -> dict[str, np.ndarray]:
        """Everything training needs to resume: weights, targets, Adam's moments and step."""
        out = {"theta": self.theta.cpu().numpy().copy(), "target": self.target.cpu().numpy().copy()}
        if self.moments[2] > 0.0:
            out["value_moments"] = self.moments.copy()
        if self.adam_step > 0:
            out["adam_m"] = self.adam_m.cpu().numpy().copy()
            out["adam_v"] = self.adam_v.cpu().numpy().copy()
            out["adam_step"] = np.asarray(float(self.adam_step), dtype=np.float64)
        return out

    def load(self, state: dict[str, np.ndarray]) -> None:
        """Inverse of `state` (arrays checked for shape and finiteness by the caller).

        Weights that learnt normalised values (saved with `value_moments`) go on so with
        deep.popart_rate, and are turned into values in the task's units without it; weights
        saved without go on in the task's units either way (the statistics start afresh).
        """
        self.theta.copy_(torch.as_tensor(state["theta"], dtype=torch.float32))
        self.target.copy_(torch.as_tensor(state["target"], dtype=torch.float32))
        self.moments = np.array(state.get("value_moments", np.zeros(3)), dtype=np.float64)
        if self.moments[2] > 0.0 and self.config.deep.popart_rate == 0.0:
            self._rescale(value_scale(self.moments), value_scale(np.zeros(3)))
            self.moments = np.zeros(3)
        self._forget_adam()
        if "adam_m" in state:
            self.adam_m.copy_(torch.as_tensor(state["adam_m"], dtype=torch.float32))
            self.adam_v.copy_(torch.as_tensor(state["adam_v"], dtype=torch.float32))
            self.adam_step = int(state["adam_step"])


def checked_generator_state(value: Any, device: str | torch.device) -> torch.Tensor | None:
    """A saved generator's bytes as `device`'s generator takes them (ValueError: no generator's state).

    None where they are another device type's generator's (a CPU's or a CUDA device's, told by
    their length): a checkpoint moved between a CPU and a GPU keeps everything else. Bytes of
    any other length are damage.
    """
    words = np.asarray(value)
    if words.dtype != np.uint8 or words.ndim != 1:
        raise ValueError(f"training state random_noise: {words.dtype} {words.shape}, not a state")
    generator = torch.Generator(device=check_device(str(device)))
    own = int(generator.get_state().shape[0])
    if words.shape[0] != own:
        lengths = {int(torch.Generator().get_state().shape[0]), CUDA_GENERATOR_BYTES}
        if words.shape[0] not in lengths:
            known = " or ".join(map(str, sorted(lengths)))
            raise ValueError(f"training state random_noise: {words.shape[0]} bytes, no generator's "
                             f"state (a CPU's or a CUDA device's is {known})")  # fmt: skip
        logger.warning("training state random_noise is of another device type's generator: the "
                       "smoothing noise is drawn afresh from its seed")  # fmt: skip
        return None
    state = torch.from_numpy(words.copy())
    try:
        generator.set_state(state)  # a scratch generator: only checked here
    except RuntimeError as exc:
        raise ValueError(f"training state random_noise: {exc}") from exc
    return state
