"""MAVLink autopilot peers that behave like PX4 or like ArduCopter where the service depends on it.

Written with pymavlink (MAVLink 2, common dialect) over a plain UDP socket, in a background thread.
The service's real MAVSDK link talks to them on localhost, and tests assert on what arrives on the wire.

:class:`Px4Peer`, like PX4:

* HEARTBEAT (``MAV_AUTOPILOT_PX4``, quadrotor) with ``MAV_MODE_FLAG_CUSTOM_MODE_ENABLED`` and the PX4
  custom mode (main mode in bits 16-23, sub mode in bits 24-31), the armed flag; sent at
  ``heartbeat_hz`` and at once after every mode change.
* COMMAND_LONG: ``MAV_CMD_DO_SET_MODE`` (param2 main mode, param3 sub mode) acked; OFFBOARD is
  accepted only when setpoints have been arriving (at least ``offboard_min_setpoints`` in the last
  second, the newest within ``offboard_loss_timeout_s``), else DENIED. ``COMPONENT_ARM_DISARM`` acked.
  ``REQUEST_MESSAGE`` for AUTOPILOT_VERSION answered; message-interval requests acked; anything else
  UNSUPPORTED.
* Offboard-loss failsafe: in OFFBOARD with no setpoint for ``offboard_loss_timeout_s`` it switches to
  Hold (AUTO.LOITER) by itself, as PX4's COM_OF_LOSS_T does.
* Telemetry at ``telemetry_hz``: LOCAL_POSITION_NED, ATTITUDE, EXTENDED_SYS_STATE (in air),
  SYS_STATUS, GLOBAL_POSITION_INT. The position integrates the commanded body velocity in OFFBOARD.

:class:`ArduCopterPeer`, like ArduCopter (what differs is what the ArduPilot link must handle):

* HEARTBEAT (``MAV_AUTOPILOT_ARDUPILOTMEGA``, quadrotor), the custom mode is ArduCopter's mode number
  (``ArduCopter/mode.h``: GUIDED 4, LOITER 5, BRAKE 17, ...).
* No telemetry but the HEARTBEAT until asked: ``MAV_CMD_SET_MESSAGE_INTERVAL`` (param1 message id,
  LOCAL_POSITION_NED, ATTITUDE, GLOBAL_POSITION_INT, SYS_STATUS, EXTENDED_SYS_STATE, EKF_STATUS_REPORT;
  param2 interval in µs, -1 off) starts each message at its own rate, as ArduPilot does per link. Every
  request is kept in :attr:`ArduCopterPeer.interval_requests`.
* ``MAV_CMD_DO_SET_MODE`` (param1 base mode with the custom-mode flag, param2 mode number) acked
  ACCEPTED or FAILED (ArduPilot's answer to a refused mode); GUIDED needs no setpoint stream.
* In GUIDED, a velocity target is flown for ``guid_timeout_s`` (``GUID_TIMEOUT``, 3 s by default) after
  it arrived, then the vehicle brakes and hovers, **still in GUIDED**: ArduCopter has no offboard-loss
  failsafe. LOITER and BRAKE hover.

Everything received is recorded with the monotonic receive time: :attr:`setpoints` (every
SET_POSITION_TARGET_LOCAL_NED), :attr:`commands` (every COMMAND_LONG) and :attr:`mode_log`; and what a
ground station would see of the service: :attr:`heartbeats` (every HEARTBEAT from another
component), :attr:`status_texts` (STATUSTEXT) and :attr:`obstacle_distances` (OBSTACLE_DISTANCE, as
the autopilot's collision prevention reads them).
"""

from __future__ import annotations

import math
import socket
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass

from peers.fakes import wait_until
from pymavlink.dialects.v20 import ardupilotmega
from pymavlink.dialects.v20 import common as mavlink

# PX4 custom main modes (px4_custom_mode.h) and AUTO sub modes.
MAIN_MANUAL = 1
MAIN_ALTCTL = 2
MAIN_POSCTL = 3
MAIN_AUTO = 4
MAIN_ACRO = 5
MAIN_OFFBOARD = 6
MAIN_STABILIZED = 7
SUB_AUTO_READY = 1
SUB_AUTO_TAKEOFF = 2
SUB_AUTO_LOITER = 3
SUB_AUTO_MISSION = 4
SUB_AUTO_RTL = 5
SUB_AUTO_LAND = 6

