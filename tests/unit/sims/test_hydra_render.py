"""Rendered vision for HyDrA: template matching, the renderer, and saving what the cameras see."""

import logging
import threading

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from sims.hydra import HydraConfig, HydraEnv, HydraVec
from sims.hydra.render import ImageTracker
from sims.hydra.vision import VisionConfig
from tests.fakes import render_problem
from wfnn_bench.hydra import follow_target
from wfnn_client.frames import FrameWriter


@pytest.fixture
def rendering():
    problem = render_problem()
    if problem is not None:
        pytest.skip(f"no off-screen rendering here: {problem}")


def disc_image(centres, radius=10.0, size=(160, 120), background=0.8, seed=0):
    """Grey image [h, w] with dark discs at centres (x, y in pixels from the top-left)."""
    w, h = size
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    image = np.full((h, w), background, dtype=np.float32)
    image += np.float32(0.05) * (xx / w).astype(np.float32)  # shading, as under a lamp
    for cx, cy in centres:
        image[(xx - cx) ** 2 + (yy - cy) ** 2 <= radius**2] = 0.05
    rng = np.random.default_rng(seed)
    return image + rng.normal(0, 0.01, image.shape).astype(np.float32)


def to_pixel(x, y, size=(160, 120)):
    """Image coordinates from the top-left -> from the centre."""
    return np.array([x - size[0] / 2, y - size[1] / 2])


def test_template_tracker_follows_loses_and_reacquires():
    cfg = VisionConfig(width=160, height=120, quantise=False, window_px=12.0)
    tracker = ImageTracker(cfg)
    first = disc_image([(60.3, 50.0)])
    assert tracker.acquire(first, to_pixel(60.3, 50.0), 10.0)
    m = tracker.observe(first)
    assert m.found and m.switched
    np.testing.assert_allclose(m.pixel, to_pixel(60.3, 50.0), atol=0.3)
    # A small move stays inside the search window: the same target, found where it went.
    m = tracker.observe(disc_image([(66.8, 47.0)], seed=1))
    assert m.found and not m.switched
    np.testing.assert_allclose(m.pixel, to_pixel(66.8, 47.0), atol=0.3)
    # Too far for the window in one frame: lost there, found again by the whole-image search.
    m = tracker.observe(disc_image([(120.0, 60.0)], seed=2))
    assert m.found and m.switched
    np.testing.assert_allclose(m.pixel, to_pixel(120.0, 60.0), atol=0.3)
    # Nothing that looks like the template: lost.
    assert not tracker.observe(disc_image([], seed=3)).found
    # Half hidden by something white: no match.
    hidden = disc_image([(120.0, 60.0)], seed=4)
    hidden[:, 120:] = 0.85
    assert not tracker.observe(hidden).found


def test_template_tracker_takes_any_target_that_looks_the_same():
    tracker = ImageTracker(VisionConfig(width=160, height=120, quantise=False))
    assert tracker.acquire(disc_image([(40.0, 60.0)]), to_pixel(40.0, 60.0), 10.0)
    two = [(40.0, 60.0), (115.0, 60.0)]
    seen = tracker.observe(disc_image(two))
    assert seen.found
    # Keeps its target while it stays in the window, although the other matches as well.
    for k in range(5):
        m = tracker.observe(disc_image(two, seed=10 + k))
        assert m.found and not m.switched and m.target == seen.target
        np.testing.assert_allclose(m.pixel, seen.pixel, atol=0.5)
    # Its target disappears: the other one is taken, as a new acquisition.
    m = tracker.observe(disc_image([(115.0, 60.0)], seed=20))
    assert m.found and m.switched and m.target != seen.target
    np.testing.assert_allclose(m.pixel, to_pixel(115.0, 60.0), atol=0.5)


def test_a_plain_patch_is_not_taken_as_a_template():
    tracker = ImageTracker(VisionConfig(width=160, height=120))
    assert not tracker.acquire(disc_image([]), to_pixel(80.0, 60.0), 10.0)
    assert not tracker.acquire(disc_image([(3.0, 60.0)]), to_pixel(3.0, 60.0), 10.0)  # at the edge
    assert tracker.template is None and not tracker.observe(disc_image([(80.0, 60.0)])).found


