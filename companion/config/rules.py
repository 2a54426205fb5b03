"""Parsing of rule antecedents written as text, e.g. ``"center is near and up is not far"``.

Grammar (keywords are case-insensitive; names are lower-case identifiers)::

    antecedent := clause (connective clause)*      # one connective per rule: all "and" or all "or"
    clause     := VARIABLE "is" ["not"] TERM
    connective := "and" | "or"

Mixing ``and`` and ``or`` in one rule is rejected rather than given a precedence a reader may not
expect: write two rules instead (Mamdani aggregation ORs rules together anyway).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

_NAME = re.compile(r"^[a-z_][a-z0-9_]*$")


@dataclass(frozen=True)
class Clause:
    """One literal of an antecedent: ``variable is [not] term``."""

    variable: str
    term: str
    negated: bool = False


@dataclass(frozen=True)
class Antecedent:
    """A flat conjunction or disjunction of clauses."""

    clauses: tuple[Clause, ...]
    connective: Literal["and", "or"] = "and"

    def __str__(self) -> str:
        parts = [f"{c.variable} is {'not ' if c.negated else ''}{c.term}" for c in self.clauses]
        return f" {self.connective} ".join(parts)


def parse_antecedent(text: str) -> Antecedent:
    """Parse ``text`` into an :class:`Antecedent`.

    Raises:
        ValueError: with a message that quotes the offending part of ``text``.
    """
    tokens = text.split()
    if not tokens:
        raise ValueError("empty rule condition")
    clauses: list[Clause] = []
    connectives: set[str] = set()
    i = 0
    while True:
        if i + 3 > len(tokens):
            raise ValueError(f"incomplete clause {' '.join(tokens[i:]) or '(nothing)'!r} in {text!r}")
        variable, is_kw = tokens[i], tokens[i + 1].lower()
        if is_kw != "is":
            raise ValueError(f"expected 'is' after {variable!r}, got {tokens[i + 1]!r} in {text!r}")
        j = i + 2
        negated = False
        if tokens[j].lower() == "not":
            negated = True
            j += 1
            if j >= len(tokens):
                raise ValueError(f"missing term after 'not' in {text!r}")
        term = tokens[j]
        for kind, name in (("variable", variable), ("term", term)):
            if not _NAME.match(name):
                raise ValueError(f"bad {kind} name {name!r} in {text!r}: use lower-case letters, digits, _")
        clauses.append(Clause(variable=variable, term=term, negated=negated))
        i = j + 1
        if i == len(tokens):
            break
        conn = tokens[i].lower()
        if conn not in ("and", "or"):
            raise ValueError(f"expected 'and' or 'or', got {tokens[i]!r} in {text!r}")
        connectives.add(conn)
        i += 1
        if i == len(tokens):
            raise ValueError(f"condition ends with {conn!r} in {text!r}")
    if len(connectives) > 1:
        raise ValueError(f"mixes 'and' and 'or' in {text!r}: split it into two rules")
    connective: Literal["and", "or"] = "or" if connectives == {"or"} else "and"
    return Antecedent(clauses=tuple(clauses), connective=connective)
