import dataclasses
import json

import numpy as np
import pytest

from sims.boat import BoatVec
from tests.fakes import small_config
from wfnn_common.config import ConfigError, ExplorationConfig, LearnerConfig, with_options


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
        # Below float32's smallest normal number, 1 / k made the first minibatch update's weights NaN.
        ({"advantage_k": 1e-39}, "advantage_k"),
        ({"eps": 1e-46}, "eps"),  # 0 in float32: a weight 1 / 0 where an action lies on a wire
        ({"n_wires": 0}, "n_wires"),
        ({"state_low": (1.0, 0.0, 0.0)}, "state range"),
        ({"action_high": (1.0,)}, "action_low/high"),
        ({"derivatives": "sloppy"}, "derivatives"),
        # Ranges scaling divides by: a half-width that underflows, or a width beyond float64.
        ({"state_low": (0.0, 0.0), "state_high": (5e-324, 1.0)}, "too narrow or too wide"),
        ({"action_low": (-1e308,), "action_high": (1e308,)}, "too narrow or too wide"),
        # A finite width whose midpoint overflows: every state was judged invalid, silently.
        ({"state_low": (1e308, 0.0), "state_high": (1.7e308, 1.0)}, "too narrow or too wide"),
        ({"divergence_threshold": float("nan")}, "divergence_threshold"),
        ({"valid_margin": 1e300}, "valid_margin"),
        # Past int64, a server's divergence monitor failed at its first batch and stopped the
        # server (a config travels in a client's status: a fresh server adopts it).
        ({"divergence_patience": 2**64}, "divergence_patience"),
        # The thesis' network travels in one snapshot too, and its minibatch update is bounded.
        ({"n_hidden": 4096, "n_wires": 1024}, "parameters"),
        ({"update": "minibatch", "batch_size": 1 << 20, "n_wires": 1024}, "minibatch update"),
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


def test_a_spec_difference_names_what_differs():
    """The same learner with another network was refused as of "another task or ranges"."""
    cfg = small_config()
    assert small_config(n_wires=8).spec_difference(cfg) == "another network: n_wires 8, not 4"
    wider = small_config(state_high=tuple(v + 1 for v in cfg.state_high), n_hidden=7)
    both = f"another task or ranges and another network: n_hidden 7, not {cfg.n_hidden}"
    assert wider.spec_difference(cfg) == both
    deep, thesis = LearnerConfig.for_task(BoatVec, learner="deep"), LearnerConfig.for_task(BoatVec)
    assert deep.spec_difference(thesis) == "the deep learner's, not the thesis learner's"
    two = dataclasses.replace(deep, deep=dataclasses.replace(deep.deep, value_layers=2, hidden=(64,)))
    assert two.spec_difference(deep) == "another network: hidden [64], not [128, 128]; value_layers 2, not 1"
    # Ranges written as whole numbers hash to another spec, though equal: what differs is named.
    four = small_config(state_dim=4)  # (not the spec whose warning another test awaits)
    whole = LearnerConfig.from_dict({**four.to_dict(), "state_low": [-1] * 4})
    assert whole.spec_hash() != four.spec_hash() and whole.spec_difference(four) == "another task or ranges"


def test_numpy_scalars_are_held_as_pythons_and_whole_number_ranges_are_warned_of(caplog):
    """numpy's scalars made to_json fail. Ranges written as integers (-1, not -1.0) hash to another
    spec than a task's own ranges: they read as before (files written from them keep loading) and a
    warning says why a task's clients will be of another spec."""
    floats = small_config()
    numpy = small_config(state_low=tuple(np.float32(v) for v in floats.state_low), n_wires=np.int64(4))
    assert numpy.to_json() == small_config(n_wires=4).to_json()
    assert type(numpy.n_wires) is int and all(type(v) is float for v in numpy.state_low)
    d = floats.to_dict()
    whole = {**d, "state_low": [int(v) if v == int(v) else v for v in d["state_low"]]}
    assert any(isinstance(v, int) for v in whole["state_low"])
    with caplog.at_level("WARNING", logger="wfnn_common.config"):
        again = LearnerConfig.from_json(json.dumps(whole))
        LearnerConfig.from_json(json.dumps(whole))  # once per spec: a server's statuses repeat configs
    assert again.to_json() == json.dumps(whole, sort_keys=True)  # as written: its hash as before
    said = [r.getMessage() for r in caplog.records if "whole numbers" in r.getMessage()]
    assert len(said) == 1 and "state_low" in said[0] and again.spec_hash() in said[0]
    caplog.clear()
    with caplog.at_level("WARNING", logger="wfnn_common.config"):
        LearnerConfig.from_json(floats.to_json())
    assert not caplog.records


def test_for_task_takes_the_tasks_ranges():
    from sims.boat import BoatVec

    cfg = LearnerConfig.for_task(BoatVec, thinks_per_action=3)
    assert cfg.state_low == BoatVec.state_low and cfg.action_high == BoatVec.action_high
    assert cfg.thinks_per_action == 3 and cfg.gamma == 0.8


