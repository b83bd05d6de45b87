import itertools

import mujoco
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from sims.hydra import AXES, HydraConfig, HydraEnv, HydraVec
from sims.hydra.model import JOINTS
from sims.hydra.vision import Camera, VisionConfig


def subsets(names):
    return [c for r in range(len(names) + 1) for c in itertools.combinations(names, r)]


def test_all_256_configurations_have_consistent_sizes():
    rng = np.random.default_rng(0)
    configs = list(itertools.product(subsets(JOINTS), subsets(AXES)))
    assert len(configs) == 256
    tasks = {}
    for joints, axes in configs:
        cfg = HydraConfig(joints=joints, axes=axes)
        nj, na = len(joints), len(axes)
        assert len(cfg.state_names) == 2 * (nj + na) and len(cfg.reward_names) == nj + 2 * na
        task = tasks[(joints, axes)] = (
            HydraVec(1, cfg) if (nj, na) in ((0, 0), (4, 4), (1, 1), (2, 3)) else None
        )
        if task is None:
            continue
        assert len(task.state_high) == 2 * (nj + na) and len(task.action_high) == nj
        x = task.reset(rng)
        assert x.shape == (1, 2 * (nj + na))
        tr = task.step(np.zeros((1, nj)))
        assert tr.state.shape == (1, 2 * (nj + na)) and np.isfinite(tr.reward).all()
        comps = task.reward_components(np.zeros((1, 4)), np.zeros((1, 4)), tr.state)
        assert comps.shape == (1, nj + 2 * na) and (comps >= 0).all()


def test_bad_configurations_are_refused():
    for kw in (
        {"joints": ("neck",)},
        {"axes": ("right_z",)},
        {"joints": ("pan", "pan")},
        {"regime": "juggling"},
    ):
        with pytest.raises(ValueError):
            HydraConfig(**kw)


@pytest.mark.parametrize("regime", ["swing", "static", "mixed", "elastic"])
def test_gymnasium_check_env(regime):
    env = HydraEnv(
        HydraConfig(regime=regime, joints=("pan", "right"), axes=("right_x", "right_y")), max_steps=20
    )
    check_env(env, skip_render_check=True)


def test_the_pinhole_projection():
    task = HydraVec(1, HydraConfig())
    task.reset(np.random.default_rng(0))
    data, cam = task.data[0], task.cameras[0]["right"]
    mujoco.mj_forward(task.model, data)
    pos, axis = data.cam_xpos[cam.id], -data.cam_xmat[cam.id].reshape(3, 3)[:, 2]
    centre, depth = cam.project(data, pos + 2.0 * axis)
    np.testing.assert_allclose(centre, [0.0, 0.0], atol=1e-9)
    assert depth == pytest.approx(2.0)
    right = data.cam_xmat[cam.id].reshape(3, 3)[:, 0]  # the camera's x axis: image right
    up = data.cam_xmat[cam.id].reshape(3, 3)[:, 1]
    pixel, _ = cam.project(data, pos + 2.0 * axis + 0.1 * right + 0.05 * up)
    np.testing.assert_allclose(pixel, [cam.focal * 0.05, -cam.focal * 0.025], rtol=1e-9)
    assert cam.project(data, pos - axis)[1] < 0  # behind the camera


def test_the_tracker_loses_targets_out_of_view_and_blurred_and_reacquires():
    task = HydraVec(1, HydraConfig(regime="static"))
    task.reset(np.random.default_rng(0))
    model, data = task.model, task.data[0]
    cam = Camera(model, "right", VisionConfig(noise_px=0.0), np.random.default_rng(0))
    mujoco.mj_forward(model, data)
    disc = task._candidates[0]
    groups = task._groups
    pos = data.cam_xpos[cam.id] - 0.7 * data.cam_xmat[cam.id].reshape(3, 3)[:, 2]  # in front of the board
    data.mocap_pos[task._disc_mocap[0]] = pos
    mujoco.mj_kinematics(model, data)
    first = cam.observe(model, data, [(disc, data.geom_xpos[disc].copy())], groups)
    assert first.found and first.switched and np.abs(first.pixel).max() <= 1.0
    same = cam.observe(model, data, [(disc, data.geom_xpos[disc].copy())], groups)
    assert same.found and not same.switched
    # A jump across the image between two frames blurs it out.
    jump = data.geom_xpos[disc] + 0.08 * data.cam_xmat[cam.id].reshape(3, 3)[:, 0]
    assert not cam.observe(model, data, [(disc, jump)], groups).found
    # Far outside the image.
    side = data.geom_xpos[disc] + 2.0 * data.cam_xmat[cam.id].reshape(3, 3)[:, 0]
    assert not cam.observe(model, data, [(disc, side)], groups).found


def test_a_hidden_target_is_not_seen():
    task = HydraVec(1, HydraConfig(regime="mixed"))
    task.reset(np.random.default_rng(0))
    model, data = task.model, task.data[0]
    cam = task.cameras[0]["right"]
    mujoco.mj_forward(model, data)
    cylinder = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "cylinder")
    # A point straight behind the cylinder, on the line of sight from the camera.
    behind = data.cam_xpos[cam.id] + 2.0 * (data.geom_xpos[cylinder] - data.cam_xpos[cam.id])
    weight = task._candidates[0]
    assert not cam._visible(model, data, weight, behind, task._groups)
    assert cam._visible(model, data, weight, data.geom_xpos[weight].copy(), task._groups)


