"""Gymnasium tasks behind the client's task interface."""

import dataclasses
import json
import logging
import shutil
from decimal import Decimal
from fractions import Fraction

import gymnasium as gym
import numpy as np
import pytest

from sims.gym import MEASURED_MARGIN, GymVec
from wfnn_common.config import MAX_ACTION_DIM, MAX_STATE_DIM, LearnerConfig
from wfnn_common.learners import make_learner


def test_pendulum_ranges_steps_and_restarts_at_its_time_limit():
    task = GymVec("Pendulum-v1")
    assert task.state_low == (-1.0, -1.0, -8.0) and task.action_high == (2.0,)
    assert task.max_episode_steps == 200 and task.rate_hz == pytest.approx(20.0)
    rng = np.random.default_rng(0)
    x = task.reset(rng)
    assert x.shape == (1, 3)
    for k in range(200):
        tr = task.step(np.array([[5.0]]))  # clipped to the action space
        assert tr.learnable[0] and not tr.terminal[0]  # a time limit is not a terminal state
        if k < 199:
            np.testing.assert_array_equal(task.observe(), tr.state)
    # The time limit restarted the episode: the state to act from is a new start, not the last.
    assert task.episodes == 1 and len(task.returns) == 1 and task.returns[0] < 0
    assert not np.allclose(task.observe(), tr.state)
    task.close()


def test_a_terminated_episode_is_learned_as_terminal_and_restarts():
    task = GymVec("MountainCarContinuous-v0")
    task.reset(np.random.default_rng(0))
    task.env.unwrapped.state = np.array([0.44, 0.06])  # just short of the goal, moving toward it
    task._obs = task.env.unwrapped.state[None].copy()
    tr = task.step(np.array([[1.0]]))
    assert tr.terminal[0] and tr.state[0, 0] >= 0.45 and task.observe()[0, 0] < 0
    task.close()


def test_tasks_without_box_spaces_or_unknown_ids_are_refused_clearly():
    with pytest.raises(ValueError, match="action space must be a 1-D Box"):
        GymVec("CartPole-v1")
    with pytest.raises(ValueError, match="cannot make"):
        GymVec("NoSuchTask-v9")


@pytest.mark.parametrize("error", [ImportError("install the extra package"), TypeError("bad argument")])
def test_a_task_whose_constructor_fails_is_refused_naming_it(error):
    def make(**kwargs):
        raise error

    gym.register(f"WfnnTestFails{type(error).__name__}-v0", entry_point=make)
    with pytest.raises(ValueError, match=f"WfnnTestFails{type(error).__name__}-v0.*{error}"):
        GymVec(f"WfnnTestFails{type(error).__name__}-v0")


class _Drift(gym.Env):
    """Unbounded observations: a random walk the actions push (declared bounds infinite)."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (2,), np.float64)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x = np.zeros(2)
        return self.x.copy(), {}

    def step(self, action):
        self.x = self.x + np.array([float(action[0]), 10.0 * self.np_random.normal()])
        return self.x.copy(), 0.0, False, False, {}


def test_infinite_observation_bounds_are_measured_from_random_play():
    gym.register("WfnnTestDrift-v0", entry_point=_Drift, max_episode_steps=100)
    task = GymVec("WfnnTestDrift-v0", probe_steps=3000)
    low, high = np.array(task.state_low), np.array(task.state_high)
    assert np.isfinite(low).all() and np.isfinite(high).all()
    again = GymVec("WfnnTestDrift-v0", probe_steps=3000)  # the same seed measures the same ranges
    assert again.state_low == task.state_low and again.state_high == task.state_high
    again.close()
    # And so does another seed: the ranges go into the learner's spec, and runs of one task with
    # other seeds share weights, logs and servers (weights of seed 0 were refused by seed 1).
    other = GymVec("WfnnTestDrift-v0", seed=1, probe_steps=3000)
    assert other.state_low == task.state_low and other.state_high == task.state_high
    other.close()
    # The second coordinate wanders about 17 times further than the first.
    assert 8 < (high[1] - low[1]) / (high[0] - low[0]) < 35  # steps of 10 against about 0.6
    # Measured ranges are estimates: a state far beyond them is still learned (only non-finite
    # ones are refused), by either learner.
    for learner in ("thesis", "deep"):
        lcfg = LearnerConfig.for_task(task, learner=learner)
        assert lcfg.valid_margin == MEASURED_MARGIN
        wfnn = make_learner(lcfg)
        far = high + 50 * (high - low)
        assert wfnn.learn(far, np.zeros(task.env.action_space.shape), far, 0.0)
        assert not wfnn.learn(far * np.nan, np.zeros(task.env.action_space.shape), far, 0.0)
    task.close()
    declared = GymVec("Pendulum-v1")
    assert LearnerConfig.for_task(declared).valid_margin == declared.valid_margin == 1.0
    declared.close()


class _Spaces(gym.Env):
    """A task whose spaces and observations a test chooses (set on the class before making it)."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (3,), np.float64)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
    nan_every = 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return self._obs(), {}

    def _obs(self):
        # One coordinate moves, one is still (a contact force that random play never makes), one
        # is NaN now and then where nan_every is set.
        obs = np.array([self.np_random.normal(), 0.0, self.np_random.normal()])
        if self.nan_every and self.t % self.nan_every == 0:
            obs[2] = np.nan
        return obs

    def step(self, action):
        self.t += 1
        return self._obs(), 1.0, False, False, {}


