"""A small TOML writer for the documents acm-rs writes (readable: inline arrays and tables).

Reading uses the standard library's ``tomllib``. Supported values: str, bool, int, float
(including inf/nan), lists and dicts; top-level lists of dicts become arrays of tables and
top-level dicts become tables.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping

_BARE = re.compile(r"^[A-Za-z0-9_-]+$")


def _key(k: str) -> str:
    return k if _BARE.match(k) else json.dumps(k)


def _value(v: object) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, Mapping):
        return "{ " + ", ".join(f"{_key(str(k))} = {_value(x)}" for k, x in v.items()) + " }"
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _is_table_array(v: object) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, Mapping) for x in v)


def dumps(doc: Mapping[str, object]) -> str:
    """Serialise ``doc`` to TOML text."""
    lines: list[str] = []
    tables: list[tuple[str, Mapping]] = []
    arrays: list[tuple[str, list]] = []
    for k, v in doc.items():
        if isinstance(v, Mapping):
            tables.append((k, v))
        elif _is_table_array(v):
            arrays.append((k, v))  # type: ignore[arg-type]
        else:
            lines.append(f"{_key(k)} = {_value(v)}")
    for k, t in tables:
        lines += ["", f"[{_key(k)}]"] + [f"{_key(str(a))} = {_value(b)}" for a, b in t.items()]
    for k, arr in arrays:
        for item in arr:
            lines += ["", f"[[{_key(k)}]]"]
            lines += [f"{_key(str(a))} = {_value(b)}" for a, b in item.items()]
    return "\n".join(lines) + "\n"
