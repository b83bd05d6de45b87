"""`wfnn report`: self-contained HTML of a finished run or benchmark."""

import json
import re

import pytest
from typer.testing import CliRunner

from wfnn_bench.report import REPORT_HEADS, ReportConfig, ReportError, app, run
from wfnn_client.config import ClientConfig
from wfnn_client.controllers import parse_mix
from wfnn_client.run import run as run_client


def test_a_runs_report_has_its_figures_curves_log_and_config(tmp_path):
    out = tmp_path / "run"
    metrics = run_client(ClientConfig(sim="boat", rate_hz=0, episodes=4, thinks_per_action=2, out=out, seed=3,
                                      behaviour_policy=parse_mix("wfnn=1,handcoded=1")))  # fmt: skip
    html_path = run(ReportConfig(path=out))
    assert html_path == out / "report.html" and (out / "report.png").stat().st_size > 10_000
    html = html_path.read_text()
    assert "<h2>Run</h2>" in html and "Experience log journal" in html and "Learner config" in html
    assert f"<td>experiences learned</td><td>{metrics['experiences_learned']}</td>" in html
    # Self-contained: every picture inline, nothing fetched.
    assert re.search(r'src="data:image/png;base64,[A-Za-z0-9+/=]{1000,}"', html)
    assert not re.search(r'src="(http|/)', html)
    assert "behaviour policy handcoded" in html and "episodes driven by" in html
    # An experience log is no folder of benchmarks, and a report is never written into one.
    journal = out / "journal"
    before = {p.name: p.read_bytes() for p in journal.iterdir() if p.is_file()}
    with pytest.raises(ReportError, match="experience log"):
        run(ReportConfig(path=journal))
    with pytest.raises(ReportError, match="never written into an experience log"):
        run(ReportConfig(path=out, out=journal / "r.html"))
    assert {p.name: p.read_bytes() for p in journal.iterdir() if p.is_file()} == before


def test_benchmark_reports_show_scalars_and_the_benchmarks_plot(tmp_path):
    (tmp_path / "b.json").write_text(json.dumps({"score": 0.25, "goal": {"met": True, "goal": "x < 1"},
                                                 "curve": [1, 2, 3], "machine": {"cpus": 2}}))  # fmt: skip
    (tmp_path / "b.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"0" * 100)
    (tmp_path / "c.json").write_text(json.dumps({"n": 3}))
    one = run(ReportConfig(path=tmp_path / "b.json"))
    html = one.read_text()
    assert one.name == "b_report.html" and "<td>score</td><td>0.25</td>" in html
    assert "<td>goal.met</td><td>yes</td>" in html and "curve" not in html and "cpus 2" in html
    assert "data:image/png;base64," in html
    both = run(ReportConfig(path=tmp_path, out=tmp_path / "all.html")).read_text()
    assert "<h2>b</h2>" in both and "<h2>c</h2>" in both


def test_a_benchmarks_nested_figures_are_shown_but_not_its_configs(tmp_path):
    """vs-sb3's figures sit three objects deep: only its name and machine were shown."""
    result = {"tasks": {"Pendulum-v1": {"deep": {"final_return_median": -121.5, "config": {"gamma": 0.99}}}},
              "config": {"seeds": 5}, "wide": {f"f{i}": i for i in range(600)}}  # fmt: skip
    (tmp_path / "v.json").write_text(json.dumps(result))
    html = run(ReportConfig(path=tmp_path / "v.json")).read_text()
    assert "<td>tasks.Pendulum-v1.deep.final_return_median</td><td>-121.5</td>" in html
    assert "gamma" not in html and "seeds" not in html
    assert "the first 500 of 601 figures" in html and "wide.f498" in html and "wide.f499" not in html


def test_unusable_input_is_refused_with_the_reason(tmp_path):
    with pytest.raises(ReportError, match="give a run directory"):
        run(ReportConfig(path=tmp_path / "missing"))
    with pytest.raises(ReportError, match=r"neither metrics\.json"):
        run(ReportConfig(path=tmp_path))
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ReportError, match="not readable JSON"):
        run(ReportConfig(path=tmp_path / "bad.json"))
    result = CliRunner().invoke(app, ["report", str(tmp_path / "missing")])
    assert result.exit_code == 2 and "give a run directory" in result.output


