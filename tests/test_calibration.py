"""Calibration loaders, Rectifier and IdentityRectifier (companion.core: calibration, calibration_files,
zed_conf, rectifier)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.config.core import CalibrationConfig
from companion.core.calibration import StereoCalibration
from companion.core.calibration_files import load_calibration, load_opencv_calibration
from companion.core.geometry import StereoGeometry
from companion.core.rectifier import IdentityRectifier, Rectifier, make_rectifier, remap_linear_reference
from companion.core.zed_conf import ZED_RESOLUTIONS, load_zed_conf
from companion.errors import CalibrationError, FrameError

DATA = Path(__file__).parent / "data"
SAMPLE_CONF = DATA / "SN000000.conf"
VGA = (672, 376)
ITER = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)


# ------------------------------------------------------------------ fixtures / helpers


def _rvec(R: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.ascontiguousarray(R))[0].reshape(3)


def _rot(rvec: tuple[float, float, float]) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))[0]


def _distorted_rig(size: tuple[int, int] = VGA) -> StereoCalibration:
    """A VGA-like rig with unequal intrinsics, lens distortion and a clear rotation between the eyes."""
    w, h = size
    s = w / 672.0
    K1 = np.array([[352.0 * s, 0.0, 338.5 * s], [0.0, 351.2 * s, 186.0 * s], [0.0, 0.0, 1.0]])
    K2 = np.array([[349.1 * s, 0.0, 331.0 * s], [0.0, 349.6 * s, 192.4 * s], [0.0, 0.0, 1.0]])
    D1 = np.array([-0.172, 0.027, 4e-4, -2e-4, 0.0])
    D2 = np.array([-0.165, 0.024, -1e-4, 3e-4, 0.001])
    R = _rot((0.012, -0.018, 0.009))
    T = np.array([-0.12, 0.0015, 0.0025])
    return StereoCalibration(K1=K1, D1=D1, K2=K2, D2=D2, R=R, T=T, image_size=size, source="synthetic")


def _ideal_rig(size: tuple[int, int] = VGA) -> StereoCalibration:
    K = np.array([[350.0, 0.0, 335.5], [0.0, 350.0, 187.5], [0.0, 0.0, 1.0]])
    return StereoCalibration(
        K1=K, D1=np.zeros(5), K2=K, D2=np.zeros(5), R=np.eye(3), T=np.array([-0.12, 0.0, 0.0]), image_size=size
    )


_ZED_EYE = {"fx": 700.1, "fy": 700.3, "cx": 641.2, "cy": 357.9, "k1": -0.171, "k2": 0.0262}


def _zed_text(
    *,
    res: str = "HD",
    drop: tuple[str, str] | None = None,
    stereo: dict[str, float] | None = None,
    extra: dict[str, float] | None = None,
) -> str:
    """A ZED .conf with one resolution; ``drop=(section, key)`` removes a key, ``stereo`` overrides."""
    sections: dict[str, dict[str, float]] = {
        f"LEFT_CAM_{res}": dict(_ZED_EYE, **(extra or {})),
        f"RIGHT_CAM_{res}": dict(_ZED_EYE, fx=699.2, fy=699.4, cx=645.0, cy=360.1, **(extra or {})),
        "STEREO": {
            "Baseline": 119.9,
            "TY": -0.05,
            "TZ": 0.2,
            f"CV_{res}": -0.0021,
            f"RX_{res}": 0.0034,
            f"RZ_{res}": -0.0008,
            **(stereo or {}),
        },
    }
    lines: list[str] = []
    for name, keys in sections.items():
        lines.append(f"[{name}]")
        lines += [f"{k} = {v}" for k, v in keys.items() if drop != (name, k)]
        lines.append("")
    return "\n".join(lines)


def _write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def _write_filestorage(path: Path, calib: StereoCalibration, *, size_style: str = "seq", T_units: str | None = None,
                       T_scale: float = 1.0, skip: str | None = None) -> None:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for key in ("K1", "D1", "K2", "D2", "R"):
        if key != skip:
            fs.write(key, getattr(calib, key) if key[0] != "D" else getattr(calib, key).reshape(1, -1))
    if skip != "T":
        fs.write("T", (calib.T * T_scale).reshape(3, 1))
    if T_units is not None:
        fs.write("T_units", T_units)
    if size_style == "seq":
        fs.startWriteStruct("image_size", cv2.FileNode_SEQ)
        for v in calib.image_size:
            fs.write("", int(v))
        fs.endWriteStruct()
    elif size_style == "wh":
        fs.write("image_width", int(calib.image_size[0]))
        fs.write("image_height", int(calib.image_size[1]))
    fs.release()


def _assert_same_calibration(a: StereoCalibration, b: StereoCalibration) -> None:
    for key in ("K1", "D1", "K2", "D2", "R", "T"):
        np.testing.assert_allclose(getattr(a, key), getattr(b, key), rtol=1e-12, atol=1e-15, err_msg=key)
    assert a.image_size == b.image_size


# ------------------------------------------------------------------ ZED .conf


@pytest.mark.parametrize("res", list(ZED_RESOLUTIONS))
def test_zed_sample_loads_every_resolution(res: str) -> None:
    size = ZED_RESOLUTIONS[res]
    calib = load_calibration(SAMPLE_CONF, size)
    assert calib.image_size == size
    assert f"[{res}]" in calib.source and "SN000000.conf" in calib.source
    scale = {"2K": 2.0, "FHD": 2.0, "HD": 1.0, "VGA": 0.5}[res]
    assert calib.K1[0, 0] == pytest.approx(699.67 * scale)
    assert calib.K1[1, 1] == pytest.approx(699.67 * scale)
    assert calib.K2[0, 0] == pytest.approx(700.44 * scale)
    assert 0.4 * size[0] < calib.K1[0, 2] < 0.6 * size[0] and 0.4 * size[1] < calib.K1[1, 2] < 0.6 * size[1]
    np.testing.assert_allclose(calib.D1, [-0.172617, 0.0270588, 0.000412513, -0.000213427, 0.0])
    # OpenCV convention: T = (-Baseline, TY, TZ) in metres, right camera at +x.
    np.testing.assert_allclose(calib.T, [-0.119894, -0.0213394e-3, 0.156281e-3])
    assert calib.baseline_m == pytest.approx(0.12, abs=2e-4)
    np.testing.assert_allclose(_rvec(calib.R), [0.00348423, -0.00094757, -0.00077958], atol=1e-12)


def test_zed_sample_gives_positive_disparity() -> None:
    calib = load_calibration(SAMPLE_CONF, (1280, 720))
    rect = Rectifier(calib)
    assert rect.P2[0, 3] < 0
    assert rect.geometry.baseline_m == pytest.approx(calib.baseline_m, rel=1e-9)
    # A point 2 m straight ahead, through the raw model and the rectification: d = x_l - x_r > 0.
    X = np.array([[0.1, -0.05, 2.0]])
    pl = cv2.projectPoints(X, np.zeros(3), np.zeros(3), calib.K1, calib.D1)[0]
    pr = cv2.projectPoints(X, _rvec(calib.R), calib.T, calib.K2, calib.D2)[0]
    ul = cv2.undistortPoints(pl, calib.K1, calib.D1, R=rect.R1, P=rect.P1, criteria=ITER).reshape(2)
    ur = cv2.undistortPoints(pr, calib.K2, calib.D2, R=rect.R2, P=rect.P2, criteria=ITER).reshape(2)
    d = ul[0] - ur[0]
    z_rect = (rect.R1 @ X[0])[2]
    assert d > 0
    assert rect.geometry.focal_baseline_px_m / d == pytest.approx(z_rect, rel=1e-6)


def test_zed_conf_matches_stereolabs_writer_convention(tmp_path: Path) -> None:
    # Stereolabs' saveCalibZED writes Baseline = -T[0], TY = T[1], TZ = T[2], RX/CV/RZ = Rodrigues(R)
    # from cv::stereoCalibrate's (R, T) in mm; loading must give back that (R, T), in metres.
    R = _rot((0.004, -0.011, 0.002))
    T_mm = np.array([-62.9, 0.31, -0.47])
    rv = _rvec(R)
    text = _zed_text(
        stereo={"Baseline": -T_mm[0], "TY": T_mm[1], "TZ": T_mm[2], "RX_HD": rv[0], "CV_HD": rv[1], "RZ_HD": rv[2]}
    )
    calib = load_zed_conf(_write(tmp_path, "SN1.conf", text), (1280, 720))
    np.testing.assert_allclose(calib.T, T_mm / 1000.0, rtol=1e-12)
    np.testing.assert_allclose(calib.R, R, atol=1e-12)


def test_zed_optional_distortion_terms_default_to_zero_and_are_read_when_present(tmp_path: Path) -> None:
    calib = load_zed_conf(_write(tmp_path, "SN1.conf", _zed_text()), (1280, 720))
    np.testing.assert_allclose(calib.D1, [-0.171, 0.0262, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(calib.K1, [[700.1, 0, 641.2], [0, 700.3, 357.9], [0, 0, 1]])
    text = _zed_text(extra={"p1": 1e-4, "p2": -2e-4, "k3": 0.003})
    calib = load_zed_conf(_write(tmp_path, "SN2.conf", text), (1280, 720))
    np.testing.assert_allclose(calib.D2, [-0.171, 0.0262, 1e-4, -2e-4, 0.003])


def test_zed_per_resolution_translation_wins_over_plain(tmp_path: Path) -> None:
    text = _zed_text(res="VGA", stereo={"TY_VGA": 0.5, "TZ_VGA": -0.25})
    calib = load_zed_conf(_write(tmp_path, "SN1.conf", text), VGA)
    np.testing.assert_allclose(calib.T, [-0.1199, 0.0005, -0.00025])


def test_zed_unknown_resolution_is_rejected() -> None:
    with pytest.raises(CalibrationError) as info:
        load_calibration(SAMPLE_CONF, (1000, 500))
    msg = str(info.value)
    assert "no section for 1000x500" in msg and "ZED resolutions are" in msg
    assert "672x376" in msg and "2208x1242" in msg


@pytest.mark.parametrize(
    ("section", "key"),
    [
        ("LEFT_CAM_HD", "fx"),
        ("LEFT_CAM_HD", "cy"),
        ("RIGHT_CAM_HD", "k2"),
        ("STEREO", "Baseline"),
        ("STEREO", "CV_HD"),
        ("STEREO", "RX_HD"),
        ("STEREO", "RZ_HD"),
        ("STEREO", "TY"),
        ("STEREO", "TZ"),
    ],
)
def test_zed_missing_key_is_named(tmp_path: Path, section: str, key: str) -> None:
    path = _write(tmp_path, "SN1.conf", _zed_text(drop=(section, key)))
    with pytest.raises(CalibrationError) as info:
        load_zed_conf(path, (1280, 720))
    msg = str(info.value)
    assert key in msg and section in msg and str(path) in msg


def test_zed_missing_section_is_named(tmp_path: Path) -> None:
    path = _write(tmp_path, "SN1.conf", _zed_text(res="VGA"))
    with pytest.raises(CalibrationError, match=r"no \[LEFT_CAM_HD\] section"):
        load_zed_conf(path, (1280, 720))


@pytest.mark.parametrize(
    ("stereo", "words"),
    [
        ({"Baseline": 0.12}, ["Baseline", "millimetres"]),
        ({"Baseline": -119.9}, ["Baseline", "millimetres"]),
        ({"CV_HD": "abc"}, ["CV_HD", "'abc'", "not a number"]),
        ({"TY": "nan"}, ["TY", "not finite"]),
    ],
)
def test_zed_bad_values_are_rejected(tmp_path: Path, stereo: dict, words: list[str]) -> None:
    path = _write(tmp_path, "SN1.conf", _zed_text(stereo=stereo))
    with pytest.raises(CalibrationError) as info:
        load_zed_conf(path, (1280, 720))
    for word in words:
        assert word in str(info.value)


def test_zed_unreadable_or_garbled_file(tmp_path: Path) -> None:
    missing = tmp_path / "SN404.conf"
    with pytest.raises(CalibrationError) as info:
        load_calibration(missing, (1280, 720))
    assert str(missing) in str(info.value) and "cannot read" in str(info.value)
    garbled = _write(tmp_path, "SN2.conf", "fx = 700\nthis is not an ini file\n")
    with pytest.raises(CalibrationError) as info:
        load_calibration(garbled, (1280, 720))
    assert str(garbled) in str(info.value)


# ------------------------------------------------------------------ OpenCV files


@pytest.mark.parametrize(("suffix", "size_style"), [(".yaml", "seq"), (".yml", "wh"), (".xml", "seq"), (".json", "wh")])
def test_opencv_filestorage_round_trip(tmp_path: Path, suffix: str, size_style: str) -> None:
    calib = _distorted_rig()
    path = tmp_path / f"stereo{suffix}"
    _write_filestorage(path, calib, size_style=size_style)
    loaded = load_calibration(path, VGA)
    _assert_same_calibration(loaded, calib)
    assert loaded.source == str(path)


def test_opencv_yaml_ignores_unrelated_maps(tmp_path: Path) -> None:
    calib = _distorted_rig()
    path = tmp_path / "stereo.yaml"
    _write_filestorage(path, calib)
    text = path.read_text().replace("K1:", "meta:\n   tool: checkerboard\n   squares: 54\nK1:", 1)
    path.write_text(text)
    _assert_same_calibration(load_calibration(path, VGA), calib)


def test_opencv_plain_json(tmp_path: Path) -> None:
    calib = _distorted_rig()
    data = {k: getattr(calib, k).tolist() for k in ("K1", "D1", "K2", "D2", "R", "T")}
    data["image_size"] = list(calib.image_size)
    path = _write(tmp_path, "stereo.json", json.dumps(data))
    _assert_same_calibration(load_opencv_calibration(path), calib)


def test_opencv_npz_round_trip(tmp_path: Path) -> None:
    calib = _distorted_rig()
    path = tmp_path / "stereo.npz"
    np.savez(path, K1=calib.K1, D1=calib.D1, K2=calib.K2, D2=calib.D2, R=calib.R, T=calib.T,
             image_size=np.array(calib.image_size))
    _assert_same_calibration(load_calibration(path, VGA), calib)
    # T in millimetres with the documented hint.
    path_mm = tmp_path / "stereo_mm.npz"
    np.savez(path_mm, K1=calib.K1, D1=calib.D1, K2=calib.K2, D2=calib.D2, R=calib.R, T=calib.T * 1000.0,
             image_width=672, image_height=376, T_units="mm")
    np.testing.assert_allclose(load_calibration(path_mm, VGA).T, calib.T, rtol=1e-12)


def test_opencv_T_units_mm_and_bad_unit(tmp_path: Path) -> None:
    calib = _distorted_rig()
    mm = tmp_path / "mm.yaml"
    _write_filestorage(mm, calib, T_units="mm", T_scale=1000.0)
    np.testing.assert_allclose(load_calibration(mm, VGA).T, calib.T, rtol=1e-12)
    bad = tmp_path / "bad.yaml"
    _write_filestorage(bad, calib, T_units="inch")
    with pytest.raises(CalibrationError, match="T_units"):
        load_calibration(bad, VGA)


@pytest.mark.parametrize("key", ["K1", "D1", "K2", "D2", "R", "T"])
def test_opencv_missing_key_names_key_and_file(tmp_path: Path, key: str) -> None:
    path = tmp_path / "stereo.yaml"
    _write_filestorage(path, _distorted_rig(), skip=key)
    with pytest.raises(CalibrationError) as info:
        load_calibration(path, VGA)
    msg = str(info.value)
    assert f"missing {key}" in msg and str(path) in msg


def test_opencv_missing_image_size(tmp_path: Path) -> None:
    path = tmp_path / "stereo.yaml"
    _write_filestorage(path, _distorted_rig(), size_style="none")
    with pytest.raises(CalibrationError, match="image_size"):
        load_calibration(path, VGA)


def test_opencv_resolution_mismatch_is_an_error_not_a_rescale(tmp_path: Path) -> None:
    path = tmp_path / "stereo.yaml"
    _write_filestorage(path, _distorted_rig((1280, 720)))
    with pytest.raises(CalibrationError) as info:
        load_calibration(path, VGA)
    assert "is for 1280x720 but frames are 672x376" in str(info.value)


def test_unreadable_unknown_and_corrupt_files(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="no such file"):
        load_calibration(tmp_path / "nope.yaml", VGA)
    with pytest.raises(CalibrationError, match="unknown extension '.txt'"):
        load_calibration(_write(tmp_path, "c.txt", "x"), VGA)
    with pytest.raises(CalibrationError, match="cannot parse"):
        load_calibration(_write(tmp_path, "c.yaml", "%YAML:1.0\nK1: [1, 2\n"), VGA)
    with pytest.raises(CalibrationError, match="cannot parse"):
        load_calibration(_write(tmp_path, "c.json", "{not json"), VGA)
    with pytest.raises(CalibrationError, match="cannot parse"):
        load_calibration(_write(tmp_path, "c.npz", "not a zip"), VGA)


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"K1": np.eye(2)}, ["K1", "(3, 3)"]),
        ({"K2": np.diag([0.0, 1.0, 1.0])}, ["K2", "camera matrix"]),
        ({"D1": np.zeros(6)}, ["D1", "6 coefficients"]),
        ({"R": np.diag([1.0, 1.0, -1.0])}, ["R", "rotation"]),
        ({"R": np.full((3, 3), np.nan)}, ["R", "non-finite"]),
        ({"T": np.zeros(3)}, ["T", "zero"]),
        ({"T": np.zeros(4)}, ["T", "(3,)"]),
        ({"image_size": (0, 376)}, ["image_size", "positive"]),
    ],
)
def test_stereo_calibration_validates(change: dict, words: list[str]) -> None:
    base = _ideal_rig()
    kwargs = {k: getattr(base, k) for k in ("K1", "D1", "K2", "D2", "R", "T", "image_size")}
    kwargs.update(change)
    with pytest.raises(CalibrationError) as info:
        StereoCalibration(**kwargs, source="unit-test")
    msg = str(info.value)
    assert "unit-test" in msg
    for word in words:
        assert word in msg


def test_stereo_calibration_arrays_are_read_only_float64() -> None:
    calib = StereoCalibration(
        K1=[[350, 0, 336], [0, 350, 188], [0, 0, 1]],
        D1=[0, 0, 0, 0],
        K2=np.array([[350, 0, 336], [0, 350, 188], [0, 0, 1]], dtype=np.int32),
        D2=np.zeros((1, 5)),
        R=np.eye(3),
        T=[[-0.12], [0], [0]],
        image_size=(672, 376),
    )
    assert calib.K1.dtype == np.float64 and calib.T.shape == (3,) and calib.D2.shape == (5,)
    with pytest.raises(ValueError):
        calib.K1[0, 0] = 1.0


# ------------------------------------------------------------------ rectification correctness


def _points_in_rectified_view(rect: Rectifier, n: int, rng: np.random.Generator) -> np.ndarray:
    """3-D points (raw-left frame, metres) that land inside both rectified images, depth 0.5–20 m."""
    w, h = rect.calibration.image_size
    f = rect.geometry.focal_px
    z = rng.uniform(0.5, 20.0, n)
    d = rect.geometry.focal_baseline_px_m / z
    u = rng.uniform(0.08 * w, 0.92 * w, n) + d * rng.uniform(0.0, 1.0, n)
    u = np.minimum(u, 0.92 * w)
    u = np.maximum(u, 0.08 * w + d)
    v = rng.uniform(0.08 * h, 0.92 * h, n)
    x_rect = np.stack([(u - rect.geometry.cx_px) / f * z, (v - rect.geometry.cy_px) / f * z, z], axis=1)
    return x_rect @ rect.R1  # rows: R1.T @ X_rect, i.e. back to the raw left frame


def test_rectified_points_share_rows_and_give_true_depth() -> None:
    calib = _distorted_rig()
    rect = Rectifier(calib)
    X = _points_in_rectified_view(rect, 400, np.random.default_rng(11))
    # Raw pixels from the calibration's own model (what the real cameras would see).
    pl = cv2.projectPoints(X, np.zeros(3), np.zeros(3), calib.K1, calib.D1)[0]
    pr = cv2.projectPoints(X, _rvec(calib.R), calib.T, calib.K2, calib.D2)[0]
    # ... pushed through the rectification.
    ul = cv2.undistortPoints(pl, calib.K1, calib.D1, R=rect.R1, P=rect.P1, criteria=ITER).reshape(-1, 2)
    ur = cv2.undistortPoints(pr, calib.K2, calib.D2, R=rect.R2, P=rect.P2, criteria=ITER).reshape(-1, 2)
    assert np.max(np.abs(ul[:, 1] - ur[:, 1])) < 0.05  # same row
    disparity = ul[:, 0] - ur[:, 0]
    assert np.all(disparity > 0)
    depth = rect.geometry.focal_baseline_px_m / disparity
    z_true = (X @ rect.R1.T)[:, 2]  # depth along the rectified optical axis
    assert np.max(np.abs(depth / z_true - 1.0)) < 0.005
    # The rig really is distorted and rotated: without rectification the rows would not agree.
    assert np.max(np.abs(pl[:, 0, 1] - pr[:, 0, 1])) > 2.0


def test_maps_sample_the_raw_image_where_the_model_says() -> None:
    calib = _distorted_rig()
    rect = Rectifier(calib)
    w, h = calib.image_size
    vv, uu = np.mgrid[0:h:7, 0:w:7]
    pix = np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)], axis=1).astype(np.float64)
    for K, D, Rr, P, mx, my in (
        (calib.K1, calib.D1, rect.R1, rect.P1, rect.map_left_x, rect.map_left_y),
        (calib.K2, calib.D2, rect.R2, rect.P2, rect.map_right_x, rect.map_right_y),
    ):
        assert mx.dtype == np.float32 and mx.shape == (h, w) and not mx.flags.writeable
        rays_rect = pix @ np.linalg.inv(P[:, :3]).T
        rays_raw = rays_rect @ Rr  # R^T applied to each row
        raw = cv2.projectPoints(rays_raw, np.zeros(3), np.zeros(3), K, D)[0].reshape(-1, 2)
        np.testing.assert_allclose(mx[vv, uu].ravel(), raw[:, 0], atol=2e-3)
        np.testing.assert_allclose(my[vv, uu].ravel(), raw[:, 1], atol=2e-3)


def _render_plane_pair(calib: StereoCalibration, rect: Rectifier, z0: float) -> tuple[np.ndarray, np.ndarray]:
    """Raw left/right images of a textured plane at depth z0 (rectified-left frame), from the raw model."""
    w, h = calib.image_size
    rng = np.random.default_rng(2024)
    n_waves = 14
    freq = rng.uniform(3.0, 20.0, n_waves) * np.exp(1j * rng.uniform(0, 2 * np.pi, n_waves))  # cycles per metre
    phase = rng.uniform(0, 2 * np.pi, n_waves)

    def texture(points_rect: np.ndarray) -> np.ndarray:
        x, y = points_rect[:, 0:1], points_rect[:, 1:2]
        arg = 2 * np.pi * (freq.real * x + freq.imag * y) + phase
        return 128.0 + 115.0 * np.sin(arg).sum(axis=1) / np.sqrt(n_waves * 2.0)

    vv, uu = np.mgrid[0:h, 0:w]
    pix = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(np.float64).reshape(-1, 1, 2)
    images = []
    centre_r = -calib.R.T @ calib.T  # right camera centre, raw-left frame
    eyes = ((calib.K1, calib.D1, np.eye(3), np.zeros(3)), (calib.K2, calib.D2, calib.R.T, centre_r))
    for K, D, to_left, centre in eyes:
        norm = cv2.undistortPoints(pix, K, D, R=None, P=None, criteria=ITER).reshape(-1, 2)
        rays = np.concatenate([norm, np.ones((norm.shape[0], 1))], axis=1) @ to_left.T  # raw-left frame
        rays_rect = rays @ rect.R1.T
        c_rect = rect.R1 @ centre
        s = (z0 - c_rect[2]) / rays_rect[:, 2]
        points_rect = c_rect + rays_rect * s[:, None]
        images.append(np.clip(np.rint(texture(points_rect)), 0, 255).astype(np.uint8).reshape(h, w))
    return images[0], images[1]


def test_rectified_images_of_a_plane_have_the_predicted_disparity() -> None:
    calib = _distorted_rig()
    rect = Rectifier(calib)
    z0 = 1.5
    raw_l, raw_r = _render_plane_pair(calib, rect, z0)
    left, right = rect.rectify(raw_l, raw_r)
    expected = rect.geometry.focal_baseline_px_m / z0
    k = int(round(expected))
    h, w = left.shape
    # Compare the left window with the right window moved by the whole-pixel disparity, so phase
    # correlation measures only the sub-pixel rest (full overlap, no edge bias).
    rows = slice(h // 2 - 80, h // 2 + 80)
    cols_l = slice(w // 2 - 128, w // 2 + 128)
    cols_r = slice(w // 2 - 128 - k, w // 2 + 128 - k)
    hann = cv2.createHanningWindow((256, 160), cv2.CV_64F)

    def shift(a: np.ndarray, b: np.ndarray) -> tuple[float, float, float]:
        wa, wb = a[rows, cols_l].astype(np.float64), b[rows, cols_r].astype(np.float64)
        (dx, dy), response = cv2.phaseCorrelate(wa, wb, hann)
        return k - dx, dy, response  # the right image is shifted left by d

    d, dy, response = shift(left, right)
    assert response > 0.5
    assert d == pytest.approx(expected, rel=0.005)
    assert abs(dy) < 0.1
    # Without rectification the raw pair is clearly off (distortion + rotation between the eyes).
    raw_d, raw_dy, _ = shift(raw_l, raw_r)
    assert abs(raw_dy) > 1.0 or abs(raw_d - expected) > 1.0


# ------------------------------------------------------------------ rectify(), maps and buffers


def test_rectify_equals_cv2_remap_and_writes_into_buffers() -> None:
    rect = Rectifier(_distorted_rig())
    rng = np.random.default_rng(9)
    frame = rng.integers(0, 256, (376, 2 * 672), dtype=np.uint8)
    raw_l, raw_r = frame[:, :672], frame[:, 672:]  # views, as split_side_by_side gives them
    exp_l = cv2.remap(raw_l, rect.map_left_x, rect.map_left_y, cv2.INTER_LINEAR)
    exp_r = cv2.remap(raw_r, rect.map_right_x, rect.map_right_y, cv2.INTER_LINEAR)
    left, right = rect.rectify(raw_l, raw_r)
    np.testing.assert_array_equal(left, exp_l)
    np.testing.assert_array_equal(right, exp_r)
    out_l = np.empty((376, 672), np.uint8)
    out_r = np.empty((376, 672), np.uint8)
    got_l, got_r = rect.rectify(raw_l, raw_r, out_left=out_l, out_right=out_r)
    assert got_l is out_l and got_r is out_r
    np.testing.assert_array_equal(out_l, exp_l)
    np.testing.assert_array_equal(out_r, exp_r)


def test_rectify_rejects_wrong_sizes_and_buffers() -> None:
    rect = Rectifier(_distorted_rig())
    good = np.zeros((376, 672), np.uint8)
    with pytest.raises(FrameError, match="1280x720 but the rectifier was built for 672x376"):
        rect.rectify(np.zeros((720, 1280), np.uint8), good)
    with pytest.raises(FrameError, match="output buffer"):
        rect.rectify(good, good, out_left=np.zeros((376, 671), np.uint8))
    with pytest.raises(FrameError, match="output buffer"):
        rect.rectify(good, good, out_right=np.zeros((376, 672), np.float32))


@pytest.mark.skipif(int(cv2.__version__.split(".")[0]) < 5, reason="formula verified against OpenCV 5.x remap")
def test_remap_reference_is_bit_exact_with_cv2() -> None:
    rect = Rectifier(_distorted_rig(), alpha=1.0)  # alpha 1: maps reach outside the raw image (border)
    src = np.random.default_rng(4).integers(0, 256, (376, 672), dtype=np.uint8)
    ref = remap_linear_reference(src, rect.map_left_x, rect.map_left_y)
    np.testing.assert_array_equal(ref, rect.rectify(src, src)[0])
    rng = np.random.default_rng(8)
    mx = (np.mgrid[0:50, 0:70][1] * 1.07 - 3.0 + rng.normal(0, 2.0, (50, 70))).astype(np.float32)
    my = (np.mgrid[0:50, 0:70][0] * 0.93 + 2.0 + rng.normal(0, 2.0, (50, 70))).astype(np.float32)
    small = rng.integers(0, 256, (48, 64), dtype=np.uint8)
    np.testing.assert_array_equal(remap_linear_reference(small, mx, my), cv2.remap(small, mx, my, cv2.INTER_LINEAR))


# ------------------------------------------------------------------ geometry


def test_geometry_of_an_undistorted_unrotated_rig() -> None:
    calib = _ideal_rig()
    rect = Rectifier(calib)
    g = rect.geometry
    assert (g.width_px, g.height_px) == VGA
    assert g.focal_px == pytest.approx(calib.K1[0, 0], rel=1e-9)
    assert g.baseline_m == pytest.approx(float(np.linalg.norm(calib.T)), rel=1e-12)
    assert (g.cx_px, g.cy_px) == (pytest.approx(335.5, abs=1e-6), pytest.approx(187.5, abs=1e-6))
    # The maps are the identity, so rectify leaves the images as they are.
    vv, uu = np.mgrid[0:376, 0:672]
    np.testing.assert_allclose(rect.map_left_x, uu, atol=1e-3)
    np.testing.assert_allclose(rect.map_right_y, vv, atol=1e-3)
    img = np.random.default_rng(2).integers(0, 256, (376, 672), dtype=np.uint8)
    np.testing.assert_array_equal(rect.rectify(img, img)[0][1:-1, 1:-1], img[1:-1, 1:-1])


def test_geometry_baseline_is_in_metres_for_a_zed_file() -> None:
    rect = Rectifier(load_calibration(SAMPLE_CONF, VGA))
    assert rect.geometry.baseline_m == pytest.approx(0.1199, abs=5e-4)
    assert 300 < rect.geometry.focal_px < 360


@pytest.mark.parametrize(
    ("T", "words"),
    [((0.12, 0.0, 0.0), ["LEFT of the left one"]), ((0.0, -0.12, 0.0), ["vertical rig"])],
)
def test_rectifier_refuses_rigs_that_would_give_negative_disparity(T: tuple, words: list[str]) -> None:
    base = _ideal_rig()
    calib = StereoCalibration(K1=base.K1, D1=base.D1, K2=base.K2, D2=base.D2, R=base.R, T=np.array(T),
                              image_size=VGA, source="swapped.yaml")
    with pytest.raises(CalibrationError) as info:
        Rectifier(calib)
    assert "swapped.yaml" in str(info.value)
    for word in words:
        assert word in str(info.value)


# ------------------------------------------------------------------ identity and make_rectifier


def test_identity_rectifier_returns_inputs() -> None:
    g = StereoGeometry.ideal(640, 480, 90.0, 0.12)
    ident = IdentityRectifier(g)
    left = np.zeros((480, 640), np.uint8)
    right = np.ones((480, 640), np.uint8)
    out_l, out_r = ident.rectify(left, right)
    assert out_l is left and out_r is right
    assert ident.map_left_x is None and ident.map_right_y is None and ident.is_identity
    assert not Rectifier.is_identity
    with pytest.raises(FrameError, match="640x480"):
        ident.rectify(np.zeros((376, 672), np.uint8), right)


def test_make_rectifier_without_file_is_the_ideal_rig() -> None:
    cfg = CalibrationConfig(ideal_hfov_deg=90.0, ideal_baseline_m=0.12)
    rect = make_rectifier(cfg, 640, 480)
    assert isinstance(rect, IdentityRectifier)
    assert rect.geometry == StereoGeometry.ideal(640, 480, 90.0, 0.12)
    assert rect.geometry.focal_px == pytest.approx(320.0)


def test_make_rectifier_with_files(tmp_path: Path) -> None:
    rect = make_rectifier(CalibrationConfig(file=SAMPLE_CONF, rectify_alpha=0.0), 1280, 720)
    assert isinstance(rect, Rectifier) and rect.calibration.image_size == (1280, 720)
    assert rect.geometry.baseline_m == pytest.approx(0.1199, abs=5e-4)
    path = tmp_path / "stereo.yaml"
    _write_filestorage(path, _distorted_rig())
    rect = make_rectifier(CalibrationConfig(file=path, rectify_alpha=1.0), 672, 376)
    assert isinstance(rect, Rectifier) and rect.alpha == 1.0
    with pytest.raises(CalibrationError, match="is for 672x376 but frames are 1280x720"):
        make_rectifier(CalibrationConfig(file=path), 1280, 720)


# ------------------------------------------------------------------ garbage files name the file and the problem


@pytest.mark.parametrize(
    ("name", "content", "words"),
    [
        ("c.npz", b"hello world\x00\x01\x02", ["not an .npz archive"]),
        ("c.npz", b"PK\x03\x04garbage", ["not an .npz archive"]),
        ("c.yaml", b"%YAML:1.0\n---\nK1: [1, 2\n", ["not valid YAML", "line 3", "Missing ,"]),
        ("c.yaml", b"\x89PNG garbage\x00\xff", ["not valid YAML", "not a mapping of keys"]),
        ("c.yaml", b"", ["is empty"]),
        ("c.yaml", b"K1: !!opencv-matrix\n  rows: 3\n", ["K1 is not a matrix"]),
        ("c.xml", b'<?xml version="1.0"?>\n<opencv_storage><K1>1 2</K1', ["not valid XML", "line 2"]),
        ("c.json", b'{"K1": [[1,0],[0,1]]', ["not valid JSON"]),
        ("c.json", b"\xff\xfe\x00", ["not valid JSON", "binary"]),
        ("SN1.conf", b"garbage\n[[[\n", ["not a valid ZED .conf", "line 1", "[SECTION]"]),
        ("SN2.conf", b"\xff\xfe\x00binary", ["not a valid ZED .conf", "not text"]),
        ("SN3.conf", b"[LEFT_CAM_VGA]\nfx=700\n", ["no [LEFT_CAM_HD] section", "it has: LEFT_CAM_VGA"]),
    ],
)
def test_garbage_calibration_files_say_what_is_wrong(tmp_path: Path, name: str, content: bytes, words: list[str]) -> None:
    path = tmp_path / name
    path.write_bytes(content)
    size = (1280, 720) if name.endswith(".conf") else VGA
    with pytest.raises(CalibrationError) as info:
        load_calibration(path, size)
    msg = str(info.value)
    assert str(path) in msg and "\n" not in msg and "OpenCV(" not in msg and ".cpp" not in msg, msg
    for word in words:
        assert word in msg, msg


def test_npz_with_python_objects_and_a_directory_are_named(tmp_path: Path) -> None:
    np.savez(tmp_path / "obj.npz", K1=np.array([{"a": 1}], dtype=object))
    with pytest.raises(CalibrationError, match="Python objects"):
        load_calibration(tmp_path / "obj.npz", VGA)
    (tmp_path / "d.yaml").mkdir()
    with pytest.raises(CalibrationError, match="is a directory"):
        load_calibration(tmp_path / "d.yaml", VGA)


@pytest.mark.parametrize("suffix", [".yaml", ".yml", ".xml", ".json", ".npz"])
def test_save_calibration_writes_the_projects_format_in_every_container(tmp_path: Path, suffix: str) -> None:
    from companion.core.calibration_files import save_calibration

    rig = _distorted_rig()
    path = save_calibration(rig, tmp_path / f"c{suffix}", {"rms_px": 0.21, "views": 14, "board": "chessboard:9x6:0.025"})
    back = load_calibration(path, VGA)
    for key in ("K1", "D1", "K2", "D2", "R", "T"):
        np.testing.assert_allclose(getattr(back, key), getattr(rig, key), rtol=1e-12, atol=1e-15)
    assert back.image_size == VGA
    with pytest.raises(CalibrationError, match="metadata may not be called 'T'"):
        save_calibration(rig, tmp_path / f"d{suffix}", {"T": 1.0})
