"""Config sections of the service shell: camera source, vehicle link, ZeroMQ bus, daemon.

Every field: type, default, bounds, unit in its name, description.
Sections or fields that the running service cannot change without a restart (the camera, the vehicle
connection, the bus endpoints and keys) are listed in :data:`RESTART_FIELDS`; a live ``set_config`` or
``reload`` reports them and leaves them as they are until the next start, except the scene placement
of :data:`LIVE_CAMERA_FIELDS`.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Literal

from pydantic import Field, field_validator, model_validator

from companion.config._base import StrictModel
from companion.config.view import VIEW_RESTART_FIELDS

#: The ZED's UVC modes: one eye's (width, height) -> the frame rates it offers, Hz. The UVC frame is
#: side by side, so its width is twice the eye's.
ZED_MODES: Mapping[tuple[int, int], tuple[float, ...]] = MappingProxyType(
    {
        (2208, 1242): (15.0,),
        (1920, 1080): (30.0, 15.0),
        (1280, 720): (60.0, 30.0, 15.0),
        (672, 376): (100.0, 60.0, 30.0, 15.0),
    }
)

#: Dotted paths (a section, or section.field) that take effect only at the next start.
RESTART_FIELDS: tuple[str, ...] = (
    "camera",
    "bus",
    "vehicle.connection",
    "vehicle.autopilot",
    "vehicle.telemetry_rate_hz",
    "vehicle.component_id",
    "vehicle.system_id",
) + tuple(f"view.{f}" for f in VIEW_RESTART_FIELDS)
#: Fields inside a restart-only section that apply live anyway: where the simulated scene lies in the
#: autopilot's frame (the PX4 SITL harness places the course at the hovering vehicle just before
#: ``engage``).
LIVE_CAMERA_FIELDS: tuple[str, ...] = ("sim_origin_north_m", "sim_origin_east_m", "sim_origin_down_m", "sim_origin_yaw_deg")

_CONNECTION_SCHEMES = ("udpin://", "udpout://", "udp://", "tcpin://", "tcpout://", "tcp://", "serial://")
_ZMQ_SCHEMES = ("tcp://", "ipc://", "inproc://")
#: An endpoint of ``auto``: an ipc:// socket in the service's runtime directory (companion/service/runtime.py).
AUTO_ENDPOINT = "auto"


def _is_loopback_tcp(endpoint: str) -> bool:
    host = endpoint.removeprefix("tcp://").rsplit(":", 1)[0].strip("[]")
    return host in ("127.0.0.1", "localhost", "::1") or host.startswith("127.")


def zed_modes_text() -> str:
    """The ZED modes as one line, e.g. ``2208x1242@15, 1920x1080@30/15, ...`` (per eye)."""
    return ", ".join(
        f"{w}x{h}@{'/'.join(f'{r:g}' for r in rates)}" for (w, h), rates in ZED_MODES.items()
    )


class CameraConfig(StrictModel):
    """Where frames come from (restart to change)."""

    source: Literal["sim", "uvc", "replay"] = Field(
        default="sim",
        description="sim: the built-in renderer; uvc: a camera over UVC (V4L2), see model; replay: a recording.",
    )
    model: Literal["zed", "sbs", "pair"] = Field(
        default="zed",
        description=(
            "uvc: which camera. zed: a ZED (side by side, its modes are checked); sbs: any side-by-side UVC "
            "stereo camera, in any mode it offers; pair: two V4L2 cameras, one per eye (device = left, "
            "device_right = right), grabbed as close in time as the driver allows, the skew between them "
            "reported in health. sbs and pair need a calibration file (calibration.file; make one with "
            "`companion calibrate stereo`): the service refuses to start without one."
        ),
    )
    width_px: int = Field(default=672, ge=64, le=4416, description="Width of ONE eye, pixels (ZED: 2208/1920/1280/672).")
    height_px: int = Field(default=376, ge=48, le=2160, description="Height of one eye, pixels (ZED: 1242/1080/720/376).")
    fps_hz: float = Field(default=30.0, gt=0.0, le=120.0, description="Requested frame rate, frames per second.")
    device: str = Field(
        default="/dev/video0",
        min_length=1,
        max_length=200,
        description="uvc: the V4L2 device node of the camera (or its index, e.g. '0'); pair: the left eye's.",
    )
    device_right: str | None = Field(
        default=None,
        min_length=1,
        max_length=200,
        description="uvc, model pair: the V4L2 device node (or index) of the right eye's camera.",
    )
    fourcc: str = Field(
        default="YUYV",
        min_length=4,
        max_length=4,
        description=(
            "uvc: the pixel format asked of the driver, four characters: YUYV (uncompressed; the ZED's) or "
            "MJPG (what many USB cameras need for large modes at full rate); `v4l2-ctl --list-formats-ext` "
            "lists what a camera offers."
        ),
    )
    pixels: Literal["luma", "bgr"] = Field(
        default="luma",
        description=(
            "uvc, models zed and sbs, fourcc YUYV: luma: the camera's YUYV bytes are taken as they come "
            "(OpenCV's CAP_PROP_CONVERT_RGB off) and their Y is the grey the pipeline matches: no colour "
            "decoding on the CPU, 2 bytes a pixel to the GPU instead of 3; the preview, recordings and "
            "calibration views decode colour for what they show. bgr: OpenCV decodes every frame to BGR "
            "first. Other fourccs (MJPG) and model pair always decode to BGR."
        ),
    )
    pair_max_skew_ms: float = Field(
        default=8.0,
        gt=0.0,
        le=1000.0,
        description=(
            "uvc, model pair: when the driver's timestamps of the two eyes' frames differ by more than "
            "this, the earlier camera's next frame is taken instead (once per frame), milliseconds. The "
            "skew is reported in health (camera.skew_ms); an unsynchronised pair at 30 fps can be up to "
            "33 ms apart, which at 1 m/s is 3 cm of motion between the eyes."
        ),
    )
    open_timeout_s: float = Field(
        default=10.0,
        gt=0.0,
        le=600.0,
        description=(
            "At start, the service waits this long for the first frame; none by then is a startup "
            "failure (exit code 78, not restarted in a loop), seconds."
        ),
    )
    reconnect_initial_s: float = Field(
        default=0.2, gt=0.0, le=10.0, description="First wait before reopening a camera that disappeared, seconds."
    )
    reconnect_max_s: float = Field(
        default=5.0, gt=0.0, le=120.0, description="Longest wait between reopen attempts (the back-off doubles up to it), seconds."
    )
    replay_path: Path | None = Field(
        default=None,
        description=(
            "replay: a recording written by `companion record`: a folder of PNG frames with "
            "timestamps.csv, or a video file (.mkv/.avi) with <file>.timestamps.csv beside it; or a "
            "recorded flight of another tool: an ASL/EuRoC folder (mav0/cam0, mav0/cam1), a ROS 1 .bag or a "
            "ROS 2 bag (its folder, or the .db3/.mcap in it; needs `pip install 'companion[recorded]'`). "
            "width_px and height_px must be the recording's eye size."
        ),
    )
    replay_left_topic: str | None = Field(
        default=None,
        min_length=1,
        max_length=300,
        description=(
            "replay of a rosbag: the left eye's image topic (sensor_msgs/Image or CompressedImage); unset = "
            "the topic with left, cam0 or infra1 in its name that has a right, cam1 or infra2 twin."
        ),
    )
    replay_right_topic: str | None = Field(
        default=None, min_length=1, max_length=300, description="replay of a rosbag: the right eye's image topic (with replay_left_topic)."
    )
    replay_max_skew_ms: float = Field(
        default=5.0,
        gt=0.0,
        le=1000.0,
        description=(
            "replay of an ASL folder or a rosbag: a left and a right frame whose timestamps differ by more than "
            "this are not a pair (the eyes would see the scene at two moments), milliseconds; the frame left "
            "without a partner is skipped."
        ),
    )
    replay_rate_hz: float | None = Field(
        default=None,
        gt=0.0,
        le=1000.0,
        description="replay: deliver frames at this rate, Hz; unset = at the recorded timestamps (or fps_hz without them).",
    )
    replay_loop: bool = Field(default=False, description="replay: start again at the end instead of stopping.")
    replay_preload: bool = Field(
        default=False,
        description="replay: decode every frame into memory at open, so decoding costs nothing while streaming (benchmarks).",
    )
    sim_north_m: float = Field(
        default=2.0, ge=-1000.0, le=1000.0, description="sim: camera position north in the corridor scene, metres."
    )
    sim_east_m: float = Field(
        default=0.0, ge=-1000.0, le=1000.0, description="sim: camera position east (0 = the corridor's axis), metres."
    )
    sim_altitude_m: float = Field(default=1.5, gt=0.0, le=100.0, description="sim: camera altitude above the ground, metres.")
    sim_yaw_deg: float = Field(
        default=0.0, ge=-180.0, le=180.0, description="sim: heading, degrees clockwise from north (the corridor runs north)."
    )
    sim_scene_seed: int = Field(default=0, ge=0, le=2**31 - 1, description="sim: seed of the corridor's obstacles and textures.")
    sim_obstacles: int = Field(default=18, ge=0, le=200, description="sim: number of obstacles in the corridor.")
    sim_noise_grey: float = Field(
        default=0.0, ge=0.0, le=50.0, description="sim: standard deviation of the per-frame sensor noise, grey levels (0 = none)."
    )
    sim_world: Literal["corridor", "course"] = Field(
        default="corridor",
        description=(
            "sim: the scene: 'corridor' (sim_scene_seed, sim_obstacles) or 'course', a course of the "
            "simulator's library (sim_course, sim_course_seed), as `companion sim` and `companion sitl` fly it."
        ),
    )
    sim_course: Literal["corridor", "doorway", "forest", "pitch", "side", "deadend", "office", "detour", "head-on", "wall"] = Field(
        default="doorway", description="sim, world 'course': the course kind."
    )
    sim_course_seed: int = Field(default=0, ge=0, le=2**31 - 1, description="sim, world 'course': the course seed.")
    sim_pose: Literal["fixed", "telemetry"] = Field(
        default="fixed",
        description=(
            "sim: where the camera is: 'fixed' at sim_north_m/sim_east_m/sim_altitude_m/sim_yaw_deg, or "
            "'telemetry': the vehicle's pose as the autopilot reports it over the vehicle link (PX4 SITL "
            "in the loop), placed in the scene by sim_origin_*."
        ),
    )
    sim_origin_north_m: float = Field(
        default=0.0, ge=-1e5, le=1e5, description="sim, telemetry pose: the scene origin's north in the autopilot's local frame, metres."
    )
    sim_origin_east_m: float = Field(
        default=0.0, ge=-1e5, le=1e5, description="sim, telemetry pose: the scene origin's east in the autopilot's local frame, metres."
    )
    sim_origin_down_m: float = Field(
        default=0.0,
        ge=-1e4,
        le=1e4,
        description="sim, telemetry pose: the scene's ground as a local down coordinate of the autopilot (its z on the ground), metres.",
    )
    sim_origin_yaw_deg: float = Field(
        default=0.0,
        ge=-180.0,
        le=180.0,
        description="sim, telemetry pose: the scene's north axis as a heading in the autopilot's local frame, degrees clockwise from north.",
    )
    sim_pose_max_age_s: float = Field(
        default=0.3,
        gt=0.0,
        le=5.0,
        description=(
            "sim, telemetry pose: a pose older than this gives no frame (as from a camera that stopped), "
            "so the service's stale-frame failsafe acts when telemetry stops, seconds."
        ),
    )

    @model_validator(mode="after")
    def _check(self) -> CameraConfig:
        if self.reconnect_max_s < self.reconnect_initial_s:
            raise ValueError(
                f"reconnect_max_s ({self.reconnect_max_s}) must be >= reconnect_initial_s ({self.reconnect_initial_s})"
            )
        if not all(33 <= ord(ch) < 127 for ch in self.fourcc):
            raise ValueError(f"fourcc must be four printable characters (e.g. YUYV, MJPG), got {self.fourcc!r}")
        if self.model == "pair" and self.source == "uvc":
            if self.device_right is None:
                raise ValueError("model = 'pair' needs device_right (the right eye's camera; device is the left's)")
            if self.device_right == self.device:
                raise ValueError(f"device and device_right are the same ({self.device}); a pair needs two cameras")
        if self.source == "uvc" and self.model == "zed":
            rates = ZED_MODES.get((self.width_px, self.height_px))
            if rates is None:
                raise ValueError(
                    f"{self.width_px}x{self.height_px} is not a ZED mode; one eye must be one of {zed_modes_text()} "
                    "(another side-by-side camera: model = 'sbs'; two cameras: model = 'pair')"
                )
            if self.fps_hz not in rates:
                raise ValueError(
                    f"the ZED gives {self.width_px}x{self.height_px} at "
                    f"{'/'.join(f'{r:g}' for r in rates)} Hz, not {self.fps_hz:g} Hz"
                )
        if self.source == "replay" and self.replay_path is None:
            raise ValueError("source = 'replay' needs replay_path (a recording from `companion record`)")
        if (self.replay_left_topic is None) != (self.replay_right_topic is None):
            raise ValueError("replay_left_topic and replay_right_topic go together: set both or neither")
        return self


class VehicleConfig(StrictModel):
    """The autopilot link (MAVSDK) and how the service enters and leaves offboard."""

    radius_m: float = Field(
        default=0.25,
        gt=0.0,
        le=5.0,
        description=(
            "Radius of a sphere round the vehicle's centre that holds the whole airframe, props "
            "included, m: the local planner keeps every surface outside it (docs/planner.md)."
        ),
    )
    odometry_drift_m_s: float = Field(
        default=0.5,
        ge=0.0,
        le=2.0,
        description=(
            "How far the velocity the autopilot reports may be from the vehicle's real motion, m/s "
            "(a velocity estimate off by a few tenths of a m/s, wind it does not see): the local "
            "planner measures the difference from the reported position's track, predicts its paths "
            "with it and takes it off the setpoint, up to this much (0 = the reported velocity is "
            "the motion)."
        ),
    )
    connection: str = Field(
        default="udpin://0.0.0.0:14540",
        min_length=1,
        max_length=200,
        description=(
            "MAVSDK connection URL: udpin://0.0.0.0:14540 for PX4 SITL, tcpout://127.0.0.1:5762 for ArduPilot "
            "SITL (its SERIAL1), serial:///dev/ttyTHS1:921600 on a Jetson (restart to change)."
        ),
    )
    autopilot: Literal["auto", "px4", "ardupilot"] = Field(
        default="auto",
        description=(
            "Which autopilot flies: 'px4' (OFFBOARD), 'ardupilot' (ArduCopter, GUIDED), or 'auto': the one the "
            "heartbeat names. A heartbeat from another autopilot than the one set is a startup failure "
            "(restart to change)."
        ),
    )
    telemetry_rate_hz: float = Field(
        default=30.0,
        ge=1.0,
        le=100.0,
        description=(
            "ArduPilot: the rate asked for position, velocity and attitude on the service's link "
            "(MAV_CMD_SET_MESSAGE_INTERVAL; ArduCopter streams almost nothing unasked). PX4's own stream "
            "rates are left as they are (restart to change), Hz."
        ),
    )
    setpoint_rate_hz: float = Field(
        default=20.0, ge=2.0, le=100.0, description="Rate at which setpoints are streamed, whatever the vision rate, Hz."
    )
    connect_timeout_s: float = Field(
        default=10.0,
        gt=0.0,
        le=600.0,
        description="Wait this long for the autopilot's heartbeat before logging a warning (the service keeps waiting), seconds.",
    )
    offboard_prestream_s: float = Field(
        default=0.5,
        ge=0.0,
        le=5.0,
        description="On engage, zero setpoints are streamed this long before offboard is requested (PX4 refuses offboard without a stream), seconds.",
    )
    engage_timeout_s: float = Field(
        default=3.0,
        gt=0.0,
        le=30.0,
        description="Offboard not confirmed by the autopilot's heartbeat this long after it was requested: the engage is abandoned, seconds.",
    )
    hold_retry_s: float = Field(
        default=2.0,
        gt=0.0,
        le=30.0,
        description=(
            "While the service is leaving offboard to Hold and the vehicle still reports OFFBOARD, Hold is "
            "requested again after this long (longer than one heartbeat period), seconds."
        ),
    )
    leave_timeout_s: float = Field(
        default=10.0,
        gt=0.0,
        le=120.0,
        description=(
            "Hold not confirmed this long after the service began leaving offboard: it stops streaming "
            "setpoints so that PX4's own offboard-loss failsafe acts, seconds."
        ),
    )
    require_armed_to_engage: bool = Field(
        default=True, description="Refuse 'engage' while the vehicle is disarmed (the service never arms it)."
    )
    engage_on_offboard_switch: bool = Field(
        default=False,
        description=(
            "Engage from the sticks: while the service is ready (vehicle connected and armed, frames fresh, "
            "not in offboard) it streams zero-velocity setpoints, so that a pilot's switch to PX4's Offboard "
            "(an RC switch or QGroundControl; ArduCopter: GUIDED) is accepted and hands the vehicle to the "
            "service, with every check of 'engage'. Switching away gives it back. Zero velocity in any other "
            "mode is ignored by the autopilot (docs/service.md)."
        ),
    )
    component_id: int = Field(
        default=196,
        ge=1,
        le=254,
        description=(
            "The service's MAVLink component id on the companion computer (196: MAV_COMP_ID_OBSTACLE_AVOIDANCE; "
            "restart to change)."
        ),
    )
    system_id: int = Field(
        default=1,
        ge=1,
        le=254,
        description=(
            "The service's MAVLink system id: the vehicle's (the autopilot's MAV_SYS_ID / SYSID_THISMAV), so that "
            "the ground station lists the service as a component of the vehicle and PX4 watches its heartbeat "
            "(COM_OBC_LOSS_T: 'Connection to mission computer lost'); restart to change."
        ),
    )
    heartbeat_rate_hz: float = Field(
        default=1.0,
        ge=0.2,
        le=10.0,
        description=(
            "Rate of the service's own HEARTBEAT carrying its state (standby, active while engaged, critical "
            "in failsafe, while degraded or without camera), Hz."
        ),
    )
    status_text: bool = Field(
        default=True,
        description="Send STATUSTEXT to the ground station on every state change, new brake or pause, and camera loss.",
    )
    status_text_min_interval_s: float = Field(
        default=1.0,
        ge=0.05,
        le=60.0,
        description=(
            "STATUSTEXT rate limit: one line per this long once the burst is spent (a newer line replaces a "
            "waiting one, so the last word always arrives), seconds."
        ),
    )
    status_text_burst: int = Field(
        default=3, ge=1, le=20, description="STATUSTEXT lines that may go out back to back before the rate limit applies."
    )

    @field_validator("connection")
    @classmethod
    def _scheme(cls, v: str) -> str:
        if not v.startswith(_CONNECTION_SCHEMES):
            raise ValueError(f"connection {v!r} must start with one of {', '.join(_CONNECTION_SCHEMES)}")
        return v

    @model_validator(mode="after")
    def _check(self) -> VehicleConfig:
        if self.hold_retry_s >= self.leave_timeout_s:
            raise ValueError(
                f"hold_retry_s ({self.hold_retry_s}) must be shorter than leave_timeout_s ({self.leave_timeout_s})"
            )
        return self


class BusConfig(StrictModel):
    """The ZeroMQ control plane (restart to change)."""

    health_endpoint: str = Field(
        default="auto",
        min_length=1,
        max_length=200,
        description=(
            "PUB endpoint for health messages (JSON). auto: ipc://<runtime dir>/health.sock (the systemd "
            "RuntimeDirectory /run/companion, else $XDG_RUNTIME_DIR/companion, else /tmp/companion-<uid>), "
            "mode 0660. tcp:// only on loopback unless CURVE keys are set."
        ),
    )
    control_endpoint: str = Field(
        default="auto",
        min_length=1,
        max_length=200,
        description=(
            "ROUTER endpoint for JSON requests. auto: ipc://<runtime dir>/control.sock, mode 0660, so only "
            "the service's user and group can command it. tcp:// only on loopback (then every local user "
            "can) unless CURVE keys are set."
        ),
    )
    health_rate_hz: float = Field(
        default=10.0, gt=0.0, le=100.0, description="Health messages per second (plus one on every state change), Hz."
    )
    max_request_bytes: int = Field(
        default=65536,
        ge=256,
        le=1_048_576,
        description=(
            "Largest control request accepted, bytes; up to twice this gets an error reply, anything larger "
            "is cut off by ZeroMQ itself (the connection is dropped before the message is buffered)."
        ),
    )
    requests_per_s_per_client: float = Field(
        default=50.0,
        gt=0.0,
        le=1000.0,
        description=(
            "Request budget of one connection, requests per second (a burst of as many is allowed); "
            "beyond it a request gets a 'RateLimited' error reply and is not carried out."
        ),
    )
    max_requests_per_s: float = Field(
        default=200.0,
        gt=0.0,
        le=10000.0,
        description="Request budget of all connections together, requests per second; beyond it, 'RateLimited'.",
    )
    max_connections: int = Field(
        default=32,
        ge=1,
        le=1000,
        description=(
            "Control connections at once; a further one is refused in the ZeroMQ handshake. A connection "
            "that does not complete its handshake within 2 s is closed."
        ),
    )
    curve_server_secret_key_file: Path | None = Field(
        default=None,
        description=(
            "CURVE: the server's secret certificate (a zmq.auth .key_secret file). Set together with "
            "curve_authorized_keys_dir to require CURVE authentication on both sockets."
        ),
    )
    curve_authorized_keys_dir: Path | None = Field(
        default=None,
        description="CURVE: a folder of the public certificates (.key files) of the clients allowed to connect.",
    )

    @field_validator("health_endpoint", "control_endpoint")
    @classmethod
    def _zmq_scheme(cls, v: str) -> str:
        if v != AUTO_ENDPOINT and not v.startswith(_ZMQ_SCHEMES):
            raise ValueError(f"endpoint {v!r} must be 'auto' or start with one of {', '.join(_ZMQ_SCHEMES)}")
        return v

    @model_validator(mode="after")
    def _check(self) -> BusConfig:
        if (self.curve_server_secret_key_file is None) != (self.curve_authorized_keys_dir is None):
            raise ValueError(
                "curve_server_secret_key_file and curve_authorized_keys_dir must be set together (or neither)"
            )
        if (
            self.health_endpoint == self.control_endpoint
            and self.health_endpoint != AUTO_ENDPOINT
            and not self.health_endpoint.endswith((":*", ":0"))
        ):
            raise ValueError(f"health_endpoint and control_endpoint are the same ({self.health_endpoint})")
        if self.curve_server_secret_key_file is None:
            # Without authentication the control plane (which can engage the vehicle) must not be
            # reachable from the network.
            for name in ("health_endpoint", "control_endpoint"):
                endpoint = getattr(self, name)
                if endpoint.startswith("tcp://") and not _is_loopback_tcp(endpoint):
                    raise ValueError(
                        f"{name} {endpoint!r} is reachable from the network: bind to 127.0.0.1 or ipc://, "
                        "or set curve_server_secret_key_file and curve_authorized_keys_dir"
                    )
        return self

    @property
    def curve_enabled(self) -> bool:
        return self.curve_server_secret_key_file is not None


class ServiceConfig(StrictModel):
    """The daemon itself."""

    autostart: bool = Field(
        default=False,
        description="Engage once at start, as soon as the vehicle and the camera are ready, without an 'engage' request (tests and simulation only).",
    )
    override_max_duration_s: float = Field(
        default=10.0,
        gt=0.0,
        le=300.0,
        description="Longest manual override an 'override' request may ask for; then the service is automatic again, seconds.",
    )
    override_respects_brake: bool = Field(
        default=True,
        description="During an override, a BRAKE decision (something near ahead) still zeroes the forward speed.",
    )
    skip_late_frames: bool = Field(
        default=True,
        description=(
            "When the pipeline is free and the frame waiting for it is older than half a frame "
            "interval, wait for the next frame (due sooner) instead: keeps the frame-to-setpoint "
            "latency bounded when the pipeline is slower than the camera. Skipped frames count as dropped."
        ),
    )
    shutdown_timeout_s: float = Field(
        default=5.0,
        gt=0.0,
        le=60.0,
        description="On SIGTERM, wait at most this long for Hold to be confirmed before closing anyway, seconds.",
    )
