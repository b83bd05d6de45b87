"""End-to-end runs of the command-line tools with tiny budgets (real processes)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytestmark = [pytest.mark.slow, pytest.mark.multiprocess]

BIN = Path(sys.executable).parent


def run(args, timeout=300):
    env = {**os.environ, "COLUMNS": "120"}
    proc = subprocess.run(args, capture_output=True, text=True, timeout=timeout, env=env)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc


def test_bench_boat_writes_json_fields_and_plot(tmp_path):
    j, p = tmp_path / "boat.json", tmp_path / "boat.png"
    out = run(
        [
            BIN / "wfnn-bench",
            "boat",
            "--controllers",
            "3",
            "--targets",
            "2",
            "--thinks",
            "5",
            "--json",
            j,
            "--plot",
            p,
        ]
    )
    assert "median_last10" in out.stdout
    data = json.loads(j.read_text())
    assert p.stat().st_size > 10_000
    for key in ("random_ref", "handcoded_ref", "wall_s", "thinks_per_s", "tests", "step1_random_ref"):
        assert key in data
    assert [r["condition"] for r in data["results"]] == ["advantage", "q"]
    for r in data["results"]:
        assert r["controllers"] == 3
        assert len(r["scores"]) == 3 and len(r["scores"][0]) == 2
        assert all(0 < s < 10 for row in r["scores"] for s in row)
        assert 0 <= r["frac_acceptable"] <= 1
        assert r["median_last10"] > 0 and r["thinks_per_s"] > 0
        assert np.shape(r["returns"]) == (3, 2) and np.shape(r["greedy_returns"]) == (3, 10)
        assert r["median_return_last10"] < 0 and r["greedy_median_return"] < 0
        for terms in (r["return_terms_last10"], r["greedy_return_terms"]):
            assert set(terms) == {"distance", "energy", "coarseness"} and max(terms.values()) <= 0
            assert terms["distance"] < 0
    assert [h["gain_scale"] for h in data["handcoded_gains"]] == [1.0, 0.5, 0.3, 0.2, 0.1, 0.05]
    assert "hand-coded x0.1: score / return" in out.stdout
    assert "q: greedy return terms: distance / energy / coarseness" in out.stdout


def test_bench_boat_runs_deep_controllers(tmp_path):
    j = tmp_path / "boat.json"
    run([BIN / "wfnn-bench", "boat", "--learner", "deep", "--mode", "q", "--controllers", "2",
         "--targets", "2", "--learner-options", '{"deep": {"hidden": [32, 32]}, "batch_size": 64}',
         "--json", j])  # fmt: skip
    (r,) = json.loads(j.read_text())["results"]
    assert r["condition"] == "q" and r["controllers"] == 2 and len(r["scores"][0]) == 2
    # One update per action by default: two targets of 200 actions for each controller.
    assert r["thinks"] == 2 * 2 * 200 and all(0 < s < 10 for row in r["scores"] for s in row)
    assert r["learner_config"]["deep"]["hidden"] == [32, 32] and r["learner_config"]["batch_size"] == 64
    zero_width = '{"deep": {"hidden": [0]}}'
    refused = [BIN / "wfnn-bench", "boat", "--learner", "deep", "--learner-options", zero_width]
    bad = subprocess.run(refused, capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "deep.hidden" in bad.stderr and "Traceback" not in bad.stderr


def test_bench_boat_refuses_a_bad_mode():
    proc = subprocess.run(
        [BIN / "wfnn-bench", "boat", "--mode", "sideways"], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode != 0 and "mode" in (proc.stdout + proc.stderr)


def test_bench_cartpole_and_speed(tmp_path):
    j, p = tmp_path / "cp.json", tmp_path / "cp.png"
    run(
        [
            BIN / "wfnn-bench",
            "cartpole",
            "--runs",
            "2",
            "--steps",
            "600",
            "--thinks",
            "5",
            "--json",
            j,
            "--plot",
            p,
        ]
    )
    data = json.loads(j.read_text())
    assert len(data["attempt_steps"]) == 2 and all(len(a) >= 1 for a in data["attempt_steps"])
    assert p.exists()
    j2 = tmp_path / "speed.json"
    run(
        [
            BIN / "wfnn-bench",
            "speed",
            "--act-calls",
            "500",
            "--thinks",
            "5000",
            "--population",
            "4",
            "--json",
            j2,
            "--plot",
            tmp_path / "speed.png",
        ]
    )
    assert (tmp_path / "speed.png").stat().st_size > 0
    speed = json.loads(j2.read_text())
    for key in (
        "act_p50_us",
        "act_p99_us",
        "act_p50_us_deep",
        "act_p99_us_deep",
        "incremental_thinks_per_s",
        "minibatch_updates_per_s",
        "population_thinks_per_s",
    ):
        assert speed[key] > 0
    assert speed["deep_network"]["hidden"] == [128, 128]


def test_client_runs_learns_and_saves(tmp_path):
    out = tmp_path / "run"
    run([BIN / "wfnn-client", "--sim", "positioning", "--episodes", "3", "--rate-hz", "0", "--out", out])
    metrics = json.loads((out / "metrics.json").read_text())
    assert len(metrics["scores"]) == 3 and metrics["think/thinks"] > 0 and metrics["weights/version"] >= 1
    assert metrics["following"] == "local" and metrics["experiences_learned"] > 0
    for name in ("weights.npz", "experiences.npz", "learning_curve.png"):
        assert (out / name).exists()
    from wfnn_io.persist import load_experiences, load_weights

    cfg, params, meta = load_weights(out / "weights.npz")
    assert meta["sim"] == "positioning" and params.population == 1
    assert load_experiences(out / "experiences.npz", cfg).reward.shape[0] == metrics["learn/experiences"]


def test_a_client_no_server_answered_says_so_and_claims_no_weights(tmp_path):
    """It printed "N experiences" and "saved weights" where no server took any and none came."""
    from wfnn_server.spawn import endpoint, free_port

    out = tmp_path / "run"
    proc = run([BIN / "wfnn-client", "--sim", "positioning", "--episodes", "100", "--rate-hz", "30",
                "--duration", "2", "--server", endpoint(free_port()), "--out", out])  # fmt: skip
    assert "(none acknowledged by a server)" in proc.stdout and "saved metrics.json" in proc.stdout
    assert json.loads((out / "metrics.json").read_text())["weights_saved"] == []
    assert not (out / "weights.npz").exists()


def test_client_hydra_with_rendered_vision_saves_camera_frames(tmp_path):
    from tests.fakes import render_problem

    if (problem := render_problem()) is not None:
        pytest.skip(f"no off-screen rendering here: {problem}")
    out = tmp_path / "run"
    proc = run([BIN / "wfnn-client", "--sim", "hydra", "--episodes", "1", "--rate-hz", "0", "--thinks", "5",
                "--vision", "render", "--camera-every", "100", "--out", out])  # fmt: skip
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["config"]["client"]["hydra"]["vision"]["source"] == "render"
    assert metrics["ticks"] == 450 and metrics["experiences_learned"] > 0
    frames = sorted(p.name for p in (out / "cameras").glob("*.png"))
    assert frames == [f"{t:07d}.png" for t in range(0, 450, 100)]
    assert metrics["camera_frames"] == {"written": 5, "dropped": 0, "failed": 0}
    assert "5 camera frames" in proc.stdout


def test_client_nomad_forages_on_rendered_vision_and_saves_camera_frames(tmp_path):
    from tests.fakes import render_problem

    if (problem := render_problem()) is not None:
        pytest.skip(f"no off-screen rendering here: {problem}")
    out = tmp_path / "run"
    run([BIN / "wfnn-client", "--sim", "nomad", "--behaviour", "forage", "--vision", "render",
         "--episodes", "1", "--rate-hz", "0", "--lockstep", "--thinks", "5", "--balls", "24",
         "--camera-every", "200", "--out", out])  # fmt: skip
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["config"]["client"]["nomad"]["vision"]["source"] == "render"
    assert metrics["ticks"] == 600 and metrics["wander/learn/experiences"] >= 590
    # Lock-step runs are reproducible: this one's untrained wanderer meets a target (a threaded
    # run's think timing changes the path from run to run, and with it whether it does).
    assert metrics["targets_found"] >= 1 and metrics["servo/learn/experiences"] > 0
    assert metrics["camera_frames"]["written"] == 3


@pytest.mark.parametrize("behaviour", ["servo", "wander", "forage"])
def test_client_nomad_behaviours_run_and_save(tmp_path, behaviour):
    out = tmp_path / "run"
    # Lock-step: reproducible, so whether the untrained wanderer meets a target is not luck.
    run([BIN / "wfnn-client", "--sim", "nomad", "--behaviour", behaviour, "--episodes", "1", "--rate-hz", "0",
         "--lockstep", "--thinks", "5", "--balls", "24", "--out", out])  # fmt: skip
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["ticks"] == (150 if behaviour == "servo" else 600)
    assert metrics["experiences_learned"] > 0
    assert metrics["metric"].startswith("mean |pixel" if behaviour == "servo" else "metres")
    if behaviour != "forage":
        assert (out / "weights.npz").exists() and metrics["config"]["client"]["nomad"][
            "behaviour"
        ] == behaviour
        return
    # Foraging: a learner per behaviour, pursuit of every target found.
    assert metrics["following"] == "servo:local wander:local"
    driving = {name: b["ticks_driving"] for name, b in metrics["behaviours"].items()}
    assert driving["servo"] > 0 and driving["servo"] + driving["wander"] == 600
    assert metrics["targets_found"] >= 1 and metrics["config"]["client"]["forage"]["pursue"] == "every"
    for name in ("servo", "wander"):
        assert (out / f"weights_{name}.npz").exists() and metrics[f"{name}/learn/experiences"] > 0
    # Every action reaches the wanderer (experiences in its replay memory, less encoder glitches).
    assert metrics["wander/learn/experiences"] >= 590
    again = tmp_path / "again"  # start both learners from the saved weights
    run([BIN / "wfnn-client", "--sim", "nomad", "--behaviour", "forage", "--episodes", "1", "--rate-hz", "0",
         "--thinks", "5", "--weights", out, "--out", again])  # fmt: skip
    assert (again / "weights_servo.npz").exists()


def test_bench_nomad_writes_servo_figures_and_tick_cost(tmp_path):
    j, p = tmp_path / "nomad.json", tmp_path / "nomad.png"
    out = run([BIN / "wfnn-bench", "nomad", "--controllers", "2", "--episodes", "2", "--eval-every", "1",
               "--wander-episodes", "3", "--forage-minutes", "1", "--thinks", "5", "--render-ticks", "20",
               "--json", j, "--plot", p])  # fmt: skip
    assert "servo_final_error_px" in out.stdout
    data = json.loads(j.read_text())
    assert [e["episode"] for e in data["servo"]["evaluations"]] == [1, 2]
    assert 0 <= data["servo_final_error_px"] <= 200
    assert data["proportional"]["final_error_px"][0] < 15  # the task is doable
    assert 0 < data["tick_ms_p50"] < 50
    assert p.stat().st_size > 10_000
    assert len(data["wander"]["distance_m"]) == 2 and len(data["wander"]["distance_m"][0]) == 3
    assert len(data["wander"]["path"]) == 3 * 600
    assert "early" in data["wander_m_per_collision"] and data["servo_from_wander_score"] >= 0
    bare = data["wander_no_veto"]  # without the veto every minute is counted, vetoes are none
    assert sum(map(sum, bare["vetoes"])) == 0 and len(bare["collisions"][0]) == 3
    assert [e["minutes"] for e in data["servo_every_second_target"]["evaluations"]] == [1]
    watched, passive = data["servo_from_wander"], data["servo_from_wander_passive"]
    assert passive["learner"]["bc_weight"] == 0.2 and passive["learner"]["symmetries"][0]["name"] == "mirror"
    # Each watched experience is also learned mirrored, and both as 4 phantom-goal copies (less
    # copies outside the declared state ranges, and wild encoder readings).
    for seen, stored in zip(passive["experiences_watched"], passive["experiences_stored"], strict=True):
        assert 0 < 2 * seen < stored <= 10 * seen
    for seen, stored in zip(watched["experiences_watched"], watched["experiences_stored"], strict=True):
        assert 0 < stored <= seen
    assert data["servo_from_wander_passive_score"] >= 0
    rendering = data["render"]
    if rendering["available"]:  # the proportional servo works on rendered images too
        assert rendering["servo_final_error_px"] < 15 and 0.5 < rendering["carpet_agreement"] <= 1
    else:
        assert "render" in rendering["reason"] or "GL" in rendering["reason"]
    assert 0 <= data["servo_untrained_px"] <= 200


def test_bench_nomad_servo_only_with_the_deep_learner(tmp_path):
    j, p = tmp_path / "nomad.json", tmp_path / "nomad.png"
    out = run([BIN / "wfnn-bench", "nomad", "--controllers", "2", "--episodes", "2", "--eval-every", "1",
               "--learner", "deep", "--servo-only", "--json", j, "--plot", p])  # fmt: skip
    assert "servo_final_error_px" in out.stdout and "wander" not in out.stdout
    data = json.loads(j.read_text())
    assert data["servo"]["learner_config"]["learner"] == "deep" and "wander" not in data
    assert [e["episode"] for e in data["servo"]["evaluations"]] == [1, 2]
    # Two episodes of 150 actions per controller, most of them learned from.
    assert all(150 < e <= 300 for e in data["servo"]["evaluations"][-1]["experiences"])
    assert 0 <= data["servo_final_error_px"] <= 200 and p.stat().st_size > 10_000


def test_client_refuses_an_unknown_vision_source(tmp_path):
    proc = subprocess.run(
        [BIN / "wfnn-client", "--sim", "hydra", "--vision", "sonar", "--out", tmp_path],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode != 0 and "vision source" in proc.stdout + proc.stderr
    assert not (tmp_path / "metrics.json").exists()


CLIENT_WITHOUT_TORCH = """
import sys
sys.modules["torch"] = None  # any import of torch now fails
import numpy as np
from sims.boat import BoatVec
from wfnn_client.config import ClientConfig
from wfnn_client.run import learner_config
from wfnn_client.think_thread import ActLearnThinkMT
from wfnn_common.learner import WFNN
task = BoatVec(1)
learner = WFNN(learner_config(task, ClientConfig()))
x = task.reset(np.random.default_rng(0))[0]
with ActLearnThinkMT(learner) as mt:
    for _ in range(50):
        u = mt.act(x).action
        tr = task.step(u[None])
        mt.learn(x, u, tr.state[0], tr.reward[0])
        x = tr.state[0]
    import time
    deadline = time.monotonic() + 120  # the first think compiles the kernel on a fresh machine
    while learner.thinks[0] == 0 and mt.error is None and time.monotonic() < deadline:
        time.sleep(0.01)