def test_joint_velocity_ramps_at_the_acceleration_limit():
    cfg = HydraConfig(joints=("pan", "right"), axes=("right_x",))
    task = HydraVec(1, cfg)
    task.reset(np.random.default_rng(0))
    right = task._qpos[3]
    start = task.data[0].qpos[right]
    task.step(np.array([[0.0, 1.2]]))
    tick = 1.0 / cfg.rate_hz
    # The command ramps at 20 rad/s^2: 1.2 rad/s is reached after 60 ms of the 66.7 ms tick.
    ramp_time = 1.2 / cfg.max_acceleration[3]
    most = 0.5 * 1.2 * ramp_time + 1.2 * (tick - ramp_time)
    moved = task.data[0].qpos[right] - start
    assert 0.5 * most < moved <= most * 1.05
    assert task.observe()[0, 3] == pytest.approx(1.2)  # the state's velocity is the command
    pan = task.data[0].qpos[task._qpos[0]]
    task.step(np.array([[1.0, 0.0]]))
    assert task.data[0].qpos[task._qpos[0]] - pan < 0.5 * 1.0 * tick  # pan is slower (5 rad/s^2)
    # Its ramp continues over the following ticks: 5 rad/s^2 reaches 1 rad/s after 0.2 s (3 ticks).
    pan_dof = task.model.jnt_dofadr[mujoco.mj_name2id(task.model, mujoco.mjtObj.mjOBJ_JOINT, "pan")]
    task.step(np.array([[1.0, 0.0]]))
    assert task.data[0].qvel[pan_dof] == pytest.approx(2 * tick * 5.0, abs=0.1)  # the actuator lags a little
    task.step(np.array([[1.0, 0.0]]))
    assert task.data[0].qvel[pan_dof] == pytest.approx(1.0, abs=0.1)


def test_lost_targets_make_invalid_states_and_unlearnable_transitions():
    task = HydraVec(1, HydraConfig(regime="swing", lost_reset_s=0.5))
    task.reset(np.random.default_rng(3))
    seen_lost = seen_valid = False
    for _ in range(60):
        tr = task.step(np.array([[1.2]]))  # turn away to the joint limit: the target is lost
        if np.isnan(tr.state[0, 2]):
            seen_lost = True
            assert not tr.learnable[0]
        else:
            seen_valid = True
    assert seen_lost and seen_valid and task.recentred[0] >= 1


def test_a_lost_target_costs_half_the_image_not_nothing():
    """Its pixels read as 0: losing the target was paid the best reward (a Gymnasium learner
    slewing away scored -0.2 to -63 against a tracker's -96 to -136)."""
    env = HydraEnv()
    env.reset(seed=0)
    cfg = env.unwrapped.task.config
    lost = []
    for _ in range(12):
        _, reward, *_ = env.step(env.action_space.high)  # turn away at full speed: the target is lost
        if np.isnan(env.unwrapped.task.pixels[0]).any():
            lost.append(reward)
            assert env.unwrapped.task.pixel_error()[0] == cfg.vision.width / 2
    assert lost and max(lost) <= -cfg.position_weight


def test_static_targets_step_and_the_step_is_not_learned():
    cfg = HydraConfig(regime="static", static_hold_s=(0.5, 0.5), static_hidden_s=0.1)
    task = HydraVec(1, cfg)
    task.reset(np.random.default_rng(0))
    positions, learnable = [], []
    for _ in range(40):
        tr = task.step(np.zeros((1, 1)))
        positions.append(task.data[0].mocap_pos[task._disc_mocap[0]].copy())
        learnable.append(bool(tr.learnable[0]))
    changes = [k for k in range(1, 40) if not np.allclose(positions[k], positions[k - 1])]
    assert len(changes) >= 3
    assert all(not learnable[k] for k in changes)


def test_a_control_tick_is_deterministic_for_a_seed():
    def run(seed):
        task = HydraVec(1, HydraConfig(regime="mixed", joints=("right",), axes=("right_x",)), seed=seed)
        task.reset(np.random.default_rng(seed))
        return np.array([task.step(np.array([[0.3]])).state for _ in range(20)])

    np.testing.assert_array_equal(run(1), run(1))


def test_lag_is_recovered_from_a_delayed_copy():
    from wfnn_bench.hydra import lag_s

    t = np.arange(600) / 15.0
    target = np.sin(2 * np.pi * t / 2.5)
    joint = np.sin(2 * np.pi * (t - 0.2) / 2.5)
    assert lag_s(target, joint, 15.0) == pytest.approx(0.2, abs=0.02)
    assert lag_s(target, target, 15.0) == pytest.approx(0.0, abs=1e-9)
    assert np.isnan(lag_s(target, np.zeros_like(t), 15.0))
