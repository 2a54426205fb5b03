"""PX4's velocity and yaw-rate step response, measured in SITL (``companion sitl --scenario step-response``).

The ground station itself flies offboard (MAVSDK on PX4's GCS link, no service): after a steady
hover at :data:`STEP_ALTITUDE_M` it sends body-frame velocity and yaw-rate setpoints that step
(:data:`STEPS`: forward 0 -> 1 -> 0 and 0 -> 3 -> 0 m/s, the same to the right, yaw rate 0 -> 45 -> 0
and 0 -> 90 -> 0 deg/s), each held long enough to settle, and records PX4's own telemetry (its
velocity estimate and body yaw rate, as the service sees them). Each axis's steps are then fitted
with the simulator's vehicle model (:mod:`companion.sim.stepfit`: a first-order lag with an
acceleration limit, without and with a pure delay), the constants ``sim.velocity_time_constant_s``,
``max_horizontal_accel_m_s2``, ``yaw_rate_time_constant_s`` and ``max_yaw_accel_deg_s2`` stand for.
"""

from __future__ import annotations

import asyncio
import csv
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.sim.stepfit import StepData, StepFit, fit_steps
from companion.sitl.flight import SITL_PARAMS
from companion.sitl.pilot import Pilot, Sample
from companion.sitl.px4 import SitlError

log = logging.getLogger(__name__)

#: Height of the hover the steps start from, metres above the take-off point.
STEP_ALTITUDE_M = 3.0


@dataclass(frozen=True)
class Step:
    """One setpoint held for a while: body forward, right (m/s), yaw rate (deg/s), for ``hold_s`` seconds."""

    axis: str  # "forward", "right" or "yaw": the axis this setpoint steps (what it is fitted on)
    forward_m_s: float
    right_m_s: float
    yaw_rate_deg_s: float
    hold_s: float


#: The sequence flown after the hover, each from the one before.
STEPS: tuple[Step, ...] = (
    Step("forward", 1.0, 0.0, 0.0, 6.0),
    Step("forward", 0.0, 0.0, 0.0, 6.0),
    Step("forward", 3.0, 0.0, 0.0, 7.0),
    Step("forward", 0.0, 0.0, 0.0, 7.0),
    Step("right", 0.0, 1.0, 0.0, 6.0),
    Step("right", 0.0, 0.0, 0.0, 6.0),
    Step("right", 0.0, 3.0, 0.0, 7.0),
    Step("right", 0.0, 0.0, 0.0, 7.0),
    Step("yaw", 0.0, 0.0, 45.0, 5.0),
    Step("yaw", 0.0, 0.0, 0.0, 4.0),
    Step("yaw", 0.0, 0.0, 90.0, 5.0),
    Step("yaw", 0.0, 0.0, 0.0, 4.0),
)


def _axis_value(axis: str, step: Step) -> float:
    return {"forward": step.forward_m_s, "right": step.right_m_s, "yaw": step.yaw_rate_deg_s}[axis]


def body_values(s: Sample, yaw_rad: float) -> tuple[float, float, float]:
    """Forward and right velocity (m/s) in the frame of heading ``yaw_rad``, and the yaw rate (deg/s), of ``s``."""
    c, si = math.cos(yaw_rad), math.sin(yaw_rad)
    vn, ve = float(s.velocity_ned_m_s[0]), float(s.velocity_ned_m_s[1])
    return c * vn + si * ve, -si * vn + c * ve, math.degrees(s.yaw_rate_rad_s)