assert mt.error is None and learner.thinks[0] > 0, (mt.error, learner.thinks)
import wfnn_client.remote, wfnn_client.run, wfnn_io.bus, wfnn_io.protocol  # the C/S client too
from wfnn_common.learners import make_learner, weights_from_flat
deep = make_learner(learner_config(task, ClientConfig(learner="deep")))  # acting on a server's snapshots
for _ in range(5):
    u = deep.act(x).action
    deep.learn(x, u, x, -1.0)
assert deep.act(x, explore=False, params=weights_from_flat(deep.config, deep.params.flat.copy())).valid
assert "torch" not in [m for m in sys.modules if sys.modules[m] is not None]
print("ok")
"""


def test_client_acts_and_thinks_without_torch():
    proc = subprocess.run(
        [sys.executable, "-c", CLIENT_WITHOUT_TORCH], capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0 and "ok" in proc.stdout, proc.stderr


def test_bench_transport_writes_the_figures(tmp_path):
    j, p = tmp_path / "transport.json", tmp_path / "transport.png"
    out = run(
        [
            BIN / "wfnn-bench",
            "transport",
            "--experiences",
            "3000",
            "--seconds",
            "3",
            "--outage-seconds",
            "0",
            "--json",
            j,
            "--plot",
            p,
        ]
    )
    assert "experiences_per_s" in out.stdout
    data = json.loads(j.read_text())
    for key in ("experiences_per_s", "snapshot_p50_ms", "snapshot_p99_ms", "tick_jitter_p99_ms"):
        assert data[key] > 0, key
    assert data["experiences_lost"] == 0 and data["throughput"]["experiences"] == 3000
    assert data["realtime"]["ticks"] >= 40 and data["realtime"]["snapshots_applied"] >= 1
    assert set(data["goals"]) == {
        "experiences_per_s",
        "experiences_lost",
        "snapshot_p99_ms",
        "tick_jitter_p99_ms",
    }
    assert p.stat().st_size > 10_000


@pytest.mark.parametrize(
    "args, message",
    [
        (["--fsync", "sometimes"], "fsync"),
        (["--id", "a/b"], "server id"),
        (["--mode", "star"], "mode"),
    ],
)
def test_server_refuses_bad_options(tmp_path, args, message):
    proc = subprocess.run(
        [BIN / "wfnn-server", "--data-dir", tmp_path, "--quiet", *args],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode != 0 and message in proc.stdout + proc.stderr


def test_client_refuses_bad_options(tmp_path):
    proc = subprocess.run(
        [BIN / "wfnn-client", "--sim", "boat", "--rate-hz", "10", "--lockstep", "--out", tmp_path],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode != 0 and "lock-step" in proc.stdout + proc.stderr
    assert not (tmp_path / "metrics.json").exists()
    proc = subprocess.run(
        [BIN / "wfnn-client", "--sim", "cartpole", "--symmetries", "--rate-hz", "0", "--out", tmp_path],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == 2 and "declares no symmetries" in proc.stdout + proc.stderr
    proc = subprocess.run(
        [BIN / "wfnn-client", "--sim", "boat", "--behaviour-policy", "wfnn=1,pid=1", "--out", tmp_path],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == 2 and "unknown behaviour policy 'pid'" in proc.stdout + proc.stderr
    assert "Traceback" not in proc.stdout + proc.stderr and not (tmp_path / "metrics.json").exists()


def test_client_learns_the_boats_mirror_images_when_asked(tmp_path):
    out = tmp_path / "run"
    run([BIN / "wfnn-client", "--sim", "boat", "--symmetries", "--episodes", "2", "--rate-hz", "0",
         "--lockstep", "--thinks", "5", "--out", out])  # fmt: skip
    metrics = json.loads((out / "metrics.json").read_text())
    assert [s["name"] for s in metrics["config"]["learner"]["symmetries"]] == ["mirror"]
    from wfnn_io.persist import load_experiences, load_weights

    cfg, _, _ = load_weights(out / "weights.npz")
    stored = load_experiences(out / "experiences.npz", cfg)
    n = metrics["experiences_learned"]
    # Lock-step: every experience is learned before the next action, so the replay holds them all.
    assert n > 0 and stored.reward.shape[0] == 2 * n  # each real experience and its mirror image


def test_bench_hydra_writes_table71_and_tick_cost(tmp_path):
    j, p = tmp_path / "hydra.json", tmp_path / "hydra.png"
    out = run(
        [BIN / "wfnn-bench", "hydra", "--controllers", "2", "--episodes", "2", "--eval-episodes", "1",
         "--four-dof-controllers", "1", "--four-dof-episodes", "1", "--thinks", "5", "--render-ticks", "30",
         "--json", j, "--plot", p]
    )  # fmt: skip
    assert "rms_error_px" in out.stdout
    data = json.loads(j.read_text())
    for trained in ("static", "swing"):
        for evaluated in ("static", "swing"):
            cell = data["table71"][trained][evaluated]
            assert 0 <= cell["rms_error_px"] < 400 and cell["action_roughness"] >= 0
            assert cell["lag_s"] is None or 0 <= cell["lag_s"] <= 1.0
    assert 0 < data["tick_ms_p50"] < 50
    assert len(data["analysis"]["swing"]["accel_by_position"]) == 2
    assert p.stat().st_size > 10_000
    rendering = data["render"]
    if rendering["available"]:
        assert set(rendering["regimes"]) == {"static", "swing", "mixed", "elastic"}
        assert 0 < rendering["regimes"]["swing"]["tracked_fraction"] <= 1
        assert rendering["regimes"]["swing"]["error_px_p50"] < 2.0
        assert 0 < rendering["tick_ms_p50_render"] < 200
        assert (tmp_path / "hydra_cameras.png").stat().st_size > 10_000
    else:
        assert "render" in rendering["reason"] or "GL" in rendering["reason"]


def test_bench_passive_writes_its_figures(tmp_path):
    j, p = tmp_path / "passive.json", tmp_path / "passive.png"
    out = run([BIN / "wfnn-bench", "passive", "--controllers", "2", "--log-targets", "2", "--passive-thinks",
               "4000", "--online-targets", "10", "--thinks", "5", "--eval-targets", "2", "--json", j,
               "--plot", p])  # fmt: skip
    assert "passive_score" in out.stdout
    data = json.loads(j.read_text())
    for key in ("handcoded_score", "passive_score", "phantom_only_score", "passive_phantom_only_score",
                "passive_no_bc_score", "passive_thesis_score"):  # fmt: skip
        assert data[key] > 0
    assert 0.1 < data["handcoded_score"] < 0.5  # the hand-coded controller's Section 4.2 figure
    assert data["zero_thrust_score"] == 1.0  # a boat that never moves stays one unit from each target
    # Rewards are squashed (Eq 3.6, gamma 0.8) and never positive.
    assert -0.2 <= data["handcoded_reward"] < 0 and -0.2 <= data["passive_reward"] < 0
    assert [data["passive"][k] for k in ("bc_weight", "advantage_k", "alpha")] == [0.5, 1.0, 0.05]
    assert [data["passive_no_bc"][k] for k in ("bc_weight", "advantage_k", "alpha")] == [0.0, 1.0, 0.05]
    assert [data["passive_thesis"][k] for k in ("bc_weight", "advantage_k", "alpha")] == [0.0, 0.2, 0.25]
    criteria = {"passive_score_within_20pct_of_handcoded", "passive_reward_above_handcoded"}
    assert criteria <= set(data["criteria"])
    # Three behaviour policies, four logged boats each, two targets of 200 actions: all read back
    # and all learned (each policy's boats are distinct clients of the merged logs).
    assert sum(data["logs"]["experiences"].values()) == 3 * 4 * 2 * 200 == data["logs"]["learned"]
    assert [c["thinks"] for c in data["passive"]["curve"]] == [1000, 2000, 3000, 4000]
    assert "mirror_experience_ratio" in data and p.stat().st_size > 10_000


def test_bench_passive_runs_the_deep_learner_beside_the_thesis_reference(tmp_path):
    j = tmp_path / "passive_deep.json"
    options = '{"deep": {"hidden": [32, 32], "value_hidden": 16}, "batch_size": 64}'
    out = run([BIN / "wfnn-bench", "passive", "--learner", "deep", "--learner-options", options,
               "--controllers", "1", "--log-targets", "1", "--passive-thinks", "1000",
               "--online-targets", "10", "--thinks", "0", "--eval-targets", "1", "--bc-weight", "1.0",
               "--passive-advantage-k", "0.9", "--json", j])  # fmt: skip
    assert "online (deep)" in out.stdout
    # Not a terminal: progress comes as plain lines, the last at the end of the work.
    assert "passive: 0/" in out.stdout and "(100%)" in out.stdout
    data = json.loads(j.read_text())
    assert data["config"]["learner"] == "deep" and data["logs"]["learned"] == 3 * 4 * 200
    for key in ("passive", "passive_no_bc", "passive_phantom_only"):
        c = data[key]
        # k from --passive-advantage-k; Adam's step the deep learner's default
        assert (c["learner"], c["advantage_k"], c["alpha"]) == ("deep", 0.9, 3e-4)
        assert [e["thinks"] for e in c["curve"]] == [250, 500, 750, 1000]
        assert c["return"] < 0 and c["score"] > 0
    assert (data["passive"]["bc_weight"], data["passive_no_bc"]["bc_weight"]) == (1.0, 0.0)
    # The reference stays the thesis' learner with its own k and rate (its options untouched).
    thesis = data["passive_thesis"]
    settings = (thesis["learner"], thesis["advantage_k"], thesis["alpha"], thesis["bc_weight"])
    assert settings == ("thesis", 0.2, 0.25, 0.0)
    assert data["online"]["learner"] == "deep" and len(data["online"]["median_per_target"]) == 10
    # Zero thrust: one unit from every target for all 200 actions; bang-bang thrust costs reward.
    assert data["zero_thrust_score"] == 1.0
    assert data["zero_thrust_return"] < 0 and data["handcoded_return"] < 0
    bad = subprocess.run([BIN / "wfnn-bench", "passive", "--learner", "deep", "--learner-options",
                          '{"n_wires": 0}'], capture_output=True, text=True, timeout=60)  # fmt: skip
    assert bad.returncode != 0 and "n_wires" in bad.stdout + bad.stderr


def test_client_drives_a_gymnasium_task(tmp_path):
    out = tmp_path / "run"
    run([BIN / "wfnn-client", "--env", "Pendulum-v1", "--episodes", "2", "--rate-hz", "0", "--lockstep",
         "--thinks", "5", "--out", out])  # fmt: skip
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["config"]["client"]["env"] == "Pendulum-v1" and metrics["ticks"] == 400
    assert metrics["experiences_learned"] == 400 and -16.3 <= min(metrics["scores"]) <= 0
    proc = subprocess.run([BIN / "wfnn-client", "--env", "CartPole-v1", "--out", tmp_path / "x"],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert proc.returncode != 0 and "Box" in proc.stdout + proc.stderr


def test_client_drives_a_gymnasium_mujoco_task(tmp_path):
    out = tmp_path / "run"
    run([BIN / "wfnn-client", "--env", "InvertedPendulum-v5", "--episodes", "1", "--rate-hz", "0",
         "--lockstep", "--thinks", "2", "--out", out])  # fmt: skip
    metrics = json.loads((out / "metrics.json").read_text())
    # 1,000 steps of the time limit; the pole falls and its episodes restart inside the client's.
    assert metrics["ticks"] == 1000 and metrics["experiences_learned"] == 1000
    assert len(metrics["config"]["learner"]["state_low"]) == 4 and 0 < metrics["scores"][0] <= 1.0
    # In real time, at the task's own rate (its time step is 0.04 s), not a default one.
    run([BIN / "wfnn-client", "--env", "InvertedPendulum-v5", "--episodes", "1", "--duration", "0.3",
         "--thinks", "1", "--out", tmp_path / "timed"])  # fmt: skip
    timed = json.loads((tmp_path / "timed" / "metrics.json").read_text())
    assert timed["config"]["client"]["rate_hz"] == pytest.approx(25.0)


def test_bench_vs_sb3_reports_curves_step_cost_and_act_latency(tmp_path):
    j, p = tmp_path / "vs.json", tmp_path / "vs.png"
    run([BIN / "wfnn-bench", "vs-sb3", "--tasks", "wfnn/Boat-v0", "--steps", "400", "--seeds", "2",
         "--eval-every", "200", "--eval-episodes", "1", "--thinks", "2", "--learners", "thesis,deep",
         "--deep-options", '{"deep": {"hidden": [16, 16], "warmup": 50}}',
         "--json", j, "--plot", p])  # fmt: skip
    data = json.loads(j.read_text())
    boat = data["tasks"]["wfnn/Boat-v0"]
    for algorithm in ("thesis", "deep", "sac", "td3"):
        r = boat[algorithm]
        if "skipped" in r:  # Stable-Baselines3 is an optional dependency
            assert algorithm in ("sac", "td3") and "stable-baselines3" in r["skipped"]
            continue
        assert r["steps"] == [200, 400] and len(r["return_median"]) == 2 and len(r["final_returns"]) == 2
        assert r["return_q25"][-1] <= r["return_median"][-1] <= r["return_q75"][-1] < 0
        assert r["s_per_step"] > 0 and 0 < r["act_us"] <= r["act_us_p99"]
        assert len(r["final_lengths"]) == 2 and all(0 < n <= 200 for n in r["final_lengths"])  # 200 a target
        assert [len(seed) for seed in r["lengths"]] == [2, 2]
    assert boat["deep"]["config"]["learner"] == "deep" and boat["deep"]["config"]["deep"]["hidden"] == [
        16,
        16,
    ]
    assert boat["thesis"]["config"]["thinks_per_action"] == 2
    assert p.stat().st_size > 10_000


def test_bench_relearn_resets_and_relearns_from_the_store(tmp_path):
    j, p = tmp_path / "relearn.json", tmp_path / "relearn.png"
    out = run([BIN / "wfnn-bench", "relearn", "--controllers", "2", "--episodes", "2", "--eval-every", "1",
               "--thinks", "3", "--json", j, "--plot", p])  # fmt: skip
    assert "relearn_fraction" in out.stdout
    data = json.loads(j.read_text())
    assert all(0 < n <= 2 * 450 for n in data["stored_experiences"])
    assert len(data["online_error_px"]) == len(data["with_store_error_px"]) == 2
    assert 1 <= len(data["store_only_error_px"]) <= 2 and 1 <= len(data["store_only_passive_error_px"]) <= 2
    # The store alone thinks in chunks of one evaluation interval's thinks (450 actions x 3).
    assert [row[0] for row in data["store_only_thinks"]][:1] == [1350]
    assert [row[0] for row in data["store_only_passive_thinks"]][:1] == [1350]
    assert data["passive_learner"] == {"bc_weight": 0.5, "alpha": 0.05, "advantage_k": 1.0}
    for c in data["controllers"]:
        assert c["pre_divergence_error_px"] > 0 and c["online_robot_s_to_reach"] in (30.0, 60.0, None)
        assert c["with_store_robot_s_to_reach"] in (30.0, 60.0, None)
    assert p.stat().st_size > 10_000


def test_bench_dashboard_measures_what_the_dashboard_costs(tmp_path):
    j, p = tmp_path / "dashboard.json", tmp_path / "dashboard.png"
    out = run([BIN / "wfnn-bench", "dashboard", "--seconds", "4", "--warmup", "6", "--repeats", "1",
               "--json", j, "--plot", p])  # fmt: skip
    assert "dashboard CPU" in out.stdout
    data = json.loads(j.read_text())
    off, on = data["runs"]
    assert not off["dashboard"] and on["dashboard"] and on["messages"] >= 4 * (4 + 6) - 8
    assert off["dashboard_cpu_s"] == 0 and on["dashboard_cpu_s"] > 0 and on["server_cpu_s"] > 0
    assert off["experiences_stored"] > 0 and on["experiences_stored"] > 0
    assert data["added_fraction_attributed"] > 0 and p.stat().st_size > 10_000


def test_bench_safety_measures_what_survives(tmp_path):
    j, p = tmp_path / "safety.json", tmp_path / "safety.png"
    out = run([BIN / "wfnn-bench", "safety", "--episodes", "2", "--seconds", "6", "--json", j, "--plot", p])
    assert "restart empty" in out.stdout
    data = json.loads(j.read_text())
    logs = data["damaged_logs"]
    assert logs["experiences"] == 400 and data["logs_bytes_changed"] == 0
    assert 0 < logs["middle"]["replay_experiences"] < 400 and logs["torn_tail"]["inspect_experiences"] < 400
    assert data["restart_empty"]["produced"] > 50 and data["restart_experiences_missing"] == 0
    assert [f["megabytes"] for f in data["huge_frames"]] == [40, 30]
    assert set(data["goals"]) == {"logs_bytes_changed", "restart_experiences_missing",
                                  "storm_longest_without_weights_s", "huge_frames_overruns"}  # fmt: skip
    assert p.stat().st_size > 10_000


def test_a_benchmark_stopped_by_sigterm_stops_its_servers_and_leaves_no_files(tmp_path):
    """`kill` of a benchmark left its think server running, and its temporary files behind."""
    import signal
    import time

    (tmp_path / "tmp").mkdir()
    env = {**os.environ, "TMPDIR": str(tmp_path / "tmp")}
    bench = subprocess.Popen([BIN / "wfnn-bench", "transport", "--experiences", "1000", "--seconds", "1",
                              "--outage-seconds", "0", "--no-busy"], env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True)  # fmt: skip
    deadline, server = time.monotonic() + 60, None
    while server is None and time.monotonic() < deadline:
        children = subprocess.run(["ps", "-o", "pid=,args=", "--ppid", str(bench.pid)], capture_output=True,
                                  text=True).stdout.splitlines()  # fmt: skip
        server = next((int(c.split()[0]) for c in children if "wfnn-server" in c), None)
        time.sleep(0.05)
    assert server is not None, "the benchmark started no server"
    bench.send_signal(signal.SIGTERM)
    output, _ = bench.communicate(timeout=60)
    assert bench.returncode == 128 + signal.SIGTERM, output
    with pytest.raises(ProcessLookupError):
        os.kill(server, 0)
    assert list((tmp_path / "tmp").iterdir()) == []


def test_a_server_that_was_starting_when_its_starter_stopped_is_stopped(tmp_path, monkeypatch):
    """The starter never got the server to stop: it outlived the benchmark or test that made it."""
    import wfnn_server.spawn as spawn

    def interrupted(port, timeout_s=30.0):
        raise KeyboardInterrupt

    monkeypatch.setattr(spawn, "wait_listening", interrupted)
    server = spawn.ServerProcess(tmp_path / "srv", spawn.free_port())
    with pytest.raises(KeyboardInterrupt):
        server.start()
    assert server.proc is not None and server.proc.poll() is not None


def test_a_server_its_starter_is_stopped_from_while_it_forks_is_stopped(tmp_path, monkeypatch):
    """SIGTERM inside Popen, after the fork: the server's process was never known, never stopped."""
    import signal

    import wfnn_server.spawn as spawn
    from wfnn_io.cli_errors import Terminated

    real, started = spawn.subprocess.Popen, []

    def popen_then_sigterm(*args, **kwargs):
        started.append(real(*args, **kwargs))
        os.kill(os.getpid(), signal.SIGTERM)  # as if it came before Popen returned
        return started[-1]

    def terminate(signum, frame):
        raise Terminated(signum)

    monkeypatch.setattr(spawn.subprocess, "Popen", popen_then_sigterm)
    previous = signal.signal(signal.SIGTERM, terminate)  # as `guarded` installs it
    try:
        server = spawn.ServerProcess(tmp_path / "srv", spawn.free_port())
        with pytest.raises(Terminated):
            server.start()
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert started and started[0].poll() is not None


