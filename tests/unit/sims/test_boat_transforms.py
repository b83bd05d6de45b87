"""Boat experience transformations: the mirror image and phantom targets agree with the dynamics."""

import numpy as np
import pytest

from sims.boat import BoatConfig, BoatVec, mirror, phantom


def _trajectory(boat: BoatVec, actions: np.ndarray) -> tuple[np.ndarray, ...]:
    """Experiences (state, action, next_state, reward) [T, ...] of boat 0 under `actions` [T, 2]."""
    rows = []
    for u in actions:
        x = boat.observe()[0]
        tr = boat.step(u[None])
        rows.append((x, u, tr.state[0], tr.reward[0]))
    return tuple(np.array(col) for col in zip(*rows, strict=True))


@pytest.mark.parametrize("dt", [0.1, 1.0])
def test_the_mirror_image_is_what_the_mirrored_boat_meets(dt):
    rng = np.random.default_rng(0)
    cfg = BoatConfig(dt=dt)
    boat, twin = BoatVec(1, cfg), BoatVec(1, cfg)
    boat.reset(rng)
    twin.reset(rng)
    twin.target = boat.target * np.array([1.0, -1.0])  # the target reflected in the boat's axis
    actions = rng.uniform(-1, 1, (60, 2))
    real = _trajectory(boat, actions)
    mirrored = _trajectory(twin, actions[:, ::-1])
    for got, expected in zip(mirror(*real), mirrored, strict=True):
        np.testing.assert_allclose(got, expected, atol=1e-12)
    # Mirroring twice gives back the experiences.
    for got, expected in zip(mirror(*mirror(*real)), real, strict=True):
        np.testing.assert_allclose(got, expected)


@pytest.mark.parametrize("dt", [0.1, 1.0])
def test_a_phantom_target_gives_the_experiences_a_boat_chasing_it_would_have(dt):
    rng = np.random.default_rng(1)
    cfg = BoatConfig(dt=dt)
    boat = BoatVec(1, cfg)
    boat.reset(rng)
    actions = rng.uniform(-1, 1, (80, 2))
    for u in actions[:20]:  # get the boat moving and turning
        boat.step(u[None])
    # A twin boat in the same state whose target is displaced by `world` (world frame).
    twin = BoatVec(1, cfg)
    for name in ("pos", "heading", "vel", "turn_rate", "prev_thrust"):
        setattr(twin, name, np.array(getattr(boat, name), copy=True))
    world = np.array([0.7, -0.4])
    twin.target = boat.target + world
    real, expected = _trajectory(boat, actions[20:]), _trajectory(twin, actions[20:])
    # The displacement in the boat's frame at each experience's state (the twin's target minus
    # the boat's): phantom() must then give the twin's next states and rewards.
    offsets = expected[0][:, :2] - real[0][:, :2]
    got = phantom(*real, offsets, cfg)
    for g, e in zip(got, expected, strict=True):
        np.testing.assert_allclose(g, e, atol=1e-12)
    # The offsets are the world displacement seen from the boat: same length throughout.
    np.testing.assert_allclose(np.hypot(*offsets.T), np.hypot(*world), atol=1e-12)


def test_a_zero_offset_leaves_experiences_unchanged():
    rng = np.random.default_rng(2)
    boat = BoatVec(1)
    boat.reset(rng)
    real = _trajectory(boat, rng.uniform(-1, 1, (10, 2)))
    for got, expected in zip(phantom(*real, np.zeros((10, 2))), real, strict=True):
        np.testing.assert_allclose(got, expected)
