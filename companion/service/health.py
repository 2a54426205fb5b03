"""The service's health concern: the health message (see docs/service.md for its fields) and its publisher.

:class:`HealthReporter` is a part of :class:`~companion.service.daemon.Service` (a mixin): it reads the
counters and state the daemon keeps (frames processed, latencies, the last setpoint, the supervisor, the
capture thread and the vehicle link) and publishes the message on the bus at ``bus.health_rate_hz`` and
on every state change. It runs on the service's event loop and never commands anything.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import time
from collections.abc import Awaitable, Callable
from typing import Any

import numpy as np

from companion.core.types import REGION_NAMES, VelocitySetpoint
from companion.core.words import decision_words
from companion.service import protocol
from companion.service.aio import wait_event
from companion.service.parts import TaskPart
from companion.service.preview_frame import thresholds_m

log = logging.getLogger(__name__)


def _percentile_ms(values: collections.deque, q: float) -> float | None:
    if not values:
        return None
    return float(np.percentile(np.fromiter(values, np.float64), q)) * 1e3


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
    from companion.core.calibration import make_rectifier
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


class HealthReporter:
    """The health part of the service (mixed into :class:`~companion.service.daemon.Service`)."""

    def _rig_status(self) -> dict[str, Any] | None:
        """:func:`rig_status` of the config in force, worked out once per config (a calibration file is
        read for it)."""
        cached = getattr(self, "_rig_status_cache", None)
        if cached is None or cached[0] is not self.config:
            cached = (self.config, rig_status(self.config))
            self._rig_status_cache = cached
        return cached[1]

    def health_message(self) -> dict[str, Any]:
        """The health message (the field list: docs/service.md)."""
        now = self._clock()
        latest = self._latest
        capture = self._capture.status() if self._capture is not None else None
        v = self.link.state() if self.link is not None else None
        recent = [t for t in self._processed_times if now - t <= 1.0]
        result = latest.result if latest is not None else None
        decision = result.decision if result is not None else None
        self._health_seq += 1
        vehicle_link = self._vehicle_status
        if v is not None and self._vehicle_status == "connected":
            vehicle_link = "connected" if v.connected else "lost"
        return {
            "type": "health",
            "seq": self._health_seq,
            "time_s": now,
            "unix_time_s": time.time(),
            "state": self.supervisor.state.value,
            "reason": self.supervisor.reason,
            "engaged": self.supervisor.engaged,
            "offboard_switch_ready": self.supervisor.ready,
            "config_version": self.config_version,
            "fps": float(len(recent)),
            "frame_age_ms": (now - result.timestamp_s) * 1e3 if result is not None else None,
            "stages_ms": dict(result.timings_ms) if result is not None else {},
            "frame_to_setpoint_ms": {
                "last": self._last_latency_s * 1e3 if self._last_latency_s is not None else None,
                "median": _percentile_ms(self._latency_s, 50),
                "p99": _percentile_ms(self._latency_s, 99),
                "samples": len(self._latency_s),
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
            "setpoint": _setpoint_dict(self._last_setpoint),
            "setpoint_age_ms": (now - self._last_setpoint_s) * 1e3 if self._last_setpoint_s is not None else None,
            "setpoints_sent": self._setpoints_sent,
            "override": self.supervisor.override_status(now),
            "memory": self.supervisor.memory_status(),
            "goal": self.supervisor.goal_status(v.position_ned_m if v is not None else None),
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
            "processed_frames": self._processed,
            "dropped_frames": (capture.dropped if capture is not None else 0) + self._skipped_frames(),
            "processed_twice": self._processed_twice,
            "frame_errors": self._frame_errors,
            "last_error": self._last_error,
            "control": self._control_status(),
            "mavlink": self.presence.status(),
            "thresholds_m": thresholds_m(self.config),
            "rig": self._rig_status(),
            "preview": self.view.publisher.status() if self.view is not None and self.view.publisher is not None else None,
        }

    def _control_status(self) -> dict[str, int] | None:
        """The control server's counts: live connections, requests received, refused by the budgets
        (``rate_limited``) or the bound on requests in progress (``busy``), malformed (``bad``),
        replies dropped (a client that does not read them), handshakes refused (too many connections)."""
        server = self.control_server
        if server is None:
            return None
        st = server.stats
        return {
            "connections": server.connections,
            "received": st.received,
            "rate_limited": st.rate_limited,
            "busy": st.busy,
            "bad": st.bad,
            "replies_dropped": st.replies_dropped,
            "refused_connections": self.bus.stats()["refused_connections"] if self.bus is not None else 0,
        }

    def _skipped_frames(self) -> int:
        return self._processor.skipped if self._processor is not None else 0

    async def _publish_health(self) -> None:
        if self.bus is None:
            return
        try:
            self.bus.publish(protocol.encode(self.health_message()))
        except asyncio.CancelledError:
            raise
        except Exception:
            log.exception("publishing health failed")



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