@pytest.mark.parametrize(
    ("metrics", "reason"),
    [
        (b"\x92\x00not text", "not readable JSON"),
        (b"[1, 2]", "no scores"),
        (b'{"scores": [1, "x"]}', "malformed metrics"),
        (b'{"scores": [1, 2], "config": 5}', "malformed metrics"),
        (b'{"scores": [1, 1' + b"0" * 400 + b"]}", "malformed metrics"),
        (b'{"scores": ' + b"[" * 100_000 + b"]" * 100_000 + b"}", "metrics.json"),
        (b'{"scores": "1789"}', "malformed metrics"),  # a string's characters were drawn as scores
        (b'{"scores": [[1, 2], [3, 4]]}', "malformed metrics"),
        (b'{"scores": [true, 2]}', "malformed metrics"),
        (b'{"scores": {"a": 1}}', "malformed metrics"),
    ],
)
def test_a_damaged_run_metrics_file_is_named_in_one_line_and_left_as_it_was(tmp_path, metrics, reason):
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "metrics.json").write_bytes(metrics)
    result = CliRunner().invoke(app, ["report", str(tmp_path / "run")])
    assert result.exit_code == 2 and reason in result.output and "metrics.json" in result.output
    assert result.output.count("\n") == 1 and not (tmp_path / "run" / "report.html").exists()
    assert (tmp_path / "run" / "metrics.json").read_bytes() == metrics


def test_a_diverged_runs_huge_scores_are_reported_not_drawn(tmp_path, recwarn):
    """Scores at float64's limits (a diverged run) once made the figure's span overflow."""
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "metrics.json").write_text('{"scores": [1e308, -1e308, 1, 2, 3, NaN, 5, 6, null]}')
    result = CliRunner().invoke(app, ["report", str(tmp_path / "run")])
    assert result.exit_code == 0, result.output
    html = (tmp_path / "run" / "report.html").read_text()
    assert "4 episode scores missing (no finite metric), beyond +-1e+300 or not finite are not drawn" in html
    assert (tmp_path / "run" / "report.png").read_bytes().startswith(b"\x89PNG")
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]


def test_a_report_is_never_written_over_what_it_reads(tmp_path):
    """`--out speed.json` replaced the benchmark's result with the page about it."""
    (tmp_path / "speed.json").write_text('{"benchmark": "speed", "act_p99_us": 3.5}')
    (tmp_path / "speed.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    for out in ("speed.json", "speed.png"):
        with pytest.raises(ReportError, match="the report is HTML"):
            run(ReportConfig(path=tmp_path / "speed.json", out=tmp_path / out))
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "metrics.json").write_text('{"scores": [1, 2, 3]}')
    (tmp_path / "run" / "learning_curve.png").write_bytes(b"\x89PNG\r\n\x1a\ncurve")
    for out in (tmp_path / "run" / "learning_curve.html", tmp_path / "speed.html"):  # a run's, a plot
        with pytest.raises(ReportError, match=r"would replace .*\.png \(a result's\)"):
            run(ReportConfig(path=tmp_path / "run", out=out))
    assert (tmp_path / "run" / "learning_curve.png").read_bytes().endswith(b"curve")
    run(ReportConfig(path=tmp_path / "run", out=tmp_path / "elsewhere.html"))
    assert (tmp_path / "elsewhere.png").read_bytes().startswith(b"\x89PNG")
    (tmp_path / "elsewhere.html").unlink()
    (tmp_path / "elsewhere.png").unlink()
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()} == before


