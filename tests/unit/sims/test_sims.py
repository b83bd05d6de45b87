import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from sims.boat import BoatConfig, BoatEnv, BoatVec, handcoded_boat
from sims.cartpole import CartPoleConfig, CartPoleEnv, CartPoleVec
from sims.hydra import HydraEnv
from sims.nomad import NomadEnv
from sims.positioning import PositioningConfig, PositioningEnv, PositioningVec, handcoded_positioning
from wfnn_bench import boat as boat_bench
from wfnn_bench.boat import BoatBenchConfig, Hold, handcoded_sweep, run_condition, run_protocol


@pytest.mark.parametrize("make", [BoatEnv, CartPoleEnv, PositioningEnv])
def test_gymnasium_check_env(make):
    env = make()
    check_env(env, skip_render_check=True)
    obs, _ = env.reset(seed=3)
    assert env.observation_space.contains(obs)


@pytest.mark.parametrize("make", [BoatEnv, CartPoleEnv, PositioningEnv, HydraEnv, NomadEnv])
def test_a_nan_or_missing_action_or_one_of_another_width_is_refused_and_changes_nothing(make):
    """np.clip keeps NaN: a boat's state stayed NaN for good, and a cart-pole then never failed and
    was paid 0, the best reward; a cart-pole took the first of any number of actions."""
    env = make()
    env.reset(seed=0)
    width = env.action_space.shape[0]
    for bad in ([np.nan] * width, None, [0.0] * (width + 2)):
        with pytest.raises(ValueError, match="action"):
            env.step(bad)
    after, reward, *_ = env.step(np.zeros(width))
    assert np.isfinite(after).all() and np.isfinite(reward)
    task = env.unwrapped.task
    task.reset(np.random.default_rng(0))
    for bad in (np.full((1, width), np.nan), np.zeros((1, width + 1)), np.zeros((2, width))):
        with pytest.raises(ValueError, match="action"):
            task.step(bad)
    assert np.isfinite(task.observe()).all()


@pytest.mark.parametrize(
    "make, field, value",
    [(CartPoleConfig, "pole_mass", 0.0), (CartPoleConfig, "half_length", 0.0), (CartPoleConfig, "dt", -0.02),
     (CartPoleConfig, "max_angle", -1.0), (CartPoleConfig, "max_force", -10.0),
     (CartPoleConfig, "reset_noise", -1.0),
     (PositioningConfig, "velocity_weight", -5.0), (PositioningConfig, "jump_probability", 2.0),
     (PositioningConfig, "dt", 0.0), (PositioningConfig, "target_range", -1.0)],
)  # fmt: skip
def test_task_settings_no_such_system_has_are_refused(make, field, value):
    """Masses or a length of 0 gave NaN states that never failed; a negative velocity weight paid
    rewards above 0, the largest the task declares."""
    with pytest.raises(ValueError, match=field):
        make(**{field: value})


def test_episodes_of_no_step_are_refused():
    """max_steps 0 or below truncated every episode at its first step."""
    for steps in (0, -5):
        with pytest.raises(ValueError, match="max_steps"):
            CartPoleEnv(max_steps=steps)


def test_boat_one_euler_step_of_eq37_and_reward_eq38():
    boat = BoatVec(1, BoatConfig(dt=0.5))
    boat.reset(np.random.default_rng(0))
    boat.heading[:] = 0.3
    boat.vel[:] = [[0.4, 0.1]]
    boat.turn_rate[:] = 0.2
    boat.prev_thrust[:] = [[0.1, -0.2]]
    boat.target[:] = [[1.0, 1.0]]
    a, b = 0.8, -0.6
    tr = boat.step(np.array([[a, b]]))
    c, s = np.cos(0.3), np.sin(0.3)
    pos = 0.5 * np.array([c * 0.4 - s * 0.1, s * 0.4 + c * 0.1])
    np.testing.assert_allclose(boat.pos[0], pos)
    assert boat.heading[0] == pytest.approx(0.3 + 0.5 * 0.2)
    assert boat.turn_rate[0] == pytest.approx(0.2 + 0.5 * (0.1 * (a - b) - 0.15 * 0.2))
    np.testing.assert_allclose(
        boat.vel[0], [0.4 + 0.5 * (0.1 * (a + b) - 0.15 * 0.4), 0.1 + 0.5 * (-0.15 * 0.1)]
    )
    d = np.hypot(*(np.array([1.0, 1.0]) - pos))
    expected = -0.5 * d - 0.5 * (a * a + b * b) - 2 * ((a - 0.1) ** 2 + (b + 0.2) ** 2)
    assert tr.reward[0] == pytest.approx(expected)
    np.testing.assert_allclose(tr.state[0, 5:], [a, b])


