"""Every benchmark refuses, when it is configured, a seed whose derived seeds its learners would refuse."""

import pytest

from wfnn_bench import boat, cartpole, faults, hydra, nomad, passive, relearn, safety, speed, transport
from wfnn_bench.common import BENCH_MAX_SEED
from wfnn_common.config import MAX_SEED

CONFIGS = [
    boat.BoatBenchConfig, cartpole.CartPoleBenchConfig, faults.FaultsBenchConfig, hydra.HydraBenchConfig,
    nomad.NomadBenchConfig, passive.PassiveBenchConfig, relearn.RelearnBenchConfig,
    safety.SafetyBenchConfig, speed.SpeedBenchConfig, transport.TransportBenchConfig,
]  # fmt: skip


@pytest.mark.parametrize("make", CONFIGS, ids=lambda c: c.__name__)
def test_a_benchmark_refuses_a_seed_out_of_its_range_when_configured(make):
    assert make(seed=BENCH_MAX_SEED).seed == BENCH_MAX_SEED
    for seed in (-1, BENCH_MAX_SEED + 1, 10**16):
        with pytest.raises(ValueError, match=rf"seed must be in \[0, {BENCH_MAX_SEED}\]"):
            make(seed=seed)


def test_the_largest_seed_s_derived_learner_seeds_are_valid():
    """The boat benchmark was refused mid-run, after its progress began, for seeds above 4.6e15:
    its controllers' seed is seed x 1,000 + 2, beyond MAX_SEED, and its message gave a range the
    given seed lay in."""
    bench = boat.BoatBenchConfig(seed=BENCH_MAX_SEED)
    assert boat.learner_config(bench, 1.0, bench.seed * 1000 + 2).seed <= MAX_SEED