def _register(name, **attrs):
    env_class = type(name, (_Spaces,), attrs)
    gym.register(f"WfnnTest{name}-v0", entry_point=env_class, max_episode_steps=50)
    return f"WfnnTest{name}-v0"


def test_measured_ranges_leave_out_non_finite_values_and_give_a_still_observation_a_unit_span():
    task = GymVec(_register("NanSome", nan_every=7), probe_steps=500)
    low, high = np.array(task.state_low), np.array(task.state_high)
    assert np.isfinite(low).all() and np.isfinite(high).all()
    assert (low[1], high[1]) == (-0.5, 0.5)  # never moved: a range of 1 around its value
    assert 3 < high[2] - low[2] < 12  # a standard normal's 1-99% span (4.7), widened: NaNs left out
    task.close()


class _Shifted(_Spaces):
    """Declared in [0, inf) (or unbounded), its first observation lies about `at`."""

    observation_space = gym.spaces.Box(np.array([0.0, -np.inf, -np.inf]), np.inf, (3,), np.float64)
    at = -100.0

    def _obs(self):
        return np.array([self.at + self.np_random.normal(), 0.0, 0.0])


@pytest.mark.parametrize(
    ("attrs", "message"),
    [
        ({}, r"observation 0 is declared in \[0, inf\].*lie beyond its declared bound"),
        ({"observation_space": gym.spaces.Box(-np.inf, np.inf, (3,), np.float64), "at": 1e308}, "too large"),
        (
            {
                "observation_space": gym.spaces.Box(
                    np.array([10.0, -np.inf, -np.inf]), np.inf, (3,), np.float64
                ),
                "at": np.nan,
            },
            r"observation 0 is declared in \[10, inf\] and was never finite",
        ),
    ],
)
@pytest.mark.filterwarnings("ignore:.*not within the observation space")  # Gymnasium's checker sees it too
def test_observations_beyond_their_declared_bound_or_too_large_to_scale_are_named(attrs, message):
    name = f"Shifted{len(attrs)}{attrs.get('at', 0)}".replace(".", "").replace("+", "")
    with pytest.raises(ValueError, match=message):
        GymVec(_register(name, **{"_obs": _Shifted._obs, "at": _Shifted.at,
                                  "observation_space": _Shifted.observation_space, **attrs}))  # fmt: skip


F32_MAX = float(np.finfo(np.float32).max)


@pytest.mark.parametrize(("low", "high"), [(-np.inf, np.inf), (0.0, np.inf), (-F32_MAX, F32_MAX)])
def test_an_unbounded_observation_never_finite_is_refused_whatever_its_declared_bound(low, high):
    """Its range was made up (-0.5 to 0.5), not refused, unless a declared bound lay outside it
    (float32's largest size stands for no bound, as infinity does)."""
    space = gym.spaces.Box(np.array([low, -np.inf]), np.array([high, np.inf]), (2,), np.float64)
    never = _register(f"NeverFinite{low}{high}".replace(".", "").replace("+", ""), observation_space=space,
                      _obs=lambda self: np.full(2, np.nan))  # fmt: skip
    with pytest.raises(ValueError, match=r"observation 0 is declared in \[\S+, \S+\] and was never finite"):
        GymVec(never)


