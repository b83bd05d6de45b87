"""The deep wire-fitting learner: its numpy act, torch update, returns, state and interface."""

import logging
import platform
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

from wfnn_common import config as config_module
from wfnn_common import deep_net
from wfnn_common.config import MAX_SEED, ConfigError, DeepConfig, LearnerConfig, with_options
from wfnn_common.deep import DeepWFNN
from wfnn_common.deep_torch import (
    SEPARATION_EPS,
    Critics,
    best_wire,
    compiled_loss,
    loss,
    separation,
    wirefit,
)
from wfnn_common.learner import RANDOM_STATE
from wfnn_common.learners import make_learner, make_population, n_params, weights_from_flat
from wfnn_common.surface import SurfaceGrid
from wfnn_common.symmetry import Symmetry
from wfnn_io.persist import load_checkpoint, load_weights, save_weights


class Task:
    state_low, state_high = (-1.0, -2.0), (1.0, 2.0)
    action_low, action_high = (-2.0,), (2.0,)


def config(**over):
    deep = over.pop("deep", {})
    base = {"hidden": (32, 32), "value_hidden": 16, "warmup": 0}
    return LearnerConfig.for_task(Task(), learner="deep", deep=DeepConfig(**{**base, **deep}), **over)


def test_config_defaults_round_trip_and_spec_hash():
    cfg = LearnerConfig.for_task(Task(), learner="deep")
    assert cfg.gamma == 0.99 and cfg.thinks_per_action == 1 and not cfg.squash_reward
    assert cfg.exploration.kind == "smooth" and cfg.exploration.sigma == 0.1
    assert LearnerConfig.from_json(cfg.to_json()) == cfg
    thesis = LearnerConfig.for_task(Task())
    # The thesis' spec hash is what it was before the deep learner existed: its files stay valid.
    spec = LearnerConfig(state_low=(0.0,), state_high=(1.0,), action_low=(0.0,), action_high=(1.0,))
    assert spec.spec_hash() == "283bc71bbd8b7642"
    hashes = {thesis.spec_hash(), cfg.spec_hash(), with_options(cfg, {"deep": {"hidden": [64]}}).spec_hash()}
    assert len(hashes) == 3
    # A spec written before value_layers existed (one layer) keeps its hash; more layers are another.
    assert cfg.spec_hash() == "b776c36b7fd2661e"
    assert with_options(cfg, {"deep": {"value_layers": 2}}).spec_hash() not in hashes
    # Training-only fields do not change what a snapshot means.
    assert with_options(cfg, {"deep": {"lr": 1e-3}, "gamma": 0.9}).spec_hash() == cfg.spec_hash()
    with pytest.raises(ConfigError, match=r"deep\.n_step"):
        with_options(cfg, {"deep": {"n_step": 0}})
    with pytest.raises(ConfigError, match="unknown DeepConfig"):
        LearnerConfig.from_dict({**cfg.to_dict(), "deep": {"bogus": 1}})
    with pytest.raises(ConfigError, match="learner must be"):
        with_options(cfg, {"learner": "other"})


@pytest.mark.parametrize(("layer_norm", "value_layers"), [(False, 1), (True, 1), (False, 2), (True, 3)])
def test_numpy_and_torch_critics_agree(layer_norm, value_layers):
    cfg = config(deep={"layer_norm": layer_norm, "value_layers": value_layers})
    shapes = deep_net.DeepShapes.of(cfg)
    rng = np.random.default_rng(0)
    theta = np.concatenate([deep_net.init_critic(shapes, rng) for _ in range(2)])
    x = rng.uniform(-1, 1, (5, 2))
    u_t, q_t = Critics(shapes).wires(Critics(shapes).blocks(torch.tensor(theta)), torch.tensor(x))
    for j in range(2):
        params = weights_from_flat(cfg, theta[None, j * shapes.n_params : (j + 1) * shapes.n_params].copy())
        u, q = deep_net.wires(params, x)
        np.testing.assert_allclose(u, u_t[j].numpy(), atol=1e-10)
        np.testing.assert_allclose(q, q_t[j].numpy(), atol=1e-10)
        assert u.shape == (5, cfg.n_wires, 1) and np.abs(u).max() <= 1.0
    u = rng.uniform(-1, 1, (5, 1))
    np.testing.assert_allclose(
        deep_net.wirefit_normalised(u_t[0].numpy(), q_t[0].numpy(), u, 0.1, 1e-4),
        wirefit(u_t[0], q_t[0], torch.tensor(u), 0.1, 1e-4).numpy(), atol=1e-10,
    )  # fmt: skip


def test_wire_fitting_peaks_at_the_best_wire():
    rng = np.random.default_rng(1)
    wire_u, wire_q = rng.uniform(-1, 1, (4, 6, 2)), rng.normal(size=(4, 6))
    best = best_wire(torch.tensor(wire_u), torch.tensor(wire_q)).numpy()
    at_best = deep_net.wirefit_normalised(wire_u, wire_q, best, 0.1, 1e-4)
    np.testing.assert_allclose(at_best, wire_q.max(axis=1), atol=0.02)
    elsewhere = deep_net.wirefit_normalised(wire_u, wire_q, rng.uniform(-1, 1, (4, 2)), 0.1, 1e-4)
    assert (elsewhere <= at_best + 1e-9).all()


def test_top_k_interpolates_only_the_nearest_wires():
    rng = np.random.default_rng(2)
    wire_u, wire_q = rng.uniform(-1, 1, (5, 6, 2)), rng.normal(size=(5, 6))
    u = rng.uniform(-1, 1, (5, 2))
    everything = deep_net.wirefit_normalised(wire_u, wire_q, u, 0.1, 1e-4)
    for k in (6, 9):  # k at least N: every wire, as k = 0
        np.testing.assert_allclose(deep_net.wirefit_normalised(wire_u, wire_q, u, 0.1, 1e-4, k), everything)
    # k = 1: the value of the wire of largest weight (smallest distance with the smoothing term).
    span = wire_q.max(1, keepdims=True) - wire_q.min(1, keepdims=True)
    d = ((u[:, None] - wire_u) ** 2).sum(-1) + 0.1 * (wire_q.max(1, keepdims=True) - wire_q) / span
    nearest = wire_q[np.arange(5), d.argmin(1)]
    np.testing.assert_allclose(deep_net.wirefit_normalised(wire_u, wire_q, u, 0.1, 1e-4, 1), nearest)
    three = deep_net.wirefit_normalised(wire_u, wire_q, u, 0.1, 1e-4, 3)
    assert not np.allclose(three, everything) and not np.allclose(three, nearest)
    q_t = torch.tensor(wire_q, requires_grad=True)
    u_t = torch.tensor(wire_u, requires_grad=True)
    q = wirefit(u_t, q_t, torch.tensor(u), 0.1, 1e-4, 3)
    np.testing.assert_allclose(q.detach().numpy(), three, atol=1e-12)
    q.sum().backward()
    assert q_t.grad is not None and u_t.grad is not None
    # Only the three nearest wires of each state learn from it, values and actions alike.
    far = np.argsort(d, axis=1)[:, 3:]
    rows = np.arange(5)[:, None]
    near = np.argsort(d, axis=1)[:, :3]
    assert (q_t.grad.numpy()[rows, far] == 0).all() and (q_t.grad.numpy()[rows, near] != 0).all()
    assert (u_t.grad.numpy()[rows, far] == 0).all()
    with pytest.raises(ConfigError, match=r"deep\.top_k"):
        config(deep={"top_k": -1})


def test_top_k_learners_train_and_show_the_same_q():
    cfg = config(n_wires=6, batch_size=32, deep={"top_k": 2})
    learner = DeepWFNN(cfg)
    rng = np.random.default_rng(3)
    s, a = rng.uniform(-1, 1, (200, 2)), rng.uniform(-2, 2, (200, 1))
    learner.learn_many(s, a, s, -(a[:, 0] ** 2), np.ones(200, dtype=bool))
    learner.think(20)
    assert np.isfinite(learner.last_think.td_abs[0])
    surface = SurfaceGrid(cfg, (0,), 11)(learner.params, np.array([0.1, 0.2]))
    x = np.array([0.1, 0.2])
    q = [learner.q_value(x, np.array([a])) for a in surface.axes[0]]
    np.testing.assert_allclose(surface.q, q)
    every_wire = DeepWFNN(with_options(cfg, {"deep": {"top_k": 0}}), params=learner.params)
    assert not np.allclose(q, [every_wire.q_value(x, np.array([a])) for a in surface.axes[0]])


