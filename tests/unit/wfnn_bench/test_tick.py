"""The robot benchmarks time a control tick with the kind of learner that learned."""

import numpy as np
import pytest

from sims.hydra.task import HydraVec
from wfnn_bench.common import tick_learner
from wfnn_bench.hydra import tick_cost
from wfnn_common.deep import DeepWFNN
from wfnn_common.learner import WFNN


def test_a_deep_tick_acts_with_the_network_not_a_warm_up_draw():
    task = HydraVec(1)
    assert isinstance(tick_learner(task, "thesis"), WFNN)
    deep = tick_learner(task, "deep")
    assert isinstance(deep, DeepWFNN)
    x = task.reset(np.random.default_rng(0))[0]
    # Warm-up actions are uniform draws over the range (spread 0.29 of it); the network's
    # explored actions lie close about its best wire.
    span = np.asarray(task.action_high) - np.asarray(task.action_low)
    greedy = deep.act(x, explore=False).action
    explored = np.array([deep.act(x).action for _ in range(200)])
    assert (explored.std(axis=0) < 0.15 * span).all()
    assert (np.abs(np.median(explored, axis=0) - greedy) < 0.05 * span).all()
    task.close()


@pytest.mark.parametrize("kind", ["thesis", "deep"])
def test_hydra_tick_cost_runs_with_either_learner(kind):
    tick = tick_cost(20, 0, learner_kind=kind)
    assert 0 < tick["tick_ms_p50"] <= tick["tick_ms_p99"]