def _old_reset(self, *, seed=None, options=None):
    return np.zeros(3)


def _old_step(self, action):
    return np.zeros(3), 1.0, False, {}


@pytest.mark.parametrize(
    ("attrs", "message"),
    [
        ({"reset": _old_reset}, r"reset\(\) returned a ndarray, not Gymnasium's \(observation, info\)"),
        ({"step": _old_step}, r"failed in step: .*expected 5, got 4"),  # Gymnasium's wrappers unpack it first
        ({"_obs": lambda self: np.array([1j, 0, 0])}, "returned an observation that is not numbers"),
        (
            {"_obs": lambda self: np.array(["0.1", 0.0, 0.0], dtype=object)},
            "an observation that is not numbers",
        ),
    ],
)
@pytest.mark.filterwarnings("ignore::UserWarning")  # Gymnasium's checker warns of them too
def test_a_task_that_does_not_speak_gymnasiums_api_is_refused_naming_it(attrs, message):
    """An old API's reset failed with "too many values to unpack", not naming the task; a complex
    observation lost its imaginary part with only a warning."""
    name = _register(f"OldApi{next(iter(attrs)).strip('_')}{len(message)}", **attrs)
    with pytest.raises((ValueError, RuntimeError), match=f"WfnnTestOldApi.*{message}"):
        task = GymVec(name, probe_steps=100) if "_obs" in attrs else GymVec(name)
        task.reset(np.random.default_rng(0))
        task.step(np.zeros((1, 1)))


def test_bounds_of_float32s_largest_size_stand_for_none():
    huge = float(np.finfo(np.float32).max)
    task = GymVec(_register("HugeObs", observation_space=gym.spaces.Box(-huge, huge, (3,), np.float32)))
    assert task.valid_margin == MEASURED_MARGIN and max(task.state_high) < 100  # measured, not +-3.4e38
    task.close()
    with pytest.raises(ValueError, match="action space must be bounded"):
        GymVec(_register("HugeAct", action_space=gym.spaces.Box(-huge, huge, (1,), np.float32)))


@pytest.mark.parametrize(
    ("space", "message"),
    [
        (gym.spaces.Box(0, 3, (1,), np.int64), "real numbers"),
        (gym.spaces.Box(np.array([0.0, 0.5]), np.array([1.0, 0.5]), (2,), np.float64), "action 1 has low ="),
    ],
)
def test_action_spaces_that_cannot_be_learned_are_refused_naming_the_task(space, message):
    with pytest.raises(ValueError, match=message) as refused:
        GymVec(_register(f"Act{len(message)}", action_space=space))
    assert "WfnnTestAct" in str(refused.value) and "\n" not in str(refused.value)


def test_a_task_with_more_variables_than_a_learner_takes_is_refused_before_its_ranges_are_probed():
    """The probe kept every observation: 100,000 unbounded ones took 4 GB and 19 s to refuse."""
    wide = gym.spaces.Box(-np.inf, np.inf, (MAX_STATE_DIM + 1,), np.float64)
    with pytest.raises(ValueError, match=f"at most {MAX_STATE_DIM} observation variables"):
        GymVec(_register("Wide", observation_space=wide))
    many = gym.spaces.Box(-1.0, 1.0, (MAX_ACTION_DIM + 1,), np.float32)
    with pytest.raises(ValueError, match=f"at most {MAX_ACTION_DIM} action variables"):
        GymVec(_register("ManyActions", action_space=many))


class _StillFarOut(_Spaces):
    def _obs(self):
        return np.array([self.np_random.normal(), 1e12, 7.5e13])


def test_a_still_observation_far_from_zero_gets_a_range_a_learner_can_scale():
    """Given a width of 1 at 1e12, the range was refused as too narrow to scale."""
    gym.register("WfnnTestStillFarOut-v0", entry_point=_StillFarOut, max_episode_steps=50)
    task = GymVec("WfnnTestStillFarOut-v0")
    assert task.state_low[1] < 1e12 < task.state_high[1] and task.state_low[2] < 7.5e13 < task.state_high[2]
    LearnerConfig.for_task(task)  # accepted
    task.close()