@dataclass(frozen=True)
class StepResponseResult:
    """What the step-response flight measured.

    Attributes:
        steps: per step flown, ``(axis, from, to, StepFit without delay, StepFit with delay)``.
        fits: per axis, the joint fit of all its steps: ``(StepFit without delay, StepFit with delay)``.
        csv_path: where the telemetry went (time since the first step, setpoint, body velocity, yaw rate).
    """

    steps: tuple[tuple[str, float, float, StepFit, StepFit], ...]
    fits: dict[str, tuple[StepFit, StepFit]] = field(default_factory=dict)
    csv_path: Path | None = None

    @property
    def passed(self) -> bool:
        """Every axis was fitted (its residual below a fifth of its largest step)."""
        largest = {"forward": 3.0, "right": 3.0, "yaw": 90.0}
        return all(axis in self.fits and self.fits[axis][0].rms < 0.2 * top for axis, top in largest.items())

    def lines(self) -> list[str]:
        unit = {"forward": ("m/s", "m/s²"), "right": ("m/s", "m/s²"), "horizontal": ("m/s", "m/s²"), "yaw": ("deg/s", "deg/s²")}
        out = ["step                        lag (no delay)  accel limit    rms   |  lag    delay  accel limit    rms"]
        for axis, a, b, f0, f1 in self.steps:
            u, ua = unit[axis]
            out.append(
                f"{axis:7s} {a:5.1f} -> {b:5.1f} {u:5s}   {f0.tau_s:5.2f} s    {_accel(f0)} {ua:6s} {f0.rms:5.3f}  |  "
                f"{f1.tau_s:5.2f} s {f1.delay_s:5.2f} s {_accel(f1)} {f1.rms:5.3f}"
            )
        for axis, (f0, f1) in self.fits.items():
            u, ua = unit[axis.split(",")[0]]
            out.append(
                f"{axis} (all steps): lag {f0.tau_s:.2f} s, acceleration limit {_accel(f0).strip()} {ua}, rms {f0.rms:.3f} {u}; "
                f"with a delay: lag {f1.tau_s:.2f} s after {f1.delay_s:.2f} s, limit {_accel(f1).strip()} {ua}, rms {f1.rms:.3f} {u}"
            )
        if self.csv_path is not None:
            out.append(f"telemetry: {self.csv_path}")
        return out


def _accel(f: StepFit) -> str:
    return f"{f.accel_limit:7.2f}" if f.accel_reached else "  (n/r)"


class OffboardPilot(Pilot):
    """The ground station flying offboard itself (MAVSDK's Offboard plugin on the GCS link)."""

    async def _attached(self, system: Any) -> None:
        from mavsdk.asyncio.plugins.offboard import OffboardAsync

        self.offboard = OffboardAsync(system)

    async def send_velocity_body(self, forward_m_s: float, right_m_s: float, down_m_s: float, yaw_rate_deg_s: float) -> float:
        """Send one body-frame velocity setpoint (MAVSDK re-sends it at 20 Hz); returns when it was sent."""
        from mavsdk.asyncio.plugins.offboard import VelocityBodyYawspeed

        t = self._clock()
        await self.offboard.set_velocity_body(VelocityBodyYawspeed(forward_m_s, right_m_s, down_m_s, yaw_rate_deg_s))
        return t

    async def start_offboard(self) -> None:
        from mavsdk.asyncio.plugins.offboard import OffboardError

        try:
            await self.offboard.start()
        except OffboardError as err:
            raise SitlError(f"PX4 refused Offboard from the ground station: {err} (mode {self.flight_mode})") from None

    def _plugins(self) -> list[Any]:
        return [*super()._plugins(), getattr(self, "offboard", None)]


def _segments(pilot: Pilot, marks: list[tuple[float, Step]], hover: Step, yaw_rad: float) -> list[tuple[str, float, float, StepData]]:
    """Each step's samples (from its setpoint's change to the next), as :class:`StepData` on its axis."""
    out = []
    previous = hover
    for i, (t0, step) in enumerate(marks):
        t1 = marks[i + 1][0] if i + 1 < len(marks) else t0 + step.hold_s
        rows = [s for s in pilot.samples if t0 <= s.time_s < t1]
        axis = step.axis
        k = {"forward": 0, "right": 1, "yaw": 2}[axis]
        t = np.array([s.time_s - t0 for s in rows])
        v = np.array([body_values(s, yaw_rad)[k] for s in rows])
        a, b = _axis_value(axis, previous), _axis_value(axis, step)
        out.append((axis, a, b, StepData(t, v, a, b)))
        previous = step
    return out


def write_csv(path: Path, pilot: Pilot, marks: list[tuple[float, Step]], yaw_rad: float) -> None:
    """The telemetry from the first step on: time s, time since the setpoint was sent s, setpoint
    forward/right m/s and yaw deg/s, body
    forward/right m/s, yaw rate deg/s (the frame of the heading at the first step)."""
    t_first = marks[0][0]
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t_s", "since_step_s", "sp_forward_m_s", "sp_right_m_s", "sp_yaw_rate_deg_s", "forward_m_s", "right_m_s", "yaw_rate_deg_s"])
        j = 0
        for s in pilot.samples:
            if s.time_s < t_first:
                continue
            while j + 1 < len(marks) and marks[j + 1][0] <= s.time_s:
                j += 1
            step = marks[j][1]
            fwd, right, yaw = body_values(s, yaw_rad)
            w.writerow([f"{s.time_s - t_first:.4f}", f"{s.time_s - marks[j][0]:.4f}", step.forward_m_s, step.right_m_s, step.yaw_rate_deg_s,
                        f"{fwd:.4f}", f"{right:.4f}", f"{yaw:.3f}"])


