"""Field type checks shared by every config dataclass, and the one error they raise.

Its own module so that `config` and the modules `config` imports (such as `symmetry`) check their
fields the same way without importing each other.
"""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any

import numpy as np


class ConfigError(ValueError):
    """A configuration value is out of its allowed range or inconsistent."""


def _is_int(v: Any) -> bool:
    return isinstance(v, int | np.integer) and not isinstance(v, bool | np.bool_)


def _is_number(v: Any) -> bool:
    try:
        return (_is_int(v) or isinstance(v, float | np.floating)) and math.isfinite(float(v))
    except OverflowError:  # an integer beyond any float (JSON allows 1 with 400 zeros)
        return False


_CHECKS: dict[str, Any] = {
    "int": _is_int,
    "float": _is_number,
    "bool": lambda v: isinstance(v, bool | np.bool_),
    "str": lambda v: isinstance(v, str),
    "tuple[float, ...]": lambda v: isinstance(v, tuple) and all(_is_number(x) for x in v),
    "tuple[int, ...]": lambda v: isinstance(v, tuple) and all(_is_int(x) for x in v),
    "tuple[str, ...]": lambda v: isinstance(v, tuple) and all(isinstance(x, str) for x in v),
}
_WHAT = {"int": "an integer", "float": "a finite number", "bool": "true or false", "str": "a string",
         "tuple[float, ...]": "finite numbers", "tuple[int, ...]": "integers",
         "tuple[str, ...]": "strings"}  # fmt: skip


def _python_number(v: Any) -> int | float:
    """A checked number as Python's own type.

    An integer stays one, as written, so that configs and their spec hashes read as before.
    """
    return int(v) if _is_int(v) else float(v)


_CANONICAL: dict[str, Any] = {
    "int": int, "float": _python_number, "bool": bool,
    "tuple[float, ...]": lambda v: tuple(_python_number(x) for x in v),
    "tuple[int, ...]": lambda v: tuple(int(x) for x in v),
}  # fmt: skip
"""Each checked kind's values as Python's types, not numpy's (whose scalars made `to_json` fail)."""


def check_fields(config: Any) -> None:
    """Check that each int, float, bool or str field (or tuple of them) of a config holds that type.

    Floats must be finite (NaN and infinity are refused); `X | None` fields may also be None. Each
    value is then held as Python's type (`_CANONICAL`).

    Called first in each config's `__post_init__`, so a config made from a file, a command line
    or the network is checked the same way; each config then checks its own ranges.
    """
    for f in dataclasses.fields(config):
        kind = str(f.type).replace(" | None", "")
        check = _CHECKS.get(kind)
        value = getattr(config, f.name)
        if check is None or (value is None and str(f.type).endswith("| None")):
            continue
        if not check(value):
            what = f"{type(config).__name__}.{f.name}"
            raise ConfigError(f"{what} must be {_WHAT[kind]}, got {cut_repr(value)}")
        if kind in _CANONICAL:
            object.__setattr__(config, f.name, _CANONICAL[kind](value))  # frozen dataclasses too


def cut_repr(value: Any, most: int = 200) -> str:
    """`value`'s repr for a refusal, cut to `most` characters with "..." (it may be of any length)."""
    shown = repr(value)
    return shown if len(shown) <= most else shown[:most] + "..."


def parse_json(text: str | bytes, what: str, max_bytes: int = 1 << 20) -> Any:
    """JSON text -> value; anything wrong (too long, not JSON, nested too deep) is a ConfigError."""
    if len(text) > max_bytes:
        raise ConfigError(f"{what}: {len(text)} bytes is more than {max_bytes}")
    try:
        return json.loads(text)
    except (ValueError, RecursionError, TypeError) as exc:
        raise ConfigError(f"{what}: not JSON ({type(exc).__name__}: {str(exc)[:200]})") from None