def test_separation_pushes_wires_apart():
    close = torch.tensor([[[0.0], [0.01], [0.5]]], requires_grad=True)
    separation(close).backward()
    assert close.grad is not None and close.grad[0, 0, 0] > 0 > close.grad[0, 1, 0]
    assert separation(torch.tensor([[[0.0], [1.0]]])) < separation(torch.tensor([[[0.0], [0.1]]]))


def test_act_is_the_best_wire_and_needs_no_torch():
    learner = make_learner(config())
    x = np.array([0.3, -1.0])
    act = learner.act(x, explore=False)
    wire_u, wire_q = deep_net.wires(learner.params, learner.state_scaler.to_unit(x[None]))
    assert act.value == pytest.approx(wire_q[0].max())
    assert act.action == pytest.approx(wire_u[0, wire_q[0].argmax()] * 2.0)
    code = (
        "import sys, numpy as np\n"
        "from wfnn_common.config import LearnerConfig\nfrom wfnn_common.learners import make_learner\n"
        "class T: state_low=(-1.,); state_high=(1.,); action_low=(-1.,); action_high=(1.,)\n"
        "L = make_learner(LearnerConfig.for_task(T(), learner='deep'))\n"
        "L.act(np.zeros(1)); L.learn(np.zeros(1), np.zeros(1), np.zeros(1), 0.0)\n"
        "assert 'torch' not in sys.modules, 'torch imported'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


@pytest.mark.parametrize("layer_norm", [False, True])
def test_the_act_path_matches_the_batch_wires_and_weights_are_immutable(layer_norm):
    learner = DeepWFNN(config(deep={"layer_norm": layer_norm}))
    rng = np.random.default_rng(3)
    x = rng.uniform(-1, 1, (4, 2))

    def agree() -> None:
        u, q = deep_net.wires(learner.params, x)
        unit = np.zeros(2), np.ones(2)
        for i in range(4):
            _, _, u1, q1, _ = deep_net.act_one(*learner.params.act_layout, x[i], *unit, np.inf)
            np.testing.assert_allclose(u1, u[i], atol=1e-12)
            np.testing.assert_allclose(q1, q[i], atol=1e-12)

    agree()
    # act's arrays are derived from the weights once: writing them in place would leave act stale.
    with pytest.raises(ValueError, match="read-only"):
        learner.params.flat[0, 0] = 1.0
    before = learner.params
    learner.learn(np.zeros(2), np.zeros(1), np.zeros(2), -1.0)
    learner.think(2)
    assert learner.params is not before and not np.array_equal(learner.params.flat, before.flat)
    agree()
    learner.reset_weights(np.ones(1, dtype=bool))
    agree()


def _fed(learner: DeepWFNN) -> DeepWFNN:
    rng = np.random.default_rng(4)
    learner.learn_many(rng.uniform(-1, 1, (64, 2)), rng.uniform(-2, 2, (64, 1)),
                       rng.uniform(-1, 1, (64, 2)), -rng.random(64), np.zeros(64, dtype=bool))  # fmt: skip
    return learner


def _loss_args(trainer, seed):
    """`loss`'s arguments after the critics and config: the trainer's blocks and targets, a
    random minibatch of 32 of the test task's shapes, and values' (mean, std) of (-3, 2.5)."""
    rng = np.random.default_rng(seed)
    batch = (torch.tensor(rng.uniform(-1, 1, shape), dtype=torch.float32)
             for shape in [(32, 2), (32, 1), (32,), (32, 2), (32,), (32, 1)])  # fmt: skip
    return (trainer.blocks, trainer.target, *batch, torch.tensor([-3.0, 2.5]))


@pytest.mark.parametrize(
    "options", [{}, {"top_k": 3, "tanh_limit": 3.0}, {"value_layers": 2}, {"popart_rate": 0.01}]
)
def test_the_gradient_taken_block_by_block_is_the_whole_vectors(options):
    learner = _fed(DeepWFNN(config(deep=options)))
    learner.think(2)  # an earlier gradient is in the vector, and Adam has moved the weights
    trainer = learner._train()
    args = _loss_args(trainer, seed=4)
    whole = trainer.theta.clone().requires_grad_(True)
    (expected,) = torch.autograd.grad(
        loss(trainer.critics, trainer.config, trainer.critics.blocks(whole), *args[1:])[0], whole
    )
    got = trainer.gradient(loss(trainer.critics, trainer.config, *args)[0])
    assert got.shape == trainer.theta.shape and expected.abs().min() < expected.abs().max()
    torch.testing.assert_close(got, expected, rtol=0.0, atol=0.0)


def test_a_failing_compiler_leaves_the_same_update(monkeypatch, caplog):
    def broken(fn, **kwargs):
        def compiled(*args):
            raise RuntimeError("no C++ compiler here")

        return compiled

    monkeypatch.setattr(torch, "compile", broken)
    compiled_loss.cache_clear()  # compiled in an earlier test with this config: compile again
    compiled, plain = _fed(DeepWFNN(config(deep={"compile": True}))), _fed(DeepWFNN(config()))
    try:
        with caplog.at_level(logging.WARNING):
            compiled.think(3)
    finally:
        compiled_loss.cache_clear()  # the broken compiler's function is not for later tests
    plain.think(3)
    assert "training uncompiled" in caplog.text and compiled._trainer._compiled is False
    np.testing.assert_array_equal(compiled.params.flat, plain.params.flat)


@pytest.mark.parametrize("options", [{}, {"popart_rate": 0.01}])
def test_a_compiled_update_is_compiled_before_thinking_and_leaves_no_trace(monkeypatch, options):
    """Compiled at its first real update, it held a robot's loop up for seconds (local thinking):
    `prepare_thinking(compile=True)`, which runs before the loop, compiles it on zeros laid out as
    every update's minibatch (torch guards on strides: contiguous zeros were compiled again at the
    first update), changing nothing. Torch's own tracing and guards, a backend that only counts."""
    graphs = []
    real_compile = torch.compile

    def counting(gm, example_inputs):
        graphs.append(gm)
        return gm.forward

    monkeypatch.setattr(torch, "compile", lambda fn, **kw: real_compile(fn, backend=counting, dynamic=False))
    # Torch's first compile in a process turns distributions' argument checks off for good: put back
    # after (a later test's SAC, learning NaN rewards, no longer failed).
    validating = torch.distributions.Distribution._validate_args
    compiled_loss.cache_clear()
    torch._dynamo.reset()
    try:
        warmed = _fed(DeepWFNN(config(deep={"compile": True, **options})))
        plain = _fed(DeepWFNN(config(deep=options)))
        warmed.prepare_thinking()  # not asked to compile: the first update would
        assert graphs == []
        warmed.prepare_thinking(compile=True)
        assert len(graphs) == 1
        trainer = warmed._train()
        assert trainer.adam_step == 0 and not trainer._grad.any()
        assert torch.equal(trainer.theta, trainer.target)
        warmed.think(3)
        plain.think(3)
        assert len(graphs) == 1  # not compiled again
    finally:
        compiled_loss.cache_clear()
        torch._dynamo.reset()
        torch.distributions.Distribution.set_default_validate_args(validating)
    np.testing.assert_allclose(warmed.params.flat, plain.params.flat, rtol=1e-5, atol=1e-6)


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("c++") is None, reason="torch.compile on a CPU needs a C++ compiler")
@pytest.mark.parametrize(
    "options",
    [{"top_k": 0}, {"top_k": 3}, {"separate_best": False, "tanh_limit": 3.0}, {"value_layers": 2},
     {"popart_rate": 0.01}],
)  # fmt: skip
def test_the_compiled_loss_and_gradient_are_the_uncompiled_ones(options):
    trainer = _fed(DeepWFNN(config(deep={"compile": True, **options})))._train()
    args = _loss_args(trainer, seed=5)
    compiled = trainer._compiled_loss(args)
    assert trainer._compiled not in (None, False), "torch.compile fell back"
    plain = loss(trainer.critics, trainer.config, *args)
    for a, b in zip(compiled, plain, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    grad_compiled = trainer.gradient(compiled[0]).clone()
    grad_plain = trainer.gradient(plain[0])
    torch.testing.assert_close(grad_compiled, grad_plain, rtol=1e-4, atol=1e-6)
    # Learners that differ only in their seed (a population's members) share the compiled loss.
    other = _fed(DeepWFNN(config(seed=7, deep={"compile": True, **options})))
    other.think(1)
    assert other._trainer._compiled is trainer._compiled


@pytest.mark.parametrize(
    ("hidden", "state_dim", "action_dim", "layer_norm", "value_layers"),
    [((128, 128), 11, 3, True, 1), ((7,), 1, 1, False, 2), ((40, 9, 33), 5, 2, True, 3)],
)
def test_the_compiled_act_is_the_batch_forward_pass(hidden, state_dim, action_dim, layer_norm, value_layers):
    """`act_one` (transposed weights, ReLU zeros skipped) gives `wires` of any shape, the first best wire."""
    shapes = deep_net.DeepShapes(state_dim, action_dim, hidden, 24, 6, layer_norm, value_layers)
    rng = np.random.default_rng(11)
    params = deep_net.DeepParams(deep_net.init_critic(shapes, rng)[None], shapes)
    mid, half = rng.normal(size=state_dim), rng.uniform(0.5, 2.0, state_dim)
    states = mid + half * rng.uniform(-3.0, 3.0, (20, state_dim))
    wire_u, wire_q = deep_net.wires(params, (states - mid) / half)
    for s, u, q in zip(states, wire_u, wire_q, strict=True):
        valid, x, u1, q1, best = deep_net.act_one(*params.act_layout, s, mid, half, 3.0)
        assert valid and best == q.argmax()
        np.testing.assert_allclose(x, (s - mid) / half, rtol=1e-15, atol=1e-15)
        np.testing.assert_allclose(u1, u, atol=1e-12)
        np.testing.assert_allclose(q1, q, atol=1e-12)
    outside = states[0].copy()
    outside[-1] = mid[-1] + 3.5 * half[-1]
    assert not deep_net.act_one(*params.act_layout, outside, mid, half, 3.0)[0]
    assert not deep_net.act_one(*params.act_layout, outside * np.nan, mid, half, np.inf)[0]


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="the setting is glibc's malloc's")
def test_freed_memory_is_kept_for_reuse():
    """An update's temporaries, freed and made again, must not page-fault each time (that doubled it)."""
    # In a process of its own: threads other tests leave winding down would fault pages too. The
    # first blocks grow the heap (how many depends on what was imported), so they are not counted.
    # 40 MiB is above the 32 MiB to which glibc's own threshold adapts: without the setting each
    # block is a fresh mapping (10,240 faults).
    script = (
        "import resource, torch\n"
        "from wfnn_common.deep_torch import keep_freed_memory\n"
        "keep_freed_memory()\n"
        "torch.set_num_threads(1)\n"
        "for k in range(30):\n"
        "    if k == 10:\n"
        "        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
        "    block = torch.empty(10 << 20)  # 40 MiB\n"
        "    block.fill_(1.0)\n"
        "    del block\n"
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)\n"
    )
    faults = int(subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True,
                                timeout=120).stdout)  # fmt: skip
    # At most a few fresh blocks' worth (once, on a busy machine, two blocks were): far from all 20.
    assert faults < 5 * 10_240, f"{faults} page faults for 20 reused blocks (204,800 if each were fresh)"


