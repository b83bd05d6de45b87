"""One-line errors of the tools (`wfnn_io.cli_errors`)."""

import pytest

from wfnn_io.cli_errors import describe


def _chained(outer: str, inner: Exception) -> Exception:
    try:
        try:
            raise inner
        except Exception as exc:
            raise ValueError(outer) from exc
    except ValueError as exc:
        return exc


def test_a_cause_is_named_once_even_when_its_error_quotes_it():
    inner = ValueError("Expecting value: line 1 column 2")
    assert describe(_chained("log.json: unreadable (Expecting value: line 1 column 2)", inner)) == (
        "log.json: unreadable (Expecting value: line 1 column 2)"
    )
    assert describe(_chained("cannot load w.npz", ValueError("not a zip"))) == "cannot load w.npz: not a zip"
    missing = FileNotFoundError(2, "No such file or directory", "x.npz")
    assert describe(_chained("weights", missing)) == "weights: x.npz: No such file or directory"


def test_a_cause_of_the_same_os_error_naming_another_file_is_still_said(tmp_path):
    """Only the temporary file `naming_file` renamed is left unsaid: another file's error of the
    same errno (a fallback that failed too) and errors without an errno are causes to tell."""
    try:
        try:
            open(tmp_path / "nope" / "weights.npz")
        except OSError:
            open(tmp_path / "nope" / "backup.npz")
    except OSError as exc:
        said = describe(exc)
    assert "backup.npz: No such file" in said and "weights.npz: No such file" in said
    jpeg = OSError("cannot write mode RGBA as JPEG")
    assert describe(_chained("x", jpeg)) == "x: cannot write mode RGBA as JPEG"
    png = OSError("PNG encoding failed")
    png.__cause__ = OSError("cannot write mode RGBA as JPEG")
    assert describe(png) == "PNG encoding failed: cannot write mode RGBA as JPEG"


def test_a_write_that_fails_names_the_file_asked_for_not_a_temporary_one(tmp_path):
    from pathlib import Path

    import pytest

    from wfnn_io.persist import atomic_write_text, writable

    (tmp_path / "dir").mkdir()
    for write in (atomic_write_text, lambda p, _: writable(p)):
        for target in (tmp_path / "dir", Path("/proc/wfnn-test.json")):  # /proc takes no new file
            with pytest.raises(OSError) as info:
                write(target, "x")
            assert describe(info.value).startswith(f"{target}: "), describe(info.value)
            assert ".tmp" not in describe(info.value)  # nor the cause that named it
    assert [p.name for p in tmp_path.iterdir()] == ["dir"]  # nothing left beside it


def test_a_run_ended_by_sigterm_exits_143_and_a_later_ctrl_c_in_the_process_still_130(capsys):
    import pytest

    from wfnn_io.cli_errors import Terminated, guarded

    def terminated() -> None:
        raise Terminated(15)

    def interrupted() -> None:
        raise KeyboardInterrupt

    for app, code, said in ((terminated, 143, "terminated"), (interrupted, 130, "interrupted")):
        with pytest.raises(SystemExit) as stopped:
            guarded(app)()
        assert stopped.value.code == code and said in capsys.readouterr().err


def test_sigterm_ends_a_tool_as_ctrl_c_does_and_its_handler_is_restored_after(capsys):
    """Killed by the default action, a tool left what it was writing, and a benchmark its servers."""
    import os
    import signal
    import time

    import pytest

    from wfnn_io.cli_errors import guarded

    cleaned = []

    def app() -> None:
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)  # the handler raises here
        finally:
            cleaned.append(True)

    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(SystemExit) as stopped:
        guarded(app)()
    assert stopped.value.code == 143 and "terminated" in capsys.readouterr().err and cleaned
    assert signal.getsignal(signal.SIGTERM) is before