def test_a_constant_declared_observation_gets_a_range_and_a_gymnasium_tasks_rewards_may_be_positive():
    space = gym.spaces.Box(np.array([-1.0, 2.0, -1.0]), np.array([1.0, 2.0, 1.0]), (3,), np.float64)
    task = GymVec(_register("ConstObs", observation_space=space))
    assert (task.state_low[1], task.state_high[1]) == (1.5, 2.5)
    # The thesis' divergence threshold assumes rewards of at most zero; this task pays +1 a step.
    cfg = LearnerConfig.for_task(task)
    assert cfg.divergence_threshold == 1.5
    assert LearnerConfig.for_task(task, learner="deep").divergence_threshold == 1e4
    task.close()


def test_this_projects_own_tasks_declare_rewards_of_at_most_zero_through_gymnasium():
    import sims.boat  # noqa: F401  # registers wfnn/Boat-v0

    boat = GymVec("wfnn/Boat-v0")
    assert boat.max_reward == 0.0 and LearnerConfig.for_task(boat).divergence_threshold == 0.5
    boat.close()


class _NanReward(_Spaces):
    every = 10

    def step(self, action):
        self.t += 1
        return self._obs(), float("nan") if self.t % self.every == 0 else -1.0, False, False, {}


class _AlwaysNanReward(_NanReward):
    every = 1


def test_a_tasks_non_finite_rewards_are_counted_apart_from_the_episodes_score(tmp_path):
    from wfnn_client.config import ClientConfig
    from wfnn_client.run import run

    gym.register("WfnnTestNanReward-v0", entry_point=_NanReward, max_episode_steps=50)
    config = ClientConfig(sim="gym", env="WfnnTestNanReward-v0", rate_hz=0, episodes=2, out=tmp_path / "r")
    metrics = run(config)
    # The mean of the 45 finite rewards: a NaN step is not a reward of 0.
    assert metrics["scores"] == [-1.0, -1.0] and metrics["last10_median"] == -1.0
    assert metrics["metric_not_finite"] == 10
    assert metrics["client/reward_mean"] == -1.0
    # No finite reward at all: no score (null in the JSON), not a perfect-looking 0.
    gym.register("WfnnTestAlwaysNanReward-v0", entry_point=_AlwaysNanReward, max_episode_steps=20)
    config = dataclasses.replace(config, env="WfnnTestAlwaysNanReward-v0", episodes=1, out=tmp_path / "n")
    metrics = run(config)
    assert np.isnan(metrics["scores"][0]) and np.isnan(metrics["last10_median"])
    saved = json.loads((tmp_path / "n" / "metrics.json").read_text())
    assert saved["scores"] == [None] and saved["last10_median"] is None


def test_the_clients_summary_says_why_a_score_is_nan_and_a_curve_it_could_not_draw_is_not_claimed(tmp_path):
    from typer.testing import CliRunner

    from wfnn_client import cli

    gym.register("WfnnTestAlwaysNanRewardCli-v0", entry_point=_AlwaysNanReward, max_episode_steps=5)
    gym.register("WfnnTestHugeRewardCli-v0", entry_point=_Rewarding, max_episode_steps=5)
    out = tmp_path / "r"
    result = CliRunner().invoke(cli.app, ["--env", "WfnnTestAlwaysNanRewardCli-v0", "--rate-hz", "0",
                                          "--episodes", "1", "--out", str(out)])  # fmt: skip
    said = " ".join(result.output.split())
    assert result.exit_code == 0, said
    assert (
        "episode 1 nan -> episode 1 nan" in said and "5 steps' metric was not finite; nan: none was" in said
    )
    assert (out / "learning_curve.png").exists() and "metrics.json and learning_curve.png" in said
    # The same folder again, with scores matplotlib cannot draw: the earlier curve is not passed off.
    # (Another task's: its journal, which would refuse it, goes first.)
    shutil.rmtree(out / "journal")
    result = CliRunner().invoke(cli.app, ["--env", "WfnnTestHugeRewardCli-v0", "--rate-hz", "0",
                                          "--episodes", "1", "--out", str(out)])  # fmt: skip
    said = " ".join(result.output.split())
    assert result.exit_code == 0, said
    assert not (out / "learning_curve.png").exists() and "(no learning curve: see above)" in said