def test_warmup_actions_are_uniform_then_the_learners_own():
    learner = make_learner(config(deep={"warmup": 200}))
    x = np.zeros(2)
    first = np.array([learner.act(x).action[0] for _ in range(200)])
    greedy = learner.act(x, explore=False).action[0]
    assert first.min() < -1.5 and first.max() > 1.5  # spread over the whole range [-2, 2]
    later = np.array([learner.act(x).action[0] for _ in range(50)])
    assert np.abs(later - greedy).max() < 0.2 * 4  # gaussian sigma 0.1 of the range's half width


def test_learns_the_best_action_of_a_contextual_bandit():
    """One-step episodes, reward -(u - x0)^2: the greedy action must follow the state."""
    cfg = config(batch_size=64, deep={"lr": 3e-3, "target_noise": 0.0})
    learner = DeepWFNN(cfg)
    rng = np.random.default_rng(0)
    s = rng.uniform(-1, 1, (2000, 2))
    a = rng.uniform(-2, 2, (2000, 1))
    r = -((a[:, 0] - s[:, 0]) ** 2)
    learner.learn_many(s, a, s, r, np.ones(2000, dtype=bool))
    before = learner.think(1).td_abs[0]
    for _ in range(15):
        learner.think(100)
    assert learner.last_think.td_abs[0] < 0.5 * before
    tests = np.array([[-0.8, 0.0], [0.0, 1.0], [0.7, -1.0]])
    greedy = np.array([learner.act(t, explore=False).action[0] for t in tests])
    np.testing.assert_allclose(greedy, tests[:, 0], atol=0.5)  # of the range [-2, 2]
    assert int(learner.thinks[0]) == 1501


def test_n_step_returns_follow_consecutive_experiences_only():
    cfg = config(gamma=0.5, deep={"n_step": 3})
    learner = DeepWFNN(cfg)
    z = np.zeros(2)
    chain = [((0.1, 0), (0.2, 0), 1.0, False), ((0.2, 0), (0.3, 0), 2.0, False),
             ((0.3, 0), (0.4, 0), 4.0, False),
             ((0.9, 0), (0.5, 0), 8.0, False),  # starts elsewhere: a break
             ((0.5, 0), (0.6, 0), 16.0, True), ((0.6, 0), (0.7, 0), 32.0, False)]  # fmt: skip
    for s, sn, r, term in chain:
        learner.learn(np.array(s), z[:1], np.array(sn), r, term)
    batch = learner._n_step(np.arange(6))
    np.testing.assert_allclose(
        batch["reward"], [1 + 0.5 * 2 + 0.25 * 4, 2 + 0.5 * 4, 4, 8 + 0.5 * 16, 16, 32]
    )
    np.testing.assert_allclose(batch["discount"], [0.125, 0.25, 0.5, 0.0, 0.0, 0.5])
    np.testing.assert_allclose(batch["next_state"][:, 0], np.array([0.4, 0.4, 0.4, 0.0, 0.0, 0.7]) / 1.0)


def test_n_step_returns_follow_each_clients_chain_however_the_clients_interleave():
    """Two clients' experiences reach a server interleaved (one at a time, or in batches of
    different sizes): each return follows its own client's chain to its full length."""
    cfg = config(gamma=0.5, deep={"n_step": 3})
    z = np.zeros(1)
    a = [((0.1, 0.0), (0.2, 0.0), 1.0), ((0.2, 0.0), (0.3, 0.0), 2.0), ((0.3, 0.0), (0.4, 0.0), 4.0)]
    b = [((0.0, 0.1), (0.0, 0.2), 8.0), ((0.0, 0.2), (0.0, 0.3), 16.0), ((0.0, 0.3), (0.0, 0.4), 32.0)]
    one_by_one = DeepWFNN(cfg)
    for (sa, na, ra), (sb, nb, rb) in zip(a, b, strict=True):
        one_by_one.learn(np.array(sa), z, np.array(na), ra)
        one_by_one.learn(np.array(sb), z, np.array(nb), rb)
    batch = one_by_one._n_step(np.arange(6))  # stored a0 b0 a1 b1 a2 b2
    np.testing.assert_allclose(batch["reward"], [1 + 1 + 1, 8 + 8 + 8, 2 + 2, 16 + 16, 4, 32])
    np.testing.assert_allclose(batch["discount"], [0.125, 0.125, 0.25, 0.25, 0.5, 0.5])
    np.testing.assert_allclose(batch["next_state"], [[0.4, 0], [0, 0.2]] * 3)  # state ranges [1, 2]

    def block(rows):
        s, sn, r = (np.array([row[i] for row in rows]) for i in range(3))
        return s, np.zeros((len(rows), 1)), sn, r, np.zeros(len(rows), dtype=bool)

    batched = DeepWFNN(cfg)
    for rows in ([b[0]], a[:2], b[1:], a[2:]):  # stored b0 a0 a1 b1 b2 a2
        batched.learn_many(*block(rows))
    rewards = batched._n_step(np.arange(6))["reward"]
    np.testing.assert_allclose(rewards, [8 + 8 + 8, 1 + 1 + 1, 2 + 2, 16 + 16, 32, 4])


def test_n_step_returns_never_follow_an_overwritten_experience():
    cfg = config(gamma=0.5, replay_capacity=4, deep={"n_step": 3})
    learner = DeepWFNN(cfg)
    z = np.zeros(1)
    learner.learn(np.array([0.1, 0.0]), z, np.array([0.2, 0.0]), 1.0)
    for k in range(4):  # elsewhere, filling the ring: the first experience is overwritten
        learner.learn(np.array([0.5, 0.1 * k]), z, np.array([0.6, 0.1 * k]), 0.0)
    # Continues the overwritten one (slot 0's tenant now): no return runs on into it.
    learner.learn(np.array([0.2, 0.0]), z, np.array([0.3, 0.0]), 2.0)  # into slot 1
    batch = learner._n_step(np.arange(4))
    np.testing.assert_allclose(batch["discount"], [0.5] * 4)
    np.testing.assert_allclose(batch["reward"], [0.0, 2.0, 0.0, 0.0])