def test_a_range_written_minus_zero_keeps_its_hash_and_is_warned_of(caplog):
    """-0.0 == 0.0, but a spec's hash must never change under the data written with it (weights,
    stores, journals): like whole numbers, -0.0 hashes as written, and reading it says so."""
    plus = small_config(state_low=(0.0, -1.0, -1.0), state_high=(1.0, 0.0, 1.0))
    minus = small_config(state_low=(-0.0, -1.0, -1.0), state_high=(1.0, -0.0, 1.0))
    assert plus == minus and plus.spec_hash() != minus.spec_hash()
    with caplog.at_level("WARNING", logger="wfnn_common.config"):
        again = LearnerConfig.from_json(minus.to_json())
    assert again.spec_hash() == minus.spec_hash()
    said = [r.getMessage() for r in caplog.records if "-0.0" in r.getMessage()]
    assert len(said) == 1 and "state_low, state_high" in said[0] and minus.spec_hash() in said[0]


def test_overrides_set_only_the_fields_given_and_options_come_last():
    from wfnn_common.config import LearnerOverrides

    base = small_config()
    assert LearnerOverrides().apply(base) == base and not LearnerOverrides()
    out = LearnerOverrides(seed=3, thinks_per_action=7, bc_weight=0.5, learning_rate=0.1,
                           options='{"gamma": 0.9, "thinks_per_action": 9}').apply(base)  # fmt: skip
    assert (out.seed, out.bc_weight, out.alpha, out.gamma, out.thinks_per_action) == (3, 0.5, 0.1, 0.9, 9)
    assert out.n_hidden == base.n_hidden and out.advantage_k == base.advantage_k
    deep = LearnerOverrides(learning_rate=1e-3).apply(small_config(learner="deep"))
    assert deep.deep.lr == 1e-3 and deep.alpha == small_config(learner="deep").alpha


def test_a_learning_rate_one_learner_can_hold_is_taken_and_checked_by_the_config_it_meets():
    """A thesis alpha of 2 (allowed up to 10) is no deep Adam step (up to 1): a server that adopts
    its clients' config does not know which it will meet, so it refused such an alpha before."""
    from wfnn_common.config import ConfigError, LearnerOverrides

    overrides = LearnerOverrides(learning_rate=2.0)
    assert overrides.apply(small_config()).alpha == 2.0
    with pytest.raises(ConfigError, match=r"deep\.lr must be in \(0, 1\]") as info:
        overrides.apply(small_config(learner="deep"))
    with pytest.raises(ConfigError) as info:  # neither learner: both rules, neither probe's figures
        LearnerOverrides(learning_rate=20.0)
    assert "alpha must be in (0, 10]" in str(info.value) and "deep.lr must be in (0, 1]" in str(info.value)
    assert "config:" not in str(info.value)


def test_options_may_name_the_learner_they_are_for_but_not_another():
    """Each learner starts from its own defaults: a switch in the options kept the other's."""
    from wfnn_common.config import ConfigError, with_options

    for learner, other in (("thesis", "deep"), ("deep", "thesis")):
        base = small_config(learner=learner)
        assert with_options(base, {"learner": learner, "seed": 4}) == with_options(base, {"seed": 4})
        with pytest.raises(ConfigError, match="--learner"):
            with_options(base, {"learner": other})


@pytest.mark.parametrize(
    "kw", [{"bc_weight": 2.0}, {"learning_rate": -1.0}, {"advantage_k": 0.0}, {"options": "[1]"},
           {"options": "{not json"}, {"seed": "1"}],
)  # fmt: skip
def test_bad_overrides_are_refused_when_made(kw):
    from wfnn_common.config import LearnerOverrides

    with pytest.raises(ValueError) as info:
        LearnerOverrides(**kw)
    assert "config:" not in str(info.value)  # the check's own probe config is not the user's