def test_boat_relative_target_is_in_the_boat_frame():
    boat = BoatVec(1)
    boat.pos[:] = [[1.0, 1.0]]
    boat.heading[:] = np.pi / 2  # facing +y
    boat.target[:] = [[1.0, 3.0]]  # straight ahead
    np.testing.assert_allclose(boat.relative_target()[0], [2.0, 0.0], atol=1e-12)
    boat.target[:] = [[0.0, 1.0]]  # to the left
    np.testing.assert_allclose(boat.relative_target()[0], [0.0, 1.0], atol=1e-12)


def test_boat_new_targets_are_one_unit_away():
    boat = BoatVec(50)
    boat.reset(np.random.default_rng(0))
    np.testing.assert_allclose(boat.distance(), 1.0)


def test_handcoded_boat_beats_random_and_zero_on_the_protocol():
    def score(policy, seed=0):
        rng = np.random.default_rng(seed)
        boat = BoatVec(10)
        boat.reset(rng)
        return np.median(run_protocol(boat, 3, rng, policy).scores)

    rng = np.random.default_rng(1)
    hand = score(handcoded_boat)
    rand = score(lambda x: rng.uniform(-1, 1, (x.shape[0], 2)))
    zero = score(lambda x: np.zeros((x.shape[0], 2)))
    assert zero == pytest.approx(1.0)
    assert hand < 0.4 < rand


def test_the_protocol_reports_each_targets_return_beside_its_score():
    rng = np.random.default_rng(0)
    boat = BoatVec(4)
    boat.reset(rng)
    # Zero thrust from rest: the boat stays one unit from each target, so every step's reward is
    # -distance_weight (no thrust, no change of thrust): -0.5 x 200 steps per target.
    scores, returns, terms = run_protocol(boat, 3, rng, lambda x: np.zeros((x.shape[0], 2)))
    np.testing.assert_allclose(scores, 1.0)
    np.testing.assert_allclose(returns, -100.0)
    np.testing.assert_allclose(terms, np.broadcast_to([-100.0, 0.0, 0.0], (4, 3, 3)), atol=1e-9)
    # A controller that switches full thrust back and forth pays for the changes: 2 x (2^2 + 2^2)
    # per step after the first (2 x 2 for the first, from rest), and 0.5 x 2 for the thrust,
    # beside the distance term.
    sign = [1.0]

    def bang(x):
        sign[0] = -sign[0]
        return np.full((x.shape[0], 2), sign[0])

    boat.reset(rng)
    scores, returns, terms = run_protocol(boat, 1, rng, bang)
    distance_part = -0.5 * 200 * scores[:, 0]
    np.testing.assert_allclose(returns[:, 0] - distance_part, -(200 * 1.0 + 199 * 16.0 + 4.0), rtol=1e-9)
    # The terms: the distance term, the thrust (0.5 x 2 per step) and its changes, summing to the return.
    np.testing.assert_allclose(terms[:, 0, 0], distance_part, rtol=1e-9)
    np.testing.assert_allclose(terms[:, 0, 1], -200.0, rtol=1e-12)
    np.testing.assert_allclose(terms[:, 0, 2], -(199 * 16.0 + 4.0), rtol=1e-12)
    np.testing.assert_allclose(terms.sum(axis=-1), returns, rtol=1e-12)


