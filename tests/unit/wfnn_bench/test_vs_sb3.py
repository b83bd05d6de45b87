"""vs-sb3: its greedy evaluation (mean return and mean episode length) and its SB3 runs."""

import json
import tempfile
from dataclasses import replace

import gymnasium as gym
import numpy as np
import pytest

from wfnn_bench.vs_sb3 import VsSb3Config, _evaluate, run_sb3


class _Walk(gym.Env):
    """A walk along a line that ends (terminated) at 3 or beyond; reward 1 per step, 5 on arrival."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (1,), np.float64)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x = 0.0
        return np.array([self.x]), {}

    def step(self, action):
        self.x += float(action[0])
        arrived = self.x >= 3.0
        return np.array([self.x]), 5.0 if arrived else 1.0, arrived, False, {}


def test_evaluation_reports_the_mean_return_and_the_mean_episode_length():
    gym.register("WfnnTestWalk-v0", entry_point=_Walk, max_episode_steps=20)
    # Full steps arrive on the third; half steps on the sixth; standing still runs to the limit.
    assert _evaluate(lambda obs: np.array([1.0], np.float32), "WfnnTestWalk-v0", 2, 0) == (7.0, 3.0)
    assert _evaluate(lambda obs: np.array([0.5], np.float32), "WfnnTestWalk-v0", 3, 0) == (10.0, 6.0)
    assert _evaluate(lambda obs: np.array([0.0], np.float32), "WfnnTestWalk-v0", 1, 0) == (20.0, 20.0)


def test_an_sb3_run_leaves_no_log_folders_in_the_temporary_directory(tmp_path, monkeypatch):
    pytest.importorskip("stable_baselines3")
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # where SB3's own logger would write
    result = run_sb3("td3", "Pendulum-v1", 60, 0, VsSb3Config(eval_every=20, eval_episodes=1))
    assert result["steps"] == [20, 40, 60] and len(result["returns"]) == 3
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith("SB3-")] == []


def test_progress_counts_environment_steps_at_each_evaluation():
    from wfnn_bench.vs_sb3 import run, steps_total

    cfg = VsSb3Config(tasks=("Pendulum-v1",), steps=(25,), algorithms=("wfnn",), seeds=2, eval_every=10,
                      eval_episodes=1, thinks=1, act_calls=5)  # fmt: skip
    heard: list[int] = []
    result = run(cfg, heard.append)
    # Evaluations at 10, 20 and 25 steps of each seed: a run shows how far it has got as it goes.
    assert heard == [10, 10, 5, 10, 10, 5]
    assert sum(heard) == steps_total(cfg) == 50
    assert result["tasks"]["Pendulum-v1"]["thesis"]["steps"] == [10, 20, 25]


def test_an_evaluation_of_a_task_without_a_time_limit_ends():
    gym.register("WfnnTestEndless-v0", entry_point=_Walk, max_episode_steps=None)
    # Standing still never arrives; the episode is cut at EVAL_LIMIT steps.
    from wfnn_bench.vs_sb3 import EVAL_LIMIT

    assert _evaluate(lambda obs: np.array([0.0], np.float32), "WfnnTestEndless-v0", 2, 0) == (
        EVAL_LIMIT,
        EVAL_LIMIT,
    )


def test_every_task_is_checked_before_the_first_run():
    from wfnn_bench.vs_sb3 import run

    cfg = VsSb3Config(tasks=("Pendulum-v1", "CartPole-v1"), steps=(25, 25), algorithms=("wfnn",), seeds=1)
    heard: list[int] = []
    with pytest.raises(ValueError, match="CartPole-v1: the action space"):
        run(cfg, heard.append)
    assert heard == []  # Pendulum never started


def test_a_learner_config_that_cannot_be_built_stops_the_run_before_it_starts():
    """Deep options or a task too large for a learner are found before the first run, naming the task."""
    from wfnn_bench.vs_sb3 import run

    cfg = VsSb3Config(tasks=("Pendulum-v1",), steps=(25,), algorithms=("wfnn",), learners=("thesis", "deep"),
                      seeds=1, deep_options='{"n_wires": 0}')  # fmt: skip
    heard: list[int] = []
    with pytest.raises(ValueError, match="Pendulum-v1: n_wires"):
        run(cfg, heard.append)
    assert heard == []  # the thesis' learner never started
    # A device torch does not see was found only as the deep learner's first run started.
    import torch

    missing = f"cuda:{torch.cuda.device_count()}"
    cfg = replace(cfg, deep_options=json.dumps({"deep": {"device": missing}}))
    with pytest.raises(ValueError, match=f"Pendulum-v1: deep.device {missing}: torch sees no such"):
        run(cfg, heard.append)
    assert heard == []


@pytest.mark.parametrize(
    "kw, message",
    [
        ({"seed": -5}, "seeds -5 to -3"),
        ({"seed": (1 << 62) - 2}, "must lie in"),
        ({"seed": 1 << 32, "algorithms": ("wfnn", "sac")}, "SB3 takes seeds up to"),
        ({"deep_options": '{"learner": "thesis"}', "learners": ("deep",)}, "--learners"),
        ({"deep_options": '{"seed": 5}', "learners": ("deep",)}, "set no seed"),  # every run's would be 5
        ({"deep_options": '{"n_wires": 4}', "learners": ("thesis",)}, "does not run"),
        ({"deep_options": '{"n_wires": 4}', "learners": ("deep",), "algorithms": ("sac",)}, "does not run"),
        ({"reward_scale": 0.0}, "reward scale"),
        ({"reward_scale": -1.0}, "reward scale"),
        ({"reward_scale": float("nan")}, "reward_scale must be a finite number"),
        ({"reward_scale": 1e7}, "reward scale"),
    ],
)
def test_bad_vs_sb3_configs_are_refused(kw, message):
    with pytest.raises(ValueError, match=message):
        VsSb3Config(**kw)
    assert VsSb3Config(seed=1 << 32, algorithms=("wfnn",)).seed == 1 << 32  # WFNN alone takes more


@pytest.mark.parametrize(
    ("field", "names"),
    [
        ("tasks", ("Pendulum-v1", "Pendulum-v1")),
        ("algorithms", ("wfnn", "wfnn")),
        ("learners", ("thesis", "thesis")),
    ],
)
def test_a_name_given_twice_is_refused(field, names):
    """Each is a key of the results: every run was made and all but the last of a name's lost."""
    steps = {"steps": (1, 2)} if field == "tasks" else {"tasks": ("Pendulum-v1",), "steps": (1,)}
    with pytest.raises(ValueError, match=f"{field} named twice"):
        VsSb3Config(**{field: names}, **steps)


