"""`wfnn report PATH`: a self-contained HTML report (and a PNG) of a finished run or benchmark.

PATH may be
- a client run directory (`wfnn-client --out DIR`, the main job's `runs/main`): the run's
  figures, its learning curve with a running median (who drove each episode, where a behaviour
  policy mix was used), box plots of the scores of the first and last episodes, the experience
  log's behaviour policies and flags, the learner config, and the first and last camera pictures;
- a benchmark's JSON (`wfnn-bench ... --json FILE`): its scalar figures, goals and the plot the
  benchmark drew beside it (FILE with .png);
- a directory of benchmark JSONs (`docs/results/`): one section per benchmark.

Pictures are embedded (base64), so the HTML file stands alone. Written beside the input unless
told otherwise: `report.html`, and for a run `report.png` (the curve and box plots).
"""

from __future__ import annotations

import base64
import io
import json
import logging
import os
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import jinja2
import numpy as np
import typer
from numpy.typing import NDArray

from wfnn_common.config import check_fields, settings
from wfnn_io.cli_errors import file_given, guarded, one_line, path_given
from wfnn_io.logs import is_log
from wfnn_io.persist import (
    atomic_write_bytes,
    atomic_write_text,
    read_regular_bytes,
    read_regular_head,
    read_regular_text,
    writable,
)
from wfnn_io.protocol import PNG_SIGNATURE

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class ReportConfig:
    """What to report on and where to write it."""

    path: Path
    """A client run directory, a benchmark JSON, or a directory of benchmark JSONs."""
    out: Path | None = None
    """The HTML file (default: `report.html` in the run directory or beside the JSON)."""

    def __post_init__(self) -> None:
        check_fields(self)


class ReportError(ValueError):
    """The path is not something a report can be made of (the message says why)."""


@dataclass
class Section:
    """One part of the report: a title, a table of figures, pictures and notes."""

    title: str
    rows: list[tuple[str, str]]
    images: list[tuple[str, str]]
    """(caption, data URI)."""
    notes: list[str]


TEMPLATE = jinja2.Environment(autoescape=True).from_string("""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><meta name="generator" content="wfnn report">
<title>{{ title }}</title>
<style>
 body { font-family: system-ui, sans-serif; margin: 1.2rem auto; max-width: 1100px; color: #222; }
 h1 { font-size: 1.4rem; } h2 { font-size: 1.15rem; border-bottom: 1px solid #ddd; padding-bottom: 0.2rem; }
 table { border-collapse: collapse; font-size: 0.9rem; margin: 0.4rem 0 0.8rem 0; }
 td { padding: 0.15rem 0.7rem; border-bottom: 1px solid #eee; vertical-align: top; }
 td:first-child { color: #555; } td:last-child { font-variant-numeric: tabular-nums; }
 figure { margin: 0.5rem 0 1rem 0; } figcaption { color: #555; font-size: 0.85rem; }
 img { max-width: 100%; border: 1px solid #eee; } .note { color: #444; font-size: 0.9rem; }
</style></head><body>
<h1>{{ title }}</h1>
<p class="note">{{ subtitle }}</p>
{% for s in sections %}
<h2>{{ s.title }}</h2>
{% for n in s.notes %}<p class="note">{{ n }}</p>{% endfor %}
{% if s.rows %}<table>
{% for k, v in s.rows %}<tr><td>{{ k }}</td><td>{{ v }}</td></tr>{% endfor %}
</table>{% endif %}
{% for caption, uri in s.images %}
<figure><img src="{{ uri }}" alt="{{ caption }}"><figcaption>{{ caption }}</figcaption></figure>
{% endfor %}
{% endfor %}
</body></html>
""")


def _uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode()


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        if not np.isfinite(value):
            return "-"
        # A count kept as a float (a learner's figures are) in full: 54321, not 5.432e+04.
        return str(int(value)) if value.is_integer() and abs(value) < 1e15 else f"{value:.4g}"
    if isinstance(value, bool) or value is None:
        return {True: "yes", False: "no", None: "-"}[value]
    return str(value)


