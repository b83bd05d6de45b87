"""The tools' entry points: a tool's module is imported under the care its run is given.

Importing a tool (numpy, Zenoh, MuJoCo, for some torch) takes up to a second, before its own
handling of Ctrl-C (`cli_errors.guarded`) is in place: a Ctrl-C then printed a Python traceback
of the import, where a moment later it ends the tool in one line, `interrupted`, exit 130. The
console scripts point at the packages' `main` functions made here, which import nothing heavy.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable


def tool(module: str, entry: str = "main") -> Callable[[], None]:
    """An entry point that imports `module` and runs its `entry`; a Ctrl-C meanwhile ends it in one line."""

    def main() -> None:
        try:
            run: Callable[[], None] = getattr(importlib.import_module(module), entry)
        except KeyboardInterrupt:
            print("interrupted", file=sys.stderr)
            sys.exit(130)
        run()

    main.__doc__ = f"`{module}.{entry}`, imported under the tool's care."
    return main