class _Rewarding(_Spaces):
    reward = 1e308

    def step(self, action):
        self.t += 1
        return self._obs(), self.reward, False, False, {}


def test_finite_rewards_that_sum_past_float64s_range_are_counted_apart_too(tmp_path):
    from wfnn_client.config import ClientConfig
    from wfnn_client.run import run

    gym.register("WfnnTestHugeReward-v0", entry_point=_Rewarding, max_episode_steps=20)
    config = ClientConfig(sim="gym", env="WfnnTestHugeReward-v0", rate_hz=0, episodes=1, out=tmp_path / "r")
    metrics = run(config)
    assert metrics["scores"] == [1e308]  # the mean over the one step that could be summed
    assert metrics["metric_not_finite"] == 19  # each step past the first
    # A score matplotlib cannot put on an axis leaves the run's figures whole, without its plot.
    assert json.loads((tmp_path / "r" / "metrics.json").read_text())["scores"] == [1e308]


def test_a_greedy_run_of_saved_weights_sizes_its_divergence_threshold_by_the_rewards_it_meets(tmp_path):
    """Not learning, the robot still meets the rewards that say how large healthy values are."""
    from wfnn_client.config import ClientConfig
    from wfnn_client.run import run
    from wfnn_common.deep_net import DeepShapes
    from wfnn_common.learners import weights_from_flat
    from wfnn_io.persist import load_weights, save_weights

    rich = type("Rich", (_Rewarding,), {"reward": 1e4})
    gym.register("WfnnTestRich-v0", entry_point=rich, max_episode_steps=120)
    options = '{"deep": {"hidden": [8], "value_hidden": 4, "warmup": 0}, "batch_size": 8}'
    common = {"sim": "gym", "env": "WfnnTestRich-v0", "rate_hz": 0, "lockstep": True, "episodes": 1,
              "learner": "deep", "learner_options": options}  # fmt: skip
    run(ClientConfig(**common, thinks_per_action=0, out=tmp_path / "a"))
    cfg, params, meta = load_weights(tmp_path / "a" / "weights.npz")
    a, b, _ = DeepShapes.of(cfg).slices()["bo"]
    flat = params.flat.copy()
    flat[0, a:b] = 1e5  # values a task paying 1e4 a step reaches, far above the config's 1e4
    save_weights(tmp_path / "a" / "weights.npz", cfg, weights_from_flat(cfg, flat), meta)
    saved = tmp_path / "a" / "weights.npz"
    metrics = run(ClientConfig(**common, learn=False, weights=saved, out=tmp_path / "b"))
    assert metrics["learn/divergence_resets"] == 0 and metrics["client/q_mean"] > 9e4