SCALARS_DEPTH = 4
"""How deep nested objects are followed: vs-sb3's figures sit at tasks.<task>.<learner>.<figure>."""
MAX_ROWS = 500
"""Most figures a benchmark's table shows (a note says how many more there are)."""
MAX_CLIENT_ROWS = 50
"""Clients (and behaviour policies) of an experience log listed in its section."""


def _scalars(data: dict[str, Any], prefix: str = "", depth: int = 0) -> list[tuple[str, str]]:
    """The plain figures of a JSON object: numbers, strings and booleans.

    Nested objects are followed SCALARS_DEPTH levels deep, but for the configs, machine facts and
    traces they hold; lists are left out.
    """
    rows: list[tuple[str, str]] = []
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict) and depth < SCALARS_DEPTH and key not in ("config", "machine", "trace"):
            rows += _scalars(value, f"{name}.", depth + 1)
        elif isinstance(value, int | float | str | bool) or value is None:
            rows.append((name, _fmt(value)))
    return rows


DRAWABLE = 1e300
"""The largest score magnitude drawn: the axes' span must stay finite (a diverged run's scores
may reach float64's limits, and the span of two such scores would overflow)."""


def _is_score(value: Any) -> bool:
    """An episode's score as metrics.json holds it: a number, or null (not finite when written)."""
    return value is None or (isinstance(value, int | float) and not isinstance(value, bool))


def _drawable(scores: list[Any]) -> np.ndarray:
    """The episodes' scores as floats, with missing, non-finite and undrawable ones NaN."""
    values = np.asarray([np.nan if s is None else s for s in scores], dtype=np.float64)
    return np.where(np.abs(values) <= DRAWABLE, values, np.nan)


MAX_POLICIES = 8
"""Behaviour policies drawn apart in a run's figure (the most frequent); the rest are drawn as one."""


def _policy_groups(policies: list[str]) -> list[tuple[str, NDArray[np.int64]]]:
    """(name, episode indices) of the MAX_POLICIES most frequent policies, then the others together.

    One pass over the episodes: a metrics.json of 6,000 distinct names took minutes, a series and
    a legend entry each.
    """
    rows: dict[str, list[int]] = {}
    for i, name in enumerate(policies):
        rows.setdefault(name, []).append(i)
    ranked = sorted(rows, key=lambda name: (-len(rows[name]), name))
    groups = [(name, np.array(rows[name])) for name in sorted(ranked[:MAX_POLICIES])]
    rest = ranked[MAX_POLICIES:]
    if rest:
        others = np.sort(np.concatenate([np.array(rows[name]) for name in rest]))
        groups.append((f"{len(rest)} other policies", others))
    return groups


FIGURE_TEXT = 60
"""The most characters of a run's own text (its sim, metric, drivers) drawn in its figure."""


def _drawn(text: Any) -> str:
    """A run's own text as its figure shows it: one line, at most FIGURE_TEXT characters, no mathtext.

    A sim name of 5 million characters took matplotlib over a minute to fail in its rasteriser
    ("raster overflow"), an error no report's message named, and "$" starts mathtext.
    """
    line = one_line(str(text))
    if len(line) > FIGURE_TEXT:
        line = line[: FIGURE_TEXT - 1] + "\u2026"
    return line.replace("$", r"\$")