def test_bad_vision_configs_are_refused():
    for kw in ({"source": "lidar"}, {"render_scale": 2.0}, {"min_correlation": 1.5}, {"width": 8}):
        with pytest.raises(ValueError):
            VisionConfig(**kw)


@pytest.mark.parametrize("regime", ["swing", "mixed"])
def test_rendered_tracking_agrees_with_the_camera_model(rendering, regime):
    rendered = follow_target(regime, "render", 150)
    projected = follow_target(regime, "projection", 150)
    assert rendered["found"].mean() > 0.7 and projected["found"].mean() > 0.7
    errors = rendered["errors"]
    assert np.median(errors) < 0.75 and np.percentile(errors, 95) < 2.0


def test_a_covered_static_target_is_not_found_in_the_image(rendering):
    cfg = HydraConfig(regime="static", vision=VisionConfig(source="render"), static_hidden_s=0.2)
    task = HydraVec(1, cfg)
    task.reset(np.random.default_rng(0))
    assert not task.found[0, 1]  # covered while it is placed
    for _ in range(4):
        task.step(np.zeros((1, 1)))
    assert task.found[0, 1] and task._image_trackers[0]["right"].template is not None
    task.close()


def test_camera_views_and_the_gymnasium_render(rendering):
    env = HydraEnv(HydraConfig(regime="mixed"), max_steps=10, render_mode="rgb_array")
    check_env(env, skip_render_check=False)
    env.reset(seed=0)
    image = env.render()
    assert image.shape == (240, 640, 3) and image.dtype == np.uint8
    assert image.min() < 40 and image.max() > 150  # dark targets on a white board
    env.close()
    with pytest.raises(ValueError, match="render_mode"):
        HydraEnv(render_mode="human")


def test_a_renderer_stays_with_its_thread(rendering):
    task = HydraVec(1, HydraConfig())
    task.reset(np.random.default_rng(0))
    task.camera_images(0)
    failure = []
    worker = threading.Thread(target=lambda: failure.append(_try(task)))
    worker.start()
    worker.join()
    assert "thread" in failure[0]
    task.close()


def _try(task):
    try:
        task.camera_images(0)
    except RuntimeError as exc:
        return str(exc)
    return ""


def test_frame_writer_writes_pngs_and_drops_when_behind(tmp_path, monkeypatch):
    import cv2

    import wfnn_client.frames as frames

    views = {"left": np.zeros((12, 16, 3), np.uint8), "right": np.full((12, 16, 3), 255, np.uint8)}
    writer = FrameWriter(tmp_path / "a")
    for tick in range(3):
        assert writer.submit(tick, views)
    assert writer.close() == {"written": 3, "dropped": 0, "failed": 0}
    image = cv2.imread(str(tmp_path / "a" / "0000002.png"))
    assert image.shape == (12, 32, 3) and image[:, :16].max() == 0 and image[:, 16:].min() == 255

    release = threading.Event()
    real_encode = cv2.imencode

    def slow_encode(ext, image):
        release.wait(10)
        return real_encode(ext, image)

    monkeypatch.setattr(frames.cv2, "imencode", slow_encode)
    writer = FrameWriter(tmp_path / "b", queue_size=2)
    accepted = [writer.submit(tick, views) for tick in range(6)]
    release.set()
    counts = writer.close()
    assert not all(accepted) and counts["dropped"] == accepted.count(False)
    assert counts["written"] == accepted.count(True) == len(list((tmp_path / "b").glob("*.png")))


def test_a_frame_the_disk_cannot_take_leaves_no_torn_picture_and_is_told_once(tmp_path, monkeypatch, caplog):
    from pathlib import Path

    views = {"left": np.zeros((12, 16, 3), np.uint8)}
    real_write_bytes = Path.write_bytes

    def full_disk(path, data):  # half the picture lands, then the disk is full
        real_write_bytes(path, data[: len(data) // 2])
        raise OSError(28, "No space left on device")

    writer = FrameWriter(tmp_path / "c")
    monkeypatch.setattr(Path, "write_bytes", full_disk)
    with caplog.at_level(logging.WARNING, logger="wfnn_client.frames"):
        for tick in range(5):
            assert writer.submit(tick, views)
        assert writer.close() == {"written": 0, "dropped": 0, "failed": 5}
    assert list((tmp_path / "c").iterdir()) == []
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 2 and "No space left" in warnings[0] and warnings[1].startswith("5 camera frames")
