"""Render the documented default config (``config/companion.toml``) from the models themselves.

Each field's description, bounds and unit live once, in the pydantic model; this module writes them as
TOML comments above the default value, and each controller rule's ``doc`` above the rule. A test keeps
the committed file equal to :func:`render_default_toml`, so the documentation cannot drift.
"""

from __future__ import annotations

import json
import math
import textwrap
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, get_args, get_origin

from pydantic import BaseModel
from pydantic.fields import FieldInfo

from companion.config._base import StrictModel

if TYPE_CHECKING:
    from companion.config import CompanionConfig

_WRAP = 98


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isinf(value) or math.isnan(value):
            raise ValueError(f"cannot write {value} to TOML")
        return repr(value)
    if isinstance(value, (str, Path)):
        return json.dumps(str(value), ensure_ascii=False)
    if isinstance(value, BaseModel):
        return _inline_table(value.model_dump(mode="python", exclude_none=True))
    if isinstance(value, dict):
        return _inline_table(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"no TOML form for {type(value).__name__}")


def _inline_table(d: dict[str, Any]) -> str:
    return "{ " + ", ".join(f"{k} = {_toml_value(v)}" for k, v in d.items()) + " }"


def _bounds(info: FieldInfo) -> str:
    parts = []
    # A union such as ``Annotated[int, Field(ge=0)] | Literal["auto"]`` keeps its bounds on its member.
    members = [m for arg in get_args(info.annotation) if get_origin(arg) is Annotated for m in get_args(arg)[1:]]
    members = [x for m in members for x in (m.metadata if isinstance(m, FieldInfo) else [m])]
    for m in [*info.metadata, *members]:
        for attr, sym in (("ge", ">="), ("gt", ">"), ("le", "<="), ("lt", "<"), ("multiple_of", "multiple of")):
            v = getattr(m, attr, None)
            if v is not None:
                parts.append(f"{sym} {v}")
    return f" [{', '.join(parts)}]" if parts else ""


def _comment(text: str, indent: str = "") -> list[str]:
    return [indent + "# " + line for line in textwrap.wrap(text, _WRAP - len(indent) - 2)]


def _section(name: str, model: StrictModel) -> list[str]:
    cls = type(model)
    lines = [f"[{name}]"]
    doc = (cls.__doc__ or "").strip().splitlines()[0] if cls.__doc__ else ""
    if doc:
        lines[:0] = _comment(doc)
    deferred: list[str] = []
    for field, info in cls.model_fields.items():
        value = getattr(model, field)
        if field in ("main_rules", "corner_rules"):
            deferred += _rules(f"{name}.{field}", value, info)
            continue
        if isinstance(value, dict) and value and all(isinstance(v, BaseModel) for v in value.values()):
            # A table of terms reads best as a sub-table, one term a line (sub-tables follow the keys).
            deferred += ["", *_comment(info.description or ""), f"[{name}.{field}]"]
            deferred += [f"{k} = {_toml_value(v)}" for k, v in value.items()]
            continue
        lines += _comment((info.description or "") + _bounds(info))
        if value is None:
            lines.append(f"# {field} = ...  (unset)")
        else:
            lines.append(f"{field} = {_toml_value(value)}")
    return lines + deferred


def _rules(table: str, rules: list[Any], info: FieldInfo) -> list[str]:
    lines = [""] + _comment(info.description or "")
    for rule in rules:
        lines.append("")
        lines.append(f"[[{table}]]")
        lines.append(f"name = {_toml_value(rule.name)}")
        lines.append(f"when = {_toml_value(rule.when)}")
        lines.append(f"then = {_toml_value(dict(rule.then))}")
        if rule.weight != 1.0:
            lines.append(f"weight = {_toml_value(rule.weight)}")
        if rule.doc:
            lines.append(f"doc = {_toml_value(rule.doc)}")
    return lines


def render_default_toml() -> str:
    """The documented default configuration as TOML text (what ``config/companion.toml`` holds)."""
    from companion.config import CompanionConfig

    cfg = CompanionConfig()
    out = [
        "# companion: the documented default configuration.",
        "#",
        "# Generated from the config models (tools/gen-default-config.py); a test keeps it equal to the",
        "# built-in defaults, so the service behaves the same with this file or with none. Copy it to",
        "# /etc/companion/companion.toml and edit. Every value carries its unit in its name; bounds are in",
        "# [brackets]. Unknown keys are rejected. Reload a running service with `companion ctl reload`",
        "# or `systemctl reload companion`.",
    ]
    return render_config_toml(cfg, out)


def render_config_toml(cfg: CompanionConfig, header: list[str]) -> str:
    """``cfg`` as documented TOML text that loads back to an equal config, after the ``header`` lines
    (comments). Settings written "auto" are written "auto" again (not as resolved for this machine)."""
    out = list(header)
    for name in type(cfg).model_fields:
        section = getattr(cfg, name)
        auto = {f: "auto" for s, f in cfg._from_auto if s == name}
        out.append("")
        out += _section(name, section.model_copy(update=auto) if auto else section)
    return "\n".join(out) + "\n"