def test_a_reports_figure_replaces_no_picture_but_its_own_and_a_refusal_writes_nothing(tmp_path):
    """--out pics/photo.html replaced the user's photo.png with the run's figure; and a report
    refused for its figure's place (a FIFO there) had already replaced the HTML."""
    import os

    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "metrics.json").write_text('{"scores": [1, 2, 3]}')
    (tmp_path / "photo.png").write_bytes(b"\x89PNG\r\n\x1a\nmine")
    with pytest.raises(ReportError, match=r"photo.png, which is no report's figure"):
        run(ReportConfig(path=tmp_path / "run", out=tmp_path / "photo.html"))
    assert (tmp_path / "photo.png").read_bytes().endswith(b"mine") and not (tmp_path / "photo.html").exists()
    old_report = '<!doctype html>\n<html lang="en"><head><meta charset="utf-8"><title>wfnn run r</title>OLD'
    (tmp_path / "keep.html").write_text(old_report)
    os.mkfifo(tmp_path / "keep.png")
    with pytest.raises(OSError, match="not a regular file"):
        run(ReportConfig(path=tmp_path / "run", out=tmp_path / "keep.html"))
    assert (tmp_path / "keep.html").read_text() == old_report
    # A report's own pair is rewritten as a whole.
    run(ReportConfig(path=tmp_path / "run", out=tmp_path / "r.html"))
    first = (tmp_path / "r.png").read_bytes()
    run(ReportConfig(path=tmp_path / "run", out=tmp_path / "r.html"))
    assert (tmp_path / "r.png").read_bytes() == first and "<h2>Run</h2>" in (tmp_path / "r.html").read_text()
    # Its figure is marked as a report's: a report cut short before its HTML (or moved away) is
    # written again, not refused for good.
    (tmp_path / "r.html").unlink()
    run(ReportConfig(path=tmp_path / "run", out=tmp_path / "r.html"))
    assert (tmp_path / "r.html").exists() and (tmp_path / "r.png").read_bytes() == first


def test_a_deep_runs_report_shows_the_deep_learners_settings_not_the_thesis_ones():
    from tests.fakes import small_config
    from wfnn_common.config import settings

    deep = dict(settings(json.loads(small_config(learner="deep").to_json())))  # as metrics.json has it
    assert deep["deep.hidden"] == [8, 8] and "deep.lr" in deep and "deep.warmup" in deep
    assert not {"n_hidden", "alpha", "derivatives", "update"} & set(deep)
    assert "exploration.kind" in deep and "state_low" not in deep
    thesis = dict(settings(small_config().to_dict()))
    assert "state_low" not in thesis
    assert thesis["n_hidden"] == 6 and not [k for k in thesis if k.startswith("deep")]


def test_pictures_that_are_not_the_runs_own_pngs_are_named_not_embedded(tmp_path):
    """A link out of the run, a FIFO or a file that is no PNG: noted, never read into the page."""
    import os
    import threading

    run_dir = tmp_path / "run"
    (run_dir / "cameras").mkdir(parents=True)
    (tmp_path / "secret.key").write_bytes(b"the key" * 100)
    (run_dir / "cameras" / "a.png").symlink_to(tmp_path / "secret.key")
    os.mkfifo(run_dir / "cameras" / "z.png")
    (run_dir / "metrics.json").write_text(json.dumps({"scores": [1.0, 2.0, 3.0], "episode_policies": ["x"]}))
    done = []
    worker = threading.Thread(target=lambda: done.append(run(ReportConfig(path=run_dir))), daemon=True)
    worker.start()
    worker.join(30.0)
    assert done, "the report waited on a FIFO"
    html = done[0].read_text()
    assert "a.png not shown: a link out of the run directory" in html and "z.png not shown" in html
    assert "the key" not in html and "dGhlIGtleX" not in html  # nor its base64


