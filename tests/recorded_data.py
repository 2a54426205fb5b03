"""Recorded flights the tests make themselves: rendered stereo pairs (with their true depth) written in
the ASL/EuRoC layout and into ROS 1 and ROS 2 bags through rosbags' writers, and a known rig written as
each calibration family ``companion calibrate import`` reads."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from companion.core.geometry import StereoGeometry
from companion.sim.render import Box, Pose, Scene, StereoRenderer

#: The rendered rig: small eyes so that the tests run fast; a 11 cm baseline as the EuRoC MAV's.
GEOMETRY = StereoGeometry.ideal(320, 200, hfov_deg=90.0, baseline_m=0.11)
#: The wall ahead (its face), metres north of the start.
WALL_M = 6.0
#: Frame period, nanoseconds (20 Hz, the EuRoC cameras' rate); the first frame's time.
PERIOD_NS = 50_000_000
T0_NS = 1_403_636_579_763_555_584


@dataclass(frozen=True)
class Flight:
    """Rendered pairs along a straight approach to a wall.

    Attributes:
        left, right: uint8 ``(H, W)`` grey eyes, one per frame.
        times_ns: each frame's time, nanoseconds.
        centre_depth_m: the true depth of the image centre in each frame, metres.
    """

    left: list[np.ndarray]
    right: list[np.ndarray]
    times_ns: list[int]
    centre_depth_m: list[float]


def render_flight(n: int = 12, start_m: float = 0.0, speed_m_s: float = 1.0, seed: int = 3) -> Flight:
    """``n`` frames at 20 Hz, flying north at ``speed_m_s`` toward a textured wall at :data:`WALL_M`."""
    scene = Scene(obstacles=(Box.on_ground(WALL_M + 0.05, 0.0, (0.1, 6.0, 4.0)),), ground=True)
    renderer = StereoRenderer(GEOMETRY, scene, seed=seed)
    left, right, times, depth = [], [], [], []
    for i in range(n):
        north = start_m + speed_m_s * i * PERIOD_NS / 1e9
        r = renderer.render(Pose.at(north, 0.0, 1.5))
        left.append(cv2.cvtColor(r.left_bgr, cv2.COLOR_BGR2GRAY))
        right.append(cv2.cvtColor(r.right_bgr, cv2.COLOR_BGR2GRAY))
        times.append(T0_NS + i * PERIOD_NS)
        h, w = r.depth_m.shape
        depth.append(float(r.depth_m[h // 2, w // 2]))
    return Flight(left, right, times, depth)


def _k(geometry: StereoGeometry) -> list[float]:
    g = geometry
    return [g.focal_px, g.focal_px, g.cx_px, g.cy_px]


def write_asl(
    folder: Path, flight: Flight, *, drop_right: tuple[int, ...] = (), skip: tuple[int, ...] = (), sensor_yaml: bool = True
) -> Path:
    """``folder/mav0/cam0`` and ``cam1`` as the EuRoC datasets hold them: ``data.csv``, ``data/<ns>.png``,
    ``sensor.yaml`` (the rendered rig: no distortion, cam1 :data:`GEOMETRY`'s baseline to the right).
    ``drop_right``: frames whose right image is left out (unmatched); ``skip``: frames left out of both
    (a gap). Returns ``folder``."""
    b = GEOMETRY.baseline_m
    for cam, images in (("cam0", flight.left), ("cam1", flight.right)):
        data = folder / "mav0" / cam / "data"
        data.mkdir(parents=True, exist_ok=True)
        rows = ["#timestamp [ns],filename"]
        for i, (t, image) in enumerate(zip(flight.times_ns, images)):
            if i in skip or (cam == "cam1" and i in drop_right):
                continue
            cv2.imwrite(str(data / f"{t}.png"), image)
            rows.append(f"{t},{t}.png")
        (folder / "mav0" / cam / "data.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
        if sensor_yaml:
            x = 0.0 if cam == "cam0" else b
            tbs = [1.0, 0.0, 0.0, x, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]
            (folder / "mav0" / cam / "sensor.yaml").write_text(
                "%YAML:1.0\n"
                "sensor_type: camera\n"
                f"comment: rendered {cam}\n"
                "T_BS:\n  cols: 4\n  rows: 4\n"
                f"  data: [{', '.join(repr(v) for v in tbs)}]\n"
                "rate_hz: 20\n"
                f"resolution: [{GEOMETRY.width_px}, {GEOMETRY.height_px}]\n"
                "camera_model: pinhole\n"
                f"intrinsics: [{', '.join(repr(v) for v in _k(GEOMETRY))}] #fu, fv, cu, cv\n"
                "distortion_model: radial-tangential\n"
                "distortion_coefficients: [0.0, 0.0, 0.0, 0.0]\n",
                encoding="utf-8",
            )
    return folder


def _camera_info_fields(eye: int) -> dict[str, np.ndarray]:
    g = GEOMETRY
    K = np.array([g.focal_px, 0.0, g.cx_px, 0.0, g.focal_px, g.cy_px, 0.0, 0.0, 1.0])
    P = np.array([g.focal_px, 0.0, g.cx_px, -g.focal_px * g.baseline_m * eye, 0.0, g.focal_px, g.cy_px, 0.0, 0.0, 0.0, 1.0, 0.0])
    return {"K": K, "D": np.zeros(5), "R": np.eye(3).reshape(-1), "P": P}


def write_bag(
    path: Path, flight: Flight, *, ros1: bool = False, compressed: bool = False, camera_info: bool = True,
    encoding: str = "mono8", storage: str = "sqlite3",
) -> Path:
    """The flight as a ZED-wrapper-like bag: ``/zed/left/image_rect_gray`` and ``/zed/right/image_rect_gray``
    (``sensor_msgs/Image`` in ``encoding``, or ``CompressedImage`` PNGs), and ``/zed/left/camera_info``,
    ``/zed/right/camera_info`` with the rendered rig. ROS 2 (``path`` is the bag's folder; ``storage``
    sqlite3 or mcap) or ROS 1 (``path`` is the ``.bag``). Returns ``path``."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    T = store.types
    Time = T["builtin_interfaces/msg/Time"]
    Header = T["std_msgs/msg/Header"]
    Image = T["sensor_msgs/msg/Image"]
    Compressed = T["sensor_msgs/msg/CompressedImage"]
    Info = T["sensor_msgs/msg/CameraInfo"]
    Roi = T["sensor_msgs/msg/RegionOfInterest"]
    img_type = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
    suffix = "image_rect_gray/compressed" if compressed else "image_rect_gray"

    def header(t: int) -> object:
        stamp = Time(sec=t // 1_000_000_000, nanosec=t % 1_000_000_000)
        return Header(seq=0, stamp=stamp, frame_id="zed_left") if ros1 else Header(stamp=stamp, frame_id="zed_left")

    def image_msg(image: np.ndarray, t: int) -> object:
        if compressed:
            ok, png = cv2.imencode(".png", image)
            assert ok
            return Compressed(header=header(t), format="mono8; png compressed", data=png.reshape(-1))
        data = image
        if encoding == "bgr8":
            data = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        elif encoding == "rgb8":
            data = cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
        h, w = image.shape
        ch = 1 if encoding == "mono8" else 3
        return Image(header=header(t), height=h, width=w, encoding=encoding, is_bigendian=0, step=w * ch, data=np.ascontiguousarray(data).reshape(-1))

    def info_msg(eye: int, t: int) -> object:
        f = _camera_info_fields(eye)
        roi = Roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        names = ("D", "K", "R", "P") if ros1 else ("d", "k", "r", "p")
        return Info(
            header=header(t), height=GEOMETRY.height_px, width=GEOMETRY.width_px, distortion_model="plumb_bob",
            **dict(zip(names, (f["D"], f["K"], f["R"], f["P"]))), binning_x=0, binning_y=0, roi=roi,
        )

    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        writer = Writer(path, version=8, storage_plugin=StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3)
    with writer:
        conns = {
            "left": writer.add_connection(f"/zed/left/{suffix}", img_type, typestore=store),
            "right": writer.add_connection(f"/zed/right/{suffix}", img_type, typestore=store),
        }
        if camera_info:
            conns["left_info"] = writer.add_connection("/zed/left/camera_info", "sensor_msgs/msg/CameraInfo", typestore=store)
            conns["right_info"] = writer.add_connection("/zed/right/camera_info", "sensor_msgs/msg/CameraInfo", typestore=store)
        for i, t in enumerate(flight.times_ns):
            # The right eye's message is written a little later, as a driver publishes it.
            writer.write(conns["left"], t, serialize(image_msg(flight.left[i], t), img_type))
            writer.write(conns["right"], t + 1000, serialize(image_msg(flight.right[i], t), img_type))
            if camera_info and i == 0:
                writer.write(conns["left_info"], t, serialize(info_msg(0, t), "sensor_msgs/msg/CameraInfo"))
                writer.write(conns["right_info"], t, serialize(info_msg(1, t), "sensor_msgs/msg/CameraInfo"))
    return path