def test_an_error_raised_from_a_full_disk_is_the_machines_one_line_and_exit_2(capsys, caplog):
    import errno
    import logging

    import pytest

    from wfnn_io.cli_errors import guarded, log_failure

    def recorded() -> None:
        try:
            raise OSError(errno.ENOSPC, "No space left on device")
        except OSError as exc:
            raise RuntimeError("writing the experience record failed") from exc

    def faulty() -> None:
        raise RuntimeError("a fault in the tool")

    for app, code in ((recorded, 2), (faulty, 1)):
        with pytest.raises(SystemExit) as stopped:
            guarded(app)()
        err = capsys.readouterr().err
        assert stopped.value.code == code and len(err.strip().splitlines()) == 1
        assert ("--verbose shows where" in err) == (code == 1)
    logger = logging.getLogger("test_full_disk")
    with caplog.at_level(logging.INFO, logger="test_full_disk"):
        for app in (recorded, faulty):
            try:
                app()
            except RuntimeError as exc:
                log_failure(logger, "stopping failed too", exc)
    full, fault = caplog.records
    assert full.exc_info is None and "No space left on device" in full.getMessage()
    assert fault.exc_info is not None


def test_a_file_to_write_named_with_a_trailing_slash_is_refused_before_anything_runs(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    import pytest

    from wfnn_io.cli_errors import file_given

    assert file_given(str(tmp_path / "a.json")) == tmp_path / "a.json"
    with pytest.raises(ValueError, match="names a folder"):
        file_given(f"{tmp_path / 'a.json'}/")
    out = f"{tmp_path / 'speed.json'}/"
    command = [sys.executable, "-m", "wfnn_bench.cli", "speed", "--json", out]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120, cwd=Path(__file__).parents[3])
    assert done.returncode == 2 and "names a folder" in done.stderr and list(tmp_path.iterdir()) == []


def test_a_ctrl_c_while_a_tool_is_imported_ends_it_in_one_line(tmp_path, monkeypatch, capsys):
    """A Ctrl-C in a tool's first second (its imports) printed a Python traceback of the import."""
    from wfnn_io.launch import tool

    (tmp_path / "slow_tool.py").write_text("raise KeyboardInterrupt\n")  # as a Ctrl-C mid-import
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(SystemExit) as stop:
        tool("slow_tool")()
    assert stop.value.code == 130 and capsys.readouterr().err == "interrupted\n"
    (tmp_path / "fine_tool.py").write_text("def main():\n    print('ran')\n")
    tool("fine_tool")()
    assert capsys.readouterr().out == "ran\n"


def test_every_console_script_imports_its_tool_under_that_care():
    import importlib
    import tomllib
    from pathlib import Path

    scripts = tomllib.loads(Path("pyproject.toml").read_text())["project"]["scripts"]
    assert set(scripts) == {"wfnn-client", "wfnn-server", "wfnn-router", "wfnn-bench", "wfnn-logs", "wfnn"}
    for target in scripts.values():
        package, name = target.split(":")
        assert "." not in package  # a package's own light module, not the tool's
        main = getattr(importlib.import_module(package), name)
        assert main.__qualname__ == "tool.<locals>.main", target


def test_a_usage_errors_control_characters_are_shown_as_escapes(capsys):
    """A bad --env's name came back through Gymnasium's message with its ESC as it was: the
    operator's terminal took the rest as a command (it set its title)."""
    import pytest
    import typer

    from wfnn_io.cli_errors import guarded

    def bad() -> None:
        raise typer.BadParameter("cannot make 'Pend\x1b]0;pwned\x07ulum-v1'", param_hint="--env")

    with pytest.raises(SystemExit) as stopped:
        guarded(bad)()
    err = capsys.readouterr().err
    assert stopped.value.code == 2 and "\x1b" not in err and "\x07" not in err and "\\x1b]0;pwned" in err


def test_a_connect_endpoint_of_port_0_is_refused_and_a_listen_one_taken():
    import pytest

    from wfnn_io.bus import NetConfig

    NetConfig(listen=("tcp/127.0.0.1:0",))
    with pytest.raises(ValueError, match="port 0 is no port to connect to"):
        NetConfig(connect=("tcp/127.0.0.1:0",))
