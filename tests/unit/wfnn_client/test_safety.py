import numpy as np
import pytest

from sims.positioning import PositioningVec
from wfnn_client.config import ClientConfig
from wfnn_client.safety import SafetyConfig, SafetyLayer
from wfnn_client.sims import SIMS, SimOptions, positioning_wall_veto
from wfnn_io.protocol import EXP_FILTERED, EXP_SAFE_ACTION, EXP_VETO_ACTUAL

LOW, HIGH = (-1.0, -2.0), (1.0, 2.0)


def layer(period=0.1, veto=None, **kw):
    return SafetyLayer(SafetyConfig(**kw), LOW, HIGH, period, veto)


def test_no_weights_gives_the_safe_action():
    s = layer(safe_action=(0.5, -2.0))
    d = s.decide(None, np.zeros(2), 0.0)
    np.testing.assert_array_equal(d.executed, [0.5, -2.0])
    assert d.flags == EXP_SAFE_ACTION and d.proposed is None and s.counts["no_weights"] == 1


@pytest.mark.parametrize(
    "safe, component", [((0.5, -3.0), "component 1 is -3"), ((1.5, 0.0), r"component 0 is 1\.5")]
)
def test_a_safe_action_the_robot_cannot_execute_is_refused(safe, component):
    # Clipped, it would be another action than the one meant as safe, said nowhere.
    with pytest.raises(ValueError, match=component):
        layer(safe_action=safe)
    assert layer().safe.tolist() == [0.0, 0.0]  # the default, zero, is clipped into the range
    assert SafetyLayer(SafetyConfig(), (0.5, 1.0), (2.0, 3.0), 0.1).safe.tolist() == [0.5, 1.0]


@pytest.mark.parametrize("proposed", [[np.nan, 0.0], [0.0, np.inf], [-np.inf, np.nan]])
def test_a_non_finite_proposal_never_reaches_the_actuators(proposed):
    s = layer(safe_action=(0.5, -1.0), max_action_rate=(2.0, 10.0))
    d = s.decide(np.array(proposed), np.zeros(2), 0.0)
    np.testing.assert_array_equal(d.executed, [0.5, -1.0])
    assert d.flags == EXP_SAFE_ACTION and s.counts["non_finite"] == 1
    # A veto that answers NaN is not obeyed either.
    vetoing = layer(safe_action=(0.5, -1.0), veto=lambda state, action: np.array([np.nan, 0.0]))
    d = vetoing.decide(np.array([0.9, 1.0]), np.zeros(2), 0.0)
    np.testing.assert_array_equal(d.executed, [0.5, -1.0])
    assert d.flags == EXP_SAFE_ACTION and d.proposed is None and vetoing.counts["non_finite"] == 1


def test_the_filter_limits_each_components_change_per_second():
    s = layer(period=0.1, max_action_rate=(2.0, 10.0))  # per tick: 0.2 and 1.0
    d = s.decide(np.array([1.0, 2.0]), np.zeros(2), 0.0)
    np.testing.assert_allclose(d.executed, [0.2, 1.0])
    assert d.flags == EXP_FILTERED
    d = s.decide(np.array([1.0, 2.0]), np.zeros(2), 0.0)
    np.testing.assert_allclose(d.executed, [0.4, 2.0])
    d = s.decide(np.array([0.3, 2.0]), np.zeros(2), 0.0)
    np.testing.assert_allclose(d.executed, [0.3, 2.0])
    assert d.flags == 0 and s.counts["filtered"] == 2


def test_as_fast_as_possible_a_tick_stands_for_the_tasks_own_tick_for_the_filter():
    """It counted as a second: lock-step runs of a robot simulated at 15 to 50 Hz were filtered 15 to
    50 times more loosely than the same robot at its own rate."""
    fast = SafetyLayer(SafetyConfig(max_action_rate=(2.0, 10.0)), LOW, HIGH, 0.0, step_s=0.02)
    real = layer(period=0.02, max_action_rate=(2.0, 10.0))
    for s in (fast, real):
        np.testing.assert_allclose(s.decide(np.array([1.0, 2.0]), np.zeros(2), 0.0).executed, [0.04, 0.2])
    assert fast.deadline_s == float("inf")  # no deadline without a real-time tick


def test_a_lockstep_run_filters_its_actions_as_at_the_tasks_own_rate(tmp_path):
    from wfnn_client.run import run

    metrics = run(ClientConfig(sim="boat", rate_hz=0, lockstep=True, episodes=1, out=tmp_path / "run",
                               safety=SafetyConfig(max_action_rate=(5.0, 5.0))))  # fmt: skip
    # The boat's real-time tick is 50 Hz: 0.1 a tick, not 5.
    assert SIMS["boat"].rate_hz == 50.0 and metrics["safety"]["filtered"] > 0


