"""The service's health concern: the health message (see docs/service.md for its fields) and its publisher.

:class:`HealthReporter` builds the message from a small typed snapshot of each part
(:class:`HealthSources`: the pipeline's frame counters, the control loop's setpoints, the capture
thread's status, the vehicle link's state, the control server's counters, the presence part's);
:class:`HealthLoop` is the part that publishes it at ``bus.health_rate_hz`` and at once on every state
change. Both run on the service's event loop and never command anything.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import time
from collections.abc import Awaitable, Callable
from typing import Any

import numpy as np

from companion.core.types import REGION_NAMES, VelocitySetpoint
from companion.core.words import decision_words
from companion.service.aio import wait_event
from companion.service.parts import TaskPart
from companion.service.preview_frame import thresholds_m

log = logging.getLogger(__name__)


def _percentile_ms(values_s: tuple[float, ...], q: float) -> float | None:
    if not values_s:
        return None
    return float(np.percentile(np.asarray(values_s, np.float64), q)) * 1e3


def _setpoint_dict(sp: VelocitySetpoint | None) -> dict[str, float] | None:
    if sp is None:
        return None
    return {
        "forward_m_s": sp.forward_m_s,
        "right_m_s": sp.right_m_s,
        "down_m_s": sp.down_m_s,
        "yaw_rate_deg_s": sp.yaw_rate_deg_s,
    }


def _region_map(depth_m: Any) -> dict[str, float | None]:
    return {name: (None if not np.isfinite(v) else float(v)) for name, v in zip(REGION_NAMES, depth_m)}


def _regions(result: Any) -> dict[str, Any]:
    """``regions_m`` (what the controller used; null = unknown, including the median filter's 0 m
    stand-in for a recent unknown), ``regions_measured_m`` (this frame's measurement after the LUT;
    null = unknown) and ``regions_filtered`` (true where ``regions_m`` came out of the release filter: a
    blend, no frame's measurement)."""
    if result is None:
        return {
            "regions_m": {n: None for n in REGION_NAMES},
            "regions_measured_m": {n: None for n in REGION_NAMES},
            "regions_filtered": {n: False for n in REGION_NAMES},
        }
    measured = result.measured.depth_m if result.measured is not None else result.refined.depth_m
    filtered = result.filtered if result.filtered is not None else np.zeros(len(REGION_NAMES), bool)
    return {
        "regions_m": _region_map(result.shown_depths_m()),
        "regions_measured_m": _region_map(measured),
        "regions_filtered": {n: bool(f) for n, f in zip(REGION_NAMES, filtered)},
    }


def rig_status(cfg: Any) -> dict[str, Any] | None:
    """Health's ``rig``: what the stereo setting measures with the service's rig (the calibration file's
    rectified geometry, or the ideal rig, at the camera's eye size), in the words every tool prints.

    Returns:
        ``min_measurable_depth_m`` (``f·B / (D - 1)``, metres: nothing nearer is measured),
        ``near_unmeasurable`` (True when that is beyond where the controller's 'near' is full: a nearer
        obstacle reads unknown or, a false match, far) and ``lines`` (the rig check's findings, one
        line each, as :func:`~companion.core.rig_check.rig_check_lines` words them); None when the
        calibration cannot be loaded here (the pipeline reports that itself).
    """
    from companion.core.rectifier import make_rectifier
    from companion.core.rig_check import check_rig, near_unmeasurable, rig_check_lines
    from companion.errors import CompanionError

    try:
        geometry = make_rectifier(cfg.calibration, cfg.camera.width_px, cfg.camera.height_px).geometry
    except (CompanionError, OSError, ValueError) as err:
        log.debug("rig status: calibration not loadable here: %s", err)
        return None
    result = check_rig(geometry, cfg.stereo, cfg.regions, cfg.controller)
    return {
        "min_measurable_depth_m": round(result.nearest_depth_m, 3),
        "near_unmeasurable": near_unmeasurable(result, cfg.controller),
        "lines": rig_check_lines(result),
    }


@dataclasses.dataclass(frozen=True)
class HealthSources:
    """Where the health message comes from: each part's own snapshot, read through these callables.

    Attributes:
        clock: monotonic seconds.
        config: the config in force and its version (one consistent pair).
        supervisor: the control loop's supervisor (its public state and status methods).
        frames: the pipeline part's counters at a time (:meth:`~companion.service.frames.PipelinePart.counts`).
        latest: the newest processed frame, or None.
        capture: the capture thread's status, or None before it started.
        vehicle: the vehicle link's state (or None) and health's ``vehicle.link`` word for it.
        setpoints: the control loop's setpoint counters.
        control: the control server's counts (a dataclass), or None before it started.
        mavlink: the presence part's status.
        preview: the preview publisher's status, or None.
        last_error: the newest fault, in one line, or None.
    """

    clock: Callable[[], float]
    config: Callable[[], tuple[Any, int]]
    supervisor: Any
    frames: Callable[[float], Any]
    latest: Callable[[], Any]
    capture: Callable[[], Any]
    vehicle: Callable[[], tuple[Any, str]]
    setpoints: Callable[[], Any]
    control: Callable[[], Any]
    mavlink: Callable[[], dict[str, Any]]
    preview: Callable[[], dict[str, Any] | None]
    last_error: Callable[[], str | None]


class HealthReporter:
    """The health part's message: built from the parts' snapshots (:class:`HealthSources`), numbered."""

    def __init__(self, sources: HealthSources) -> None:
        self._src = sources
        self._seq = 0
        self._rig: tuple[Any, dict[str, Any] | None] | None = None  # (config, its rig status)

    def _rig_status(self, config: Any) -> dict[str, Any] | None:
        """:func:`rig_status` of ``config``, worked out once per config (a calibration file is read for it)."""
        if self._rig is None or self._rig[0] is not config:
            self._rig = (config, rig_status(config))
        return self._rig[1]

    def message(self) -> dict[str, Any]:
        """The health message (the field list: docs/service.md)."""
        src = self._src
        now = src.clock()
        config, config_version = src.config()
        latest = src.latest()
        capture = src.capture()
        v, vehicle_link = src.vehicle()
        frames = src.frames(now)
        sp = src.setpoints()
        control = src.control()
        supervisor = src.supervisor
        latencies = sp.latencies_s
        result = latest.result if latest is not None else None
        decision = result.decision if result is not None else None
        self._seq += 1
        return {
            "type": "health",
            "seq": self._seq,
            "time_s": now,
            "unix_time_s": time.time(),
            "state": supervisor.state.value,
            "reason": supervisor.reason,
            "engaged": supervisor.engaged,
            "offboard_switch_ready": supervisor.ready,
            "config_version": config_version,
            "fps": frames.fps,
            "frame_age_ms": (now - result.timestamp_s) * 1e3 if result is not None else None,
            "stages_ms": dict(result.timings_ms) if result is not None else {},
            "frame_to_setpoint_ms": {
                "last": sp.latency_last_s * 1e3 if sp.latency_last_s is not None else None,
                "median": _percentile_ms(latencies, 50),
                "p99": _percentile_ms(latencies, 99),
                "samples": len(latencies),
            },
            **_regions(result),
            "yaw": decision.yaw if decision is not None else None,
            "pitch": decision.pitch if decision is not None else None,
            "decision": (
                {
                    "kind": decision.kind.value,
                    "speed_fraction": decision.speed_fraction,
                    "reason": decision.reason,
                    "words": decision_words(decision.kind, decision.yaw, decision.pitch, result.refined.depth_m,
                                            decision.speed_fraction),
                }
                if decision is not None
                else None
            ),
            "setpoint": _setpoint_dict(sp.last),
            "setpoint_age_ms": (now - sp.last_s) * 1e3 if sp.last_s is not None else None,
            "setpoints_sent": sp.sent,
            "override": supervisor.override_status(now),
            "planner": supervisor.planner_status(),
            "goal": supervisor.goal_status(v.position_ned_m if v is not None else None),
            "camera": (
                {
                    "source": capture.source,
                    "status": capture.state,
                    "fps": capture.fps,
                    "frames": capture.frames,
                    "reconnects": capture.reconnects,
                    "last_error": capture.last_error,
                    "skew_ms": capture.skew_ms,
                }
                if capture is not None
                else None
            ),
            "vehicle": {
                "link": vehicle_link,
                "autopilot": v.autopilot if v is not None else "unknown",
                "flight_mode": v.flight_mode if v is not None else "UNKNOWN",
                "armed": v.armed if v is not None else False,
                "in_offboard": v.in_offboard if v is not None else False,
                "position_ned_m": v.position_ned_m.tolist() if v is not None and v.position_ned_m is not None else None,
                "attitude_rad": v.attitude_rad.tolist() if v is not None and v.attitude_rad is not None else None,
                "velocity_ned_m_s": (
                    v.velocity_ned_m_s.tolist() if v is not None and v.velocity_ned_m_s is not None else None
                ),
            },
            "processed_frames": frames.processed,
            "dropped_frames": (capture.dropped if capture is not None else 0) + frames.skipped,
            "processed_twice": frames.processed_twice,
            "frame_errors": frames.frame_errors,
            "backend": frames.backend,
            "device_lost": frames.device_lost,
            "last_error": src.last_error(),
            "control": dataclasses.asdict(control) if control is not None else None,
            "mavlink": src.mavlink(),
            "thresholds_m": thresholds_m(config),
            "rig": self._rig_status(config),
            "preview": src.preview(),
        }


class HealthLoop(TaskPart):
    """The health part's task: publishes at ``bus.health_rate_hz`` and at once on :meth:`kick` (a state
    change), through ``publish`` (which never raises).

    Args:
        publish: sends one health message now.
        rate_hz: the rate in force (read at each wait: live changes apply).
        on_died: see :class:`~companion.service.parts.TaskPart`.
    """

    name = "health"

    def __init__(
        self,
        publish: Callable[[], Awaitable[None]],
        rate_hz: Callable[[], float],
        on_died: Callable[[str, BaseException], None] | None = None,
    ) -> None:
        super().__init__(on_died)
        self._publish = publish
        self._rate_hz = rate_hz
        self._now = asyncio.Event()

    def kick(self) -> None:
        """Publish at once (on the loop)."""
        self._now.set()

    async def run(self) -> None:
        while True:
            await wait_event(self._now, 1.0 / self._rate_hz())
            self._now.clear()
            await self._publish()