def test_json_that_links_out_of_the_folder_is_not_read_into_a_report(tmp_path):
    """Pictures linking out were refused, JSON was not: a shared report carried a secret file."""
    (tmp_path / "secret").mkdir()
    (tmp_path / "secret" / "creds.json").write_text(json.dumps({"password": "hunter2"}))
    (tmp_path / "bench").mkdir()
    (tmp_path / "bench" / "b.json").write_text(json.dumps({"score": 0.25}))
    (tmp_path / "bench" / "zz.json").symlink_to(tmp_path / "secret" / "creds.json")
    html = run(ReportConfig(path=tmp_path / "bench")).read_text()
    assert "hunter2" not in html and "0.25" in html and "a link out of" in html
    (tmp_path / "ok").mkdir()
    (tmp_path / "ok" / "metrics.json").write_text(json.dumps({"scores": [1, 2, 3]}))
    from tests.unit.wfnn_io.test_logs import record

    record(tmp_path / "secret" / "journal", n=123)
    (tmp_path / "ok" / "journal").symlink_to(tmp_path / "secret" / "journal")
    html = run(ReportConfig(path=tmp_path / "ok")).read_text()
    assert "<td>123</td>" not in html and "a link out of" in html  # its count (a path may hold 123)
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "metrics.json").symlink_to(tmp_path / "secret" / "creds.json")
    with pytest.raises(ReportError, match="a link out of"):
        run(ReportConfig(path=tmp_path / "run"))


def test_a_run_of_thousands_of_behaviour_policies_is_drawn_as_a_few_groups(tmp_path):
    """One series and legend entry per name: 6,000 names took over a minute and 400 MB."""
    from wfnn_bench.report import MAX_POLICIES, _policy_groups

    policies = [f"weights:w{i}.npz" for i in range(6000)] + ["wfnn"] * 10
    groups = _policy_groups(policies)
    assert len(groups) == MAX_POLICIES + 1 and groups[-1][0] == f"{6001 - MAX_POLICIES} other policies"
    assert sorted(i for _, rows in groups for i in rows) == list(range(6010))
    assert dict((name, len(rows)) for name, rows in groups)["wfnn"] == 10
    (tmp_path / "run").mkdir()
    scores = list(range(len(policies)))
    (tmp_path / "run" / "metrics.json").write_text(
        json.dumps({"scores": scores, "episode_policies": policies})
    )
    html = run(ReportConfig(path=tmp_path / "run")).read_text()
    assert "wfnn 10" in html and "other policies" in html


def test_a_run_whose_metrics_json_is_a_dangling_link_is_refused_not_read_as_benchmarks(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "config.json").write_text('{"client": {"seed": 0}}')
    (run_dir / "metrics.json").symlink_to(tmp_path / "gone" / "metrics.json")  # out of the run: not read
    result = CliRunner().invoke(app, ["report", str(run_dir)])
    assert result.exit_code == 2 and "metrics.json" in result.output and result.output.count("\n") == 1
    assert not (run_dir / "report.html").exists()


def test_an_html_file_that_is_no_report_is_never_replaced_nor_the_png_beside_it(tmp_path):
    """Someone's own report.html was replaced, and with it their report.png: a PNG was protected
    only where no HTML stood beside it."""
    import shutil

    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "metrics.json").write_text(json.dumps({"scores": [1.0, 0.5, 0.25]}))
    run(ReportConfig(path=run_dir))
    report, figure = (run_dir / "report.html").read_bytes(), (run_dir / "report.png").read_bytes()
    run(ReportConfig(path=run_dir))  # a report replaces a report
    old_head = report.replace(b'<meta name="generator" content="wfnn report">\n', b"")
    assert old_head.startswith(REPORT_HEADS[1] + b"run ")
    (run_dir / "report.html").write_bytes(old_head)  # as reports were written before the mark
    run(ReportConfig(path=run_dir))
    assert (run_dir / "report.html").read_bytes() == report
    mine = b"<p>my notes</p>"
    (run_dir / "report.html").write_bytes(mine)
    shutil.copy(run_dir / "report.png", tmp_path / "mine.png")
    result = CliRunner().invoke(app, ["report", str(run_dir)])
    assert result.exit_code == 2 and "no report" in result.output and result.output.count("\n") == 1
    assert (run_dir / "report.html").read_bytes() == mine and (run_dir / "report.png").read_bytes() == figure