def test_a_benchmark_stopped_in_its_outage_phase_ends_at_once_and_leaves_no_files(tmp_path):
    """Its client ran in a thread of its own, which the signal never reached: it ran on to its end
    and wrote its files after the temporary folder was removed."""
    import signal
    import time

    (tmp_path / "tmp").mkdir()
    env = {**os.environ, "TMPDIR": str(tmp_path / "tmp")}
    bench = subprocess.Popen([BIN / "wfnn-bench", "transport", "--experiences", "1000", "--seconds", "1",
                              "--outage-seconds", "20", "--no-busy"], env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True)  # fmt: skip
    deadline = time.monotonic() + 120
    while not list((tmp_path / "tmp").glob("*/client3/journal")) and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(1.0)
    bench.send_signal(signal.SIGTERM)
    stopped = time.monotonic()
    output, _ = bench.communicate(timeout=60)
    assert bench.returncode == 128 + signal.SIGTERM, output
    assert time.monotonic() - stopped < 15  # the outage phase had 19 s to go
    assert list((tmp_path / "tmp").iterdir()) == []


def test_a_client_mode_server_waiting_for_its_router_stops_on_sigterm_and_one_with_none_is_refused(tmp_path):
    """Its wait for a router took no signal (a service manager's stop waited for SIGKILL), and with
    no endpoint at all it tried again at full speed, for good."""
    import signal
    import time

    from wfnn_server.spawn import endpoint, free_port

    args = ["--id", "c0", "--mode", "client", "--data-dir", tmp_path / "none", "--quiet"]
    proc = subprocess.run([BIN / "wfnn-server", *args], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "client mode needs an endpoint to connect to" in proc.stdout + proc.stderr
    assert not (tmp_path / "none").exists()
    server = subprocess.Popen([BIN / "wfnn-server", "--id", "c1", "--mode", "client", "--connect",
                               endpoint(free_port()), "--data-dir", tmp_path / "data", "--quiet"],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                              env={**os.environ, "COLUMNS": "400"})  # fmt: skip
    try:
        time.sleep(4.0)  # past its first tries
        cpu = sum(map(int, Path(f"/proc/{server.pid}/stat").read_text().rsplit(")", 1)[1].split()[11:13]))
        assert cpu / os.sysconf("SC_CLK_TCK") < 2.0, "it spun while it waited"
        server.send_signal(signal.SIGTERM)
        output, _ = server.communicate(timeout=10)
    finally:
        if server.poll() is None:
            server.kill()
            server.wait()
    assert server.returncode == 128 + signal.SIGTERM, output
    assert "no router answers at tcp/127.0.0.1:" in output and ".rs:" not in output


def test_a_client_in_client_mode_takes_one_server(tmp_path):
    """A client-mode session links to one endpoint: the second server heard nothing, unsaid."""
    proc = subprocess.run(
        [BIN / "wfnn-client", "--sim", "boat", "--mode", "client", "--server", "tcp/127.0.0.1:7447",
         "--server", "tcp/127.0.0.1:7448", "--out", tmp_path / "run"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == 2 and "links to one endpoint only" in proc.stdout + proc.stderr
    assert not (tmp_path / "run").exists()
