"""How the command-line tools end on bad input: one clear line, a nonzero exit, no traceback.

Each tool's entry point is `guarded(app)`: a file that cannot be read or written, a port in
use, a malformed endpoint or config (OSError, ValueError and their kinds) ends the run with
`error: <what>` and exit code 2, as does an error raised from an OSError (a record that a full
disk stopped); anything else with exit code 1 and the same one line.
`--verbose` adds the traceback for whoever debugs it.

What else the tools share about their console lives here too: how often a status line is
written where the output is no terminal (`Every`), and text from outside (names off the network,
a damaged file's bytes) shown without the control characters that drive a terminal (`printable`,
`log_printably`).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

_CONTROLS = {c: f"\\x{c:02x}" for c in (*range(0x20), *range(0x7F, 0xA0)) if chr(c) not in "\n\t"}
_ONE_LINE = {**_CONTROLS, ord("\n"): "\\n"}


def printable(text: str) -> str:
    """`text` with its control characters shown as escapes (ESC as backslash x1b); newlines and tabs kept.

    Client ids are checked, but other names (who chose an action, a config's field names) come
    off the network or out of a file as any text: an escape sequence printed as it is would
    drive the operator's terminal (clear it, set its title or clipboard).
    """
    return text.translate(_CONTROLS)


def one_line(text: str) -> str:
    """`printable`, with newlines shown as escapes too: what is printed as one line stays one.

    A path or name holding a newline (any file name may) printed as it is would start a line of
    its own choosing, such as a forged `error:` line or log record.
    """
    return text.translate(_ONE_LINE)


class _Printable(logging.Filter):
    """Log records rendered with `one_line` (their arguments may come from anywhere)."""

    def filter(self, record: logging.LogRecord) -> bool:
        try:
            message = record.getMessage()
        except Exception:  # a call whose arguments do not fit: the handler reports it, as without us
            return True
        clean = one_line(message)
        if clean != message:
            record.msg, record.args = clean, None
        return True


def log_failure(logger: logging.Logger, message: str, exc: BaseException) -> None:
    """Log what ended a tool's thread.

    An OSError (a full disk, a lost directory), or an error raised from one, in one line, its
    traceback only at debug level (`--verbose`): the tool's one `error:` line follows. Anything
    else with its traceback.
    """
    if environmental(exc):
        logger.error("%s (%s)", message, describe(exc))
        logger.debug("where", exc_info=exc)
    else:
        logger.error(message, exc_info=exc)


def environmental(exc: BaseException) -> bool:
    """Whether `exc` is an OSError or was raised from one (a record that a full disk stopped).

    Such an error is the machine's, not a fault in the tool: one line and exit code 2.
    """
    return isinstance(exc, OSError) or isinstance(exc.__cause__, OSError)


def log_printably() -> None:
    """Show every log record through `printable` (call once the tool's handlers are set up)."""
    for handler in logging.getLogger().handlers:
        if not any(isinstance(f, _Printable) for f in handler.filters):
            handler.addFilter(_Printable())


def describe(exc: BaseException) -> str:
    """One line: the error and the errors that caused it (`a: b: c`)."""
    parts: list[str] = []
    seen: set[int] = set()
    current: BaseException | None = exc
    effect: BaseException | None = None
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        if not _renamed(current, effect):
            parts.append(_one(current))
        effect = current
        current = current.__cause__ or (None if current.__suppress_context__ else current.__context__)
    # A cause its error already quotes ("unreadable (X)" caused by X) is not said twice.
    text = ": ".join(p for i, p in enumerate(parts) if p and not any(p in q for q in parts[:i]))
    return " ".join(text.split())


def _renamed(cause: BaseException, effect: BaseException | None) -> bool:
    """Whether `cause` is the OS error `effect` says again, naming the file asked for.

    `persist.naming_file`'s: a temporary file's name means nothing to the user. Other causes,
    of the same errno or not, are said.
    """
    return effect is not None and getattr(effect, "renamed_from", None) is cause


def path_given(value: str | Path) -> Path:
    """A path from the command line (typer's `parser`): an empty one is refused.

    `Path("")` is the current directory, so `--out ""` would write a run there without a word.
    """
    if isinstance(value, Path):
        return value  # a default
    if not value:
        raise ValueError("an empty path (give one; '.' names the current directory)")
    return Path(value)


def file_given(value: str | Path) -> Path:
    """A file to write, from the command line: as `path_given`, and one ending in a slash refused.

    Such a name is a folder's; `Path` would drop the slash unsaid and write a file there.
    """
    if isinstance(value, Path):
        return value  # a default
    path = path_given(value)
    if value.endswith(("/", os.sep)):
        raise ValueError(f"{value}: names a folder (a file's name is needed here)")
    return path


def _one(exc: BaseException) -> str:
    if (isinstance(exc, FileExistsError) and exc.filename is not None and os.path.isfile(exc.filename)
            and exc.strerror == os.strerror(errno.EEXIST)):  # fmt: skip
        # The OS's own words where a directory had to be made (an output path through a file): say
        # so. A refusal of ours to replace a file says why itself.
        return f"{exc.filename}: a file is in the way (a directory is needed there)"
    if isinstance(exc, OSError) and exc.strerror:
        where = f"{exc.filename}: " if exc.filename is not None else ""
        return f"{where}{exc.strerror}"
    text = str(exc)
    if isinstance(exc, KeyError | RecursionError | MemoryError) or not text:
        return f"{type(exc).__name__}: {text}" if text else type(exc).__name__
    return text


class Terminated(KeyboardInterrupt):
    """A run stopped by a signal such as SIGTERM, as Ctrl-C stops it (cleanly), keeping its number.

    The tool then exits as the signal's status (128 + its number), as a supervisor expects of a
    stop. Typer turns any KeyboardInterrupt into exit 130, so the number is also noted here.
    """

    def __init__(self, signum: int) -> None:
        super().__init__(f"signal {signum}")
        self.signum = signum
        _terminated.append(signum)


_terminated: list[int] = []
"""Signals that raised `Terminated` in this process."""


def _exit_code(code: int) -> int:
    """A tool's exit status: an interrupt's (130) is the terminating signal's where one was."""
    return 128 + _terminated[-1] if code == 130 and _terminated else code


def guarded(app: Callable[[], Any]) -> Callable[[], None]:
    """An entry point that runs `app` and turns an escaping exception into one line on stderr."""

    def main() -> None:
        _terminated.clear()  # a signal that ended an earlier run in this process is not this one's
        # SIGTERM (`kill`, a supervisor's stop) ends a tool as Ctrl-C does, so that what it does on
        # the way out is done: the servers a benchmark started stopped, a log being written removed.
        # A tool that serves installs its own handler meanwhile; an ignored SIGTERM stays ignored.
        with handling(terminate, signal.SIGTERM, keep_ignored=True):
            try:
                _invoke(app)
            except KeyboardInterrupt:
                print("terminated" if _terminated else "interrupted", file=sys.stderr)
                sys.exit(_exit_code(130))
            except (OSError, ValueError) as exc:
                _report(exc, 2)
            except Exception as exc:
                if _usage_error(exc):
                    return
                _report(exc, 2 if _symlink_loop(exc) or environmental(exc) else 1)

    return main


def terminate(signum: int, frame: object) -> None:
    """A signal handler: the signal ends the run as Ctrl-C does, cleanly (`Terminated`)."""
    raise Terminated(signum)


@contextlib.contextmanager
def handling(
    handler: Callable[[int, Any], None], *signums: int, keep_ignored: bool = False
) -> Iterator[None]:
    """`handler` for `signums` meanwhile, then the handlers before put back.

    Only the main thread can set a handler; elsewhere (an embedding program's thread) the signals
    are left as they are. With `keep_ignored`, an ignored signal stays ignored. Each handler is
    put back even where a signal raises while an earlier one is (one left only noted a Ctrl-C).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous: list[tuple[int, Any]] = []
    try:
        for signum in signums:
            if not (keep_ignored and signal.getsignal(signum) is signal.SIG_IGN):
                previous.append((signum, signal.signal(signum, handler)))
        yield
    finally:
        _put_back(previous)


@contextlib.contextmanager
def noting(*signums: int, keep_ignored: bool = False) -> Iterator[list[int]]:
    """`signums` only noted meanwhile (see `handling`) -> the list of those that came, in order."""
    noted: list[int] = []
    with handling(lambda signum, _frame: noted.append(signum), *signums, keep_ignored=keep_ignored):
        yield noted


def raise_noted(signum: int) -> None:
    """End the run as a signal that was only noted (`noting`) would have ended it; 0: none came."""
    if signum == signal.SIGINT:
        raise KeyboardInterrupt
    if signum:
        raise Terminated(signum)


@contextlib.contextmanager
def interrupts_after() -> Iterator[None]:
    """Ctrl-C and SIGTERM held until the block ends, then raised as they came (ignored ones stay so).

    For work that must not stop half-made (a learner's update): raised inside compiled code, the
    interrupt also came back wrapped in another error (numba's SystemError).
    """
    with noting(signal.SIGINT, signal.SIGTERM, keep_ignored=True) as noted:
        yield
    raise_noted(noted[0] if noted else 0)


def interrupt_behind(exc: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C or SIGTERM (`Terminated`) that `exc` is, or was raised from, if any.

    An interrupt raised inside compiled code comes back as the cause of another error (numba's
    "returned a result with an exception set" SystemError).
    """
    seen: set[int] = set()
    at: BaseException | None = exc
    while at is not None and id(at) not in seen:
        if isinstance(at, KeyboardInterrupt):
            return at
        seen.add(id(at))
        at = at.__cause__ or at.__context__
    return None


def _put_back(handlers: list[tuple[int, Any]]) -> None:
    if handlers:
        (signum, handler), rest = handlers[0], handlers[1:]
        try:
            signal.signal(signum, handler if handler is not None else signal.SIG_DFL)
        finally:
            _put_back(rest)


def _invoke(app: Callable[[], Any]) -> None:
    """Run `app`; a Typer app without its own error display, so that usage errors end in one line."""
    import typer
    import typer.main

    if not isinstance(app, typer.Typer):
        app()
        return
    code = typer.main.get_command(app).main(standalone_mode=False)
    if type(code) is int and code:  # an explicit exit (typer.Exit) with a nonzero code
        sys.exit(_exit_code(code))


def _usage_error(exc: Exception) -> bool:
    """A command-line usage error (an unknown option, an invalid value) ends in one line, exit 2.

    Typer's own display draws a box of several lines around it; asked for no arguments, a tool
    that shows its help does so.
    """
    import typer

    if not isinstance(exc, typer.TyperException):
        return False
    if type(exc).__name__ == "NoArgsIsHelpError":
        exc.show()  # type: ignore[attr-defined]
    else:
        message = exc.format_message() if hasattr(exc, "format_message") else str(exc)
        print(f"error: {printable(' '.join(message.split()))} (--help lists the options)", file=sys.stderr)
    sys.exit(int(getattr(exc, "exit_code", 2)))


def _symlink_loop(exc: BaseException) -> bool:
    """A path given that loops through symbolic links: bad input, as any path that cannot be used.

    Python 3.11's `Path.resolve` says so with a RuntimeError (later Pythons with an OSError, ELOOP).
    """
    return isinstance(exc, RuntimeError) and str(exc).startswith("Symlink loop from ")


def _report(exc: BaseException, code: int) -> None:
    if "--verbose" in sys.argv:
        traceback.print_exception(exc)
    hint = "" if "--verbose" in sys.argv or code == 2 else " (--verbose shows where)"
    print(f"error: {printable(describe(exc))}{hint}", file=sys.stderr)
    sys.exit(code)


STATUS_LINE_EVERY_S = 30.0
"""How often a tool whose output is not a terminal (a log file, a pipe) writes its status line."""


class Every:
    """Do something at most once every `period_s` seconds (the first time at once).

    For status lines written to a file: a progress bar redraws one line in place, which a file
    receives only when the work ends.
    """

    def __init__(self, period_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.period_s, self.clock = period_s, clock
        self._last: float | None = None

    def __call__(self, action: Callable[[], object], now: bool = False) -> None:
        """Run `action` if `period_s` has passed since the last time (or `now`)."""
        t = self.clock()
        if now or self._last is None or t - self._last >= self.period_s:
            self._last = t
            action()
