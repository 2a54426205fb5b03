"""Fuzzy logic: the rule parser, fuzzy sets, a generic compiled Mamdani engine and the avoidance controller."""

from companion.core.fuzzy.avoidance import AvoidanceController, build_system
from companion.core.fuzzy.engine import (
    FuzzySystem,
    InferenceResult,
    InputVariable,
    OutputVariable,
    Rule,
    Term,
)
from companion.core.fuzzy.sets import (
    defuzzify,
    fuzzy_and,
    fuzzy_not,
    fuzzy_or,
    gaussian,
    implicate,
    left_shoulder,
    membership,
    right_shoulder,
    trapezoid,
    triangle,
)
from companion.config.rules import Antecedent, Clause, parse_antecedent

__all__ = [
    "Antecedent",
    "AvoidanceController",
    "Clause",
    "FuzzySystem",
    "InferenceResult",
    "InputVariable",
    "OutputVariable",
    "Rule",
    "Term",
    "build_system",
    "defuzzify",
    "fuzzy_and",
    "fuzzy_not",
    "fuzzy_or",
    "gaussian",
    "implicate",
    "left_shoulder",
    "membership",
    "parse_antecedent",
    "right_shoulder",
    "trapezoid",
    "triangle",
]