def _run_figure(metrics: dict[str, Any]) -> bytes:
    """Learning curve (with a running median) and box plots of the first and last episodes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scores = _drawable(metrics["scores"])
    episodes = np.arange(1, len(scores) + 1)
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4), gridspec_kw={"width_ratios": [3, 1]})
    policies = _policies(metrics, len(scores))
    if policies and len(set(policies)) > 1:
        for name, rows in _policy_groups(policies):
            a.scatter(episodes[rows], scores[rows], s=14, label=f"driven by {_drawn(name)}")
    else:
        a.plot(episodes, scores, marker="o", ms=3, lw=0.8, label="episode")
    window = max(1, min(10, len(scores) // 4))
    if len(scores) >= 3:
        with warnings.catch_warnings():  # a window of undrawn scores has no median: a gap in the line
            warnings.simplefilter("ignore", RuntimeWarning)
            running = [np.nanmedian(scores[max(0, i - window + 1) : i + 1]) for i in range(len(scores))]
        a.plot(episodes, running, color="black", lw=1.6, label=f"running median of {window}")
    a.set_xlabel("episode")
    a.set_ylabel(_drawn(metrics.get("metric", "score")))
    a.set_title(f"{_drawn(metrics.get('sim', 'run'))}: learning curve")
    a.legend(fontsize=8)
    k = max(1, min(10, len(scores) // 2))
    first, last = scores[:k], scores[-k:]
    b.boxplot([first[np.isfinite(first)], last[np.isfinite(last)]])
    b.set_xticks([1, 2], [f"first {k}", f"last {k}"])
    b.set_title("episode scores")
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=100, metadata={"Software": REPORT_SOFTWARE})
    plt.close(fig)
    return buffer.getvalue()


RUN_FIGURES: tuple[tuple[str, str | tuple[str, ...]], ...] = (
    ("sim", "sim"), ("metric", "metric"), ("episodes", "episode"), ("first-10 median", "first10_median"),
    ("last-10 median", "last10_median"), ("experiences learned", "experiences_learned"),
    ("of them refused (not finite or out of range)", "learn/rejected"),
    ("task's own episodes", "task_episodes"), ("task's return, last-10 median", "task_returns_last10_median"),
    ("thinking in", "following"), ("wall time (s)", "wall_s"), ("control ticks", "ticks"),
    ("tick jitter p99 (ms)", "client/tick_jitter_ms_p99"), ("overruns", "client/overruns"),
    ("act latency p99 (ms)", "client/act_latency_ms_p99"),
    ("safe actions", ("client/safe_actions", "safe_actions")), ("vetoes", ("client/vetoes", "vetoes")),
    ("divergence resets (server)", "server/learn/divergence_resets"),
    ("server thinks/s", "server/think/thinks_per_s"), ("failovers", "downlink/failovers"),
)  # fmt: skip


METRICS_LIMIT = 4 << 30
"""The largest metrics.json read (a day's timing trace at 50 Hz is about 350 MB)."""


def _read_json(path: Path) -> Any:
    try:
        return json.loads(read_regular_text(path, METRICS_LIMIT))
    except (OSError, ValueError, RecursionError) as exc:
        raise ReportError(f"{path}: not readable JSON ({type(exc).__name__}: {exc})") from exc


def _outside(directory: Path, path: Path) -> str:
    """Why `path` is not read into a report ("" where it lies inside `directory`).

    A report is shared, and a link in a folder someone else made could point at any file (a key).
    """
    if path.resolve().is_relative_to(directory.resolve()):
        return ""
    return f"a link out of {directory} ({path.resolve()}) is not read into a report"


def _run_sections(directory: Path) -> tuple[list[Section], bytes]:
    path = directory / "metrics.json"
    if outside := _outside(directory, path):
        raise ReportError(f"{path}: {outside}")
    metrics = _read_json(path)
    if not isinstance(metrics, dict) or "scores" not in metrics:
        raise ReportError(f"{path} is not a client run's metrics (no scores)")
    scores = metrics["scores"]
    if not isinstance(scores, list) or not all(_is_score(s) for s in scores):
        raise ReportError(f"{path}: malformed metrics (scores must be a list of numbers, one per episode)")
    try:
        return _run_sections_of(directory, metrics)
    except (TypeError, ValueError, LookupError, AttributeError, ArithmeticError, RecursionError) as exc:
        raise ReportError(f"{path}: malformed metrics ({type(exc).__name__}: {exc})") from exc


def _run_sections_of(directory: Path, metrics: dict[str, Any]) -> tuple[list[Section], bytes]:
    figure = _run_figure(metrics)
    rows = []
    for name, keys in RUN_FIGURES:  # a figure renamed since is read under its earlier name too
        present = [k for k in ((keys,) if isinstance(keys, str) else keys) if k in metrics]
        if present:
            rows.append((name, _fmt(metrics[present[0]])))
    sections = [Section("Run", rows, [("learning curve and episode scores", _uri(figure))], [])]
    given = metrics["scores"]
    undrawn = int(np.count_nonzero(~np.isfinite(_drawable(given))))
    if undrawn:
        sections[0].notes.append(
            f"{undrawn} episode scores missing (no finite metric), beyond +-{DRAWABLE:g} or not "
            "finite are not drawn"
        )
    policies = _policies(metrics, len(metrics["scores"]))
    if policies and len(set(policies)) > 1:
        counts = {name: len(rows) for name, rows in _policy_groups(policies)}
        sections[0].notes.append("episodes driven by: " + ", ".join(f"{p} {n}" for p, n in counts.items()))
    for journal in sorted(directory.glob("journal*")):
        outside = _outside(directory, journal)
        sections.append(Section(f"Experience log {journal.name}", [], [], [f"not shown: {outside}"])
                        if outside else _journal_section(journal))  # fmt: skip
    learner = metrics.get("config", {}).get("learner")
    if isinstance(learner, dict) and learner:
        sections.append(Section("Learner config", [(k, _fmt(v)) for k, v in settings(learner)], [], []))
    cameras = sorted((directory / "cameras").glob("*.png")) if (directory / "cameras").is_dir() else []
    if cameras:
        chosen = [cameras[0], cameras[-1]] if len(cameras) > 1 else cameras
        pictures, notes = _pictures(directory, chosen)
        sections.append(Section("Cameras", [("pictures saved", str(len(cameras)))], pictures, notes))
    return sections, figure


SERVER_CONFIG = "server_config.json"
"""What a think server writes first into its data directory (`wfnn_server.server.SERVER_JSON`; not
imported: the server's module brings in both learners)."""


def _servers_data(folder: Path) -> bool:
    """Whether `folder` is a think server's data directory (its store, or its config)."""
    return folder.is_dir() and (is_log(folder / "store") or os.path.lexists(folder / SERVER_CONFIG))


REPORT_SOFTWARE = "wfnn report"
"""The PNG text chunk ("Software") that marks a report's own figure."""


REPORT_HEADS = (b'<meta name="generator" content="wfnn report">',
                b'<!doctype html>\n<html lang="en"><head><meta charset="utf-8"><title>wfnn ')  # fmt: skip
"""What marks a report's HTML in its first 4 KiB: the generator tag, or (reports written before
it) the head every report has begun with."""


def _head(path: Path, n: int = 4096) -> bytes:
    """A regular file's first n bytes; b"" for anything else."""
    try:
        return read_regular_head(path, n)
    except OSError:
        return b""


def _a_reports_figure(png: Path) -> bool:
    """Whether `png` is a figure a report wrote (its Software chunk, in the file's first 4 KiB)."""
    return b"Software\x00" + REPORT_SOFTWARE.encode() in _head(png)


def _a_report(html: Path) -> bool:
    """Whether `html` is a report's HTML (`REPORT_HEADS`), which a new report may replace."""
    head = _head(html)
    return REPORT_HEADS[0] in head or head.startswith(REPORT_HEADS[1])


def _a_results_picture(png: Path) -> bool:
    """Whether `png` is a benchmark's plot (a JSON of its name beside it) or a run's own picture."""
    png = png.resolve()
    run = png.parent.parent if png.parent.name == "cameras" else png.parent
    ours = png.name == "learning_curve.png" or png.parent.name == "cameras"
    return png.with_suffix(".json").exists() or (ours and (run / "metrics.json").exists())


PICTURE_LIMIT = 16 << 20
"""The largest picture a report embeds."""


def _pictures(directory: Path, paths: list[Path]) -> tuple[list[tuple[str, str]], list[str]]:
    """The PNG pictures among `paths` inside `directory`, as data URIs; and notes on the others.

    A picture is embedded only where it is a regular PNG file of at most PICTURE_LIMIT bytes
    inside the run directory: a report is shared, and a link in a directory someone else made
    could point at any file (a key, say); a FIFO would block the reader for good.
    """
    pictures, notes = [], []
    root = directory.resolve()
    for p in paths:
        try:
            if not p.resolve().is_relative_to(root):
                raise OSError(f"a link out of the run directory ({p.resolve()})")
            data = read_regular_bytes(p, PICTURE_LIMIT)
            if not data.startswith(PNG_SIGNATURE):
                raise ValueError("not a PNG picture")
        except (OSError, ValueError) as exc:
            notes.append(f"{p.name} not shown: {exc}")
            continue
        pictures.append((p.name, _uri(data)))
    return pictures, notes


def _policies(metrics: dict[str, Any], n: int) -> list[str]:
    """The episodes' behaviour policies, where metrics.json gives one name per episode (else none)."""
    policies = metrics.get("episode_policies")
    if isinstance(policies, list) and len(policies) == n and all(isinstance(p, str) for p in policies):
        return policies
    return []


def _journal_section(journal: Path) -> Section:
    from wfnn_io.logs import summarise

    try:
        s = summarise(journal)
    except (OSError, ValueError) as exc:
        return Section(f"Experience log {journal.name}", [], [], [f"unreadable: {exc}"])
    rows = [("experiences", str(s.experiences)), ("batches", str(s.batches)),
            ("mean reward", _fmt(s.reward_mean)), ("terminal", str(s.terminal))]  # fmt: skip
    # What a reader skipped or found missing (a page that said "experiences 544" alone hid it),
    # before anything a long list of clients could push past the table's end.
    spans, skipped = Counter(d.kind for d in s.damage), Counter[str]()
    for d in s.damage:
        skipped[d.kind] += d.length
    rows += [(f"damage {kind}", f"{n} spans, {skipped[kind]} bytes skipped")
             for kind, n in sorted(spans.items())]  # fmt: skip
    rows += [(f"records refused ({reason})", str(n)) for reason, n in sorted(s.refused.items()) if n]
    notes = [f"files named like segments, not read: {', '.join(s.strays[:8])}"] if s.strays else []
    notes += [f"its description: {s.description_error}"] if s.description_error else []
    policies = sorted(s.behaviour.items())[:MAX_CLIENT_ROWS]
    rows += [(f"behaviour policy {name}", str(n)) for name, n in policies]
    rows += [(f"flag {name}", str(n)) for name, n in sorted(s.flags.items()) if n]
    gaps, duplicates = sum(r.gaps for r in s.clients.values()), sum(r.duplicates for r in s.clients.values())
    rows.append(("gaps / duplicates (all clients)", f"{gaps} / {duplicates}"))
    # Those with gaps or duplicates first: the list is cut, and they are what a reader looks for.
    listed = sorted(s.clients.items(), key=lambda kv: (not (kv[1].gaps or kv[1].duplicates), kv[0]))
    for client, run in listed[:MAX_CLIENT_ROWS]:
        held = f"{run.experiences} experiences numbered {run.first_seq} to {run.last_seq}"
        rows.append((f"client {client}", f"{held}: {run.gaps} gaps, {run.duplicates} duplicates"))
    for what, n in (("clients", len(s.clients)), ("behaviour policies", len(s.behaviour))):
        if n > MAX_CLIENT_ROWS:
            which = "those with gaps or duplicates first" if what == "clients" else "the first by name"
            notes.append(f"{MAX_CLIENT_ROWS} of {n} {what} ({which}); `wfnn-logs inspect` lists them all")
    return Section(f"Experience log {journal.name}", rows, [], notes)


def _bench_section(path: Path) -> Section:
    data = _read_json(path)
    if not isinstance(data, dict):
        raise ReportError(f"{path}: a benchmark result is a JSON object")
    png = path.with_suffix(".png")
    images, notes = _pictures(path.parent, [png]) if png.exists() else ([], [])
    machine = data.get("machine")
    if isinstance(machine, dict):
        notes.append("measured on: " + ", ".join(f"{k} {v}" for k, v in machine.items()))
    rows = _scalars(data)
    if len(rows) > MAX_ROWS:
        notes.append(f"the first {MAX_ROWS} of {len(rows)} figures; the JSON holds them all")
    return Section(path.stem, rows[:MAX_ROWS], images, notes)


def run(config: ReportConfig) -> Path:
    """Write the report; returns the HTML file's path. Raises ReportError for unusable input."""
    path = config.path
    figure: bytes | None = None
    if path.is_dir() and os.path.lexists(path / "metrics.json"):  # a dangling link too: a run's, unreadable
        sections, figure = _run_sections(path)
        title, out = f"wfnn run {path.name}", config.out or path / "report.html"
    elif _servers_data(path) or (path.suffix == ".json" and _servers_data(path.parent)):
        # Its JSON files are a server's configs, no benchmarks, and a server's data is never written to.
        where = path if path.is_dir() else path.parent
        raise ReportError(f"{where} is a think server's data directory: its figures are in its status and "
                          "dashboard (a client run's report covers what it learned)")  # fmt: skip
    elif is_log(path):  # its log.json and client.json are no benchmarks, and logs are never written to
        raise ReportError(f"{path} is an experience log: wfnn-logs inspect summarises it (a run's report "
                          "covers the logs in it)")  # fmt: skip
    elif path.is_dir():
        found = sorted(p for p in path.glob("*.json") if not p.name.startswith("."))
        if not found:
            raise ReportError(f"{path} holds neither metrics.json (a run) nor benchmark JSON files")
        sections = [Section(p.stem, [], [], [f"not shown: {outside}"]) if (outside := _outside(path, p))
                    else _bench_section(p) for p in found]  # fmt: skip
        title, out = f"wfnn benchmarks in {path}", config.out or path / "report.html"
    elif path.suffix == ".json" and path.exists():
        sections = [_bench_section(path)]
        if not sections[0].rows and not sections[0].images:  # a report of nothing, said to be written
            raise ReportError(f"{path}: no figures in it (a benchmark result is a JSON object of them)")
        title, out = f"wfnn benchmark {path.stem}", config.out or path.with_name(f"{path.stem}_report.html")
    else:
        raise ReportError(
            f"{path}: give a run directory (with metrics.json), a benchmark JSON or a folder of them"
        )
    if is_log(out.parent) or _servers_data(out.parent):
        what = "an experience log" if is_log(out.parent) else "a think server's data directory"
        raise ReportError(f"{out}: a report is never written into {what}; give --out elsewhere")
    if out.suffix.lower() not in (".html", ".htm"):  # never over a benchmark's JSON or PNG it reads
        raise ReportError(f"--out {out}: the report is HTML; name a .html file")
    if os.path.lexists(out) and not _a_report(out):
        raise ReportError(f"--out {out}: it holds something that is no report, which the report would "
                          "replace; give another --out")  # fmt: skip
    png = out.with_suffix(".png")
    if figure is not None and _a_results_picture(png):
        raise ReportError(f"--out {out}: its figure would replace {png} (a result's)")
    someones = os.path.lexists(png) and not os.path.lexists(out) and not _a_reports_figure(png)
    if figure is not None and someones:
        # A report's figure is marked so, or has its report beside it (figures written before
        # the mark); any other picture there is someone's own.
        raise ReportError(f"--out {out}: its figure would replace {png}, which is no report's figure; "
                          "give another --out")  # fmt: skip
    for target in (out, png) if figure is not None else (out,):
        writable(target)  # both, before either is written: a refusal leaves the old report whole
    html = TEMPLATE.render(title=title, subtitle=f"from {path.resolve()}", sections=sections)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, html)  # a report being rewritten is never seen half-written
    if figure is not None:
        atomic_write_bytes(png, figure)
    log.info("wrote %s", out)
    return out


app = typer.Typer(help="wfnn tools for finished runs.", no_args_is_help=True)


@app.callback()
def _tools() -> None:
    """Tools for finished runs and benchmarks."""


@app.command()
def report(
    path: Annotated[
        Path,
        typer.Argument(parser=path_given, help="A run directory, a benchmark JSON, or a folder of them."),
    ],
    out: Annotated[Path | None, typer.Option(parser=file_given, help="The HTML file to write.")] = None,
) -> None:
    """Render a self-contained HTML report (and a PNG of a run's curves)."""
    try:
        written = run(ReportConfig(path=path, out=out))
    except ReportError as exc:
        typer.echo(f"error: {' '.join(str(exc).split())}", err=True)
        raise typer.Exit(2) from exc
    typer.echo(f"wrote {one_line(str(written))}")


main = guarded(app)
"""The console entry point: bad input ends in one line and a nonzero exit (`wfnn_io.cli_errors`)."""