def test_the_replay_size_check_counts_the_links_n_step_returns_follow():
    """A deep learner with n_step > 1 keeps one int64 link a stored experience besides its row."""
    from wfnn_common.config import MAX_REPLAY_BYTES, DeepConfig

    linked = DeepConfig(hidden=(8, 8), value_hidden=4, n_step=3)
    row = 8 * (2 * 3 + 2 + 2)  # small_config: 3 state and 2 action variables
    capacity = MAX_REPLAY_BYTES // row  # the largest a plain row allows
    small_config(learner="deep", replay_capacity=capacity)
    with pytest.raises(ConfigError, match="replay_capacity"):
        small_config(learner="deep", replay_capacity=capacity, deep=linked)
    small_config(learner="deep", replay_capacity=MAX_REPLAY_BYTES // (row + 8), deep=linked)


def test_the_bounds_leave_room_for_every_task_here():
    """The thesis' learner at its largest sizes that still fit, and narrow but real ranges, are taken."""
    small_config(n_hidden=4096, n_wires=64)  # 4096 x 3 + 128 x 4097 parameters
    small_config(update="minibatch", batch_size=4096, n_wires=64)
    small_config(state_low=(0.0, -1e-9), state_high=(1e-7, 1e-9))


HUGE = int("1" + "0" * 400)
"""An integer JSON allows and no float holds."""


@pytest.mark.parametrize(
    "patch",
    [
        {"gamma": HUGE},
        {"state_low": [HUGE] * 3},
        {"learner": "deep", "deep": {"lr": HUGE}},
        {"exploration": {"kind": "gaussian", "sigma": HUGE}},
        {
            "symmetries": [
                {
                    "name": "m",
                    "state_index": [0, 1, 2],
                    "state_sign": [1, 1, 1],
                    "action_index": [float("inf"), 1],
                    "action_sign": [1, 1],
                }
            ]
        },
    ],
)
def test_numbers_beyond_any_float_are_a_config_error_not_an_overflow(patch):
    """They escaped as OverflowError: a traceback for a client's status, exit 1 naming no field."""
    with pytest.raises(ConfigError):
        LearnerConfig.from_dict({**small_config().to_dict(), **patch})


def test_a_null_exploration_and_a_symmetry_field_no_symmetry_has_are_refused():
    """A null exploration gave the thesis' default (uniform), the deep learner's too; a symmetry's
    misspelt field was dropped without a word."""
    deep = small_config(learner="deep").to_dict()
    with pytest.raises(ConfigError, match="exploration must be an object"):
        LearnerConfig.from_dict({**deep, "exploration": None})
    with pytest.raises(ConfigError, match="exploration must be an object"):
        with_options(small_config(learner="deep"), {"exploration": None})
    mirror = {"name": "m", "state_index": [0, 1, 2], "state_sign": [1, 1, 1], "action_index": [0, 1],
              "action_sign": [1, 1]}  # fmt: skip
    assert LearnerConfig.from_dict({**deep, "symmetries": [mirror]}).symmetries[0].name == "m"
    with pytest.raises(ConfigError, match=r"unknown fields \['statesign'\]"):
        LearnerConfig.from_dict({**deep, "symmetries": [{**mirror, "statesign": [1, 1, 1]}]})


def test_options_the_learner_never_reads_are_refused():
    """`alpha` (the thesis' step) was taken for a deep learner and recorded, which learned with its
    own `deep.lr`; `deep` options for the thesis learner were dropped from what it saved."""
    deep, thesis = small_config(learner="deep"), small_config()
    for options in ({"alpha": 0.001}, {"n_hidden": 500, "gamma": 0.9}, {"update": "minibatch"}):
        with pytest.raises(ConfigError, match=r"are not the deep learner's \(its own: deep.lr"):
            with_options(deep, options)
    with pytest.raises(ConfigError, match=r"are not the thesis learner's \(choose it with --learner"):
        with_options(thesis, {"deep": {"lr": 0.5}})
    assert with_options(deep, {"deep": {"lr": 1e-3}, "gamma": 0.9}).deep.lr == 1e-3
    assert with_options(thesis, {"alpha": 0.1}).alpha == 0.1


def test_a_config_a_status_cannot_carry_is_refused():
    """680 symmetries made a config whose JSON no protocol string holds: a server adopted and
    saved it, and every status it sent after, restarts included, was refused by every client."""
    import json

    from wfnn_common.config import MAX_CONFIG_JSON, MAX_SYMMETRIES
    from wfnn_common.symmetry import Symmetry

    def mirror(k: int, s: int) -> Symmetry:
        return Symmetry(name=f"m{k}", state_index=tuple(range(s)), state_sign=(1.0,) * s, action_index=(0,),
                        action_sign=(-1.0,))  # fmt: skip

    base = LearnerConfig(state_low=(-1.0,), state_high=(1.0,), action_low=(-1.0,), action_high=(1.0,))
    assert (
        len(
            dataclasses.replace(
                base, symmetries=tuple(mirror(k, 1) for k in range(MAX_SYMMETRIES))
            ).symmetries
        )
        == 16
    )
    with pytest.raises(ConfigError, match="at most 16 symmetries"):
        dataclasses.replace(base, symmetries=tuple(mirror(k, 1) for k in range(MAX_SYMMETRIES + 1)))
    hostile = json.loads(base.to_json())
    hostile["symmetries"] = [dataclasses.asdict(mirror(k, 1)) for k in range(680)]
    with pytest.raises(ConfigError, match="symmetries"):
        LearnerConfig.from_json(json.dumps(hostile, separators=(",", ":")))
    wide = dataclasses.replace(base, state_low=(-1.0 / 3,) * 1024, state_high=(2.0 / 3,) * 1024)
    with pytest.raises(ConfigError, match="characters, more than the 65,536 a status carries"):
        dataclasses.replace(wide, symmetries=tuple(mirror(k, 1024) for k in range(4)))
    assert len(wide.to_json()) <= MAX_CONFIG_JSON