def test_a_vetoed_action_is_replaced_and_returned_for_learning_twice():
    def veto(state, action):
        return np.zeros(2) if action[0] > 0.5 else None

    s = layer(veto=veto)
    d = s.decide(np.array([0.9, 1.0]), np.zeros(2), 0.0)
    np.testing.assert_array_equal(d.executed, [0.0, 0.0])
    np.testing.assert_array_equal(d.proposed, [0.9, 1.0])
    assert d.flags == EXP_VETO_ACTUAL and s.counts["vetoed"] == 1
    assert s.decide(np.array([0.1, 1.0]), np.zeros(2), 0.0).proposed is None
    off = SafetyLayer(SafetyConfig(veto=False), LOW, HIGH, 0.1, veto)
    assert off.decide(np.array([0.9, 1.0]), np.zeros(2), 0.0).proposed is None


def test_a_late_command_is_stale_and_the_safe_action_goes_out():
    s = layer(period=0.1, act_deadline_fraction=0.5)
    assert s.decide(np.array([0.3, 0.3]), np.zeros(2), 0.049).flags == 0
    d = s.decide(np.array([0.3, 0.3]), np.zeros(2), 0.051)
    np.testing.assert_array_equal(d.executed, [0.0, 0.0])
    assert d.flags == EXP_SAFE_ACTION and s.counts["late"] == 1
    # As fast as possible, nothing is ever late.
    assert layer(period=0.0).decide(np.array([0.3, 0.3]), np.zeros(2), 10.0).flags == 0


@pytest.mark.parametrize(
    "kw", [{"act_deadline_fraction": 0.0}, {"max_action_rate": (1.0, 0.0)}, {"act_deadline_fraction": 1.5}]
)
def test_bad_safety_config_is_refused(kw):
    with pytest.raises(ValueError):
        SafetyConfig(**kw)


def test_wrong_sizes_are_refused():
    with pytest.raises(ValueError, match="safe_action"):
        layer(safe_action=(0.0,))
    with pytest.raises(ValueError, match="max_action_rate"):
        layer(max_action_rate=(1.0,))


def test_positioning_wall_veto_and_the_reward_of_a_proposal():
    task = PositioningVec(1)
    veto = positioning_wall_veto(task, wall=1.2)
    task.position[:] = 1.3
    assert veto(np.zeros(2), np.array([0.5])) is not None
    assert veto(np.zeros(2), np.array([-0.5])) is None
    task.position[:] = 0.0
    assert veto(np.zeros(2), np.array([0.5])) is None
    reward_of = SIMS["positioning"].reward_of(task)
    # Moving at full speed is charged more than standing still, for the same outcome.
    assert reward_of(np.zeros(2), np.array([1.0]), np.zeros(2)) < reward_of(
        np.zeros(2), np.zeros(1), np.zeros(2)
    )


def test_boat_reward_of_matches_the_task_for_the_executed_action():
    task = SIMS["boat"].make(SimOptions())
    x = task.reset(np.random.default_rng(0))[0]
    u = np.array([0.4, -0.7])
    tr = task.step(u[None])
    assert SIMS["boat"].reward_of(task)(x, u, tr.state[0]) == pytest.approx(tr.reward[0])


def test_a_vetoed_tick_is_learned_twice(tmp_path, monkeypatch):
    import dataclasses

    from wfnn_client import run as client_run
    from wfnn_client.brain import LocalBrain
    from wfnn_io.protocol import EXP_VETO_PROPOSED

    learned = []

    class Recording(LocalBrain):
        def learn(self, experience, acted):
            learned.append(experience)
            super().learn(experience, acted)

    def always_veto(task):
        return lambda state, action: np.zeros_like(action)

    sims = dict(client_run.SIMS)
    sims["positioning"] = dataclasses.replace(sims["positioning"], veto=always_veto)
    monkeypatch.setattr(client_run, "SIMS", sims)
    monkeypatch.setattr(
        client_run, "make_brain", lambda config, learner, *_: Recording(learner, lockstep=True)
    )
    config = ClientConfig(
        sim="positioning", episodes=1, rate_hz=0, lockstep=True, thinks_per_action=1, out=tmp_path
    )
    metrics = client_run.run(config)
    actual, proposed = learned[0::2], learned[1::2]
    # Every tick is vetoed; the learnable ones (no target jump) are learned twice.
    assert metrics["safety"]["vetoed"] == 200 and len(learned) == metrics["experiences_learned"]
    assert len(actual) == len(proposed) and 150 < len(actual) <= 200
    assert all(e.flags == EXP_VETO_ACTUAL and not e.action.any() for e in actual)
    assert all(e.flags == EXP_VETO_PROPOSED for e in proposed)
    for a, p in zip(actual, proposed, strict=True):
        np.testing.assert_array_equal(a.state, p.state)
        np.testing.assert_array_equal(a.next_state, p.next_state)  # both led to the observed state
    moving = [(a, p) for a, p in zip(actual, proposed, strict=True) if abs(p.action[0]) > 0.1]
    assert moving and all(p.reward < a.reward for a, p in moving)  # Eq 5.5: the proposal is charged