def test_a_held_action_is_chosen_every_hold_steps_and_learned_as_one_experience():
    rng = np.random.default_rng(0)
    boat = BoatVec(3)
    boat.reset(rng)
    chosen, learned, thought = [], [], []

    def choose(x):
        chosen.append(x.copy())
        return rng.uniform(-1.0, 1.0, (x.shape[0], 2))

    def learn(*experience):
        learned.append([np.array(v, copy=True) for v in experience])

    held = Hold(5, choose, learn, lambda: thought.append(len(learned)))
    steps = []  # every step's (state, action, next state, reward), as the protocol ran it

    def step(u):
        x = boat.observe()
        tr = real_step(u)
        if len(steps) == 7:  # one step in the second hold is not learnable for robot 1
            tr = tr._replace(learnable=np.array([True, False, True]))
        steps.append((x, u.copy(), tr.state, tr.reward))
        return tr

    boat.step, real_step = step, boat.step  # type: ignore[method-assign]
    run_protocol(boat, 2, rng, held.choose, held.learn, held.think)
    boat.step = real_step  # type: ignore[method-assign]
    assert len(chosen) == len(learned) == len(thought) == 2 * 200 // 5
    assert thought == list(range(1, 81))  # one think after each held action is learned
    for k, (state, action, next_state, reward, terminal, valid) in enumerate(learned):
        hold = steps[5 * k : 5 * k + 5]
        np.testing.assert_array_equal(state, hold[0][0])
        np.testing.assert_array_equal(state, chosen[k])
        for _, u, _, _ in hold:  # the same action for all five steps
            np.testing.assert_array_equal(u, action)
        np.testing.assert_array_equal(next_state, hold[-1][2])
        np.testing.assert_allclose(reward, sum(r for *_, r in hold), rtol=1e-12)
        assert not terminal.any()
        # Valid only where every step of the hold was: not robot 1's second hold.
        assert valid.tolist() == ([True, False, True] if k == 1 else [True, True, True])
    # A target's first state starts a new hold: the target jump is inside no experience.
    np.testing.assert_array_equal(learned[40][0], steps[200][0])
    assert not np.array_equal(learned[39][2], learned[40][0])
    # A terminal step would end one robot's hold and not the others': refused.
    x = boat.observe()
    held.choose(x)
    with pytest.raises(ValueError, match="terminal"):
        held.learn(x, held.choose(x), x, np.zeros(3), np.array([False, True, False]), np.ones(3, dtype=bool))


