import mujoco
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from sims.nomad import (
    Forage,
    ForageConfig,
    NomadConfig,
    NomadEnv,
    NomadForage,
    NomadVec,
    WanderConfig,
    handcoded_wander,
)
from sims.nomad import sensing as nomad_sensing
from sims.nomad.behaviours import strip_lengths
from sims.nomad.model import NomadModelConfig
from sims.nomad.sensing import IR_BEAM_DEG, WILD_ENCODER
from sims.nomad.vision import COLS, ROWS, NomadVisionConfig, interesting_cells, smooth_carpet
from wfnn_common.config import ExplorationConfig, LearnerConfig
from wfnn_common.learner import WFNN


def test_state_action_and_reward_sizes_of_both_behaviours():
    rng = np.random.default_rng(0)
    for behaviour, size in (("servo", 6), ("wander", ROWS * COLS + 2)):
        cfg = NomadConfig(behaviour=behaviour)
        task = NomadVec(2, cfg)
        assert len(cfg.state_names) == size == len(task.state_low) == len(task.state_high)
        assert len(task.action_low) == 2
        x = task.reset(rng)
        assert x.shape == (2, size)
        tr = task.step(np.zeros((2, 2)))
        assert tr.state.shape == (2, size) and tr.reward.shape == (2,) and np.isfinite(tr.reward).all()
        assert task.reward_components(x, np.zeros((2, 2)), tr.state).shape == (2, 3)
    with pytest.raises(ValueError, match="behaviour"):
        NomadConfig(behaviour="dance")  # type: ignore[arg-type]


def test_wandering_declares_the_reward_its_forward_speed_earns():
    """Declared as none above 0, a wander run's values above 0.5 were judged diverged (a reset seen
    in 45 s of a default run) though forward speed pays up to `forward_weight` a step."""
    from wfnn_common.config import POSITIVE_REWARD_THRESHOLD

    task = NomadVec(1, NomadConfig(behaviour="wander"))
    rewards = [task.step(np.array([[task.action_high[0], 0.0]])).reward[0] for _ in range(60)]
    assert 0.0 < max(rewards) <= task.max_reward == task.config.forward_weight
    assert LearnerConfig.for_task(task).divergence_threshold == POSITIVE_REWARD_THRESHOLD
    servo = NomadVec(1, NomadConfig(behaviour="servo"))
    assert servo.max_reward == 0.0 and LearnerConfig.for_task(servo).divergence_threshold == 0.5
    forage = NomadForage(task)
    declared = [forage.ranges(name).max_reward for name in ("servo", "wander")]
    assert declared == [0.0, task.config.forward_weight]


@pytest.mark.parametrize("behaviour", ["servo", "wander"])
def test_gymnasium_check_env(behaviour):
    check_env(NomadEnv(NomadConfig(behaviour=behaviour), max_steps=10), skip_render_check=True)


def placed(task, x, y, heading):
    """Robot 0 at rest at (x, y, heading), the balls far away."""
    data = task.data[0]
    data.qpos[task.parts.q] = (x, y, heading)
    data.qvel[:] = 0.0
    for k in range(len(task.ball_geoms)):
        task.world.put_ball(0, k, (3.6, 2.6 - 0.4 * k))
    mujoco.mj_forward(task.model, data)


def test_the_base_follows_velocity_commands_within_its_acceleration_limits():
    cfg = NomadConfig(behaviour="wander", encoder_noise=(0.0, 0.0), encoder_glitch=0.0, person_speed=0.0)
    task = NomadVec(1, cfg)
    task.reset(np.random.default_rng(0))
    placed(task, 0.0, 0.2, np.pi)  # facing open carpet
    task.step(np.array([[0.5, 0.0]]))
    # 0.5 m/s^2 from rest: 0.05 m/s after one 0.1 s action, whatever was asked...
    assert task.velocity()[0, 0] == pytest.approx(0.05, abs=0.015)
    for _ in range(3):
        task.step(np.array([[0.5, 0.0]]))
    # ...and the ramp carries on from where it got to over the following actions.
    assert task.velocity()[0, 0] == pytest.approx(0.2, abs=0.015)
    for _ in range(12):
        task.step(np.array([[0.5, 0.0]]))
    assert task.velocity()[0, 0] == pytest.approx(0.5, abs=0.02)
    assert task.measured[0, 0] == pytest.approx(task.velocity()[0, 0])  # no noise configured
    assert abs(task.pose()[0, 1] - 0.2) < 0.02  # no side slip
    for _ in range(10):
        task.step(np.array([[0.0, 0.8]]))
    assert task.velocity()[0, 1] == pytest.approx(0.8, abs=0.03)