@pytest.mark.parametrize(
    ("reward", "learner", "told"),
    [(1e4, "deep", True), (1e-3, "deep", True), (-1.0, "deep", False), (1e4, "thesis", False),
     (1e4, "popart", False)],
)  # fmt: skip
def test_a_deep_run_meeting_rewards_far_from_the_scale_its_defaults_suit_is_told_once(
    tmp_path, caplog, reward, learner, told
):
    from wfnn_client.config import ClientConfig
    from wfnn_client.run import REWARD_ADVICE_AFTER, run

    paying = type("Paying", (_Rewarding,), {"reward": reward})
    gym.register("WfnnTestPaying-v0", entry_point=paying, max_episode_steps=REWARD_ADVICE_AFTER // 2)
    # "popart": the deep learner with its values normalised, which suits any reward's scale.
    deep = {"hidden": [8], "value_hidden": 4, "warmup": 0}
    if learner == "popart":
        deep["popart_rate"] = 0.001
    small = json.dumps({"deep": deep, "batch_size": 8})
    config = ClientConfig(sim="gym", env="WfnnTestPaying-v0", rate_hz=0, episodes=3,
                          learner="thesis" if learner == "thesis" else "deep",
                          learner_options="" if learner == "thesis" else small, thinks_per_action=1,
                          out=tmp_path / "r")  # fmt: skip
    with caplog.at_level(logging.WARNING):
        run(config)
    said = [r.getMessage() for r in caplog.records if "root-mean-square" in r.getMessage()]
    assert len(said) == (1 if told else 0), said
    if told:
        assert f"{abs(reward):.3g} a step, outside 0.05-20" in said[0] and "popart_rate" in said[0]


class _MisShaped(gym.Env):
    """An env whose observation grows from 3 to 5 numbers at its fifth step."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (3,), np.float64)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.zeros(3), {}

    def step(self, action):
        self.t += 1
        return np.zeros(5 if self.t >= 5 else 3), -1.0, False, False, {}


def test_an_observation_that_does_not_fit_the_space_ends_the_run_naming_the_task_and_keeps_the_record(
    tmp_path,
):
    """It ended in "writing the experience record failed" and lost the experiences before it."""
    from wfnn_client.config import ClientConfig
    from wfnn_client.run import run
    from wfnn_io import logs

    gym.register("WfnnTestMisShaped-v0", entry_point=_MisShaped, max_episode_steps=50)
    task = GymVec("WfnnTestMisShaped-v0")
    task.reset(np.random.default_rng(0))
    for _ in range(4):
        task.step(np.zeros((1, 1)))
    with pytest.raises(
        ValueError, match=r"WfnnTestMisShaped-v0 returned an observation of shape \(5,\); .* \(3,\)"
    ):
        task.step(np.zeros((1, 1)))
    task.close()
    config = ClientConfig(
        sim="gym", env="WfnnTestMisShaped-v0", episodes=1, rate_hz=0.0, out=tmp_path / "run"
    )
    with pytest.raises(ValueError, match="WfnnTestMisShaped-v0 returned an observation of shape"):
        run(config)
    assert logs.summarise(tmp_path / "run" / "journal").experiences == 4


class _OddReward(gym.Env):
    """A bounded task whose fifth step returns `odd` as its reward."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float64)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self, odd=None, fail=False):
        self.odd, self.fail, self.t = odd, fail, 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.zeros(2), {}

    def step(self, action):
        self.t += 1
        if self.t >= 5 and self.fail:
            raise FloatingPointError("physics exploded")
        return np.zeros(2), (self.odd if self.t >= 5 else np.float32(-1.0)), False, False, {}


@pytest.mark.parametrize(
    "odd, said",
    [(np.array([1.0, 2.0]), r"array of shape \(2,\)"), (None, "None"), ("oops", "'oops'"), ("0.5", "'0.5'"),
     (1 + 2j, r"\(1\+2j\)"), ([1.0], r"array of shape \(1,\)"), (b"1", "b'1'"),
     (np.complex128(1 + 2j), r"np.complex128\(1\+2j\)"), (np.complex64(1), r"np.complex64")],
)  # fmt: skip
def test_a_reward_that_is_not_one_number_ends_the_run_naming_the_task(odd, said):
    """It ended in numpy's or float()'s own words ("only 0-dimensional arrays can be converted")."""
    gym.register("WfnnTestOddReward-v0", entry_point=_OddReward, kwargs={"odd": odd}, max_episode_steps=50)
    task = GymVec("WfnnTestOddReward-v0")
    task.reset(np.random.default_rng(0))
    for _ in range(4):  # numpy's scalars and Python's numbers are rewards
        task.step(np.zeros((1, 1)))
    with pytest.raises(ValueError, match=f"OddReward-v0 returned a reward that is not one number: {said}"):
        task.step(np.zeros((1, 1)))
    assert task.last_reward[0] == -1.0  # the last good one stands
    task.close()


@pytest.mark.parametrize("number", [Fraction(1, 2), Decimal("0.5"), 10**20, True, np.float16(0.5)])
def test_a_reward_that_float_takes_is_one_number_whatever_its_type(number):
    """Gymnasium's rewards are SupportsFloat: a check for numpy's and Python's types refused these."""
    gym.register(
        "WfnnTestNumberReward-v0", entry_point=_OddReward, kwargs={"odd": number}, max_episode_steps=50
    )
    task = GymVec("WfnnTestNumberReward-v0")
    task.reset(np.random.default_rng(0))
    for _ in range(5):
        task.step(np.zeros((1, 1)))
    assert task.last_reward[0] == float(number)
    task.close()


def test_a_task_that_fails_in_its_own_step_is_named_with_its_error():
    gym.register("WfnnTestFailingStep-v0", entry_point=_OddReward, kwargs={"fail": True}, max_episode_steps=9)
    task = GymVec("WfnnTestFailingStep-v0")
    task.reset(np.random.default_rng(0))
    for _ in range(4):
        task.step(np.zeros((1, 1)))
    with pytest.raises(RuntimeError, match="FailingStep-v0 failed in step: FloatingPointError: physics") as e:
        task.step(np.zeros((1, 1)))
    assert isinstance(e.value.__cause__, FloatingPointError)  # --verbose shows where
    task.close()


class _MisShapedUnbounded(_MisShaped):
    observation_space = gym.spaces.Box(-np.inf, np.inf, (3,), np.float64)


def test_an_observation_that_does_not_fit_the_space_in_the_range_probe_is_named_too():
    """The probe stacked what it saw: numpy's "inhomogeneous shape" named neither task nor cause."""
    gym.register("WfnnTestMisShapedProbe-v0", entry_point=_MisShapedUnbounded, max_episode_steps=50)
    with pytest.raises(ValueError, match=r"MisShapedProbe-v0 returned an observation of shape \(5,\)"):
        GymVec("WfnnTestMisShapedProbe-v0")


class _FallsEvery3(_Spaces):
    """Pays 1 a step and ends its episode every third step (as a hopper that keeps falling)."""

    def step(self, action):
        self.t += 1
        return self._obs(), 1.0, self.t % 3 == 0, False, {}


def test_a_gym_runs_score_claims_no_return_and_the_tasks_own_returns_are_recorded(tmp_path):
    """The score (mean reward per step) was named "x time limit = return": 1.0 here, read as a
    return of 30 where each of the task's 10 episodes returned 3."""
    from wfnn_bench.report import _run_sections
    from wfnn_client.config import ClientConfig
    from wfnn_client.run import run

    gym.register("WfnnTestFalls-v0", entry_point=_FallsEvery3, max_episode_steps=30)
    metrics = run(ClientConfig(sim="gym", env="WfnnTestFalls-v0", rate_hz=0, episodes=1, out=tmp_path / "r"))
    assert metrics["scores"] == [1.0] and metrics["metric"] == "mean reward per step"
    assert metrics["task_episodes"] == 10 and metrics["task_returns"] == [3.0] * 10
    assert metrics["task_returns_last10_median"] == 3.0
    rows = dict(_run_sections(tmp_path / "r")[0][0].rows)
    assert rows["task's own episodes"] == "10" and rows["task's return, last-10 median"] == "3"


class _LeavesItsSpace(_FallsEvery3):
    """Declares observations in [-0.1, 0.1] and gives ones near 1 (a task's bug)."""

    observation_space = gym.spaces.Box(-0.1, 0.1, (3,), np.float64)

    def _obs(self):
        return np.array([1.0, 0.5, 1.0])

    def step(self, action):
        self.t += 1
        return self._obs(), 1.0, False, False, {}


def test_a_run_whose_every_experience_the_learner_refuses_is_told_so(tmp_path, caplog):
    """It learned nothing, and only the summary line's count said so."""
    from wfnn_client.config import ClientConfig
    from wfnn_client.run import run

    gym.register("WfnnTestLeaves-v0", entry_point=_LeavesItsSpace, max_episode_steps=20)
    with caplog.at_level(logging.WARNING):
        metrics = run(
            ClientConfig(sim="gym", env="WfnnTestLeaves-v0", rate_hz=0, episodes=2, out=tmp_path / "r")
        )
    assert metrics["learn/rejected"] == 40 and metrics["learn/experiences"] == 0
    told = [r.getMessage() for r in caplog.records if "the learner refuses experiences" in r.getMessage()]
    assert len(told) == 1 and "declared observation space" in told[0]


class _Slow(_Spaces):
    dt = 1e6  # one step a million seconds


def test_a_task_slower_than_real_time_allows_is_told_so_not_blamed_on_a_flag_not_given(tmp_path):
    """Its rate was refused as `--rate-hz 1e-06`, which the user never gave."""
    from typer.testing import CliRunner

    from wfnn_client import cli

    gym.register("WfnnTestSlow-v0", entry_point=_Slow, max_episode_steps=5)
    argv = ["--env", "WfnnTestSlow-v0", "--episodes", "1", "--out", str(tmp_path / "r")]
    result = CliRunner().invoke(cli.app, argv)
    said = " ".join(result.output.replace("│", " ").split())  # out of the error's box
    assert result.exit_code == 2 and "the task's own rate is 1e-06 Hz, below real time's limit" in said, said
    assert not (tmp_path / "r").exists()


class _CountedDrift(_Drift):
    """`_Drift`, counting the actions sent to it (a robot's, it may be)."""

    sent = 0

    def step(self, action):
        _CountedDrift.sent += 1
        return super().step(action)


def test_ranges_saved_with_weights_are_taken_without_a_random_action_sent_to_measure_them(tmp_path):
    """A run given weights measured the ranges again: 2,000 random actions, outside the safety
    layer and the record, sent to a task that may drive a real robot."""
    from wfnn_client.config import ClientConfig
    from wfnn_client.run import run as run_client

    _CountedDrift.sent = 0
    gym.register("WfnnTestCountedDrift-v0", entry_point=_CountedDrift, max_episode_steps=20)
    first = ClientConfig(sim="gym", env="WfnnTestCountedDrift-v0", rate_hz=0, lockstep=True, episodes=1,
                         thinks_per_action=1, out=tmp_path / "a")  # fmt: skip
    run_client(first)
    assert _CountedDrift.sent == 2000 + 20  # the probe, then the run's one episode
    _CountedDrift.sent = 0
    again = dataclasses.replace(first, weights=tmp_path / "a" / "weights.npz", out=tmp_path / "b")
    run_client(again)
    assert _CountedDrift.sent == 20
    measured = GymVec("WfnnTestCountedDrift-v0")
    saved = GymVec("WfnnTestCountedDrift-v0", state_ranges=(measured.state_low, measured.state_high))
    assert (saved.state_low, saved.state_high, saved.valid_margin) == (
        measured.state_low, measured.state_high, measured.valid_margin)  # fmt: skip
    # Ranges that do not fit the observations (another task's) are refused, nothing measured.
    _CountedDrift.sent = 0
    with pytest.raises(
        ValueError, match="the ranges given: ranges for 1 observations, WfnnTestCountedDrift-v0 has 2"
    ):
        GymVec("WfnnTestCountedDrift-v0", state_ranges=((0.0,), (1.0,)))
    # Weights that cannot be read are refused before the task is sent anything (they were refused
    # only after the probe's 2,000 random actions).
    (tmp_path / "bad.npz").write_bytes(b"not weights")
    with pytest.raises(ValueError, match=r"bad\.npz"):
        run_client(dataclasses.replace(first, weights=tmp_path / "bad.npz", out=tmp_path / "c"))
    with pytest.raises(ValueError, match="is a directory"):
        run_client(dataclasses.replace(first, weights=tmp_path, out=tmp_path / "d"))
    assert _CountedDrift.sent == 0


class _ResetFailsLater(gym.Env):
    """A task whose episodes end after 10 steps and whose second reset fails (a simulator lost)."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float64)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
    resets = 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        _ResetFailsLater.resets += 1
        if _ResetFailsLater.resets > 1:
            raise ConnectionError("simulator lost")
        self.t = 0
        return np.zeros(2), {}

    def step(self, action):
        self.t += 1
        return np.full(2, 0.05 * self.t), 1.0, self.t == 10, False, {}


def test_a_restart_failing_at_an_episodes_end_keeps_the_transition_into_the_end(tmp_path):
    """The restart failed inside the step that ended the episode: the transition, which happened,
    was lost with it (learned by no one, in no record)."""
    from wfnn_client.config import ClientConfig
    from wfnn_client.run import run as run_client
    from wfnn_io import logs

    _ResetFailsLater.resets = 0
    gym.register("WfnnTestResetFailsLater-v0", entry_point=_ResetFailsLater, max_episode_steps=50)
    cfg = ClientConfig(sim="gym", env="WfnnTestResetFailsLater-v0", rate_hz=0, lockstep=True, episodes=3,
                       thinks_per_action=1, out=tmp_path / "a")  # fmt: skip
    with pytest.raises(RuntimeError, match="failed in reset: ConnectionError: simulator lost"):
        run_client(cfg)
    [batch] = list(logs.read_batches(tmp_path / "a" / "journal"))
    assert len(batch) == 10 and batch.terminal[-1] and not batch.terminal[:-1].any()
    assert (tmp_path / "a" / "weights.npz").exists()  # the robot failed: what was learned is kept
