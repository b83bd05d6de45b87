"""The Nomad's vision from rendered images: carpet templates, the interest operator, tracking."""

import mujoco
import numpy as np
import pytest

from sims.nomad import NomadConfig, NomadVec
from sims.nomad.render import CarpetGrid
from sims.nomad.vision import COLS, ROWS, NomadVisionConfig, carpet_mismatch
from tests.fakes import render_problem

RENDER = NomadVisionConfig(source="render")


@pytest.fixture(scope="module")
def rendering():
    problem = render_problem()
    if problem is not None:
        pytest.skip(f"no off-screen rendering here: {problem}")


def test_vision_config_rejects_bad_settings():
    for kw in ({"source": "sonar"}, {"render_scale": 0.05}, {"min_correlation": 1.0}, {"width": 8}):
        with pytest.raises(ValueError):
            NomadVisionConfig(**kw)  # type: ignore[arg-type]


def test_carpet_grid_finds_a_patch_and_where_it_is():
    grid = CarpetGrid(RENDER)
    w, h = grid.size
    carpet = np.empty((h, w, 3), dtype=np.float32)
    carpet[:] = (0.4, 0.44, 0.54)
    with pytest.raises(RuntimeError, match="template"):
        grid.difference(carpet)
    grid.acquire(carpet)
    assert np.all(grid.mismatch(grid.difference(carpet)) == 0.0)
    # A red square inside cell (2, 3): that cell mismatches, no other does.
    r0, c0 = int(grid.row_edges[2]) + 2, int(grid.col_edges[3]) + 3
    image = carpet.copy()
    image[r0 : r0 + 5, c0 : c0 + 5] = (0.9, 0.1, 0.1)
    raw = grid.mismatch(grid.difference(image))
    assert raw[2, 3] > 0.2 and np.delete(raw.ravel(), 2 * COLS + 3).max() == 0.0
    pixel, radius = grid.object_at(grid.difference(image), [(2, 3)])
    # The square's centre, in image units (4x the rendered pixels) from the image centre.
    expected = (np.array([c0 + 2.5, r0 + 2.5]) - np.array([w / 2, h / 2])) / RENDER.render_scale
    assert np.allclose(pixel, expected)
    assert radius == pytest.approx(np.sqrt(25 / np.pi) / RENDER.render_scale)
    assert grid.object_at(grid.difference(carpet), [(2, 3)]) is None


def test_open_carpet_reads_as_carpet_anywhere_in_the_room(rendering):
    task = NomadVec(1, NomadConfig(behaviour="wander", vision=RENDER))
    task.reset(np.random.default_rng(0))
    data = task.data[0]
    sensing = task.sensing
    assert sensing._grid is not None and sensing._vision_renderer is not None
    # Poses whose view stays on the floor (the room is 8 x 6 m; the camera sees 4 m ahead).
    for pose in ((0.0, 0.0, 0.0), (-0.5, 0.4, 0.15), (0.5, -0.4, 3.0), (0.0, 1.0, -0.1)):
        data.qpos[task.parts.q] = pose
        mujoco.mj_forward(task.model, data)
        # The room's furniture, balls and person left out: only carpet in view.
        view = sensing._vision_renderer.rgb(data, "camera", hidden_groups=(2, 3)).astype(np.float32) / 255
        assert sensing._grid.mismatch(sensing._grid.difference(view)).max() < 0.15, pose
    task.close()


def test_rendered_carpet_matrix_agrees_with_the_camera_model(rendering):
    task = NomadVec(1, NomadConfig(behaviour="wander", vision=RENDER), seed=2)
    rng = np.random.default_rng(2)
    task.reset(rng)
    agree = []
    for k in range(60):
        task.step(np.array([[0.3, 0.6 * np.sin(k / 7)]]))
        looked = task.camera.look(task.model, task.data[0])
        model_raw = carpet_mismatch(task.model, *looked, task.config.vision, rng)
        agree.append(np.mean((model_raw >= 0.5) == (task.carpet_raw[0] >= 0.5)))
    task.close()
    assert np.mean(agree) > 0.85


def test_a_ball_on_open_carpet_is_found_and_tracked_in_the_images(rendering):
    task = NomadVec(1, NomadConfig(behaviour="wander", vision=RENDER, person_speed=0.0))
    task.reset(np.random.default_rng(0))
    data = task.data[0]
    data.qpos[task.parts.q] = (0.5, -0.2, np.pi)  # facing west over open carpet
    for k in range(len(task.ball_geoms)):
        task.world.put_ball(0, k, (3.5, -2.6 + 0.4 * k))  # out of view along the east wall
    task.world.put_ball(0, 2, (-1.0, -0.2))
    mujoco.mj_forward(task.model, data)
    task.step(np.zeros((1, 2)))
    assert [geom for geom, _ in task.interesting(0)] == [task.ball_geoms[2]]
    assert task.acquire(0) and task.tracked()[0] == task.ball_geoms[2]
    errors = []
    for _ in range(12):  # turn slowly: the ball moves 120 px across the image and stays tracked
        task.step(np.array([[0.0, 0.3]]))
        assert task.valid("servo")[0]
        truth, _ = task.camera.project(data, data.geom_xpos[task.ball_geoms[2]])
        errors.append(np.abs(task.pixels[0] + np.asarray(task.config.vision.goal_px) - truth).max())
    assert np.median(errors) < 3.0
    # Taken away in one go (too far for the tracker's window): lost, not found elsewhere.
    task.world.put_ball(0, 2, (-3.5, -2.6))
    mujoco.mj_forward(task.model, data)
    task.step(np.zeros((1, 2)))
    assert not task.valid("servo")[0] and task.tracked()[0] == -1
    task.close()


def test_servo_targets_in_rendered_images_follow_the_camera_model(rendering):
    task = NomadVec(2, NomadConfig(behaviour="servo", vision=RENDER), seed=1)
    task.reset(np.random.default_rng(1))
    found, errors = [], []
    goal = np.asarray(task.config.vision.goal_px)
    for _ in range(60):
        x = np.nan_to_num(task.observe())
        task.step(np.stack([-x[:, 1] / 300, -x[:, 0] / 190], axis=1))  # a proportional servo
        for i in range(task.n):
            found.append(task.valid()[i])
            if task.valid()[i]:
                truth, _ = task.camera.project(task.data[i], task.trackers[i].point(task.data[i]))
                errors.append(np.abs(task.pixels[i] + goal - truth).max())
    task.close()
    assert np.mean(found) > 0.9 and np.median(errors) < 3.0
    assert task.carpet_raw.shape == (2, ROWS, COLS)