def test_training_state_saves_and_resumes_exactly(tmp_path):
    cfg = config()
    learner = DeepWFNN(cfg)
    rng = np.random.default_rng(2)
    learner.learn_many(rng.uniform(-1, 1, (100, 2)), rng.uniform(-2, 2, (100, 1)),
                       rng.uniform(-1, 1, (100, 2)), -rng.random(100), np.zeros(100, dtype=bool))  # fmt: skip
    learner.think(20)
    state = learner.training_state()
    trained = {"theta", "target", "adam_m", "adam_v", "adam_step", "reward_scale", "random_noise"}
    assert set(state) == trained | set(RANDOM_STATE) and float(state["adam_step"]) == 20
    save_weights(tmp_path / "ck.npz", cfg, learner.params, {"thinks": 20}, training=state)
    ck_cfg, params, _, training = load_checkpoint(tmp_path / "ck.npz")
    resumed = make_learner(ck_cfg, params=params)
    resumed.load_training_state(training)
    np.testing.assert_array_equal(resumed.params.flat, learner.params.flat)
    for key in state:
        np.testing.assert_array_equal(resumed.training_state()[key], state[key])
    assert load_weights(tmp_path / "ck.npz")[1].flat.shape == (1, n_params(cfg))
    # The same minibatch from the same state makes the same step.
    batch = learner._n_step(np.arange(32))
    learner._trainer.generator.manual_seed(5)
    resumed._trainer.generator.manual_seed(5)
    assert learner._trainer.update(batch) == resumed._trainer.update(batch)
    bad = dict(state, theta=state["theta"][:-1])
    with pytest.raises(ValueError, match="theta"):
        resumed.load_training_state(bad)
    with pytest.raises(ValueError, match="target"):
        resumed.load_training_state({**state, "target": np.full_like(state["target"], np.nan)})


def test_reset_and_divergence_keep_the_experiences():
    cfg = config(divergence_threshold=-1e9, divergence_patience=3)
    learner = DeepWFNN(cfg)
    learner.learn(np.zeros(2), np.zeros(1), np.zeros(2), -1.0)
    learner.think(2)
    before = learner.params.flat.copy()
    results = [learner.act(np.zeros(2), explore=False) for _ in range(3)]
    assert [bool(r.diverged) for r in results] == [False, False, True]
    assert int(learner.resets[0]) == 1 and int(learner.buffer.count[0]) == 1
    assert not np.array_equal(before, learner.params.flat)
    learner.think(1)  # the trainer took the fresh weights too
    assert np.isfinite(learner.params.flat).all()


def test_weights_gone_non_finite_are_reset_at_the_first_act():
    learner = DeepWFNN(config())  # patience 50: a NaN does not wait for it
    learner.learn(np.zeros(2), np.zeros(1), np.zeros(2), -1.0)
    learner.think(1)
    flat = learner.params.flat.copy()
    flat[0, :] = np.nan
    learner.params = deep_net.DeepParams(flat, learner.shapes)
    result = learner.act(np.zeros(2))
    assert bool(result.diverged) and int(learner.resets[0]) == 1
    assert np.isfinite(result.action).all()  # this once, the middle of the range
    assert np.isfinite(learner.params.flat).all()
    assert np.isfinite(learner.act(np.zeros(2), explore=False).action).all()


def test_bc_weight_pulls_the_best_wire_to_logged_actions():
    """No reward signal at all: only the pull can decide where the best wire goes."""
    rng = np.random.default_rng(3)
    s = rng.uniform(-1, 1, (500, 2))
    results = {}
    for bc in (0.0, 1.0):
        learner = DeepWFNN(config(bc_weight=bc, batch_size=64, deep={"lr": 3e-3}))
        learner.learn_many(s, np.full((500, 1), 1.4), s, np.zeros(500), np.ones(500, dtype=bool))
        learner.think(300)
        results[bc] = np.array([learner.act(x, explore=False).action[0] for x in s[:20]])
    assert np.abs(results[1.0] - 1.4).max() < 0.15
    assert np.abs(results[0.0] - 1.4).mean() > np.abs(results[1.0] - 1.4).mean()


def test_symmetries_store_the_mirrored_experience():
    mirror = Symmetry(
        name="mirror", state_index=(0, 1), state_sign=(1.0, -1.0), action_index=(0,), action_sign=(-1.0,)
    )
    learner = DeepWFNN(config(symmetries=(mirror,)))
    learner.learn(np.array([0.2, 0.5]), np.array([1.0]), np.array([0.3, 0.4]), -1.0)
    assert int(learner.buffer.count[0]) == 2
    np.testing.assert_allclose(learner.buffer.action[0, 1], [-0.5])


def test_surface_shows_the_deep_wires():
    cfg = config()
    learner = DeepWFNN(cfg)
    surface = SurfaceGrid(cfg, (0,), 21)(learner.params, np.array([0.1, 0.2]))
    assert surface.wire_action.shape == (cfg.n_wires, 1) and surface.q.shape == (21,)
    assert surface.wire_value[surface.best] == pytest.approx(surface.wire_value.max())
    x = learner.state_scaler.to_unit(np.array([[0.1, 0.2]]))
    q = deep_net.wirefit_normalised(*deep_net.wires(learner.params, x), learner.action_scaler.to_unit(
        surface.axes[0][:, None]), cfg.smoothing_c, cfg.eps)  # fmt: skip
    np.testing.assert_allclose(surface.q, q[0] if q.ndim > 1 else q)


def test_make_learner_refuses_weights_of_the_other_learner():
    deep, thesis = config(), LearnerConfig.for_task(Task())
    with pytest.raises(ValueError, match="do not fit"):
        make_learner(deep, params=make_learner(thesis).params)
    with pytest.raises(ValueError, match="do not fit"):
        make_learner(thesis, params=make_learner(deep).params)
    with pytest.raises(ValueError, match="population 1"):
        make_learner(deep, population=2)


def test_an_invalid_state_is_acted_on_from_the_last_valid_one():
    learner = make_learner(config())
    good = learner.act(np.array([0.2, 0.4]), explore=False)
    for bad in (np.array([np.nan, 0.4]), np.array([0.2, np.inf])):
        result = learner.act(bad, explore=False)
        assert not result.valid and np.isfinite(result.action).all()
    # The non-finite entry takes the last valid value: the same state, the same action.
    assert learner.act(np.array([np.nan, 0.4]), explore=False).action == pytest.approx(good.action)
    batch = learner.act(np.array([[0.2, 0.4]]), explore=False)
    assert batch.action[0] == pytest.approx(good.action)


def test_a_population_takes_every_seed_a_config_takes():
    """Members' seeds wrap past MAX_SEED, where seed + i was refused (the thesis' population took it)."""
    population = make_population(config(seed=MAX_SEED), 2)
    assert [m.config.seed for m in population.members] == [MAX_SEED, 0]


def test_a_population_of_deep_learners_behaves_as_its_members():
    cfg = config(seed=4)
    population = make_population(cfg, 3)
    members = [DeepWFNN(with_options(cfg, {"seed": 4 + i})) for i in range(3)]
    rng = np.random.default_rng(5)
    for _ in range(20):
        x, u = rng.uniform(-1, 1, (3, 2)), rng.uniform(-2, 2, (3, 1))
        population.learn(x, u, x, -np.ones(3), np.zeros(3, dtype=bool))
        for i, m in enumerate(members):
            m.learn(x[i], u[i], x[i], -1.0)
        population.think(2)
        for m in members:
            m.think(2)
    states = rng.uniform(-1, 1, (3, 2))
    acted = population.act(states, explore=False, params=population.snapshot())
    assert acted.action.shape == (3, 1) and acted.value.shape == (3,)
    for i, m in enumerate(members):
        assert acted.action[i] == pytest.approx(m.act(states[i], explore=False).action)
    assert population.thinks.tolist() == [40, 40, 40] and population.buffer.count.tolist() == [20, 20, 20]
    assert population.greedy_values(states).shape == (3, 3)
    # Q of each member at its own state and action (what the passive benchmark's diagnosis asks).
    actions = rng.uniform(-2, 2, (3, 1))
    q = population.q_value(states, actions)
    assert q.shape == (3,)
    for i, m in enumerate(members):
        assert q[i] == pytest.approx(float(m.q_value(states[i], actions[i])))
    assert len(set(q.round(9).tolist())) == 3  # members differ: no member answered for another


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA device")
def test_a_cuda_device_torch_cannot_see_is_a_clear_error():
    learner = DeepWFNN(config(deep={"device": "cuda"}))
    learner.learn(np.zeros(2), np.zeros(1), np.zeros(2), -1.0)
    assert learner.act(np.zeros(2)).valid  # acting needs no torch, and no device
    with pytest.raises(ValueError, match="no such CUDA device"):
        learner.think(1)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device here")