#: Mode name (as MAVSDK's telemetry names it) -> (main, sub).
MODES: dict[str, tuple[int, int]] = {
    "MANUAL": (MAIN_MANUAL, 0),
    "ALTCTL": (MAIN_ALTCTL, 0),
    "POSCTL": (MAIN_POSCTL, 0),
    "OFFBOARD": (MAIN_OFFBOARD, 0),
    "STABILIZED": (MAIN_STABILIZED, 0),
    "HOLD": (MAIN_AUTO, SUB_AUTO_LOITER),
    "MISSION": (MAIN_AUTO, SUB_AUTO_MISSION),
    "RETURN_TO_LAUNCH": (MAIN_AUTO, SUB_AUTO_RTL),
    "LAND": (MAIN_AUTO, SUB_AUTO_LAND),
    "TAKEOFF": (MAIN_AUTO, SUB_AUTO_TAKEOFF),
}
_MODE_NAMES = {v: k for k, v in MODES.items()}

#: ArduCopter's mode names -> numbers (ArduCopter/mode.h), the ones these tests use.
COPTER_MODES: dict[str, int] = {
    "STABILIZE": 0,
    "ALT_HOLD": 2,
    "AUTO": 3,
    "GUIDED": 4,
    "LOITER": 5,
    "RTL": 6,
    "LAND": 9,
    "POSHOLD": 16,
    "BRAKE": 17,
}
_COPTER_MODE_NAMES = {v: k for k, v in COPTER_MODES.items()}

#: Messages the ArduCopter peer streams once asked (SET_MESSAGE_INTERVAL), by id.
_COPTER_STREAMABLE = frozenset(
    {
        mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
        mavlink.MAVLINK_MSG_ID_ATTITUDE,
        mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
        mavlink.MAVLINK_MSG_ID_SYS_STATUS,
        mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE,
        ardupilotmega.MAVLINK_MSG_ID_EKF_STATUS_REPORT,
    }
)


def free_udp_port() -> int:
    """An unused localhost UDP port (ephemeral; tiny race between this and its use)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass(frozen=True)
class Setpoint:
    """One SET_POSITION_TARGET_LOCAL_NED as received: monotonic time (s), frame, type mask, velocity
    (m/s, body frame for MAV_FRAME_BODY_NED), yaw rate (rad/s), and the peer's mode when it arrived."""

    t_s: float
    frame: int
    type_mask: int
    vx: float
    vy: float
    vz: float
    yaw_rate: float
    mode: str

    @property
    def is_zero(self) -> bool:
        return self.vx == 0.0 and self.vy == 0.0 and self.vz == 0.0 and self.yaw_rate == 0.0


@dataclass(frozen=True)
class Heard:
    """A HEARTBEAT from another component: monotonic time (s), its sender, MAV_TYPE, MAV_AUTOPILOT and
    MAV_STATE."""

    t_s: float
    system_id: int
    component_id: int
    type: int
    autopilot: int
    system_status: int


@dataclass(frozen=True)
class StatusText:
    """A STATUSTEXT: monotonic time (s), sender component, MAV_SEVERITY and the text."""

    t_s: float
    component_id: int
    severity: int
    text: str


@dataclass(frozen=True)
class WireObstacle:
    """An OBSTACLE_DISTANCE as received: monotonic time (s), sender component, and its fields
    (``distances`` uint16 cm, 72 of them)."""

    t_s: float
    component_id: int
    time_usec: int
    sensor_type: int
    distances: tuple[int, ...]
    increment: int
    min_distance: int
    max_distance: int
    increment_f: float
    angle_offset: float
    frame: int


@dataclass(frozen=True)
class Command:
    """One COMMAND_LONG as received: monotonic time (s), command id, params 1-7, result sent back, and
    for a DO_SET_MODE the mode it asked for, by the peer's own names (None for other commands)."""

    t_s: float
    command: int
    params: tuple[float, ...]
    result: int
    mode: str | None = None


