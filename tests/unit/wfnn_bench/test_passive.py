"""The passive benchmark's learner configs: what the options reach and what stays the reference."""

import pytest

from sims.boat import BoatVec
from wfnn_bench.passive import PassiveBenchConfig, _config, pulled
from wfnn_common.config import ConfigError, LearnerConfig


def test_options_and_thinks_reach_the_chosen_learner_but_not_the_thesis_reference():
    cfg = PassiveBenchConfig(learner="thesis", learner_options='{"alpha": 0.1, "gamma": 0.5}', thinks=3)
    own = _config(cfg, 10, "thesis")
    assert (own.alpha, own.gamma, own.thinks_per_action) == (0.1, 0.5, 3)
    reference = _config(cfg, 10, "thesis", reference=True)
    default = LearnerConfig.for_task(BoatVec)
    assert (reference.alpha, reference.gamma, reference.thinks_per_action) == (
        default.alpha, default.gamma, default.thinks_per_action,
    )  # fmt: skip
    deep = PassiveBenchConfig(learner="deep", learner_options='{"batch_size": 64}', thinks=3)
    assert _config(deep, 10, "deep").batch_size == 64 and _config(deep, 10, "deep").thinks_per_action == 3
    assert _config(deep, 10, "thesis", reference=True).thinks_per_action == default.thinks_per_action


def test_the_pull_and_k_of_the_passive_learners_override_the_options():
    cfg = PassiveBenchConfig(learner="deep", learner_options='{"bc_weight": 0.3}', bc_weight=0.7,
                             passive_advantage_k=0.9)  # fmt: skip
    config = _config(cfg, 10, "deep", **pulled(cfg))
    assert (config.bc_weight, config.advantage_k) == (0.7, 0.9)
    assert "alpha" not in pulled(cfg) and pulled(PassiveBenchConfig())["alpha"] == 0.05


@pytest.mark.parametrize(
    "fields", [{"bc_weight": 1.5}, {"passive_advantage_k": 0.0}, {"learner_options": "[1]"}]
)
def test_a_bad_setting_is_refused_before_any_log_is_made(fields):
    with pytest.raises((ConfigError, ValueError)):
        PassiveBenchConfig(learner="deep", **fields)


def test_references_meet_the_learners_targets_and_last_10_is_the_boat_benchmarks_figure():
    """The references were evaluated on one boat (targets no learner met), and "last-10" pooled
    every controller's targets into one median where `wfnn-bench boat` takes the median over
    controllers of each one's median."""
    import numpy as np

    from sims.boat import handcoded_boat
    from wfnn_bench.passive import evaluate, run

    cfg = PassiveBenchConfig(controllers=3, noise=(0.0,), log_boats=1, log_targets=1, passive_thinks=40,
                             passive_checks=1, online_targets=12, thinks=1, eval_targets=1)  # fmt: skip
    result = run(cfg)
    per_boat = result["references"]["handcoded"]["scores"]
    assert len(per_boat) == cfg.controllers
    np.testing.assert_allclose(per_boat, evaluate(handcoded_boat, cfg.controllers, cfg).scores)
    assert result["handcoded_score"] == float(np.median(per_boat))
    scores = np.asarray(result["online"]["scores"])
    assert result["online"]["score_last10"] == float(np.median(np.median(scores[:, -10:], axis=1)))