def test_the_largest_one_off_cost_of_a_run_is_told_beside_its_seconds_per_step(monkeypatch):
    """The first compiled update (or a cold numba cache) once cost 40 ms in a step of 4 ms, which a
    run of one or two seeds carries in its seconds per step (as SB3's carry its own)."""
    import time

    from wfnn_bench.vs_sb3 import run_wfnn
    from wfnn_common.learner import WFNN

    cfg = VsSb3Config(tasks=("Pendulum-v1",), steps=(40,), algorithms=("wfnn",), eval_every=10,
                      eval_episodes=1, thinks=1, act_calls=5)  # fmt: skip
    think, calls = WFNN.think, [0]

    def slow_once(self, *args, **kwargs):
        calls[0] += 1
        if calls[0] == 7:
            time.sleep(0.5)
        return think(self, *args, **kwargs)

    monkeypatch.setattr(WFNN, "think", slow_once)
    result = run_wfnn("Pendulum-v1", 40, 0, cfg)
    assert result["one_off_s"] >= 0.5 and result["s_per_step"] >= 0.5 / 40


def test_the_reward_scale_multiplies_what_learners_learn_and_not_the_returns_reported(monkeypatch):
    from wfnn_bench.vs_sb3 import run_wfnn
    from wfnn_common.learner import WFNN

    learnt: list[float] = []
    learn = WFNN.learn

    def heard(self, state, action, next_state, reward, *args, **kwargs):
        learnt.append(float(reward))
        return learn(self, state, action, next_state, reward, *args, **kwargs)

    monkeypatch.setattr(WFNN, "learn", heard)
    returns = {}
    for scale in (1.0, 1000.0):
        cfg = VsSb3Config(tasks=("Pendulum-v1",), steps=(20,), algorithms=("wfnn",), eval_every=20,
                          eval_episodes=1, thinks=0, act_calls=5, reward_scale=scale)  # fmt: skip
        returns[scale] = run_wfnn("Pendulum-v1", 20, 3, cfg)["returns"]
    np.testing.assert_allclose(np.array(learnt[20:]), 1000.0 * np.array(learnt[:20]), rtol=1e-12)
    assert min(learnt) < 0.0 and returns[1.0] == returns[1000.0]  # no thinks: the same greedy policy
    pytest.importorskip("stable_baselines3")
    from stable_baselines3.common.buffers import ReplayBuffer

    seen: list[float] = []
    store = ReplayBuffer.add

    def stored(self, obs, next_obs, action, reward, done, infos):
        seen.append(float(np.asarray(reward).reshape(-1)[0]))
        return store(self, obs, next_obs, action, reward, done, infos)

    monkeypatch.setattr(ReplayBuffer, "add", stored)
    sb3 = run_sb3("td3", "Pendulum-v1", 20, 0, VsSb3Config(eval_every=20, eval_episodes=1, reward_scale=1e-3))
    assert len(seen) == 20 and max(abs(r) for r in seen) < 0.0165  # Pendulum pays at most 16.3 a step
    assert sb3["returns"][0] < -10.0  # reported in the task's own units