def test_infrared_ring_sees_a_wall_ahead_and_the_veto_stops_driving_into_it():
    cfg = NomadConfig(behaviour="wander", person_speed=0.0, encoder_noise=(0.0, 0.0))
    task = NomadVec(1, cfg)
    task.reset(np.random.default_rng(0))
    placed(task, 3.5, 0.0, 0.0)  # the east wall is 0.5 m ahead of the centre
    task.sensing.sense(0, first=True)
    ahead, behind = task.ir[0, 0], task.ir[0, cfg.ir_sensors // 2]
    assert ahead == pytest.approx(0.5 - task.model_config.radius, abs=0.01)
    assert behind == cfg.ir_range
    veto = task.veto(0)
    replaced = veto(np.zeros(37), np.array([0.5, -0.3]))
    assert replaced is not None and replaced.tolist() == [0.0, -0.5]  # stops, turns (its way: wall ahead)
    assert veto(np.zeros(37), np.array([0.2, 0.0])) is None  # slowly: it can stop in time
    placed(task, 2.0, 2.68, 0.0)  # the north wall 0.32 m to the left, nothing ahead
    task.sensing.sense(0, first=True)
    assert veto(np.zeros(37), np.array([0.4, 0.0])) is None  # along the wall, clear of it
    assert veto(np.zeros(37), np.array([0.5, 0.8])).tolist() == [0.0, -0.5]  # arcing into it: turn right
    assert veto(np.zeros(37), np.array([-0.3, 0.0])) is None  # backing away is allowed
    assert veto(np.zeros(37), np.array([0.0, 0.8])) is None  # turning on the spot is


def test_the_veto_sees_a_pillar_beside_the_arc_the_robot_would_drive():
    cfg = NomadConfig(behaviour="wander", person_speed=0.0, encoder_noise=(0.0, 0.0))
    task = NomadVec(1, cfg)
    task.reset(np.random.default_rng(0))
    (px, py), half = NomadModelConfig().pillars[0], 0.15
    placed(task, px - 0.2, py - half - 0.33, 0.0)  # pillar0 on the left, its face 0.33 m from the centre
    task.sensing.sense(0, first=True)
    veto = task.veto(0)
    assert veto(np.zeros(37), np.array([0.5, 0.0])) is None  # straight on passes it
    assert veto(np.zeros(37), np.array([0.5, 0.8])) is not None  # the arc sweeps the side into it


def test_the_person_waits_for_a_robot_in_the_way():
    task = NomadVec(1, NomadConfig(behaviour="wander"))
    task.reset(np.random.default_rng(0))
    ax, ay = (s / 2 for s in task.model_config.arena)
    placed(task, -(ax - 1.0) + 1.0, -ay + 0.6, np.pi / 2)  # 1 m ahead of the person's start, on their line
    for _ in range(30):
        task.step(np.zeros((1, 2)))
    person = task.data[0].mocap_pos[task.parts.person].copy()
    assert person[0] < -(ax - 1.0) + 0.3 and task.collisions[0] == 0  # stopped short of the robot
    placed(task, 0.0, 0.0, 0.0)  # out of the way: they walk on
    for _ in range(10):
        task.step(np.zeros((1, 2)))
    assert task.data[0].mocap_pos[task.parts.person][0] > person[0] + 0.3


def test_driving_into_a_wall_counts_one_collision():
    cfg = NomadConfig(behaviour="wander", person_speed=0.0)
    task = NomadVec(1, cfg)
    task.reset(np.random.default_rng(0))
    placed(task, 3.0, 0.0, 0.0)
    for _ in range(40):
        task.step(np.array([[0.5, 0.0]]))
    assert task.collisions[0] == 1
    assert task.pose()[0, 0] < 4.0 - task.model_config.radius + 0.02  # the wall stopped it


def test_eq_6_2_filters_the_carpet_matrix():
    raw = np.zeros((ROWS, COLS))
    raw[3, 2] = 1.0  # an obstacle in the second row from the bottom
    out = smooth_carpet(raw, None, alpha=0.0, beta=0.0)
    assert out[:4, 2].tolist() == [1.0, 1.0, 1.0, 1.0] and out[4, 2] == 0.0  # above it: not carpet
    assert out[:, [0, 1, 3, 4, 5, 6]].max() == 0.0
    smoothed = smooth_carpet(raw, None, alpha=0.0, beta=0.25)
    assert smoothed[3, 2] == pytest.approx(0.5) and smoothed[3, 1] == smoothed[3, 3] == pytest.approx(0.25)
    edge = np.zeros((ROWS, COLS))
    edge[4, 0] = 1.0
    assert smooth_carpet(edge, None, 0.0, 0.25)[4, 0] == pytest.approx(0.5 + 0.25 * 0.0 + 0.25 * 1.0)
    previous = np.ones((ROWS, COLS))
    np.testing.assert_allclose(smooth_carpet(np.zeros((ROWS, COLS)), previous, 0.3, 0.1), 0.3)


def test_the_interest_operator_picks_small_objects_surrounded_by_carpet():
    cfg = NomadVisionConfig()
    raw = np.full((ROWS, COLS), 0.1)
    raw[2, 3] = raw[2, 4] = 0.9
    assert interesting_cells(raw, cfg) == [[(2, 3), (2, 4)]]
    raw[1, 3] = 0.9  # still small and surrounded
    assert len(interesting_cells(raw, cfg)) == 1
    raw[1:4, 3:5] = 0.9  # six cells: a wall or a pillar, not an object
    assert interesting_cells(raw, cfg) == []
    edge = np.full((ROWS, COLS), 0.1)
    edge[2, 0] = 0.9  # at the edge of the view: it may go on out of view
    assert interesting_cells(edge, cfg) == []


def test_the_camera_sees_a_ball_on_open_carpet_as_interesting():
    task = NomadVec(1, NomadConfig(behaviour="wander", person_speed=0.0))
    task.reset(np.random.default_rng(0))
    placed(task, 0.5, -0.2, np.pi)  # facing west over open carpet
    task.sensing.sense(0, first=True)
    assert task.carpet_raw[0].max() < 0.5  # carpet only
    task.world.put_ball(0, 0, (-1.0, -0.2))
    mujoco.mj_forward(task.model, task.data[0])
    task.sensing.sense(0, first=True)
    found = task.interesting(0)
    assert [geom for geom, _ in found] == [task.ball_geoms[0]]
    np.testing.assert_allclose(found[0][1][:2], (-1.0, -0.2), atol=0.15)  # where it was seen


def test_handcoded_wandering_heads_for_the_longest_carpet_strip():
    carpet = np.zeros((ROWS, COLS))
    carpet[:, :3] = 1.0  # obstacles on the left
    carpet[:2, 6] = 1.0
    assert strip_lengths(carpet, 0.5).tolist() == [0, 0, 0, 5, 5, 5, 3]
    t, r = handcoded_wander(carpet)
    assert t == pytest.approx(WanderConfig().speed) and r == pytest.approx(0.0)  # column 3: ahead
    carpet[:, 3:5] = 1.0
    t, r = handcoded_wander(carpet)
    assert t > 0 and r < 0  # column 5, on the right: turn right
    t, r = handcoded_wander(np.ones((ROWS, COLS)))
    assert t == 0.0 and r > 0  # no carpet: turn on the spot


def test_servo_targets_are_tracked_lost_out_of_view_and_placed_again():
    cfg = NomadConfig(behaviour="servo", lost_reset_s=0.5, person_speed=0.0)
    task = NomadVec(1, cfg)
    task.reset(np.random.default_rng(1))
    assert task.valid()[0] and task.trackers[0].active
    assert np.abs(task.pixels[0]).max() < 250
    lost = placed_again = False
    for _ in range(60):
        tr = task.step(np.array([[0.0, 0.8]]))  # spin: the target leaves the view
        if not task.valid()[0]:
            lost = True
            assert not tr.learnable[0] and np.isnan(tr.state[0, :4]).all()
        if task.placed[0] > 1:
            placed_again = True
    assert lost and placed_again


def test_a_wild_encoder_reading_is_acted_on_but_never_learned():
    cfg = NomadConfig(behaviour="servo", encoder_glitch=1.0)  # every reading is wild
    task = NomadVec(1, cfg)
    x = task.reset(np.random.default_rng(0))
    tr = task.step(np.zeros((1, 2)))
    assert tr.state[0, 4] == WILD_ENCODER
    learner = WFNN(LearnerConfig.for_task(task, exploration=ExplorationConfig(kind="none")))
    assert np.all(np.isfinite(learner.act(tr.state[0]).action))
    assert not learner.learn(x[0], np.zeros(2), tr.state[0], tr.reward[0])


def test_a_control_tick_is_deterministic_for_a_seed():
    def run(seed):
        task = NomadVec(1, NomadConfig(behaviour="wander"), seed=seed)
        task.reset(np.random.default_rng(seed))
        return np.array([task.step(np.array([[0.3, 0.2]])).state for _ in range(10)])

    np.testing.assert_array_equal(run(3), run(3))


def test_the_room_holds_the_configured_number_of_balls():
    task = NomadVec(1, NomadConfig(behaviour="wander", balls=15))
    assert len(task.ball_geoms) == 15 == len(set(task.ball_geoms))
    task.reset(np.random.default_rng(0))
    robot = task.pose()[0, :2]
    balls = np.array([task.data[0].geom_xpos[g][:2] for g in task.ball_geoms])
    assert np.all(np.hypot(*(balls - robot).T) > task.model_config.radius + 0.3)  # none under the robot
    with pytest.raises(ValueError, match="balls"):
        NomadVec(1, NomadConfig(balls=0))


def ball_ahead(task, distance=1.3):
    """Robot 0 facing west over open carpet with ball 0 `distance` ahead of it."""
    placed(task, 0.5, -0.2, np.pi)
    task.world.put_ball(0, 0, (0.5 - distance, -0.2))
    mujoco.mj_forward(task.model, task.data[0])
    task.sensing.sense(0, first=True)


@pytest.mark.parametrize(
    ("pursue", "dominant"),
    [("every", [True, True]), ("every_second", [False, True]), ("never", [False, False])],
)
def test_foraging_pursues_the_targets_its_rule_says(pursue, dominant):
    task = NomadVec(1, NomadConfig(behaviour="wander", person_speed=0.0))
    task.reset(np.random.default_rng(0))
    forage = Forage(task, ForageConfig(pursue=pursue))
    for k, expected in enumerate(dominant):
        ball_ahead(task)
        assert forage.update().tolist() == [expected]  # the interest operator found the ball
        assert task.tracked()[0] == task.ball_geoms[0] and forage.found[0] == k + 1
        task.trackers[0].stop()  # out of view: wandering takes over
        task.pixels[0] = np.nan
        assert forage.pursuing().tolist() == [False]


def test_a_target_held_at_the_goal_is_reached_and_moved_away():
    task = NomadVec(1, NomadConfig(behaviour="wander", person_speed=0.0))
    task.reset(np.random.default_rng(0))
    cfg = ForageConfig(collect_px=1000.0, collect_s=0.5, quiet_s=1.0)  # anywhere in view is "at the goal"
    forage = Forage(task, cfg)
    ball_ahead(task)
    pursued = []
    for _ in range(8):
        pursued.append(bool(forage.update()[0]))
        task.step(np.zeros((1, 2)))
    assert forage.reached[0] == 1 and forage.found[0] == 1
    assert pursued[:4] == [True] * 4 and not any(pursued[4:])  # reached on its fifth tick (0.5 s), then quiet
    assert task.tracked()[0] == -1 and np.isnan(task.pixels[0]).all()
    ball = task.data[0].geom_xpos[task.ball_geoms[0]][:2]
    assert np.hypot(*(ball - task.pose()[0, :2])) > 2.0  # picked up and put elsewhere
    with pytest.raises(ValueError, match="pursue"):
        ForageConfig(pursue="sometimes")  # type: ignore[arg-type]


@pytest.mark.parametrize(("beam_deg", "seen"), [(0.0, False), (IR_BEAM_DEG, True)])
def test_an_infrared_beam_sees_a_ball_between_two_sensors_centre_lines(monkeypatch, beam_deg, seen):
    monkeypatch.setattr(nomad_sensing, "IR_BEAM_DEG", beam_deg)
    task = NomadVec(1, NomadConfig(behaviour="wander", person_speed=0.0))
    task.reset(np.random.default_rng(0))
    placed(task, 0.0, -0.2, 0.0)  # facing east over open carpet
    bearing = np.deg2rad(11.25)  # half way between sensors 0 and 1
    task.world.put_ball(0, 0, (0.7 * np.cos(bearing), -0.2 + 0.7 * np.sin(bearing)))
    mujoco.mj_forward(task.model, task.data[0])
    task.sensing.sense(0, first=True)
    near = min(task.ir[0, 0], task.ir[0, 1])
    assert (near < 0.5) == seen