def test_the_boat_benchmark_holds_actions_when_told(monkeypatch):
    with pytest.raises(ValueError, match="hold must divide steps_per_target"):
        BoatBenchConfig(hold=3)
    with pytest.raises(ValueError, match="hold must divide"):
        BoatBenchConfig(hold=0)
    with pytest.raises(ValueError, match=r"steps_per_target must be in \[1, 1e6\], got 0"):
        BoatBenchConfig(steps_per_target=0)
    acts = {True: 0, False: 0}  # the learners' act calls, exploring and greedy
    real_population = boat_bench.make_population

    def counted(*args, **kwargs):
        learner = real_population(*args, **kwargs)
        act = learner.act

        def counting_act(x, explore=True, **rest):
            acts[explore] += 1
            return act(x, explore=explore, **rest)

        learner.act = counting_act
        return learner

    monkeypatch.setattr(boat_bench, "make_population", counted)
    bench = BoatBenchConfig(controllers=2, mode="q", targets=2, greedy_targets=1, thinks=1, hold=4)
    result = run_condition(bench, "q")
    # One choice, one experience and one think per held action, in learning and in the greedy
    # evaluation alike: 2 targets (1 greedy) x 200 steps / 4.
    assert acts == {True: 2 * 200 // 4, False: 200 // 4}
    assert result["thinks"] == 2 * 2 * 200 // 4
    assert np.asarray(result["scores"]).shape == (2, 2) and np.isfinite(result["greedy_median"])


def test_gentler_hand_coded_gains_trade_score_for_reward():
    sweep = handcoded_sweep(6, 2, BoatConfig(dt=1.0), 0)
    assert [h["gain_scale"] for h in sweep] == [1.0, 0.5, 0.3, 0.2, 0.1, 0.05]
    full, gentlest = sweep[0], sweep[-1]
    assert full["score"] < gentlest["score"] < 0.5 and full["return"] < gentlest["return"]
    # Gentler gains spend less on thrust and on changing it, and more on distance.
    for term in ("energy", "coarseness"):
        assert full["return_terms"][term] < gentlest["return_terms"][term] <= 0.0
    assert gentlest["return_terms"]["distance"] < full["return_terms"]["distance"] < 0.0


def test_cartpole_eq43_step_and_failure():
    cp = CartPoleVec(1)
    cp.reset(np.random.default_rng(0))
    cp.state[:] = [[0.1, 0.2, 0.05, -0.1]]
    tr = cp.step(np.array([[5.0]]))
    cfg = CartPoleConfig()
    x, xd, th, thd = 0.1, 0.2, 0.05, -0.1
    tot = cfg.cart_mass + cfg.pole_mass
    th_acc = (
        cfg.g * np.sin(th)
        + np.cos(th)
        * (
            (-5.0 - cfg.pole_mass * cfg.half_length * thd**2 * np.sin(th) + cfg.cart_friction * np.sign(xd))
            / tot
        )
        - cfg.pole_friction * thd / (cfg.pole_mass * cfg.half_length)
    ) / (cfg.half_length * (4 / 3 - cfg.pole_mass * np.cos(th) ** 2 / tot))
    x_acc = (
        5.0
        + cfg.pole_mass * cfg.half_length * (thd**2 * np.sin(th) - th_acc * np.cos(th))
        - cfg.cart_friction * np.sign(xd)
    ) / tot
    np.testing.assert_allclose(
        tr.state[0], [x + 0.02 * xd, xd + 0.02 * x_acc, th + 0.02 * thd, thd + 0.02 * th_acc]
    )
    assert not tr.terminal[0] and tr.reward[0] == 0.0
    cp.state[:] = [[0.0, 0.0, np.deg2rad(11.99), 5.0]]
    tr = cp.step(np.array([[0.0]]))
    assert tr.terminal[0] and tr.reward[0] == -1.0
    assert cp.last_attempt[0] == 2
    np.testing.assert_allclose(cp.observe()[0], 0.0)  # restarted
    cp.state[:] = [[2.39, 1.0, 0.0, 0.0]]
    assert cp.step(np.array([[10.0]])).terminal[0]


def test_cartpole_force_is_clipped_and_uncontrolled_pole_falls():
    cp = CartPoleVec(2)
    cp.reset(np.random.default_rng(0))
    cp.state[:, 2] = 0.01
    steps = 0
    while not cp.step(np.array([[0.0], [0.0]])).terminal.all() and steps < 500:
        steps += 1
    assert steps < 200
    a, b = CartPoleVec(1), CartPoleVec(1)
    a.reset(np.random.default_rng(0)), b.reset(np.random.default_rng(0))
    np.testing.assert_allclose(a.step(np.array([[100.0]])).state, b.step(np.array([[10.0]])).state)


def test_positioning_dynamics_and_irrelevant_jumps():
    task = PositioningVec(1000)
    task.reset(np.random.default_rng(0))
    p0 = task.position.copy()
    tr = task.step(np.full((1000, 1), 0.5))
    np.testing.assert_allclose(task.position, p0 + 0.2 * 0.5)
    np.testing.assert_allclose(tr.state[:, 1], 0.1)
    jumped = ~tr.learnable
    assert 5 < jumped.sum() < 40  # about 2% of the systems jumped
    np.testing.assert_allclose(tr.state[~jumped, 0], task.target[~jumped] - task.position[~jumped])


def test_handcoded_positioning_reaches_the_target():
    task = PositioningVec(5)
    x = task.reset(np.random.default_rng(0))
    errs = []
    for _ in range(200):
        tr = task.step(handcoded_positioning(x))
        errs.append(np.abs(tr.state[:, 0]))
        x = tr.state
    assert np.median(errs) < 0.05


def test_vectorised_equals_individual_instances():
    many = BoatVec(3)
    many.reset(np.random.default_rng(0))
    singles = []
    for i in range(3):
        b = BoatVec(1)
        b.pos, b.heading, b.vel = (
            many.pos[i : i + 1].copy(),
            many.heading[i : i + 1].copy(),
            many.vel[i : i + 1].copy(),
        )
        b.turn_rate, b.prev_thrust, b.target = (
            many.turn_rate[i : i + 1].copy(),
            many.prev_thrust[i : i + 1].copy(),
            many.target[i : i + 1].copy(),
        )
        singles.append(b)
    u = np.random.default_rng(1).uniform(-1, 1, (3, 2))
    tr = many.step(u)
    for i, b in enumerate(singles):
        np.testing.assert_allclose(b.step(u[i : i + 1]).state[0], tr.state[i])


def test_the_boat_at_the_texts_step_is_its_own_gymnasium_task():
    import gymnasium as gym

    env = gym.make("wfnn/BoatStep1-v0")
    assert env.unwrapped.task.config.dt == 1.0
    assert gym.make("wfnn/Boat-v0").unwrapped.task.config.dt == 0.1
    check_env(env.unwrapped, skip_render_check=True)
