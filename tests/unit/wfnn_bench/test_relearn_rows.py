"""`wfnn-bench relearn`'s table (`wfnn_bench.relearn.rows`)."""

import numpy as np


def test_a_goal_never_reached_reads_as_a_dash_not_none():
    """The table printed "None" where the other benchmarks' tables print "-"."""
    from wfnn_bench.relearn import RelearnBenchConfig, rows

    controller = {
        "pre_divergence_error_px": 4.0, "untrained_error_px": 130.0, "online_robot_s_to_reach": 12.5,
        "with_store_robot_s_to_reach": None, "store_only_thinks_to_reach": None,
        "store_only_best_error_px": 80.0,
        "store_only_passive_thinks_to_reach": 450000, "store_only_passive_wall_s_to_reach": None,
        "store_only_passive_best_error_px": 6.3,
    }  # fmt: skip
    result = {"relearn_fraction": None, "controllers": [controller], "competent_controllers": 1,
              "relearned_with_store": 0, "relearned_store_only": 0, "relearned_store_only_passive": 1,
              "online_divergence_resets": np.array([0]), "stored_experiences": np.array([900]),
              "online_wall_s": 3.0}  # fmt: skip
    table = dict(rows(result, RelearnBenchConfig()))
    assert table["controller 0: robot s to reach: from scratch / store kept"] == "12.5 / -"
    assert table["controller 0: store alone: thinks to reach / best error px"] == "- / 80.0"
    assert not any(isinstance(v, str) and "None" in v for v in table.values())  # None alone: the table's "-"