class _Astray(_Walk):
    """The walk, whose observations lie a hundred times beyond the space it declares."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float64)

    def step(self, action):
        _, reward, arrived, truncated, info = super().step(action)
        return np.array([100.0]), reward, arrived, truncated, info


@pytest.mark.filterwarnings("ignore:.*not within the observation space")
def test_experiences_a_learner_refused_are_reported_beside_its_returns(caplog):
    """A task whose every experience the learner refused gave a table of returns as if it had learnt."""
    from wfnn_bench.vs_sb3 import rows, run

    gym.register("WfnnTestAstray-v0", entry_point=_Astray, max_episode_steps=20)
    gym.register("WfnnTestWalkBounded-v0", entry_point=_Walk, max_episode_steps=20)
    cfg = VsSb3Config(tasks=("WfnnTestAstray-v0", "WfnnTestWalkBounded-v0"), steps=(30, 30),
                      algorithms=("wfnn",), eval_every=30, eval_episodes=1, thinks=1,
                      act_calls=5)  # fmt: skip
    with caplog.at_level("WARNING"):
        result = run(cfg)
    assert result["tasks"]["WfnnTestAstray-v0"]["thesis"]["refused"] == [30, 30, 30]
    assert result["tasks"]["WfnnTestWalkBounded-v0"]["thesis"]["refused"] == [0, 0, 0]
    table = dict(rows(result, cfg))
    refused = "WfnnTestAstray-v0 thesis: experiences refused per seed (not learned from)"
    assert table[refused] == "30 / 30 / 30"
    assert not any(name.startswith("WfnnTestWalkBounded-v0") and "refused" in name for name in table)
    assert "WfnnTestAstray-v0 thesis seed 0: 30 of 30 experiences refused" in caplog.text


@pytest.mark.parametrize("steps", ["abc", "1e3", "100,x"])
def test_steps_that_are_not_whole_numbers_are_refused_naming_the_option(steps):
    from typer.testing import CliRunner

    from wfnn_bench.cli import app

    result = CliRunner().invoke(app, ["vs-sb3", "--steps", steps])
    assert result.exit_code == 2 and "--steps" in result.output and "whole numbers" in result.output


class _NanReward(_Walk):
    """The walk bounded in [-10, 10], whose every 7th reward is NaN."""

    observation_space = gym.spaces.Box(-10.0, 10.0, (1,), np.float64)

    def step(self, action):
        obs, reward, arrived, truncated, info = super().step(action)
        self.t = getattr(self, "t", 0) + 1
        return np.clip(obs, -10, 10), np.nan if self.t % 7 == 0 else reward, arrived, truncated, info


@pytest.mark.filterwarnings("ignore::UserWarning")  # Gymnasium's checker warns of the NaN rewards too
def test_a_comparator_that_fails_on_the_task_loses_no_other_run(caplog, tmp_path):
    """SAC learning NaN rewards failed in torch, and the whole benchmark ended with no JSON, the
    WFNN runs already made lost."""
    from wfnn_bench.vs_sb3 import plot, rows, run

    gym.register("WfnnTestNanReward-v0", entry_point=_NanReward, max_episode_steps=50)
    cfg = VsSb3Config(tasks=("WfnnTestNanReward-v0",), steps=(300,), algorithms=("wfnn", "sac"), seeds=2,
                      eval_every=150, eval_episodes=1, thinks=1, act_calls=5)  # fmt: skip
    heard = []
    with caplog.at_level("WARNING"):
        result = run(cfg, progress=heard.append)
    task = result["tasks"]["WfnnTestNanReward-v0"]
    assert len(task["thesis"]["final_returns"]) == 2 and all(n > 0 for n in task["thesis"]["refused"])
    assert [f[:8] for f in task["sac"]["failed"]] == ["seed 0: ", "seed 1: "]
    assert task["sac"]["finished_seeds"] == [] and "steps" not in task["sac"]
    assert sum(heard) == 2 * 2 * 300  # every step counted, the failed runs' too
    table = dict(rows(result, cfg))
    assert table["WfnnTestNanReward-v0 sac"].startswith("failed: seed 0: ")
    assert table["WfnnTestNanReward-v0 sac"].endswith("(seeds finished: none)")
    assert "WfnnTestNanReward-v0 sac failed (seed 0: " in caplog.text
    plot(result, tmp_path / "plot.png")
    assert (tmp_path / "plot.png").stat().st_size > 0


def test_a_comparators_seeds_that_finished_are_kept_beside_one_that_failed(monkeypatch):
    """A later seed's failure threw away the seeds that had finished, and the seeds after it."""
    from wfnn_bench import vs_sb3

    def run_sb3(algorithm, env_id, steps, seed, cfg, progress):
        progress(steps // 2)
        if seed == 1:
            raise RuntimeError("diverged\nmore lines")
        progress(steps - steps // 2)
        return {"steps": [steps], "returns": [-100.0 * (seed + 1)], "lengths": [200.0], "s_per_step": 1e-3,
                "act_us": 100.0, "act_us_p99": 200.0}  # fmt: skip

    monkeypatch.setattr(vs_sb3, "run_sb3", run_sb3)
    monkeypatch.setattr(vs_sb3, "sb3_problem", lambda: None)
    cfg = VsSb3Config(tasks=("Pendulum-v1",), steps=(20,), algorithms=("wfnn", "sac"), seeds=3, eval_every=20,
                      eval_episodes=1, thinks=1, act_calls=5)  # fmt: skip
    heard = []
    result = vs_sb3.run(cfg, progress=heard.append)
    sac = result["tasks"]["Pendulum-v1"]["sac"]
    assert sac["failed"] == ["seed 1: RuntimeError: diverged"] and sac["finished_seeds"] == [0, 2]
    assert sac["final_returns"].tolist() == [-100.0, -300.0] and sac["final_return_median"] == -200.0
    assert sum(heard) == 2 * 3 * 20
    assert "sac_act_over_thesis_act" not in result["tasks"]["Pendulum-v1"]  # not over every seed
    table = dict(vs_sb3.rows(result, cfg))
    assert table["Pendulum-v1 sac"] == "failed: seed 1: RuntimeError: diverged (seeds finished: 0, 2)"
    assert table["Pendulum-v1 sac: final return per seed"] == "-100 / -300"


class _Boom(_Walk):
    def step(self, action):
        raise ValueError("boom")


def test_a_task_failing_in_an_evaluation_is_named():
    """It said only "boom in step" where the task failed in a greedy evaluation alone."""
    gym.register("WfnnTestBoom-v0", entry_point=_Boom, max_episode_steps=20)
    with pytest.raises(RuntimeError, match="WfnnTestBoom-v0 failed in a greedy evaluation: ValueError: boom"):
        _evaluate(lambda obs: np.array([1.0], np.float32), "WfnnTestBoom-v0", 1, 0)


class _Strict(_Walk):
    """A task that checks its actions as Gymnasium's checker does: of its space's dtype too."""

    def step(self, action):
        assert self.action_space.contains(action), f"action {action!r} not in {self.action_space}"
        return super().step(action)


def test_an_evaluation_gives_actions_of_the_action_spaces_type():
    """WFNN's float64 actions failed a float32 task's own check in its evaluation alone (training
    steps cast them: a run failed only when it was evaluated)."""
    gym.register("WfnnTestStrict-v0", entry_point=_Strict, max_episode_steps=20)
    assert _evaluate(lambda obs: np.array([1.0]), "WfnnTestStrict-v0", 1, 0) == (7.0, 3.0)