class _AutopilotPeer:
    """What both peers share: the UDP socket, the thread, the records, the kinematics.

    Args:
        port: the localhost UDP port where the service's MAVSDK listens (``udpin://127.0.0.1:PORT``);
            None (the default): a free one, chosen after the peer's own socket is bound so that the
            two can never be the same port. Read it back from :attr:`port`.
        mode: initial flight mode name.
        armed: initial armed state (a vehicle already flying, by default).
        heartbeat_hz: HEARTBEAT rate, Hz.
        deny_modes: modes whose DO_SET_MODE is refused (e.g. {"HOLD"} for a stuck shutdown).
        system_id: the autopilot's MAVLink system id.
    """

    #: The autopilot's offboard mode (velocity targets are flown only there).
    OFFBOARD_MODE = "OFFBOARD"
    THREAD_NAME = "autopilot-peer"
    DIALECT = mavlink

    def __init__(
        self,
        port: int | None,
        *,
        mode: str,
        armed: bool,
        heartbeat_hz: float,
        deny_modes: frozenset[str],
        system_id: int,
    ) -> None:
        self.deny_modes = set(deny_modes)
        self.port = port
        self.heartbeat_hz = heartbeat_hz
        self.system_id = system_id
        self._mav = self.DIALECT.MAVLink(None, srcSystem=system_id, srcComponent=mavlink.MAV_COMP_ID_AUTOPILOT1)
        self._mav.robust_parsing = True
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(("127.0.0.1", 0))
        self._sock.settimeout(0.005)
        if self.port is None:
            self.port = free_udp_port()
        self._lock = threading.Lock()
        self._mode = mode
        self._armed = armed
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._boot_s = time.monotonic()
        self._pos = [0.0, 0.0, -1.5]
        self._yaw_rad = 0.0
        self._vel_ned = (0.0, 0.0, 0.0)
        self._yaw_rate = 0.0
        self._last_vel = (0.0, 0.0, 0.0, 0.0)
        self.setpoints: list[Setpoint] = []
        self.commands: list[Command] = []
        self.mode_log: list[tuple[float, str, str]] = []  # (t_s, mode, why)
        self.heartbeats: list[Heard] = []
        self.status_texts: list[StatusText] = []
        self.obstacle_distances: list[WireObstacle] = []
        self.silent = False  # True: stop sending anything (a link cut from the autopilot side)
        self.deaf = False  # True: stop reading (what the service sends piles up unread, then is lost)

    # ------------------------------------------------------------------ control from the test

    def start(self):
        self._thread = threading.Thread(target=self._run, name=self.THREAD_NAME, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._sock.close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def mode(self) -> str:
        with self._lock:
            return self._mode

    @property
    def armed(self) -> bool:
        with self._lock:
            return self._armed

    @property
    def speed_m_s(self) -> float:
        """The peer's ground speed now, m/s."""
        with self._lock:
            return math.hypot(self._vel_ned[0], self._vel_ned[1])

    def set_mode(self, mode: str, why: str = "pilot") -> None:
        """Switch mode as a pilot's RC switch would (no command involved)."""
        with self._lock:
            self._set_mode_locked(mode, why)
        self._send_heartbeat()

    def pilot_switch(self, mode: str) -> bool:
        """A pilot's RC switch (or QGC's mode menu) to ``mode``, refused as the autopilot would refuse
        it (PX4: Offboard without a setpoint stream); True when the mode changed."""
        now = time.monotonic()
        with self._lock:
            if mode in self.deny_modes or self._mode_refused_locked(mode, now):
                return False
            self._set_mode_locked(mode, "pilot switch")
        self._send_heartbeat()
        return True

    def setpoints_since(self, t_s: float) -> list[Setpoint]:
        with self._lock:
            return [s for s in self.setpoints if s.t_s >= t_s]

    def commands_since(self, t_s: float) -> list[Command]:
        with self._lock:
            return [c for c in self.commands if c.t_s >= t_s]

    def mode_commands(self) -> list[Command]:
        with self._lock:
            return [c for c in self.commands if c.command == mavlink.MAV_CMD_DO_SET_MODE]

    def wait_for(self, predicate, timeout_s: float, poll_s: float = 0.01) -> bool:
        """Poll ``predicate()`` until it is true or ``timeout_s`` passes; returns the last value."""
        return wait_until(predicate, timeout_s, poll_s)

    # ------------------------------------------------------------------ the personality (subclasses)

    def _send_heartbeat(self) -> None:
        raise NotImplementedError

    def _mode_asked(self, msg: mavlink.MAVLink_command_long_message) -> str | None:
        """The mode a DO_SET_MODE asks for, by name (None: not one this autopilot has)."""
        raise NotImplementedError

    def _mode_refused_locked(self, wanted: str, now: float) -> bool:
        """Whether this autopilot refuses to switch to ``wanted`` now (beyond ``deny_modes``)."""
        return False

    def _velocity_locked(self, now: float) -> tuple[float, float, float, float]:
        """The body velocity and yaw rate the vehicle flies now: forward, right, down m/s, yaw rad/s."""
        raise NotImplementedError

    def _send_due_telemetry(self, now: float) -> None:
        raise NotImplementedError

    def _watch_locked(self, now: float) -> bool:
        """The autopilot's own reactions (failsafes); True when the mode changed."""
        return False

    def _handle_other_command(self, msg: mavlink.MAVLink_command_long_message, now: float) -> int:
        """A command other than DO_SET_MODE / ARM_DISARM / REQUEST_MESSAGE, under the lock: its result."""
        return mavlink.MAV_RESULT_UNSUPPORTED

    REFUSED = mavlink.MAV_RESULT_DENIED

    # ------------------------------------------------------------------ the thread

    def _set_mode_locked(self, mode: str, why: str) -> None:
        if mode != self._mode:
            self._mode = mode
            self.mode_log.append((time.monotonic(), mode, why))

    def _send(self, msg: mavlink.MAVLink_message) -> None:
        if self.silent:
            return
        try:
            self._sock.sendto(msg.pack(self._mav), ("127.0.0.1", self.port))
        except OSError:
            pass  # nobody listening yet (ECONNREFUSED on loopback): like a radio, keep going

    def _time_boot_ms(self) -> int:
        return int((time.monotonic() - self._boot_s) * 1000) & 0xFFFFFFFF

    def _integrate(self, now: float, dt_s: float) -> None:
        with self._lock:
            fwd, right, down, yaw_rate = self._velocity_locked(now)
            c, s = math.cos(self._yaw_rad), math.sin(self._yaw_rad)
            vn, ve = c * fwd - s * right, s * fwd + c * right
            self._pos[0] += vn * dt_s
            self._pos[1] += ve * dt_s
            self._pos[2] += down * dt_s
            self._yaw_rad = (self._yaw_rad + yaw_rate * dt_s + math.pi) % (2 * math.pi) - math.pi
            self._vel_ned = (vn, ve, down)
            self._yaw_rate = yaw_rate

    def _encode(self, msg_id: int) -> mavlink.MAVLink_message:
        """One telemetry message from the current kinematics."""
        with self._lock:
            x, y, z = self._pos
            vn, ve, down = self._vel_ned
            yaw, yaw_rate = self._yaw_rad, self._yaw_rate
        t = self._time_boot_ms()
        if msg_id == mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            return self._mav.local_position_ned_encode(t, x, y, z, vn, ve, down)
        if msg_id == mavlink.MAVLINK_MSG_ID_ATTITUDE:
            return self._mav.attitude_encode(t, 0.0, 0.0, yaw, 0.0, 0.0, yaw_rate)
        if msg_id == mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            return self._mav.extended_sys_state_encode(mavlink.MAV_VTOL_STATE_MC, mavlink.MAV_LANDED_STATE_IN_AIR)
        if msg_id == mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            return self._mav.global_position_int_encode(
                t, 473977420 + int(x * 90), 85455940 + int(y * 130), int((488.0 - z) * 1000), int(-z * 1000),
                int(vn * 100), int(ve * 100), int(down * 100), int(math.degrees(yaw) % 360 * 100),
            )
        if msg_id == mavlink.MAVLINK_MSG_ID_SYS_STATUS:
            sensors = 0xFFFFFF
            return self._mav.sys_status_encode(sensors, sensors, sensors, 200, 16000, 1000, 80, 0, 0, 0, 0, 0, 0)
        if msg_id == ardupilotmega.MAVLINK_MSG_ID_EKF_STATUS_REPORT:
            flags = 1 | 2 | 4 | 32 | (16 | 8 if self.position_ok else 0)  # attitude, velocity, vertical; horizontal position
            return self._mav.ekf_status_report_encode(flags, 0.1, 0.1, 0.1, 0.1, 0.0)
        raise ValueError(f"the peer cannot encode message id {msg_id}")

    def _ack(self, command: int, result: int) -> None:
        self._send(self._mav.command_ack_encode(command, result))

    def _handle_command(self, msg: mavlink.MAVLink_command_long_message, now: float) -> None:
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        cmd = msg.command
        result = mavlink.MAV_RESULT_UNSUPPORTED
        send_hb = False
        asked = None
        with self._lock:
            if cmd == mavlink.MAV_CMD_DO_SET_MODE:
                asked = self._mode_asked(msg)
                refused = asked is None or asked in self.deny_modes or self._mode_refused_locked(asked, now)
                if refused:
                    result = self.REFUSED
                else:
                    self._set_mode_locked(asked, "command")
                    result = mavlink.MAV_RESULT_ACCEPTED
                    send_hb = True
            elif cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
                self._armed = msg.param1 > 0.5
                result = mavlink.MAV_RESULT_ACCEPTED
                send_hb = True
            elif cmd == mavlink.MAV_CMD_REQUEST_MESSAGE:
                result = mavlink.MAV_RESULT_ACCEPTED
            else:
                result = self._handle_other_command(msg, now)
            self.commands.append(Command(now, cmd, params, result, asked if cmd == mavlink.MAV_CMD_DO_SET_MODE else None))
        self._ack(cmd, result)
        if cmd == mavlink.MAV_CMD_REQUEST_MESSAGE and int(msg.param1) == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            self._send_autopilot_version()
        if send_hb:
            self._send_heartbeat()

    def _send_autopilot_version(self) -> None:
        caps = (
            mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
            | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
            | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
            | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
        )
        self._send(
            self._mav.autopilot_version_encode(
                caps, (1 << 24) | (15 << 16) | (0 << 8) | 255, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 1234
            )
        )

    def _handle(self, msg: mavlink.MAVLink_message, now: float) -> None:
        kind = msg.get_type()
        if kind == "SET_POSITION_TARGET_LOCAL_NED":
            with self._lock:
                self.setpoints.append(
                    Setpoint(now, msg.coordinate_frame, msg.type_mask, msg.vx, msg.vy, msg.vz, msg.yaw_rate, self._mode)
                )
                self._last_vel = (msg.vx, msg.vy, msg.vz, msg.yaw_rate)
        elif kind == "COMMAND_LONG":
            self._handle_command(msg, now)
        elif kind == "HEARTBEAT":
            with self._lock:
                self.heartbeats.append(
                    Heard(now, msg.get_srcSystem(), msg.get_srcComponent(), msg.type, msg.autopilot, msg.system_status)
                )
        elif kind == "STATUSTEXT":
            text = msg.text if isinstance(msg.text, str) else msg.text.decode("ascii", "replace")
            with self._lock:
                self.status_texts.append(StatusText(now, msg.get_srcComponent(), msg.severity, text.rstrip("\x00")))
        elif kind == "OBSTACLE_DISTANCE":
            with self._lock:
                self.obstacle_distances.append(
                    WireObstacle(
                        now, msg.get_srcComponent(), msg.time_usec, msg.sensor_type, tuple(msg.distances),
                        msg.increment, msg.min_distance, msg.max_distance, msg.increment_f, msg.angle_offset,
                        msg.frame,
                    )
                )
        elif kind == "PARAM_REQUEST_LIST":
            self._send_params()

    def _send_params(self) -> None:
        pass

    def _run(self) -> None:
        hb_period = 1.0 / self.heartbeat_hz
        step_period = 0.01  # kinematics at 100 Hz, whatever is streamed
        next_hb = next_step = time.monotonic()
        last_step = next_step
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_hb:
                self._send_heartbeat()
                next_hb = now + hb_period
            if now >= next_step:
                self._integrate(now, now - last_step)
                last_step = now
                next_step = now + step_period
            self._send_due_telemetry(now)
            with self._lock:
                changed = self._watch_locked(now)
            if changed:
                self._send_heartbeat()
            if self.deaf:
                time.sleep(0.005)
                continue
            try:
                data = self._sock.recv(4096)
            except (TimeoutError, socket.timeout):
                continue
            except OSError:
                if self._stop.is_set():
                    return
                continue
            now = time.monotonic()
            try:
                msgs = self._mav.parse_buffer(data) or []
            except mavlink.MAVError:
                continue  # a corrupt datagram: the autopilot drops it too
            for msg in msgs:
                if msg.get_type() != "BAD_DATA":
                    self._handle(msg, now)


class Px4Peer(_AutopilotPeer):
    """The PX4 end of a UDP MAVLink link, run in a daemon thread.

    Args (besides :class:`_AutopilotPeer`'s):
        mode: initial flight mode name (see :data:`MODES`).
        telemetry_hz: rate of every telemetry message, Hz.
        offboard_loss_timeout_s: PX4's COM_OF_LOSS_T: OFFBOARD without setpoints this long -> Hold.
        offboard_min_setpoints: setpoints needed in the last second before OFFBOARD is accepted.
    """

    THREAD_NAME = "px4-peer"
    _TELEMETRY = (
        mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
        mavlink.MAVLINK_MSG_ID_ATTITUDE,
        mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE,
        mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
        mavlink.MAVLINK_MSG_ID_SYS_STATUS,
    )

    def __init__(
        self,
        port: int | None = None,
        *,
        mode: str = "POSCTL",
        armed: bool = True,
        heartbeat_hz: float = 5.0,
        telemetry_hz: float = 20.0,
        offboard_loss_timeout_s: float = 1.0,
        offboard_min_setpoints: int = 3,
        deny_modes: frozenset[str] = frozenset(),
        system_id: int = 1,
    ) -> None:
        super().__init__(port, mode=mode, armed=armed, heartbeat_hz=heartbeat_hz, deny_modes=deny_modes, system_id=system_id)
        self.telemetry_hz = telemetry_hz
        self.offboard_loss_timeout_s = offboard_loss_timeout_s
        self.offboard_min_setpoints = offboard_min_setpoints
        self._next_tel = time.monotonic()

    def _send_heartbeat(self) -> None:
        with self._lock:
            main, sub = MODES[self._mode]
            armed = self._armed
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
        custom = (main << 16) | (sub << 24)
        self._send(
            self._mav.heartbeat_encode(
                mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base, custom, mavlink.MAV_STATE_ACTIVE
            )
        )

    def _mode_asked(self, msg: mavlink.MAVLink_command_long_message) -> str | None:
        return _MODE_NAMES.get((int(msg.param2), int(msg.param3)))

    def _mode_refused_locked(self, wanted: str, now: float) -> bool:
        return wanted == "OFFBOARD" and not self._offboard_allowed_locked(now)  # PX4: no stream, no offboard

    def _velocity_locked(self, now: float) -> tuple[float, float, float, float]:
        return self._last_vel if self._mode == "OFFBOARD" else (0.0, 0.0, 0.0, 0.0)

    def _send_due_telemetry(self, now: float) -> None:
        if now < self._next_tel:
            return
        self._next_tel = now + 1.0 / self.telemetry_hz
        for msg_id in self._TELEMETRY:
            self._send(self._encode(msg_id))

    def _handle_other_command(self, msg: mavlink.MAVLink_command_long_message, now: float) -> int:
        if msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            return mavlink.MAV_RESULT_ACCEPTED
        return mavlink.MAV_RESULT_UNSUPPORTED

    def _send_params(self) -> None:
        self._send(self._mav.param_value_encode(b"COM_OF_LOSS_T", self.offboard_loss_timeout_s, 9, 1, 0))

    def _offboard_allowed_locked(self, now: float) -> bool:
        recent = [s for s in self.setpoints[-50:] if now - s.t_s <= 1.0]
        return len(recent) >= self.offboard_min_setpoints and now - recent[-1].t_s <= self.offboard_loss_timeout_s

    def _watch_locked(self, now: float) -> bool:
        lost = self._mode == "OFFBOARD" and (
            not self.setpoints or now - self.setpoints[-1].t_s > self.offboard_loss_timeout_s
        )
        if lost:
            self._set_mode_locked("HOLD", "offboard loss failsafe")
        return lost


class ArduCopterPeer(_AutopilotPeer):
    """The ArduCopter end of a UDP MAVLink link, run in a daemon thread.

    Args (besides :class:`_AutopilotPeer`'s):
        mode: initial flight mode name (see :data:`COPTER_MODES`).
        guid_timeout_s: ArduCopter's ``GUID_TIMEOUT``: a GUIDED velocity target is flown this long
            after it arrived, then the vehicle brakes and hovers in GUIDED, seconds.
        position_ok: whether the vehicle has a position estimate (LOITER, BRAKE and GUIDED need one:
            ArduCopter's ``requires_GPS``); without it those modes are refused, LOCAL_POSITION_NED is
            not sent, and EKF_STATUS_REPORT has no horizontal position flag. May be changed at any time.
    """

    OFFBOARD_MODE = "GUIDED"
    THREAD_NAME = "arducopter-peer"
    DIALECT = ardupilotmega  # EKF_STATUS_REPORT
    REFUSED = mavlink.MAV_RESULT_FAILED  # ArduPilot's answer to a mode change it refuses

    def __init__(
        self,
        port: int | None = None,
        *,
        mode: str = "LOITER",
        armed: bool = True,
        heartbeat_hz: float = 1.0,
        guid_timeout_s: float = 3.0,
        position_ok: bool = True,
        deny_modes: frozenset[str] = frozenset(),
        system_id: int = 1,
    ) -> None:
        super().__init__(port, mode=mode, armed=armed, heartbeat_hz=heartbeat_hz, deny_modes=deny_modes, system_id=system_id)
        self.guid_timeout_s = guid_timeout_s
        self.position_ok = position_ok
        self.interval_requests: list[tuple[float, int, float]] = []  # (t_s, message id, interval µs)
        self._intervals_s: dict[int, float] = {}
        self._next_send: dict[int, float] = {}

    @property
    def intervals_s(self) -> Mapping[int, float]:
        """The streams asked for: message id -> interval, seconds."""
        with self._lock:
            return dict(self._intervals_s)

    def _send_heartbeat(self) -> None:
        with self._lock:
            number = COPTER_MODES[self._mode]
            armed = self._armed
        base = (
            mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
            | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
        )
        self._send(
            self._mav.heartbeat_encode(
                mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, base, number, mavlink.MAV_STATE_ACTIVE
            )
        )

    def _mode_asked(self, msg: mavlink.MAVLink_command_long_message) -> str | None:
        if not int(msg.param1) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return None  # ArduPilot sets modes by custom mode only
        return _COPTER_MODE_NAMES.get(int(msg.param2))

    def _mode_refused_locked(self, wanted: str, now: float) -> bool:
        return wanted in ("GUIDED", "LOITER", "BRAKE") and not self.position_ok

    def _velocity_locked(self, now: float) -> tuple[float, float, float, float]:
        if self._mode != "GUIDED" or not self.setpoints:
            return (0.0, 0.0, 0.0, 0.0)
        last = self.setpoints[-1]
        if last.mode != "GUIDED" or now - last.t_s > self.guid_timeout_s:
            return (0.0, 0.0, 0.0, 0.0)  # GUID_TIMEOUT: brake and hover, still in GUIDED
        return self._last_vel

    def _send_due_telemetry(self, now: float) -> None:
        with self._lock:
            due = [i for i, period in self._intervals_s.items() if now >= self._next_send.get(i, 0.0)]
            for i in due:
                self._next_send[i] = now + self._intervals_s[i]
            position_ok = self.position_ok
        for msg_id in due:
            if msg_id == mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED and not position_ok:
                continue  # ArduPilot sends no local position without an estimate
            self._send(self._encode(msg_id))

    def _handle_other_command(self, msg: mavlink.MAVLink_command_long_message, now: float) -> int:
        if msg.command != mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            return mavlink.MAV_RESULT_UNSUPPORTED
        msg_id, interval_us = int(msg.param1), float(msg.param2)
        self.interval_requests.append((now, msg_id, interval_us))
        if not abs(msg.param3) < 1e-6:
            return mavlink.MAV_RESULT_DENIED  # ArduPilot: param3 (response target) must be 0, NaN is not
        if msg_id not in _COPTER_STREAMABLE:
            return mavlink.MAV_RESULT_FAILED
        if interval_us <= 0.0:
            self._intervals_s.pop(msg_id, None)  # -1 off; 0 the default, and the default here is off
        else:
            self._intervals_s[msg_id] = interval_us * 1e-6
            self._next_send[msg_id] = now
        return mavlink.MAV_RESULT_ACCEPTED