async def fly_step_response(pilot: OffboardPilot, workdir: Path) -> StepResponseResult:
    """The step-response flight (module doc). PX4 must be running, ``pilot`` connected.

    Raises:
        SitlError: a step failed (named).
    """
    await pilot.make_ready()
    await pilot.set_params(SITL_PARAMS)
    await pilot.take_off(STEP_ALTITUDE_M)
    await pilot.wait_steady(2.0)
    hover = Step("forward", 0.0, 0.0, 0.0, 2.0)
    marks: list[tuple[float, Step]] = []
    try:
        await pilot.send_velocity_body(0.0, 0.0, 0.0, 0.0)
        await pilot.start_offboard()
        await pilot.wait_for("OFFBOARD", lambda: pilot.in_offboard, 5.0)
        await asyncio.sleep(hover.hold_s)
        yaw_rad = float(pilot.latest().attitude_rad[2])
        for step in STEPS:
            if step.axis != "yaw" and marks and marks[-1][1].axis == "yaw":
                yaw_rad = float(pilot.latest().attitude_rad[2])
            t = await pilot.send_velocity_body(step.forward_m_s, step.right_m_s, 0.0, step.yaw_rate_deg_s)
            marks.append((t, step))
            await asyncio.sleep(step.hold_s)
            if not pilot.in_offboard:
                raise SitlError(f"PX4 left Offboard during the steps (mode {pilot.flight_mode})")
    finally:
        if pilot.in_offboard:
            await pilot.hold()
    await pilot.land()
    workdir.mkdir(parents=True, exist_ok=True)
    csv_path = workdir / "step-response.csv"
    # Yaw steps come last: one heading frames every horizontal step.
    await asyncio.to_thread(write_csv, csv_path, pilot, marks, yaw_rad)
    return analyse(_segments(pilot, marks, hover, yaw_rad), csv_path)


def analyse(segments: list[tuple[str, float, float, StepData]], csv_path: Path | None = None) -> StepResponseResult:
    """Fit each step, and each axis's steps jointly; forward and right share one horizontal fit too
    (``"horizontal"``: the simulator has one horizontal lag and limit), and one over the first 2 s
    of each step (``"horizontal, first 2 s"``)."""
    steps = []
    by_axis: dict[str, list[StepData]] = {}
    for axis, a, b, data in segments:
        steps.append((axis, a, b, fit_steps([data], with_delay=False), fit_steps([data], with_delay=True)))
        by_axis.setdefault(axis, []).append(data)
    fits = {axis: (fit_steps(d, with_delay=False), fit_steps(d, with_delay=True)) for axis, d in by_axis.items()}
    horizontal = by_axis.get("forward", []) + by_axis.get("right", [])
    if horizontal:
        fits["horizontal"] = (fit_steps(horizontal, with_delay=False), fit_steps(horizontal, with_delay=True))
        # The reaction and the braking that matter most near an obstacle, without the slow tail.
        fits["horizontal, first 2 s"] = (
            fit_steps(horizontal, with_delay=False, window_s=2.0), fit_steps(horizontal, with_delay=True, window_s=2.0)
        )
    return StepResponseResult(tuple(steps), fits, csv_path)


def read_csv(path: Path) -> list[tuple[str, float, float, StepData]]:
    """The steps of a telemetry file :func:`write_csv` wrote, for :func:`analyse` (refitting a flight)."""
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise SitlError(f"{path}: no telemetry rows")
    keys = ("sp_forward_m_s", "sp_right_m_s", "sp_yaw_rate_deg_s")
    cols = {"forward": "forward_m_s", "right": "right_m_s", "yaw": "yaw_rate_deg_s"}
    segments = []
    prev = (0.0, 0.0, 0.0)
    i = 0
    while i < len(rows):
        sp = tuple(float(rows[i][k]) for k in keys)
        j = i
        while j < len(rows) and tuple(float(rows[j][k]) for k in keys) == sp:
            j += 1
        changed = [n for n, (x, y) in zip(("forward", "right", "yaw"), zip(prev, sp)) if x != y]
        axis = changed[0] if changed else "forward"
        t = np.array([float(r["since_step_s"]) for r in rows[i:j]])
        v = np.array([float(r[cols[axis]]) for r in rows[i:j]])
        k = ("forward", "right", "yaw").index(axis)
        segments.append((axis, prev[k], sp[k], StepData(t, v, prev[k], sp[k])))
        prev = sp
        i = j
    return segments
