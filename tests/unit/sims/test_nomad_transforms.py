from dataclasses import replace

import mujoco
import numpy as np
import pytest

from sims.nomad import NomadConfig, NomadVec
from sims.nomad.transforms import phantom_goals, servo_mirror
from sims.nomad.vision import NomadVisionConfig
from tests.unit.sims.test_nomad import placed

EXACT = NomadConfig(
    behaviour="wander", encoder_noise=(0.0, 0.0), encoder_glitch=0.0, person_speed=0.0,
    vision=NomadVisionConfig(noise_px=0.0),
)  # fmt: skip


def servo_run(side: float, ticks: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robot 0 facing west over open carpet, a ball ahead and `side` x 0.3 m to its left, tracked
    (the interest operator's pick) while the robot drives turning toward `side`: servo
    (states [ticks + 1, 6], actions, rewards [ticks])."""
    task = NomadVec(1, EXACT)  # wandering: no experimenter places targets
    task.reset(np.random.default_rng(0))
    placed(task, 0.5, -0.2, np.pi)
    task.world.put_ball(0, 0, (0.5 - 1.4, -0.2 - side * 0.3))
    mujoco.mj_forward(task.model, task.data[0])
    task.sensing.sense(0, first=True)
    assert task.acquire(0)
    # The interest operator's pick on the ball depends on which of its cells it met first; the
    # ball's centre is tracked instead, the same point in both worlds.
    g = task.tracked()[0]
    task.sensing.follow(0, g, task.data[0].geom_xpos[g].copy())
    states, actions, rewards = [task.observe("servo")], [], []
    for _ in range(ticks):
        u = np.array([[0.2, side * 0.4]])
        task.step(u)
        states.append(task.observe("servo"))
        assert task.valid("servo")[0]
        actions.append(u)
        rewards.append(task.reward(states[-2], u, states[-1], "servo"))
    task.close()
    return np.concatenate(states), np.concatenate(actions), np.concatenate(rewards)


def test_the_mirrored_servo_experience_is_what_the_mirrored_robot_meets():
    left, u_left, r_left = servo_run(1.0)
    right, u_right, r_right = servo_run(-1.0)
    mirror = servo_mirror(EXACT)
    mirrored, mirrored_u, mirrored_next, mirrored_r = mirror(left[:-1], u_left, left[1:], r_left)
    assert left[0, 0] * right[0, 0] < 0  # the target starts on opposite sides of the goal
    np.testing.assert_array_equal(mirrored_u, u_right)
    np.testing.assert_allclose(mirrored, right[:-1], atol=1e-6)
    np.testing.assert_allclose(mirrored_next, right[1:], atol=1e-6)
    np.testing.assert_allclose(mirrored_r, r_right, atol=1e-9)
    assert np.all(mirrored_r == r_left)  # the reward is the mirror's too


def test_the_mirror_is_refused_where_it_is_not_exact():
    with pytest.raises(ValueError, match="straight ahead"):
        servo_mirror(replace(EXACT, camera_yaw_deg=10.0))
    with pytest.raises(ValueError, match="midline"):
        servo_mirror(replace(EXACT, vision=NomadVisionConfig(goal_px=(20.0, 60.0))))


def test_a_phantom_goal_shifts_the_errors_and_rewards_the_phantom_goal():
    states, actions, rewards = servo_run(1.0)
    s, sn = states[:-1], states[1:]
    same = phantom_goals(s, actions, sn, rewards, np.zeros((len(s), 2)), EXACT)
    for a, b in zip(same, (s, actions, sn, rewards), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-12)
    offset = np.tile([40.0, -30.0], (len(s), 1))
    ps, pu, psn, pr = phantom_goals(s, actions, sn, rewards, offset, EXACT)
    np.testing.assert_allclose(ps[:, :2], s[:, :2] - offset)
    np.testing.assert_allclose(psn[:, :2], sn[:, :2] - offset)
    np.testing.assert_array_equal(ps[:, 2:], s[:, 2:])
    task = NomadVec(1, EXACT)
    # The task's own reward (Fig 6.10) for the phantom goal's errors.
    np.testing.assert_allclose(pr, task.reward(ps, pu, psn, "servo"), atol=1e-12)
    task.close()
    assert not np.allclose(pr, rewards)