def test_a_runs_own_text_is_drawn_shortened_and_as_plain_text(tmp_path):
    """A sim name of 5 million characters kept matplotlib rasterising for over a minute, then
    failed with an error naming no file; "$" in a name is mathtext to matplotlib."""
    import time

    (tmp_path / "run").mkdir()
    metrics = {"scores": [1.0, 2.0, 3.0, 4.0], "sim": "A" * 5_000_000, "metric": "$\\foo$ cost $\\frac{a",
               "episode_policies": ["wfnn", "$x^", "wfnn", "B" * 1000]}  # fmt: skip
    (tmp_path / "run" / "metrics.json").write_text(json.dumps(metrics))
    t0 = time.perf_counter()
    result = CliRunner().invoke(app, ["report", str(tmp_path / "run")])
    assert result.exit_code == 0, result.output
    assert time.perf_counter() - t0 < 30.0
    assert (tmp_path / "run" / "report.png").read_bytes().startswith(b"\x89PNG")


def test_counts_kept_as_floats_are_shown_in_full(tmp_path):
    """A learner's counts are floats in metrics.json: 54,321 refused experiences read 5.432e+04."""
    from wfnn_bench.report import _run_sections

    (tmp_path / "metrics.json").write_text(json.dumps({
        "sim": "gym", "metric": "mean reward per step", "scores": [1.0, 2.5], "experiences_learned": 54321,
        "learn/rejected": 54321.0, "task_returns_last10_median": 0.123456, "wall_s": 2.5e20,
    }))  # fmt: skip
    rows = dict(_run_sections(tmp_path)[0][0].rows)
    assert rows["of them refused (not finite or out of range)"] == "54321"
    assert rows["task's return, last-10 median"] == "0.1235" and rows["wall time (s)"] == "2.5e+20"


def test_a_json_without_figures_gets_no_report_said_to_be_written(tmp_path):
    (tmp_path / "empty.json").write_text("{}")
    with pytest.raises(ReportError, match="no figures in it"):
        run(ReportConfig(path=tmp_path / "empty.json"))
    assert not (tmp_path / "empty_report.html").exists()


def test_a_think_servers_data_directory_is_refused_and_left_as_it_was(tmp_path):
    # Its JSON files are the server's configs, which were read as benchmarks, and the report was
    # written into the server's data directory.
    from tests.unit.wfnn_server.test_store import batch
    from wfnn_server.config import ServerConfig
    from wfnn_server.server import SERVER_JSON, record
    from wfnn_server.store import ExperienceStore

    assert SERVER_JSON == "server_config.json"  # what the report recognises a server's directory by
    stored, fresh = tmp_path / "stored", tmp_path / "fresh"
    for data in (stored, fresh):
        data.mkdir()
        record(ServerConfig(controller="t", server_id="s1", data_dir=data))
    (stored / "learner_config.json").write_text(json.dumps({"learner": "thesis"}))
    store = ExperienceStore(stored / "store", "s1", fsync="never")
    store.append(batch(0, 3))
    store.close()
    (stored / SERVER_JSON).unlink()  # the store alone marks it too (a server of an older version)
    for data in (stored, fresh):
        before = {p: p.read_bytes() for p in data.rglob("*") if p.is_file()}
        result = CliRunner().invoke(app, ["report", str(data)])
        assert result.exit_code == 2 and "think server's data directory" in result.output
        assert {p: p.read_bytes() for p in data.rglob("*") if p.is_file()} == before
    # Nor a file of one, nor a report of something else written into one.
    (tmp_path / "bench.json").write_text(json.dumps({"median": 1.5}))
    for args in (["report", str(fresh / SERVER_JSON)], ["report", str(stored / "learner_config.json")],
                 ["report", str(tmp_path / "bench.json"), "--out", str(fresh / "r.html")]):  # fmt: skip
        result = CliRunner().invoke(app, args)
        assert result.exit_code == 2 and "think server's data directory" in result.output, args
    assert sorted(p.name for p in fresh.iterdir()) == [SERVER_JSON]


