"""Settings that no longer exist, and what replaces each, so that a config written for an earlier
version is refused with the way forward rather than "unknown key".

The rule stack (course hold, the obstacle memory's guard, the detour layer and the command shapers)
was removed: the local planner (``[planner]``) is the only layer that turns the fuzzy decision into
setpoints. A file or a live change that still names one of its settings is refused, in one line that
names each and says what to do (:func:`removed_message`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from types import MappingProxyType

#: What the local planner is, for the messages.
_PLANNER = "the local planner ([planner]) replaces it"

#: Whole sections that were removed: section -> what to do.
REMOVED_SECTIONS: Mapping[str, str] = MappingProxyType(
    {
        "detour": f"removed with the rule stack; {_PLANNER} (it finds the way round on its own map) — delete the section",
        "memory": (
            f"removed with the rule stack; {_PLANNER} (it keeps its own map: planner.occupied_memory_s, "
            "free_memory_s; block_px and block_erode_px are planner.block_px and planner.block_erode_px now) "
            "— delete the section"
        ),
    }
)

#: Settings that moved: old dotted path -> new dotted path (same meaning, same unit).
MOVED_KEYS: Mapping[str, str] = MappingProxyType(
    {
        "command.cruise_speed_m_s": "planner.cruise_speed_m_s",
        "command.max_yaw_rate_deg_s": "planner.max_yaw_rate_deg_s",
        "command.max_vertical_speed_m_s": "planner.max_vertical_speed_m_s",
        "command.min_altitude_m": "planner.floor_m",
        "command.avoid_speed_fraction": "controller.avoid_speed_fraction",
        "command.avoid_speed_regions": "controller.avoid_speed_regions",
        "command.no_progress_timeout_s": "planner.no_progress_distance_m (a distance flown at cruise)",
    }
)

#: Settings removed with nothing in their place: dotted path -> what to do.
_RULE_STACK_COMMAND = (
    "heading_hold_gain_per_s max_heading_hold_rate_deg_s turn_back_after_clear_s turn_back_angle_deg "
    "line_hold_gain_per_m max_line_hold_angle_deg line_hold_lateral_gain_per_s max_line_hold_lateral_speed_m_s "
    "standoff_depth_m standoff_gain_per_s max_standoff_speed_m_s line_hold_lateral_clear_depth_m "
    "line_hold_lateral_max_aim_error_deg sideways_clear_depth_m altitude_hold_gain_per_s altitude_hold_on_avoid "
    "max_altitude_hold_speed_m_s hold_resume_delay_s hold_resume_distance_m brake_hold_gain_per_s "
    "brake_hold_max_speed_m_s regress_distance_m regress_timeout_s goal_radius_m hold_clear_depth_m "
    "motion_brake_clearance_m motion_brake_lag_s unseen_closing_range_m unseen_closing_window_s "
    "unseen_closing_min_m_s unseen_closing_max_yaw_rate_deg_s unseen_closing_max_step_m "
    "unseen_closing_max_fit_error_m unseen_closing_hold_s max_unseen_closing_counter_m_s "
    "track_velocity_window_s track_counter_fraction max_track_counter_m_s"
).split()
REMOVED_KEYS: Mapping[str, str] = MappingProxyType(
    {
        "planner.kind": "removed: the local planner is the only decision layer — delete the line",
        "envelope.memory_may_be_off": "removed with the obstacle memory — delete the line",
        "envelope.brake_hold_may_be_off": "removed with the brake's position hold — delete the line",
        **{f"command.{name}": "" for name in _RULE_STACK_COMMAND},
    }
)


def is_removed(path: str) -> bool:
    """Whether the dotted ``path`` (a section, or ``section.key``) names a removed setting."""
    return path in REMOVED_SECTIONS or path in MOVED_KEYS or path in REMOVED_KEYS


def removed_message(paths: Iterable[str]) -> str:
    """One line for the removed settings among ``paths`` (dotted: ``detour``, ``command.cruise_speed_m_s``):
    each named with what to do, those removed with nothing in their place together; "" when none is."""
    parts: list[str] = []
    plain: list[str] = []
    for path in paths:
        if path in REMOVED_SECTIONS:
            parts.append(f"[{path}]: {REMOVED_SECTIONS[path]}")
        elif path in MOVED_KEYS:
            parts.append(f"{path}: moved to {MOVED_KEYS[path]} — rename it")
        elif REMOVED_KEYS.get(path):
            parts.append(f"{path}: {REMOVED_KEYS[path]}")
        elif path in REMOVED_KEYS:
            plain.append(path)
    if plain:
        them = "them" if len(plain) > 1 else "it"
        parts.append(
            f"{', '.join(plain)}: removed with the rule stack; the local planner ([planner]) replaces {them} — delete {them}"
        )
    return "; ".join(parts)
