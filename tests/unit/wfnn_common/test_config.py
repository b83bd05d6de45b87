import pytest

from tests.fakes import small_config
from wfnn_common.config import ConfigError, ExplorationConfig, LearnerConfig


def test_thesis_defaults():
    cfg = LearnerConfig(state_low=(0.0,), state_high=(1.0,), action_low=(-1.0,), action_high=(1.0,))
    assert (
        cfg.advantage_k,
        cfg.gamma,
        cfg.alpha,
        cfg.n_hidden,
        cfg.n_wires,
        cfg.thinks_per_action,
        cfg.smoothing_c,
    ) == (
        0.2,
        0.8,
        0.25,
        10,
        9,
        200,
        0.01,
    )
    assert cfg.exploration.kind == "uniform" and cfg.exploration.p == 0.1


@pytest.mark.parametrize(
    "kw, message",
    [
        ({"gamma": 1.0}, "gamma"),
        ({"advantage_k": 0.0}, "advantage_k"),
        ({"n_wires": 0}, "n_wires"),
        ({"state_low": (1.0, 0.0, 0.0)}, "state range"),
        ({"action_high": (1.0,)}, "action_low/high"),
        ({"derivatives": "sloppy"}, "derivatives"),
    ],
)
def test_invalid_values_are_refused_with_a_clear_message(kw, message):
    with pytest.raises(ConfigError, match=message):
        small_config(**kw)


def test_exploration_validation():
    with pytest.raises(ConfigError, match=r"exploration\.p"):
        ExplorationConfig(p=1.5)


def test_roundtrip_and_spec_hash():
    cfg = small_config(exploration=ExplorationConfig(kind="gaussian", sigma=0.2))
    again = LearnerConfig.from_dict(cfg.to_dict())
    assert again == cfg
    assert again.spec_hash() == cfg.spec_hash()
    assert small_config(gamma=0.5).spec_hash() == cfg.spec_hash()  # learning settings don't change the spec
    assert small_config(n_hidden=7).spec_hash() != cfg.spec_hash()
    with pytest.raises(ConfigError, match="unknown"):
        LearnerConfig.from_dict({**cfg.to_dict(), "bogus": 1})


def test_for_task_takes_the_tasks_ranges():
    from sims.boat import BoatVec

    cfg = LearnerConfig.for_task(BoatVec, thinks_per_action=3)
    assert cfg.state_low == BoatVec.state_low and cfg.action_high == BoatVec.action_high
    assert cfg.thinks_per_action == 3 and cfg.gamma == 0.8
