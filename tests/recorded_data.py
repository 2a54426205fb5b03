"""Recorded flights the tests make themselves: rendered stereo pairs (with their true depth) written in
the ASL/EuRoC layout and into ROS 1 and ROS 2 bags through rosbags' writers, and a known rig written as
each calibration family ``companion calibrate import`` reads."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from calib_data import Rig
from companion.core.calibration import StereoCalibration
from companion.core.geometry import StereoGeometry
from companion.core.rectifier import Rectifier
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


def render_flight(
    n: int = 12, start_m: float = 0.0, speed_m_s: float = 1.0, seed: int = 3, rig: Rig | None = None
) -> Flight:
    """``n`` frames at 20 Hz, flying north at ``speed_m_s`` toward a textured wall at :data:`WALL_M`.

    With ``rig``, the frames are what that raw rig's eyes see (its lens distortion and the rotation
    between its eyes): the scene is rendered by the rig's rectified geometry and each raw pixel takes
    the rectified pixel its ray falls on (``cv2.undistortPoints`` with the rectification); ``centre_depth_m``
    is then the rectified image's centre."""
    scene = Scene(obstacles=(Box.on_ground(WALL_M + 0.05, 0.0, (0.1, 6.0, 4.0)),), ground=True)
    maps = None
    geometry = GEOMETRY
    if rig is not None:
        rect = Rectifier(StereoCalibration(rig.K1, rig.D1, rig.K2, rig.D2, rig.R, rig.T, rig.image_size))
        geometry = rect.geometry
        w, h = rig.image_size
        grid = np.stack(np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)), axis=-1).reshape(-1, 1, 2)
        maps = []
        for K, D, Rr, P in ((rig.K1, rig.D1, rect.R1, rect.P1), (rig.K2, rig.D2, rect.R2, rect.P2)):
            m = cv2.undistortPoints(grid, K, D, R=Rr, P=P).reshape(h, w, 2).astype(np.float32)
            maps.append((m[..., 0], m[..., 1]))
    renderer = StereoRenderer(geometry, scene, seed=seed)
    left, right, times, depth = [], [], [], []
    for i in range(n):
        north = start_m + speed_m_s * i * PERIOD_NS / 1e9
        r = renderer.render(Pose.at(north, 0.0, 1.5))
        eyes = [cv2.cvtColor(r.left_bgr, cv2.COLOR_BGR2GRAY), cv2.cvtColor(r.right_bgr, cv2.COLOR_BGR2GRAY)]
        if maps is not None:
            eyes = [cv2.remap(e, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE) for e, (mx, my) in zip(eyes, maps)]
        left.append(eyes[0])
        right.append(eyes[1])
        times.append(T0_NS + i * PERIOD_NS)
        hh, ww = r.depth_m.shape
        depth.append(float(r.depth_m[hh // 2, ww // 2]))
    return Flight(left, right, times, depth)


def distorted_rig() -> Rig:
    """A raw rig of :data:`GEOMETRY`'s size and baseline: unequal eyes, radial-tangential distortion
    as strong as the EuRoC MAV's, a degree between the eyes."""
    K1 = np.array([[165.0, 0.0, 158.0], [0.0, 164.0, 102.0], [0.0, 0.0, 1.0]])
    K2 = np.array([[163.5, 0.0, 162.0], [0.0, 163.0, 98.5], [0.0, 0.0, 1.0]])
    D1 = np.array([-0.28, 0.074, 2e-4, 1.8e-5])
    D2 = np.array([-0.27, 0.072, -1e-4, -3.6e-5])
    R = cv2.Rodrigues(np.array([0.004, -0.015, 0.003]))[0]
    T = np.array([-GEOMETRY.baseline_m, 0.0005, -0.0008])
    return Rig(K1, D1, K2, D2, R, T, (GEOMETRY.width_px, GEOMETRY.height_px))


def write_asl(
    folder: Path, flight: Flight, *, drop_right: tuple[int, ...] = (), skip: tuple[int, ...] = (), sensor_yaml: bool = True,
    rig: Rig | None = None,
) -> Path:
    """``folder/mav0/cam0`` and ``cam1`` as the EuRoC datasets hold them: ``data.csv``, ``data/<ns>.png``,
    ``sensor.yaml`` (the rendered rig: no distortion, cam1 :data:`GEOMETRY`'s baseline to the right; or
    ``rig``, with cam0 as the body frame). ``drop_right``: frames whose right image is left out
    (unmatched); ``skip``: frames left out of both (a gap). Returns ``folder``."""
    if rig is None:
        g = GEOMETRY
        K = np.array([[g.focal_px, 0.0, g.cx_px], [0.0, g.focal_px, g.cy_px], [0.0, 0.0, 1.0]])
        rig = Rig(K, np.zeros(4), K, np.zeros(4), np.eye(3), np.array([-g.baseline_m, 0.0, 0.0]), (g.width_px, g.height_px))
    # X_1 = [R T] X_0 and the body frame is cam0's: T_B0 = I, T_B1 = [R T]^-1.
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rig.R, rig.T
    t_bs = {"cam0": np.eye(4), "cam1": np.linalg.inv(m)}
    intrinsics = {"cam0": rig.K1, "cam1": rig.K2}
    distortion = {"cam0": rig.D1, "cam1": rig.D2}
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
            tbs = t_bs[cam].reshape(-1).tolist()
            K = intrinsics[cam]
            (folder / "mav0" / cam / "sensor.yaml").write_text(
                "%YAML:1.0\n"
                "sensor_type: camera\n"
                f"comment: rendered {cam}\n"
                "T_BS:\n  cols: 4\n  rows: 4\n"
                f"  data: [{', '.join(repr(v) for v in tbs)}]\n"
                "rate_hz: 20\n"
                f"resolution: [{GEOMETRY.width_px}, {GEOMETRY.height_px}]\n"
                "camera_model: pinhole\n"
                f"intrinsics: [{float(K[0, 0])!r}, {float(K[1, 1])!r}, {float(K[0, 2])!r}, {float(K[1, 2])!r}] #fu, fv, cu, cv\n"
                "distortion_model: radial-tangential\n"
                f"distortion_coefficients: [{', '.join(repr(float(v)) for v in distortion[cam])}]\n",
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
        if encoding == "mono16":
            data = (image.astype(np.uint16) * 256).view(np.uint8)
        h, w = image.shape
        ch = {"mono8": 1, "mono16": 2}.get(encoding, 3)
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
