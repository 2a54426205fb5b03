"""``companion calibrate import``: each family of calibration files, written by the tests from a known rig,
comes back as the same rig (baseline, focal length, the rectification maps); wrong files get one line
naming what is wrong."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from calib_data import Rig, generic_rig
from companion.calib.importers import import_calibration
from companion.cli import main
from companion.core.calibration import StereoCalibration
from companion.core.calibration_files import load_calibration
from companion.core.rectifier import Rectifier

# ------------------------------------------------------------------------------------------------ writers


def _calib(rig: Rig, model: str = "pinhole") -> StereoCalibration:
    return StereoCalibration(rig.K1, rig.D1, rig.K2, rig.D2, rig.R, rig.T, rig.image_size, model=model)


def _fisheye_rig() -> Rig:
    r = generic_rig()
    return Rig(r.K1, np.array([0.02, -0.01, 0.003, -0.0005]), r.K2, np.array([0.018, -0.008, 0.002, -0.0004]), r.R, r.T, r.image_size)


def _intrinsics(K: np.ndarray) -> list[float]:
    return [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])]


def _rt(R: np.ndarray, T: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = R
    m[:3, 3] = T
    return m


def write_kalibr(path: Path, rig: Rig, distortion: str = "radtan", camera_model: str = "pinhole") -> Path:
    def cam(K: np.ndarray, D: np.ndarray) -> dict:
        return {
            "camera_model": camera_model,
            "intrinsics": _intrinsics(K),
            "distortion_model": distortion,
            "distortion_coeffs": [float(v) for v in D[:4]],
            "resolution": list(rig.image_size),
            "rostopic": "/cam/image_raw",
        }

    cam1 = cam(rig.K2, rig.D2)
    cam1["T_cn_cnm1"] = _rt(rig.R, rig.T).tolist()
    cam1["cam_overlaps"] = [0]
    path.write_text(yaml.safe_dump({"cam0": cam(rig.K1, rig.D1), "cam1": cam1}), encoding="utf-8")
    return path


def write_asl_pair(folder: Path, rig: Rig) -> tuple[Path, Path]:
    """Two sensor.yaml files with the EuRoC header and a body frame that is neither camera."""
    T_B0 = _rt(cv2.Rodrigues(np.array([0.1, -1.5, 0.05]))[0], np.array([-0.02, -0.06, 0.01]))
    T_B1 = T_B0 @ np.linalg.inv(_rt(rig.R, rig.T))  # X_1 = T_B1^-1 T_B0 X_0 = [R T] X_0
    paths = []
    for name, K, D, T_BS in (("cam0", rig.K1, rig.D1, T_B0), ("cam1", rig.K2, rig.D2, T_B1)):
        body = yaml.safe_dump(
            {
                "sensor_type": "camera",
                "comment": f"rendered {name}",
                "T_BS": {"cols": 4, "rows": 4, "data": T_BS.reshape(-1).tolist()},
                "rate_hz": 20,
                "resolution": list(rig.image_size),
                "camera_model": "pinhole",
                "intrinsics": _intrinsics(K),
                "distortion_model": "radial-tangential",
                "distortion_coefficients": [float(v) for v in D[:4]],
            }
        )
        path = folder / f"{name}_sensor.yaml"
        path.write_text("%YAML:1.0\n" + body, encoding="utf-8")
        paths.append(path)
    return paths[0], paths[1]


def write_camera_info_pair(folder: Path, rig: Rig, message_form: bool = False) -> tuple[Path, Path]:
    """The two eyes' camera_info as ROS camera_calibration writes them (or as the message's fields)."""
    R1, R2, P1, P2, *_ = cv2.stereoRectify(rig.K1, rig.D1, rig.K2, rig.D2, rig.image_size, rig.R, rig.T.reshape(3, 1),
                                          flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0)
    paths = []
    for name, K, D, Rr, P in (("left", rig.K1, rig.D1, R1, P1), ("right", rig.K2, rig.D2, R2, P2)):
        def m(a: np.ndarray) -> dict:
            return {"rows": a.shape[0] if a.ndim == 2 else 1, "cols": a.shape[1] if a.ndim == 2 else a.size, "data": a.reshape(-1).tolist()}

        if message_form:
            doc = {"header": {"frame_id": name}, "height": rig.image_size[1], "width": rig.image_size[0], "distortion_model": "plumb_bob",
                   "D": D.tolist(), "K": K.reshape(-1).tolist(), "R": Rr.reshape(-1).tolist(), "P": P.reshape(-1).tolist()}
        else:
            doc = {"image_width": rig.image_size[0], "image_height": rig.image_size[1], "camera_name": name,
                   "camera_matrix": m(K), "distortion_model": "plumb_bob", "distortion_coefficients": m(D),
                   "rectification_matrix": m(Rr), "projection_matrix": m(P)}
        path = folder / f"{name}.yaml"
        path.write_text(yaml.safe_dump(doc), encoding="utf-8")
        paths.append(path)
    return paths[0], paths[1]


def write_opencv(folder: Path, rig: Rig, names: tuple[str, str] = ("M1", "M2"), size: bool = True, ext: str = ".yml") -> list[Path]:
    """OpenCV's stereo sample's files: intrinsics (M1 D1 M2 D2) and extrinsics (R T), or one file with all."""
    def write(path: Path, items: dict) -> Path:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
        for k, v in items.items():
            fs.write(k, v)
        fs.release()
        return path

    intr = {names[0]: rig.K1, "D1": rig.D1.reshape(1, -1), names[1]: rig.K2, "D2": rig.D2.reshape(1, -1)}
    extr = {"R": rig.R, "T": rig.T.reshape(3, 1)}
    if size:
        return [write(folder / f"stereo{ext}", {**intr, **extr, "image_width": rig.image_size[0], "image_height": rig.image_size[1]})]
    return [write(folder / f"intrinsics{ext}", intr), write(folder / f"extrinsics{ext}", extr)]


# ------------------------------------------------------------------------------------------------ checks


def assert_same_rig(got: StereoCalibration, rig: Rig, model: str = "pinhole") -> None:
    want = Rectifier(_calib(rig, model))
    have = Rectifier(got)
    assert got.model == model
    assert got.image_size == rig.image_size
    assert have.geometry.baseline_m == pytest.approx(want.geometry.baseline_m, rel=1e-9)
    assert have.geometry.focal_px == pytest.approx(want.geometry.focal_px, rel=1e-9)
    for name in ("map_left_x", "map_left_y", "map_right_x", "map_right_y"):
        assert np.abs(getattr(have, name) - getattr(want, name)).max() < 1e-3, name


def test_kalibr_radtan_camchain_is_the_rig(tmp_path: Path) -> None:
    rig = generic_rig()
    imported = import_calibration([write_kalibr(tmp_path / "camchain.yaml", rig)])
    assert imported.format == "kalibr"
    assert_same_rig(imported.calibration, rig)
    # T_cn_cnm1 is OpenCV's (R, T) as it stands: the right eye at +6 cm along x, T[0] = -0.06.
    assert imported.calibration.T[0] == pytest.approx(-0.06)


def test_kalibr_equidistant_camchain_is_rectified_as_a_fisheye(tmp_path: Path) -> None:
    rig = _fisheye_rig()
    imported = import_calibration([write_kalibr(tmp_path / "camchain.yaml", rig, distortion="equidistant")])
    assert_same_rig(imported.calibration, rig, model="fisheye")
    # It survives the project's own file: written, loaded, the same maps.
    out = tmp_path / "calib.yaml"
    assert main(["calibrate", "import", str(tmp_path / "camchain.yaml"), "--out", str(out)]) == 0
    assert_same_rig(load_calibration(out, rig.image_size), rig, model="fisheye")


def test_asl_sensor_yaml_pair_is_the_rig(tmp_path: Path) -> None:
    rig = generic_rig()
    imported = import_calibration(list(write_asl_pair(tmp_path, rig)))
    assert imported.format == "asl"
    assert_same_rig(imported.calibration, rig)


@pytest.mark.parametrize("message_form", [False, True])
def test_ros_camera_info_pair_is_the_rig(tmp_path: Path, message_form: bool) -> None:
    rig = generic_rig()
    left, right = write_camera_info_pair(tmp_path, rig, message_form)
    imported = import_calibration([left, right])
    assert imported.format == "ros"
    assert_same_rig(imported.calibration, rig)
    # Given the wrong way round, the eye with the baseline in its P is still the right one.
    swapped = import_calibration([right, left])
    assert swapped.files == (left, right) and swapped.notes
    assert_same_rig(swapped.calibration, rig)


def test_opencv_stereo_file_and_the_samples_two_files(tmp_path: Path) -> None:
    rig = generic_rig()
    (tmp_path / "one").mkdir()
    (tmp_path / "two").mkdir()
    assert_same_rig(import_calibration(write_opencv(tmp_path / "one", rig)).calibration, rig)
    two = write_opencv(tmp_path / "two", rig, names=("K1", "K2"), size=False, ext=".xml")
    assert_same_rig(import_calibration(two, image_size=rig.image_size).calibration, rig)


def test_cli_writes_the_calibration_and_prints_the_rig(tmp_path: Path, capsys) -> None:
    rig = generic_rig()
    left, right = write_asl_pair(tmp_path, rig)
    out = tmp_path / "calib.yaml"
    config = tmp_path / "companion.toml"
    config.write_text("[stereo]\nnum_disparities = 48\n", encoding="utf-8")
    assert main(["calibrate", "import", str(left), str(right), "--out", str(out), "--config", str(config), "--write-config"]) == 0
    text = capsys.readouterr().out
    rect = Rectifier(_calib(rig))
    g = rect.geometry
    assert f"baseline {g.baseline_m * 1000:.1f} mm" in text
    assert f"rectified focal length {g.focal_px:.1f} px" in text
    assert f"nearest measurable depth {g.focal_px * g.baseline_m / 47:.2f} m at 48 disparities" in text
    assert "rectified size 640x400 px" in text
    assert_same_rig(load_calibration(out, rig.image_size), rig)
    assert str(out.resolve()) in config.read_text(encoding="utf-8")


def _one_line_error(capsys, argv: list[str]) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err
    return err


def test_a_missing_key_is_named(tmp_path: Path, capsys) -> None:
    rig = generic_rig()
    out = str(tmp_path / "c.yaml")
    kalibr = write_kalibr(tmp_path / "camchain.yaml", rig)
    doc = yaml.safe_load(kalibr.read_text())
    del doc["cam1"]["T_cn_cnm1"]
    kalibr.write_text(yaml.safe_dump(doc))
    assert "missing cam1.T_cn_cnm1" in _one_line_error(capsys, ["calibrate", "import", str(kalibr), "--out", out])

    left, right = write_asl_pair(tmp_path, rig)
    right.write_text(right.read_text().replace("intrinsics:", "intrinsic:"))
    assert "missing intrinsics" in _one_line_error(capsys, ["calibrate", "import", str(left), str(right), "--out", out])

    l2, r2 = write_camera_info_pair(tmp_path, rig)
    doc = yaml.safe_load(r2.read_text())
    del doc["projection_matrix"]
    r2.write_text(yaml.safe_dump(doc))
    assert "missing projection_matrix or P or p" in _one_line_error(capsys, ["calibrate", "import", str(l2), str(r2), "--out", out])

    (tmp_path / "cv").mkdir()
    intr, extr = write_opencv(tmp_path / "cv", rig, size=False)
    assert "missing image_size" in _one_line_error(capsys, ["calibrate", "import", str(intr), str(extr), "--out", out])
    assert "missing R" in _one_line_error(capsys, ["calibrate", "import", str(intr), "--out", out, "--image-size", "640x400"])
    assert not Path(out).exists()


@pytest.mark.parametrize("model", ["omni", "ds", "eucm"])
def test_a_camera_model_the_pipeline_cannot_rectify_is_refused_by_name(tmp_path: Path, capsys, model: str) -> None:
    path = write_kalibr(tmp_path / "camchain.yaml", generic_rig(), camera_model=model)
    err = _one_line_error(capsys, ["calibrate", "import", str(path), "--out", str(tmp_path / "c.yaml")])
    assert f"camera_model is '{model}'" in err and "cannot rectify" in err


def test_wrong_files_get_one_line(tmp_path: Path, capsys) -> None:
    rig = generic_rig()
    out = str(tmp_path / "c.yaml")
    left, right = write_asl_pair(tmp_path, rig)
    assert "give both" in _one_line_error(capsys, ["calibrate", "import", str(left), "--out", out])
    assert "eyes swapped" in _one_line_error(capsys, ["calibrate", "import", str(right), str(left), "--out", out])
    kalibr = write_kalibr(tmp_path / "camchain.yaml", rig, distortion="fov")
    assert "'fov'" in _one_line_error(capsys, ["calibrate", "import", str(kalibr), "--out", out])
    other = tmp_path / "other.yaml"
    other.write_text("foo: 1\nbar: [1, 2]\n")
    assert "not a calibration this command knows" in _one_line_error(capsys, ["calibrate", "import", str(other), "--out", out])
    l2, _ = write_camera_info_pair(tmp_path, rig)
    assert "give files of one kind" in _one_line_error(capsys, ["calibrate", "import", str(left), str(l2), "--out", out])
    broken = tmp_path / "broken.yaml"
    broken.write_text("cam0: [1, 2\n")
    assert "not valid YAML" in _one_line_error(capsys, ["calibrate", "import", str(broken), "--out", out])
    assert "no such file" in _one_line_error(capsys, ["calibrate", "import", str(tmp_path / "nope.yaml"), "--out", out])
    (tmp_path / "cv").mkdir()
    mm = write_opencv(tmp_path / "cv", Rig(rig.K1, rig.D1, rig.K2, rig.D2, rig.R, rig.T * 1000, rig.image_size))
    assert "--t-units mm" in _one_line_error(capsys, ["calibrate", "import", str(mm[0]), "--out", out])
    assert main(["calibrate", "import", str(mm[0]), "--out", out, "--t-units", "mm"]) == 0


def test_opencv_yaml_without_its_header_is_read_and_its_errors_name_the_line(tmp_path: Path, capsys) -> None:
    rig = generic_rig()
    (tmp_path / "cv").mkdir()
    (written,) = write_opencv(tmp_path / "cv", rig)
    bare = tmp_path / "bare.yaml"
    bare.write_text(written.read_text().split("\n", 1)[1])  # without "%YAML:1.0"
    assert_same_rig(import_calibration([bare]).calibration, rig)
    bad = tmp_path / "bad.yaml"
    bad.write_text("M1: !!opencv-matrix\n  rows: 3\n cols: 3\n")
    err = _one_line_error(capsys, ["calibrate", "import", str(bad), "--out", str(tmp_path / "c.yaml")])
    assert "not a valid OpenCV file (line 3:" in err
