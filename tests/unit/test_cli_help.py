"""Every command line tool's help says what its source says.

Typer renders help with rich, which reads "[...]" as markup and drops it without a word: a help
text's "[thesis 0.2]" printed as nothing. The texts must come through whole.
"""

from __future__ import annotations

import importlib
from typing import Any

import pytest
import typer
from rich.text import Text

APPS = [
    "wfnn_client.cli",
    "wfnn_server.cli",
    "wfnn_server.router",
    "wfnn_bench.cli",
    "wfnn_bench.report",
    "wfnn_io.logs_cli",
]


def _help_texts(command: Any, path: str) -> list[tuple[str, str]]:
    """(where, text) for the help of a command, its options and arguments, and its subcommands."""
    texts = [(path, command.help or ""), (path, command.short_help or "")]
    for param in command.params:
        texts.append((f"{path} {param.name}", getattr(param, "help", None) or ""))
    for name, sub in getattr(command, "commands", {}).items():
        texts.extend(_help_texts(sub, f"{path} {name}"))
    return texts


@pytest.mark.parametrize("module", APPS)
def test_help_texts_come_through_rich_markup_whole(module: str) -> None:
    app = importlib.import_module(module).app
    assert isinstance(app, typer.Typer)
    texts = _help_texts(typer.main.get_command(app), module)
    assert len(texts) > 3, "the walk found no options"
    eaten = [(where, text) for where, text in texts if Text.from_markup(text).plain != text]
    assert not eaten, f"rich markup drops part of these help texts: {eaten}"


@pytest.mark.parametrize(
    ("module", "argv"),
    [
        ("wfnn_client.cli", ["--sim", "nope"]),  # a value its own check refuses
        ("wfnn_client.cli", ["--rate-hz", "abc"]),  # a value of the wrong type
        ("wfnn_bench.cli", ["boat", "--mode", "foo"]),
        ("wfnn_bench.cli", ["boat", "--controllers", "99999999999999999999"]),  # named, not numpy's limit
        # Budgets that numpy refused only after the run had begun (a server started and stopped):
        ("wfnn_bench.cli", ["boat", "--targets", "100000000000"]),
        ("wfnn_bench.cli", ["transport", "--experiences", "99999999999"]),
        ("wfnn_bench.cli", ["speed", "--act-calls", "99999999999999"]),
        ("wfnn_io.logs_cli", ["inspect"]),  # a missing argument
        ("wfnn_server.cli", ["--no-such-option"]),
        ("wfnn_client.cli", ["--out", ""]),  # an empty path is not the current directory
        ("wfnn_server.cli", ["--data-dir", ""]),
        ("wfnn_io.logs_cli", ["merge", "a", "--out", ""]),
    ],
)
def test_a_usage_error_ends_in_one_error_line(module, argv, monkeypatch, capsys):
    main = importlib.import_module(module).main
    monkeypatch.setattr("sys.argv", [module, *argv])
    with pytest.raises(SystemExit) as ended:
        main()
    assert ended.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and "Traceback" not in err, err


def test_help_still_shows_and_ends_well(monkeypatch, capsys):
    main = importlib.import_module("wfnn_bench.cli").main
    monkeypatch.setattr("sys.argv", ["wfnn-bench", "--help"])
    main()  # no SystemExit: exit code 0
    assert "Usage" in capsys.readouterr().out


def test_an_output_path_through_a_file_is_said_so_in_one_line(tmp_path, monkeypatch, capsys):
    (tmp_path / "afile").write_text("x")
    main = importlib.import_module("wfnn_bench.cli").main
    monkeypatch.setattr("sys.argv", ["wfnn-bench", "speed", "--json", str(tmp_path / "afile" / "x.json")])
    with pytest.raises(SystemExit) as ended:
        main()
    assert ended.value.code == 2
    said = f"error: {tmp_path / 'afile'}: a file is in the way (a directory is needed there)\n"
    assert capsys.readouterr().err == said


@pytest.mark.parametrize(
    "argv",
    [
        ["cartpole", "--json", "{d}/x.png", "--plot", "{d}/x.png"],
        ["cartpole", "--json", "{d}/x.png", "--plot", "{d}/sub/../x.png"],
        ["hydra", "--json", "{d}/r_cameras.png", "--plot", "{d}/r.png"],  # the plot's camera pictures
    ],
)
def test_two_outputs_in_one_file_are_refused_before_the_run(tmp_path, monkeypatch, capsys, argv):
    """The last written replaced the other: a JSON result lost under its own plot."""
    main = importlib.import_module("wfnn_bench.cli").main
    monkeypatch.setattr("sys.argv", ["wfnn-bench", *(a.format(d=tmp_path) for a in argv)])
    with pytest.raises(SystemExit) as ended:
        main()
    assert ended.value.code == 2 and "would be written to one file" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_a_refused_benchmark_makes_no_output_folder(tmp_path, monkeypatch, capsys):
    main = importlib.import_module("wfnn_bench.cli").main
    argv = ["wfnn-bench", "boat", "--mode", "bogus", "--json", str(tmp_path / "a/b/x.json")]
    monkeypatch.setattr("sys.argv", argv)
    with pytest.raises(SystemExit):
        main()
    assert list(tmp_path.iterdir()) == []


def test_a_path_that_loops_through_symbolic_links_is_bad_input_said_in_one_line(
    tmp_path, monkeypatch, capsys
):
    """Python 3.11's Path.resolve says so with a RuntimeError: it ended as an internal error, exit 1."""
    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    main = importlib.import_module("wfnn_bench.cli").main
    monkeypatch.setattr("sys.argv", ["wfnn-bench", "speed", "--json", str(tmp_path / "a" / "x.json")])
    with pytest.raises(SystemExit) as ended:
        main()
    said = capsys.readouterr().err
    assert ended.value.code == 2 and said.startswith("error: ") and len(said.splitlines()) == 1
    assert "--verbose" not in said and "ymbolic link" in said