@pytest.mark.parametrize("why, proposed, late_s", [
    ("no_weights", None, 0.0), ("non_finite", [np.nan, 0.0], 0.0), ("late", [1.0, 2.0], 0.06),
])  # fmt: skip
def test_the_safe_action_is_filtered_and_vetoed_like_any_other(why, proposed, late_s):
    """The safe action stood in for the proposal and went out as it was: a non-zero one jumped past
    the rate limit and drove into what the veto forbids (a late tick even undid a veto)."""
    s = layer(period=0.1, safe_action=(1.0, 2.0), max_action_rate=(2.0, 10.0))  # per tick: 0.2 and 1.0
    given = None if proposed is None else np.array(proposed)
    d = s.decide(given, np.zeros(2), late_s)  # at the start, the last action is the safe one
    np.testing.assert_array_equal(d.executed, [1.0, 2.0])
    assert d.flags == EXP_SAFE_ACTION
    s.previous = np.array([-1.0, -2.0])
    d = s.decide(given, np.zeros(2), late_s)
    np.testing.assert_allclose(d.executed, [-0.8, -1.0])  # at most a step from the last action
    assert d.flags == EXP_SAFE_ACTION | EXP_FILTERED and s.counts[why] == 2

    def no_positive_first(state, action):
        return np.array([0.0, action[1]]) if action[0] > 0.0 else None

    s = layer(period=0.1, safe_action=(1.0, 2.0), veto=no_positive_first)
    d = s.decide(given, np.zeros(2), late_s)
    np.testing.assert_array_equal(d.executed, [0.0, 2.0])
    assert d.flags == EXP_SAFE_ACTION | EXP_VETO_ACTUAL and s.counts["vetoed"] == 1
    assert d.proposed is None  # not the learner's choice: learned once, as executed


def test_a_safe_action_is_journaled_as_no_ones_choice(tmp_path):
    """It was recorded as chosen by the learner's weights (and flagged explored where the
    discarded proposal had been): a reader would credit the learner with it."""
    from wfnn_client import run as client_run
    from wfnn_io.logs import read_batches
    from wfnn_io.protocol import EXP_EXPLORED

    config = ClientConfig(sim="boat", episodes=1, rate_hz=50, duration_s=1.0, out=tmp_path,
                          safety=SafetyConfig(act_deadline_fraction=1e-9))  # every command late  # fmt: skip
    assert client_run.run(config)["safety"]["late"] > 0
    batches = list(read_batches(tmp_path / "journal"))
    assert batches and all(b.weights_source == "" for b in batches)
    for b in batches:
        assert (b.flags & EXP_SAFE_ACTION).all() and not (b.flags & EXP_EXPLORED).any()
        assert not b.weights_version.any() and not b.action.any()


def test_each_behaviours_log_names_the_behaviour_that_chose_the_others_actions(tmp_path):
    """A foraging robot's wander log recorded the servo learner's actions as ("", 0), the safe
    action's record, without the safe-action flag: no one's choice, and no one's safe action."""
    from sims.nomad import ForageConfig, NomadConfig
    from wfnn_client import run as client_run
    from wfnn_io.logs import read_batches

    # 24 balls, so that the episode (600 ticks) finds a target on any machine: with the default 6,
    # one machine's arithmetic (AMD EPYC) wandered the whole episode past them all.
    foraging = {"nomad": NomadConfig(behaviour="wander", balls=24), "forage": ForageConfig()}
    config = ClientConfig(sim="nomad", episodes=1, rate_hz=0.0, duration_s=60.0, lockstep=True, out=tmp_path,
                          **foraging)  # fmt: skip
    client_run.run(config)
    sources = {}
    for behaviour, other in (("servo", "wander"), ("wander", "servo")):
        for b in read_batches(tmp_path / f"journal_{behaviour}"):
            if b.weights_source == "":  # the safe action's record: only where it was the safe action
                assert (b.flags & EXP_SAFE_ACTION).all()
            sources.setdefault(behaviour, set()).add(b.weights_source)
        assert sources[behaviour] <= {"", "local", f"behaviour:{other}"}
    assert "behaviour:servo" in sources["wander"] and "local" in sources["wander"]
