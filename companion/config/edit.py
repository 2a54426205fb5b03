"""Set one key of a TOML config file in place, keeping everything else (comments, order, layout).

The calibration commands write their result into the user's config (``lut.points_m``,
``calibration.file``); rewriting the whole file from the models would drop the user's comments. This
is a small line-level editor for the simple TOML the project writes (``[table]`` headers, ``key =
value`` lines whose arrays may span lines); the result is parsed and validated whole before it is
written, so an edit this editor cannot make safely is an error, never a damaged file.
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path
from typing import Any

from companion.config.document import _toml_value
from companion.errors import ConfigError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on 3.10 only
    import tomli as tomllib

__all__ = ["set_config_value", "set_config_value_in_file", "toml_value"]

_HEADER = re.compile(r"^\s*\[\s*([A-Za-z0-9_.\-]+)\s*\]\s*(#.*)?$")
_ANY_HEADER = re.compile(r"^\s*\[\[?\s*[A-Za-z0-9_.\-\"' ]+\s*\]\]?\s*(#.*)?$")


def toml_value(value: Any) -> str:
    """``value`` (bool, number, string, path, list, table) as a TOML value."""
    return _toml_value(value)


def _depth_change(line: str) -> int:
    """Net bracket depth of a line's value part, ignoring strings and comments."""
    depth = 0
    quote: str | None = None
    escaped = False
    for ch in line:
        if quote is not None:
            if escaped:
                escaped = False
            elif ch == "\\" and quote == '"':
                escaped = True
            elif ch == quote:
                quote = None
            continue
        if ch in "\"'":
            quote = ch
        elif ch == "#":
            break
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
    return depth


def set_config_value(text: str, section: str, key: str, value: Any, *, source: str = "config") -> str:
    """``text`` (a TOML document) with ``[section] key = value``: the key's line (and the lines its
    value spans) replaced, or added under the section's header, or a new section at the end.

    Raises:
        ConfigError: the document is not TOML, sets the key in a form this editor does not rewrite
            (a dotted key, an inline table), or the result does not hold the value.
    """
    try:
        before = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{source}: not valid TOML: {err}", source=source) from None
    table = before.get(section)
    if table is not None and not isinstance(table, dict):
        raise ConfigError(f"{source}: {section} is not a table", source=source)
    new_line = f"{key} = {toml_value(value)}"
    lines = text.splitlines()
    # Find the section's header and its extent (to the next header), tracking multi-line values.
    start = end = None
    depth = 0
    for i, line in enumerate(lines):
        if depth == 0 and _ANY_HEADER.match(line):
            m = _HEADER.match(line)
            if start is not None and end is None:
                end = i
            if m is not None and m.group(1).strip() == section and start is None:
                start = i
        depth += _depth_change(line)
    if start is not None and end is None:
        end = len(lines)
    key_re = re.compile(rf"^\s*{re.escape(key)}\s*=")
    if start is None:
        if table is not None:
            raise ConfigError(
                f"{source}: [{section}] is written in a form this editor does not change (a dotted key or an inline "
                f"table); set {section}.{key} by hand",
                source=source,
            )
        if lines and lines[-1].strip():
            lines.append("")
        lines += [f"[{section}]", new_line]
    else:
        assert end is not None
        found = None
        depth = 0
        for i in range(start + 1, end):
            if depth == 0 and key_re.match(lines[i]):
                found = i
                break
            depth += _depth_change(lines[i])
        if found is None:
            if table is not None and key in table:
                raise ConfigError(
                    f"{source}: {section}.{key} is set in a form this editor does not change; set it by hand",
                    source=source,
                )
            lines.insert(start + 1, new_line)
        else:
            last = found
            depth = _depth_change(lines[found])
            while depth > 0 and last + 1 < end:
                last += 1
                depth += _depth_change(lines[last])
            lines[found : last + 1] = [new_line]
    out = "\n".join(lines) + "\n"
    try:
        after = tomllib.loads(out)
    except tomllib.TOMLDecodeError as err:  # pragma: no cover - the editor's own bug; never written
        raise ConfigError(f"{source}: editing {section}.{key} would break the file ({err}); set it by hand") from None
    if tomllib.loads(f"v = {toml_value(value)}")["v"] != after.get(section, {}).get(key):
        raise ConfigError(f"{source}: could not set {section}.{key} safely; set it by hand", source=source)
    return out


def set_config_value_in_file(path: Path, section: str, key: str, value: Any) -> None:
    """:func:`set_config_value` on a file (created when missing), validated as a whole config before
    it replaces the file (atomically, through a temporary file beside it).

    Raises:
        ConfigError: unreadable or invalid file, an edit that cannot be made safely, or a result that
            is not a valid config (nothing is written then).
    """
    from companion.config import parse_config

    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8") if path.exists() else ""
    except OSError as err:
        raise ConfigError(f"{path}: cannot read config: {err.strerror or err}", source=str(path)) from None
    out = set_config_value(text, section, key, value, source=str(path))
    parse_config(tomllib.loads(out), source=str(path))
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(out, encoding="utf-8")
        if path.exists():
            os.chmod(tmp, path.stat().st_mode & 0o7777)
        tmp.replace(path)
    except OSError as err:
        raise ConfigError(f"{path}: cannot write config: {err.strerror or err}", source=str(path)) from None