def test_thinking_on_cuda_matches_the_cpu():
    learners = [DeepWFNN(config(deep={"device": device, "target_noise": 0.0})) for device in ("cpu", "cuda")]
    rng = np.random.default_rng(6)
    block = (rng.uniform(-1, 1, (64, 2)), rng.uniform(-2, 2, (64, 1)), rng.uniform(-1, 1, (64, 2)),
             -rng.random(64), np.zeros(64, dtype=bool))  # fmt: skip
    for learner in learners:
        learner.learn_many(*block)
        learner._train().generator.manual_seed(1)
    batch = learners[0]._n_step(np.arange(32))
    steps = [learner._train().update(batch) for learner in learners]
    np.testing.assert_allclose(steps[0], steps[1], rtol=1e-4)


def test_learning_on_from_saved_weights_starts_the_twins_apart():
    cfg = config()
    saved = DeepWFNN(cfg)
    learner = make_learner(cfg, params=saved.params.copy())
    theta = learner.training_state()["theta"].astype(np.float64)
    n = n_params(cfg)
    np.testing.assert_allclose(theta[:n], saved.params.flat[0], atol=1e-6)
    gap = np.abs(theta[n:] - theta[:n])
    assert 0 < gap.max() < 0.05 * np.abs(theta[:n]).max()


def test_a_deep_config_too_large_for_memory_is_refused(monkeypatch):
    cfg = config()
    with pytest.raises(ConfigError, match="parameters"):
        with_options(cfg, {"deep": {"hidden": [4096] * 3}})
    # The bound counts exactly the parameters the network has.
    for deep in ({"hidden": [7]}, {"hidden": [32, 5, 9]}, {"hidden": [7], "value_layers": 3}):
        monkeypatch.setattr(config_module, "MAX_PARAMS", 10**9)
        size = deep_net.DeepShapes.of(with_options(cfg, {"deep": deep})).n_params
        monkeypatch.setattr(config_module, "MAX_PARAMS", size)
        with_options(cfg, {"deep": deep})
        monkeypatch.setattr(config_module, "MAX_PARAMS", size - 1)
        with pytest.raises(ConfigError, match="parameters"):
            with_options(cfg, {"deep": deep})


def test_a_deep_config_whose_trunk_activations_would_not_fit_in_memory_is_refused():
    # A few thousand parameters, but a [2, B, 4096] float32 activation of 32 GiB per minibatch.
    with pytest.raises(ConfigError, match="batch_size x"):
        with_options(
            config(), {"n_wires": 1, "batch_size": 1 << 20, "deep": {"hidden": [4096], "value_hidden": 1}}
        )
    with_options(
        config(), {"n_wires": 1, "batch_size": 1 << 10, "deep": {"hidden": [4096], "value_hidden": 1}}
    )
    # Every further value layer keeps [2, B, N, value_hidden] more.
    wide = {"n_wires": 32, "batch_size": 1 << 12, "deep": {"hidden": [8], "value_hidden": 64}}
    with_options(config(), wide)
    with pytest.raises(ConfigError, match="batch_size x"):
        with_options(config(), {**wide, "deep": {**wide["deep"], "value_layers": 2}})


@pytest.mark.parametrize("seed", [-1, 1 << 62, 1 << 64])
def test_a_seed_numpy_or_torch_would_refuse_is_refused_with_the_config(seed):
    with pytest.raises(ConfigError, match="seed"):
        config(seed=seed)


def test_n_step_returns_step_over_mirrored_copies():
    mirror = Symmetry(name="mirror", state_index=(0, 1), state_sign=(-1.0, 1.0), action_index=(0,),
                      action_sign=(-1.0,))  # fmt: skip
    learner = DeepWFNN(config(gamma=0.5, deep={"n_step": 3}, symmetries=(mirror,)))
    z = np.zeros(1)
    for s, sn, r in (((0.1, 0), (0.2, 0), 1.0), ((0.2, 0), (0.3, 0), 2.0), ((0.3, 0), (0.4, 0), 4.0)):
        learner.learn(np.array(s), z, np.array(sn), r)
    # Stored: real, mirror, real, mirror, real, mirror. Each chain follows its own kind.
    batch = learner._n_step(np.arange(6))
    np.testing.assert_allclose(batch["reward"], [1 + 1 + 1, 1 + 1 + 1, 2 + 2, 2 + 2, 4, 4])
    np.testing.assert_allclose(batch["next_state"][:, 0], [0.4, -0.4, 0.4, -0.4, 0.4, -0.4])
    # learn_many stores them in the same order, in batches as a server gets them: the same chains,
    # across the batches too.
    block = DeepWFNN(config(gamma=0.5, deep={"n_step": 3}, symmetries=(mirror,)))
    s = np.array([[0.1, 0], [0.2, 0], [0.3, 0]])
    sn = np.array([[0.2, 0], [0.3, 0], [0.4, 0]])
    r = np.array([1.0, 2.0, 4.0])
    block.learn_many(s[:2], np.zeros((2, 1)), sn[:2], r[:2], np.zeros(2, dtype=bool))
    block.learn_many(s[2:], np.zeros((1, 1)), sn[2:], r[2:], np.zeros(1, dtype=bool))
    np.testing.assert_allclose(block._n_step(np.arange(6))["reward"], batch["reward"])
    np.testing.assert_allclose(block._n_step(np.arange(6))["next_state"], batch["next_state"])


def test_a_learner_that_has_not_thought_yet_resumes_exactly(tmp_path):
    """Fresh weights are float32 values, as the trainer holds them: act before the first update
    and act after resuming from a checkpoint taken then choose the same."""
    for reset in (False, True):
        learner = DeepWFNN(config())
        if reset:
            learner.reset_weights(np.ones(1, dtype=np.bool_))
        save_weights(tmp_path / "ck.npz", learner.config, learner.params, training=learner.training_state())
        ck_cfg, params, _, training = load_checkpoint(tmp_path / "ck.npz")
        resumed = make_learner(ck_cfg, params=params)
        resumed.load_training_state(training)
        np.testing.assert_array_equal(resumed.params.flat, learner.params.flat)
        s = np.array([0.3, -0.2])
        assert resumed.act(s, explore=False).action == learner.act(s, explore=False).action


def test_a_learner_made_from_float64_weights_resumes_exactly_before_it_thinks(tmp_path):
    """Weights given in float64 (a PopArt learner's, in the task's units) were acted on as given,
    and resumed from a checkpoint taken before the first update as their float32 rounding."""
    cfg = config()
    shapes = DeepWFNN(cfg).shapes
    flat = deep_net.init_critic(shapes, np.random.default_rng(7), 1.0) * (1.0 + 1e-9)
    assert not np.array_equal(flat.astype(np.float32).astype(np.float64), flat)  # not float32 values
    learner = DeepWFNN(cfg, params=deep_net.DeepParams(flat[None].copy(), shapes))
    save_weights(tmp_path / "ck.npz", learner.config, learner.params, training=learner.training_state())
    ck_cfg, params, _, training = load_checkpoint(tmp_path / "ck.npz")
    resumed = make_learner(ck_cfg, params=params)
    resumed.load_training_state(training)
    np.testing.assert_array_equal(resumed.params.flat, learner.params.flat)
    states = np.random.default_rng(8).uniform(-1.0, 1.0, (200, 2))
    for s in states:
        a, b = learner.act(s, explore=False), resumed.act(s, explore=False)
        assert a.action == b.action and a.value == b.value
    learner.learn(states[0], np.zeros(1), states[1], -1.0)
    learner.think(1)  # and the trainer starts from the weights acted on
    assert learner.params.flat.shape == flat[None].shape