def test_a_runs_report_tells_what_its_journal_lost_to_damage(tmp_path):
    """A damaged journal's page said "experiences 544" alone: the damage, the gap it left and
    the stray segment files reached only the console."""
    out = tmp_path / "run"
    run_client(ClientConfig(sim="boat", rate_hz=0, episodes=8, thinks_per_action=1, out=out, seed=3))
    segment = out / "journal" / "00000000.seg"
    data = bytearray(segment.read_bytes())
    data[len(data) // 2 : len(data) // 2 + 64] = bytes(64)
    segment.write_bytes(bytes(data))
    (out / "journal" / "1.seg").write_bytes(b"")
    html = run(ReportConfig(path=out)).read_text()
    assert re.search(r"<td>damage corrupt</td><td>1 spans, \d+ bytes skipped</td>", html)
    held = r"<td>client [^<]+</td><td>\d+ experiences numbered 0 to 1599: 1 gaps, 0 duplicates</td>"
    assert re.search(held, html)
    assert "files named like segments, not read: 1.seg" in html


def test_a_journal_of_many_clients_lists_the_first_fifty_after_its_damage(tmp_path):
    """505 clients filled the table's 500 rows before its damage rows, which were cut unsaid."""
    import numpy as np

    from sims.boat import BoatVec
    from wfnn_client.brain import Experience, Recorder
    from wfnn_common.config import LearnerConfig
    from wfnn_io import logs

    config = LearnerConfig.for_task(BoatVec)
    for i in range(55):
        folder = tmp_path / ("whole" if i == 53 else "logs") / f"r{i:02d}"
        recorder = Recorder(folder, config, f"r{i:02d}", batch_max=4)
        for _ in range(12 if i == 53 else 8):
            recorder.add(Experience(np.zeros(config.state_dim), np.zeros(config.action_dim),
                                    np.zeros(config.state_dim), 0.0, False, 0), "local", 1)  # fmt: skip
        recorder.close()
    logs.split(tmp_path / "whole" / "r53", tmp_path / "parts", by="count", every=4)  # r53 loses 4-7
    logs.merge([tmp_path / "parts" / "part0000", tmp_path / "parts" / "part0002"], tmp_path / "logs" / "r53")
    out = tmp_path / "run"
    logs.merge(sorted((tmp_path / "logs").iterdir()), out / "journal")
    segment = out / "journal" / "00000000.seg"
    data = bytearray(segment.read_bytes())
    data[len(data) // 2 : len(data) // 2 + 16] = bytes(16)
    segment.write_bytes(bytes(data))
    (out / "metrics.json").write_text(json.dumps({"scores": [1.0, 2.0]}))
    html = run(ReportConfig(path=out)).read_text()
    assert "<td>damage corrupt</td>" in html and html.count("<td>client r") == 50
    assert (
        "50 of 55 clients (those with gaps or duplicates first); `wfnn-logs inspect` lists them all" in html
    )
    # A client with a gap is listed, whatever its name (r53 came after the first 50).
    assert re.search(r"<td>gaps / duplicates \(all clients\)</td><td>[1-9] / 0</td>", html)
    assert "<td>client r53</td><td>8 experiences numbered 0 to 11: 1 gaps, 0 duplicates</td>" in html