def test_the_divergence_threshold_the_rewards_set_is_resumed(tmp_path):
    """A learner resumed on a task of large rewards judged its own healthy weights diverged."""
    learner = DeepWFNN(config())
    learner.learn(np.zeros(2), np.zeros(1), np.zeros(2), 1e4)
    learner.think(1)
    assert learner.monitor.threshold > 1e6
    save_weights(tmp_path / "ck.npz", learner.config, learner.params, training=learner.training_state())
    ck_cfg, params, _, training = load_checkpoint(tmp_path / "ck.npz")
    resumed = make_learner(ck_cfg, params=params)
    resumed.load_training_state(training)
    assert resumed.monitor.threshold == learner.monitor.threshold
    older = {k: v for k, v in training.items() if k != "reward_scale"}  # a checkpoint made before it
    again = make_learner(ck_cfg, params=params)
    again.load_training_state(older)
    assert again.monitor.threshold == ck_cfg.divergence_threshold
    for bad in (np.float64(np.nan), np.float64(-1.0), np.float64(1e31), np.array([1.0, 2.0]), np.str_("1")):
        with pytest.raises(ValueError, match="reward_scale"):
            make_learner(ck_cfg, params=params).load_training_state({**training, "reward_scale": bad})


def test_damaged_or_partial_training_state():
    learner = DeepWFNN(config())
    learner.learn(np.zeros(2), np.zeros(1), np.zeros(2), -1.0)
    learner.think(3)
    state = learner.training_state()
    for bad in ({"adam_v": -np.abs(state["adam_v"]) - 1.0}, {"adam_step": np.float64(np.nan)},
                {"adam_step": np.float64(2.5)}, {"adam_m": state["adam_m"][:5]}):  # fmt: skip
        with pytest.raises(ValueError, match="training state"):
            make_learner(learner.config, params=learner.params.copy()).load_training_state({**state, **bad})
    n = 2 * n_params(learner.config)
    huge = state["theta"].astype(np.float64)
    huge[n // 2 + 3] = 1e39  # finite in float64, infinite in the float32 the update trains in
    other = state["theta"].copy()
    other[0] += 1.0  # critic 1 no longer the weights saved beside it
    for bad in ({"theta": huge}, {"target": huge}, {"adam_m": huge}, {"adam_v": np.abs(huge)},
                {"theta": state["theta"].astype(np.complex128)}, {"theta": np.array(["x"] * n)},
                {"adam_step": np.str_("3")}, {"adam_step": np.complex128(3)}, {"theta": other}):  # fmt: skip
        resumed = make_learner(learner.config, params=learner.params.copy())
        with pytest.raises(ValueError, match="training state"):
            resumed.load_training_state({**state, **bad})
        np.testing.assert_array_equal(resumed.params.flat, learner.params.flat)
    # Weights saved without their training: they are kept, Adam starts afresh.
    resumed = make_learner(learner.config, params=learner.params.copy())
    resumed.load_training_state({})
    np.testing.assert_array_equal(resumed.params.flat, learner.params.flat)
    assert "adam_m" not in resumed.training_state()


def test_warm_up_is_skipped_with_given_weights_and_counts_earlier_experiences():
    cfg = with_options(config(deep={"warmup": 50}), {"exploration": {"kind": "none"}})
    fresh, given = DeepWFNN(cfg), make_learner(cfg, params=DeepWFNN(cfg).params.copy())
    x = np.zeros(2)
    assert bool(fresh.act(x).explored) and not bool(given.act(x).explored)
    fresh.experienced(50)  # a robot whose journal holds 50 experiences already
    assert not bool(fresh.act(x).explored)


def test_a_learner_resumed_in_its_warm_up_takes_the_rest_of_it(tmp_path):
    """A checkpoint taken 30 actions into a warm-up of 50 resumed with the warm-up over."""
    cfg = with_options(config(deep={"warmup": 50}), {"exploration": {"kind": "none"}})
    learner, x = DeepWFNN(cfg), np.zeros(2)
    assert all(bool(learner.act(x).explored) for _ in range(30))
    state = learner.training_state()
    assert int(state["acted"]) == 30
    save_weights(tmp_path / "ck.npz", cfg, learner.params, {}, training=state)
    ck_cfg, params, _, training = load_checkpoint(tmp_path / "ck.npz")
    resumed = make_learner(ck_cfg, params=params)
    resumed.load_training_state(training)
    assert [bool(resumed.act(x).explored) for _ in range(21)] == [True] * 20 + [False]
    # A learner that never acted (a think server's) says nothing of it: a learner resumed from
    # its checkpoint counts its warm-up as done where it trained, as one made from weights alone
    # does; where it never trained either (a robot's brain that never drove), its weights are as
    # fresh as a new learner's, and it was resumed acting greedily on them, with no warm-up.
    server_side = _fed(DeepWFNN(cfg))
    server_side.think(3)
    assert "acted" not in server_side.training_state()
    resumed = make_learner(cfg, params=server_side.params.copy())
    resumed.load_training_state(server_side.training_state())
    assert not bool(resumed.act(x).explored)
    idle = DeepWFNN(cfg)
    assert "acted" not in idle.training_state()
    resumed = make_learner(cfg, params=idle.params.copy())
    resumed.load_training_state(idle.training_state())
    assert [bool(resumed.act(x).explored) for _ in range(51)] == [True] * 50 + [False]
    for bad in (np.float64(3.0), np.int64(-1), np.array([3]), np.str_("3")):
        with pytest.raises(ValueError, match="training state acted"):
            make_learner(cfg, params=params).load_training_state({**training, "acted": bad})


def test_acting_on_a_populations_weights_never_resets_them():
    population = make_population(config(divergence_threshold=-1e9, divergence_patience=1), 2)
    before = population.snapshot().flat
    acted = population.act(np.zeros((2, 2)), explore=False, params=population.params)
    assert acted.diverged.all() and population.resets.tolist() == [0, 0]
    np.testing.assert_array_equal(population.snapshot().flat, before)
    population.act(np.zeros((2, 2)), explore=False)  # its own weights: reset
    assert population.resets.tolist() == [1, 1]


def test_thesis_configs_read_as_before_and_deep_work_is_bounded():
    thesis = LearnerConfig.for_task(Task())
    assert "learner" not in thesis.to_dict() and "deep" not in thesis.to_dict()
    assert LearnerConfig.from_json(thesis.to_json()) == thesis
    with pytest.raises(ConfigError, match="batch_size x"):
        with_options(config(), {"batch_size": 65536, "n_wires": 1024, "deep": {"hidden": [1]}})
    with pytest.raises(ConfigError, match="device"):
        with_options(config(), {"deep": {"device": "cuda:\u0663"}})


def test_thinking_prepared_early_learns_the_same_numbers():
    # A server or a local brain loads torch before its threads start; the trainer it builds early
    # must be the one the first think would have built.
    learners = [make_learner(config(seed=5)) for _ in range(2)]
    assert learners[0]._trainer is None
    learners[0].prepare_thinking()
    assert learners[0]._trainer is not None and learners[1]._trainer is None
    rng = np.random.default_rng(0)
    for _ in range(40):
        s, u, sn = rng.uniform(-1, 1, 2), rng.uniform(-2, 2, 1), rng.uniform(-1, 1, 2)
        for learner in learners:
            learner.act(s)
            learner.learn(s, u, sn, -float(np.abs(s).sum()))
            learner.think(3)
    np.testing.assert_array_equal(learners[0].params.flat, learners[1].params.flat)


def test_the_divergence_threshold_follows_the_rewards_scale_and_never_falls():
    learner = DeepWFNN(config(gamma=0.99))
    z = np.zeros(2)
    learner.learn(z, np.zeros(1), z, -3.0)
    assert learner.monitor.threshold == 1e4  # small rewards: the config's threshold
    learner.learn(z, np.zeros(1), z, 2000.0)  # values up to 2e5 are sound here
    assert learner.monitor.threshold == pytest.approx(1e4 * 2000 / 10)
    learner.learn(z, np.zeros(1), z, np.nan)  # refused: counts for nothing
    learner.learn(z, np.zeros(1), z, 5.0)
    assert learner.monitor.threshold == pytest.approx(1e4 * 2000 / 10)


def test_the_divergence_threshold_follows_the_discount_too():
    """Rewards of 10 at gamma 0.9995 bound the values by 20,000: a sound value of 15,000 is no divergence."""
    learner = DeepWFNN(config(gamma=0.9995))
    z = np.zeros(2)
    learner.learn(z, np.zeros(1), z, 10.0)
    assert learner.monitor.threshold == pytest.approx(1e4 * 20)
    assert learner.monitor.threshold > 15_000
    low = DeepWFNN(config(gamma=0.9))  # a shorter horizon: the config's threshold still (never below it)
    low.learn(z, np.zeros(1), z, 10.0)
    assert low.monitor.threshold == 1e4
    negative = DeepWFNN(config(gamma=0.999, divergence_threshold=-5.0))  # scaling would make it stricter
    negative.learn(z, np.zeros(1), z, -20.0)
    assert negative.monitor.threshold == -5.0


@pytest.mark.parametrize("n", [8, 26, 40])
def test_separation_pushes_close_wires_apart_whatever_their_number(n):
    """Two wires 2e-4 apart among n: their distance and the push between them are exact, in float32."""
    rng = np.random.default_rng(0)
    u = rng.uniform(-1.0, 1.0, (1, n, 2))
    u[0, 1] = u[0, 0] + [2e-4, 0.0]
    wires = torch.tensor(u, dtype=torch.float32, requires_grad=True)
    separation(wires).backward()
    exact = torch.tensor(u, dtype=torch.float64, requires_grad=True)
    diff = exact.unsqueeze(-2) - exact.unsqueeze(-3)
    dist = (diff**2).sum(-1).add(torch.eye(n, dtype=torch.float64)).sqrt() - torch.eye(n, dtype=torch.float64)
    ((1.0 / (dist + SEPARATION_EPS)).sum() - n / SEPARATION_EPS).div(n * (n - 1)).backward()
    np.testing.assert_allclose(wires.grad.numpy()[0, :2], exact.grad.numpy()[0, :2], rtol=1e-2, atol=1e-4)


def test_init_scale_scales_the_deep_learners_initial_weights():
    one, small = DeepWFNN(config(seed=3)), DeepWFNN(config(seed=3, init_scale=0.01))
    np.testing.assert_allclose(small.params.flat, 0.01 * one.params.flat, rtol=1.2e-7)  # float32 values
    assert np.array_equal(small.params.flat.astype(np.float32), small.params.flat)
    assert np.array_equal(DeepWFNN(config(seed=3, init_scale=1.0)).params.flat, one.params.flat)


def test_weights_beyond_float32s_range_are_refused_as_the_training_state_is():
    cfg = config()
    flat = DeepWFNN(cfg).params.flat.copy()
    flat[0, 3] = 1e300
    with pytest.raises(ValueError, match="float32"):
        DeepWFNN(cfg, params=weights_from_flat(cfg, flat))


def test_separation_holds_each_states_best_wire_still_when_given_the_values():
    wires = torch.tensor([[[0.0], [0.05], [0.5]], [[0.0], [0.05], [0.5]]], requires_grad=True)
    values = torch.tensor([[1.0, 0.0, -1.0], [0.0, 2.0, -1.0]])
    separation(wires, values).backward()
    g = wires.grad
    assert g is not None and g[0, 0, 0] == 0.0 and g[1, 1, 0] == 0.0  # each state's best wire
    assert g[0, 1, 0] < 0.0 < g[1, 0, 0]  # ... still pushes its neighbour away
    assert torch.isclose(separation(wires, values), separation(wires))  # the same term, fewer movers


def test_tanh_limit_pulls_saturated_wires_back_from_tanhs_flat_ends():
    learner = _fed(DeepWFNN(config(deep={"tanh_limit": 3.0})))
    trainer = learner._train()
    critics = trainer.critics
    both = trainer.theta.view(2, critics.n)  # the weights need no gradient: the blocks are its leaves
    a, b, _ = critics.slices["bw"]
    both[:, a:b] = 10.0  # every wire's input to tanh far beyond the limit, half of them below it
    both[:, a : (a + b) // 2] = -10.0
    args = _loss_args(trainer, seed=5)
    limited = loss(critics, trainer.config, *args)[0]
    free = loss(critics, with_options(trainer.config, {"deep": {"tanh_limit": 0.0}}), *args)[0]
    grad_limited = trainer.gradient(limited).clone()
    grad_free = trainer.gradient(free)
    z = critics.wires_and_preactivations(trainer.blocks, args[2])[2]
    torch.testing.assert_close(limited - free, ((z.abs() - 3.0).clamp_min(0.0) ** 2).mean(dim=(1, 2)).sum())
    pull = (grad_limited - grad_free).view(2, critics.n)
    # a descent step brings every wire's input back toward the limit, from either side
    assert (pull[:, a : (a + b) // 2] < 0).all() and (pull[:, (a + b) // 2 : b] > 0).all()


def test_the_loss_holds_the_best_wire_still_only_when_asked():
    learner = _fed(DeepWFNN(config()))
    trainer = learner._train()
    critics = trainer.critics
    args = _loss_args(trainer, seed=6)
    grads = {}
    for held in (False, True):
        cfg = with_options(trainer.config, {"deep": {"separate_best": not held}})
        grads[held] = trainer.gradient(loss(critics, cfg, *args)[0]).clone()
    change = (grads[True] - grads[False]).view(2, critics.n)
    a, b, _ = critics.slices["Ww"]
    assert change[:, a:b].abs().max() > 0  # the switch reaches the loss
    for name in ("Vh", "Vu", "bv", "vo", "bo"):  # separation never reaches the value head
        start, end, _ = critics.slices[name]
        assert change[:, start:end].abs().max() == 0.0


def test_the_smallest_eps_the_deep_learner_accepts_keeps_its_weights_finite_on_a_wire():
    """An action exactly on the best wire (wires saturated at a bound, the action clipped there):
    below MIN_DEEP_EPS torch's float32 gradient of 1 / d overflowed and one update made every
    weight NaN, so such an eps is refused."""
    from wfnn_common.config import MIN_DEEP_EPS
    from wfnn_common.deep_net import DeepParams
    from wfnn_common.learners import make_learner

    def config(eps: float) -> LearnerConfig:
        return LearnerConfig(state_low=(-1.0,), state_high=(1.0,), action_low=(-1.0,), action_high=(1.0,),
                             learner="deep", eps=eps, batch_size=1,
                             deep=DeepConfig(hidden=(8,), value_hidden=8, warmup=0))  # fmt: skip

    with pytest.raises(ConfigError, match="deep learner"):
        config(MIN_DEEP_EPS / 2)
    cfg = config(MIN_DEEP_EPS)
    fresh = make_learner(cfg)
    flat = fresh.params.flat.copy()
    a, b, _ = fresh.shapes.slices()["bw"]
    flat[0, a:b] = 20.0  # every wire at tanh(20), which float32 rounds to the bound 1
    learner = make_learner(cfg, params=DeepParams(flat, fresh.shapes))
    x = np.array([0.3])
    learner.learn(x, np.array([1.0]), x, -1.0)
    learner.think(1)
    assert np.isfinite(learner.params.flat).all()
    assert not learner.act(x, explore=False).diverged and int(learner.resets[0]) == 0


def _task_values(trainer, vector, x):
    """Both critics' wire values [2, B, N] of the flat weights `vector` at states x, in the task's units."""
    mean, std = deep_net.value_scale(trainer.moments)
    with torch.no_grad():
        _, q = trainer.critics.wires(trainer.critics.blocks(vector), x)
    return q.double() * std + mean


def test_popart_keeps_every_value_as_it_was_when_its_statistics_move():
    learner = _fed(DeepWFNN(config(deep={"popart_rate": 0.5})))
    learner.think(3)
    trainer = learner._train()
    x = torch.tensor(np.random.default_rng(1).uniform(-1, 1, (20, 2)), dtype=torch.float32)
    before = [_task_values(trainer, v, x) for v in (trainer.theta, trainer.target)]
    scale = deep_net.value_scale(trainer.moments)
    trainer._track(torch.tensor(np.random.default_rng(2).normal(500.0, 80.0, 64), dtype=torch.float32))
    moved = deep_net.value_scale(trainer.moments)
    assert moved[0] > 200.0 and moved[1] > 10.0 * scale[1]
    for vector, values in zip((trainer.theta, trainer.target), before, strict=True):
        torch.testing.assert_close(_task_values(trainer, vector, x), values, rtol=1e-4, atol=1e-4)
    # `act`'s weights give the values in the task's units, and the same wires.
    learner._sync()
    wire_u, wire_q = deep_net.wires(learner.params, x.double().numpy())
    np.testing.assert_allclose(wire_q, before[0][0].numpy(), rtol=1e-4, atol=1e-4)
    with torch.no_grad():
        tu, _ = trainer.critics.wires(trainer.blocks, x)
    np.testing.assert_allclose(wire_u, tu[0].double().numpy(), atol=1e-5)
    # The statistics follow the targets: their mean and deviation, bias corrected.
    y = np.random.default_rng(3).normal(-40.0, 6.0, 256)
    fresh = _fed(DeepWFNN(config(deep={"popart_rate": 1e-3})))._train()
    fresh._track(torch.tensor(y, dtype=torch.float32))
    np.testing.assert_allclose(deep_net.value_scale(fresh.moments), (y.mean(), y.std()), rtol=1e-5)


@pytest.mark.parametrize("scale", [1e-2, 1.0, 1e4])
def test_popart_learns_the_best_action_whatever_the_rewards_scale(scale):
    """The contextual bandit (`test_learns_the_best_action_of_a_contextual_bandit`), its rewards
    multiplied by `scale`: with the values normalised, one setting of the learner learns each."""
    learner = DeepWFNN(config(batch_size=64, deep={"lr": 3e-3, "target_noise": 0.0, "popart_rate": 0.01}))
    rng = np.random.default_rng(0)
    s = rng.uniform(-1, 1, (2000, 2))
    a = rng.uniform(-2, 2, (2000, 1))
    learner.learn_many(s, a, s, -scale * (a[:, 0] - s[:, 0]) ** 2, np.ones(2000, dtype=bool))
    learner.think(1500)
    tests = np.array([[-0.8, 0.0], [0.0, 1.0], [0.7, -1.0]])
    greedy = np.array([learner.act(t, explore=False).action[0] for t in tests])
    np.testing.assert_allclose(greedy, tests[:, 0], atol=0.5)  # of the range [-2, 2]
    # Its values are in the task's units: the best action's value is near 0, a poor one's far below
    # (values in normalised units would be off by about 1 / std, 50 times at the smallest scale).
    # The bound is 2 scales: at 0.01 one machine's float arithmetic (AMD EPYC) left an offset of 1.04.
    assert abs(float(learner.q_value(tests[0], tests[0, :1]))) < 2.0 * scale
    assert float(learner.q_value(tests[0], [1.5])) < -2.0 * scale


def test_popart_statistics_are_saved_resumed_and_checked(tmp_path):
    cfg = config(deep={"popart_rate": 0.05})
    learner = _fed(DeepWFNN(cfg))
    learner.think(10)
    state = learner.training_state()
    assert state["value_moments"].shape == (3,) and 0.0 < state["value_moments"][2] < 1.0
    save_weights(tmp_path / "ck.npz", cfg, learner.params, {"thinks": 10}, training=state)
    ck_cfg, params, _, training = load_checkpoint(tmp_path / "ck.npz")
    resumed = make_learner(ck_cfg, params=params)
    resumed.load_training_state(training)
    np.testing.assert_array_equal(resumed.params.flat, learner.params.flat)
    np.testing.assert_array_equal(resumed.training_state()["value_moments"], state["value_moments"])
    batch = learner._n_step(np.arange(32))
    learner._trainer.generator.manual_seed(5)
    resumed._trainer.generator.manual_seed(5)
    assert learner._trainer.update(batch) == resumed._trainer.update(batch)
    # Weights that learnt normalised values, resumed without the normalisation, give the same values.
    plain = make_learner(with_options(cfg, {"deep": {"popart_rate": 0.0}}), params=learner.params.copy())
    plain.load_training_state(state)
    x = np.random.default_rng(6).uniform(-1, 1, (10, 2))
    np.testing.assert_allclose(plain.greedy_values(x), learner.greedy_values(x), rtol=1e-5, atol=1e-5)
    assert "value_moments" not in plain.training_state()
    # Statistics that are not a targets' moments, or that do not fit the weights saved beside them.
    other = state["value_moments"] * np.array([2.0, 4.0, 1.0])
    for bad in (np.array([0.1, 0.2]), np.array([0.1, -0.2, 0.5]), np.array([0.1, 0.2, 1.5]),
                np.array([np.nan, 0.2, 0.5]), np.array([1e39, 0.2, 0.5]), np.array(["a", "b", "c"]),
                other):  # fmt: skip
        resumed = make_learner(cfg, params=learner.params.copy())
        with pytest.raises(ValueError, match="training state"):
            resumed.load_training_state({**state, "value_moments": bad})
    # A reset forgets the statistics with the weights.
    learner.reset_weights(np.array([True]))
    assert "value_moments" not in learner.training_state()


@pytest.mark.parametrize("rewards", ["constant", "spread"])
def test_popart_keeps_its_weights_finite_on_the_largest_rewards_learnt(rewards):
    """Rewards of 1e19 every step (no spread: the deviation at its floor) and of up to 4e28 both
    made normalised targets whose squares overflowed float32 within a few updates."""
    learner = DeepWFNN(config(batch_size=32, deep={"popart_rate": 3e-4}))
    rng = np.random.default_rng(0)
    s, a, sn = rng.uniform(-1, 1, (200, 2)), rng.uniform(-2, 2, (200, 1)), rng.uniform(-1, 1, (200, 2))
    r = np.full(200, 1e19) if rewards == "constant" else -1e28 * (a[:, 0] - s[:, 0]) ** 2
    assert learner.learn_many(s, a, sn, r, np.zeros(200, dtype=bool)).all()
    for _ in range(30):
        learner.think(1)
        assert np.isfinite(learner._trainer.theta.numpy()).all() and np.isfinite(learner.params.flat).all()
    assert int(learner.resets[0]) == 0
    mean, _ = deep_net.value_scale(learner._trainer.moments)
    assert np.sign(mean) == np.sign(r.mean()) and abs(mean) > 1e18


@pytest.mark.parametrize(("k", "options"), [(1.0, {}), (0.5, {"top_k": 3, "tanh_limit": 0.5})])
def test_the_popart_loss_is_the_plain_loss_in_the_tasks_units_over_std_squared(k, options):
    """Normalised values change what the weights mean, not what is learnt: the loss on normalised
    weights is the loss without the option on the same critics in the task's units, over std^2
    (every term: the separation, tanh-limit and bc terms keep their weight against the values)."""
    popart = _fed(DeepWFNN(config(bc_weight=0.3, advantage_k=k, deep={"popart_rate": 0.01, **options})))
    popart.think(2)
    trainer = popart._train()
    mean, std = -3.0, 2.5
    args = _loss_args(trainer, seed=8)
    args = (*args[:-1], torch.tensor([mean, std]))
    got = loss(trainer.critics, trainer.config, *args)

    def task_units(vector):
        n = trainer.critics.n
        flat = vector.detach().double().numpy()
        both = [
            deep_net.in_task_units(flat[k * n : (k + 1) * n], trainer.critics.shapes, mean, std)
            for k in (0, 1)
        ]
        return torch.tensor(np.concatenate(both), dtype=torch.float32)

    plain_cfg = with_options(trainer.config, {"deep": {"popart_rate": 0.0}})
    theta = task_units(trainer.theta)
    plain = loss(
        trainer.critics, plain_cfg, trainer.critics.blocks(theta), task_units(trainer.target), *args[2:]
    )
    torch.testing.assert_close(got[0] * std**2, plain[0], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(got[1], plain[1], rtol=1e-5, atol=1e-4)  # Q(x, u) in the task's units
    torch.testing.assert_close(got[2], plain[2], rtol=1e-5, atol=1e-4)  # the targets


@pytest.mark.parametrize("grad_clip", [0.0, 10.0])
def test_adams_moments_stay_finite_and_resumable_on_the_largest_gradients(grad_clip):
    """Rewards of 1e25 (accepted: below MAX_REWARD) with clipping off overflowed Adam's float32
    second moment to inf, freezing the weights it covered, and the learner's own saved state was
    refused on load; with clipping on, a norm whose squares overflow float32 zeroed the gradient."""
    learner = DeepWFNN(config(batch_size=16, squash_reward=False, deep={"grad_clip": grad_clip}))
    rng = np.random.default_rng(0)
    s, a, sn = rng.uniform(-1, 1, (64, 2)), rng.uniform(-2, 2, (64, 1)), rng.uniform(-1, 1, (64, 2))
    r = np.where(np.arange(64) % 2, 1e25, -1e25)
    assert learner.learn_many(s, a, sn, r, np.zeros(64, dtype=bool)).all()
    learner.think(1)
    before = learner._trainer.theta.clone()
    learner.think(20)
    state = learner.training_state()
    for key in ("theta", "adam_m", "adam_v"):
        assert np.isfinite(state[key]).all(), key
    assert (learner._trainer.theta != before).float().mean() > 0.5  # the weights still learn
    resumed = make_learner(learner.config, params=learner.snapshot())
    resumed.load_training_state(state)  # raised "adam_v: not finite" before
