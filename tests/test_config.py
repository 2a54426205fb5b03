"""The configuration: defaults, the documented default file, validation errors that name the field."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from companion.config import CompanionConfig, apply_patch, load_config, parse_config
from companion.config.document import render_default_toml
from companion.core.rig_check import check_rig_config
from companion.errors import ConfigError

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_FILE = ROOT / "config" / "companion.toml"


def test_default_file_equals_builtin_defaults() -> None:
    assert load_config(DEFAULT_FILE) == CompanionConfig()


def test_default_file_is_the_generated_documentation() -> None:
    # Regenerate with tools/gen-default-config.py after changing a default or a description.
    assert DEFAULT_FILE.read_text(encoding="utf-8") == render_default_toml()


def test_paper_values_are_the_defaults() -> None:
    cfg = CompanionConfig()
    assert cfg.controller.input_terms["near"].params_m == (0.75, 2.25)
    assert cfg.controller.input_terms["far"].params_m == (0.75, 2.25)
    assert (cfg.regions.safe_window_width_m, cfg.regions.safe_window_height_m) == (0.5, 0.5)
    assert cfg.regions.reference_distance_m == 1.5
    assert [r.name for r in cfg.controller.main_rules][:7] == [f"R{i}" for i in range(1, 8)]
    assert cfg.command.stale_frame_timeout_s == 0.5


def _every_field(model: type, path: str = ""):
    from pydantic import BaseModel

    for name, info in model.model_fields.items():
        yield f"{path}{name}", info
        ann = info.annotation
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            yield from _every_field(ann, f"{path}{name}.")


def test_every_field_has_a_description() -> None:
    missing = [p for p, info in _every_field(CompanionConfig) if not (info.description or "").strip()]
    # Sections themselves are documented by their class docstring.
    missing = [p for p in missing if "." in p]
    assert not missing, f"fields without a description: {missing}"


@pytest.mark.parametrize(
    ("patch", "expected"),
    [
        ({"stereo": {"num_disparities": 70}}, "stereo.num_disparities"),
        ({"stereo": {"block_size_px": 8}}, "stereo.block_size_px"),
        ({"stereo": {"bogus": 1}}, "stereo.bogus"),
        ({"nope": {}}, "nope"),
        ({"regions": {"robust_percentile_pct": -1}}, "regions.robust_percentile_pct"),
        ({"lut": {"points_m": [[1.0, 1.0], [0.5, 2.0]]}}, "lut.points_m"),
        ({"lut": {"median_frames": 2}}, "median_frames must be odd"),
        ({"command": {"stale_frame_timeout_s": 6.0}}, "failsafe_timeout_s"),
        ({"controller": {"main_rules": [{"name": "x", "when": "centre is far", "then": {"yaw": "left"}}]}}, "centre"),
        ({"controller": {"main_rules": [{"name": "x", "when": "center is far", "then": {"yaw": "up"}}]}}, "'up'"),
        ({"controller": {"input_terms": {"near": {"shape": "triangle", "params_m": [1.0, 0.5, 2.0]}}}}, "non-decreasing"),
        ({"memory": {"push_baseline_m": 0.3}}, "push_baseline_m (0.3 m) must be 0 or at least 0.45 m"),
        ({"memory": {"trust_cell_m": 0.5}}, "push_baseline_m"),
    ],
)
def test_invalid_patch_names_the_field_and_keeps_the_old(patch: dict, expected: str) -> None:
    cfg = CompanionConfig()
    with pytest.raises(ConfigError) as exc:
        apply_patch(cfg, patch)
    assert expected in str(exc.value)
    assert "\n" not in str(exc.value)
    assert cfg == CompanionConfig()  # untouched


def test_patch_merges_tables_and_replaces_lists() -> None:
    cfg = apply_patch(CompanionConfig(), {"stereo": {"num_disparities": 128}, "lut": {"points_m": [[0.5, 0.6], [5, 5.5]]}})
    assert cfg.stereo.num_disparities == 128 and cfg.stereo.block_size_px == 9
    assert cfg.lut.points_m == [(0.5, 0.6), (5.0, 5.5)]


def test_config_is_frozen() -> None:
    cfg = CompanionConfig()
    with pytest.raises(Exception):
        cfg.stereo.num_disparities = 32  # type: ignore[misc]


def test_load_config_errors_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[stereo\nx=1", encoding="utf-8")
    with pytest.raises(ConfigError, match="not valid TOML") as exc:
        load_config(bad)
    assert str(bad) in str(exc.value)
    wrong = tmp_path / "wrong.toml"
    wrong.write_text("[regions]\nmin_valid_fraction = 2.0\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"regions\.min_valid_fraction.*got 2\.0"):
        load_config(wrong)


def test_parse_config_rejects_unknown_top_level_keys() -> None:
    with pytest.raises(ConfigError, match="typo_section: unknown key"):
        parse_config({"stereo": {}, "typo_section": {}})


def test_a_renamed_key_is_refused_with_its_new_name() -> None:
    """A config written before the guard's count became seconds names the new key and the conversion
    rather than "unknown key"; nothing is silently dropped."""
    with pytest.raises(ConfigError, match=r"memory\.guard_clear_after_frames: renamed memory\.guard_clear_after_s.*60 frames = 4 s.*got 120"):
        parse_config({"memory": {"guard_clear_after_frames": 120}})
    assert parse_config({"memory": {"guard_clear_after_s": 8.0}}).memory.guard_clear_after_s == 8.0


def test_region_name_type_lists_the_regions_in_order() -> None:
    from typing import get_args

    from companion.config.core import RegionName
    from companion.core.types import REGION_NAMES

    assert get_args(RegionName) == REGION_NAMES


# --------------------------------------------------------------------------------------------------
# the stereo setting against the rig (issue 15, item 6)

_RIG_640 = {"camera": {"width_px": 640, "height_px": 480},
            "calibration": {"ideal_baseline_m": 0.075, "ideal_hfov_deg": 70.0}}


def _patched(**sections: dict) -> dict:
    data = {k: dict(v) for k, v in _RIG_640.items()}
    for k, v in sections.items():
        data.setdefault(k, {}).update(v)
    return data


def test_the_defaults_pass_the_rig_check_without_a_warning() -> None:
    assert check_rig_config(CompanionConfig()) == []
    assert check_rig_config(parse_config({"camera": {"width_px": 1280, "height_px": 720},
                                          "stereo": {"num_disparities": 128}})) == []


@pytest.mark.parametrize(
    ("data", "expected"),
    [
        (_patched(stereo={"num_disparities": 256, "backend": "opencv-bm"}), "reach into the centre region"),
        (_patched(stereo={"num_disparities": 256, "backend": "cupy", "matcher": "sad"}), "use at most 240"),
        ({"regions": {"safe_window_width_m": 5.0}}, "wider or taller than the 672 x 376 px view"),
        ({"stereo": {"num_disparities": 16}}, "nothing could ever read near"),
        ({"camera": {"width_px": 100, "height_px": 60}, "stereo": {"num_disparities": 112}}, "not below"),
    ],
)
def test_settings_that_cannot_work_are_errors_naming_the_nearest_depth(data: dict, expected: str) -> None:
    with pytest.raises(ConfigError) as exc:
        check_rig_config(parse_config(data, source="rig.toml"), "rig.toml")
    msg = str(exc.value)
    assert expected in msg and "the nearest depth this rig can measure is" in msg and msg.startswith("rig.toml: ")


def test_settings_that_work_badly_are_warnings(caplog: pytest.LogCaptureFixture) -> None:
    cfg = parse_config(_patched(stereo={"num_disparities": 128}))  # the corridor setting
    warnings = check_rig_config(cfg)
    assert any("searches down to 0.27 m" in w and "96 would reach 0.36 m" in w for w in warnings)
    assert any("CPU fallback" in w for w in warnings)  # auto on a machine without a GPU: opencv-bm
    # the SGM matcher matches every column: only the depth-range warning remains
    sgm = check_rig_config(parse_config(_patched(stereo={"num_disparities": 128, "backend": "cupy"})))
    assert len(sgm) == 1 and "searches down to" in sgm[0]
    far = check_rig_config(parse_config({"stereo": {"num_disparities": 48}}))
    assert any("nearer than 0.86 m cannot be measured" in w for w in far)
    with caplog.at_level("WARNING", logger="companion.core.rig_check"):
        checked = parse_config(_patched(stereo={"num_disparities": 128}), source="x.toml")
        check_rig_config(checked, "x.toml")
    assert checked.stereo.num_disparities == 128
    assert any(r.message.startswith("x.toml: ") for r in caplog.records)


def test_a_calibration_that_cannot_be_loaded_is_left_to_the_estimator(tmp_path: Path) -> None:
    cfg = parse_config({"calibration": {"file": str(tmp_path / "missing.yaml")}, "stereo": {"num_disparities": 16}})
    assert check_rig_config(cfg) == []
    assert cfg.stereo.num_disparities == 16  # not checked here: the estimator reports the missing file


@pytest.mark.parametrize(
    ("backend", "matcher", "dense"),
    [
        ("cupy", "sgm", True),
        ("reference", "sgm", True),
        ("reference", "sad", False),
        ("opencv-bm", "sgm", False),
        ("opencv-sgbm", "sgm", False),
    ],
)
def test_the_auto_map_options_follow_the_matcher(backend: str, matcher: str, dense: bool) -> None:
    """memory.block_erode_px, detour.cone_from_start and detour.through_squeeze default to "auto", which
    the loader resolves for the backend: 1 px and on with the semi-global matcher's dense map, 0 and off
    with the others; set values stay. No "auto" is left in a loaded config."""
    from companion.config import as_written, for_backend, semi_global_map

    cfg = parse_config({"stereo": {"backend": backend, "matcher": matcher}})
    assert semi_global_map(cfg.stereo, backend) is dense
    assert (cfg.memory.block_erode_px, cfg.detour.cone_from_start, cfg.detour.through_squeeze) == (int(dense), dense, dense)
    assert cfg.stereo.backend == backend
    assert for_backend(cfg, backend) is cfg  # nothing left to resolve
    written = as_written(cfg)
    assert (written["memory"]["block_erode_px"], written["detour"]["through_squeeze"]) == ("auto", "auto")
    fixed = parse_config(
        {"stereo": {"backend": backend, "matcher": matcher}, "memory": {"block_erode_px": 2},
         "detour": {"cone_from_start": not dense}}
    )
    assert (fixed.memory.block_erode_px, fixed.detour.cone_from_start, fixed.detour.through_squeeze) == (2, not dense, dense)
    assert as_written(fixed)["memory"]["block_erode_px"] == 2


def test_a_patch_resolves_the_auto_settings_again_for_a_new_matcher() -> None:
    """A live change of matcher re-resolves the settings written "auto"; one set by the patch stays."""
    sgm = parse_config({"stereo": {"backend": "reference", "matcher": "sgm"}})
    assert sgm.detour.through_squeeze is True
    sad = apply_patch(sgm, {"stereo": {"matcher": "sad"}})
    assert (sad.memory.block_erode_px, sad.detour.through_squeeze) == (0, False)
    kept = apply_patch(sgm, {"detour": {"through_squeeze": False}})
    assert (kept.detour.through_squeeze, kept.detour.cone_from_start) == (False, True)
    assert apply_patch(kept, {"stereo": {"matcher": "sad"}}).detour.through_squeeze is False


def test_the_default_config_resolves_auto_for_the_backend_this_machine_gets() -> None:
    from companion.config import concrete_backend, semi_global_map

    cfg = CompanionConfig()
    assert concrete_backend(cfg) in ("cupy", "cpu-sgm", "opencv-bm")
    dense = semi_global_map(cfg.stereo, concrete_backend(cfg))
    assert cfg.stereo.backend == "auto"  # the estimator resolves the backend itself
    assert (cfg.memory.block_erode_px, cfg.detour.through_squeeze) == (int(dense), dense)


def test_the_auto_map_options_need_a_concrete_backend_and_name_their_field_when_wrong() -> None:
    from companion.config import for_backend

    with pytest.raises(ValueError, match="concrete stereo.backend"):
        for_backend(CompanionConfig(), "auto")
    with pytest.raises(ConfigError, match="memory.block_erode_px"):
        parse_config({"memory": {"block_erode_px": "most"}})
    with pytest.raises(ConfigError, match="memory.block_erode_px"):
        parse_config({"memory": {"block_erode_px": 5}})


def test_a_byte_that_is_not_utf8_names_the_file_and_its_offset(tmp_path: Path) -> None:
    """A Latin-1 comment appended to the file (``# café`` saved by an editor in Latin-1) once ended the
    service with a UnicodeDecodeError traceback; it is a config error naming the byte."""
    path = tmp_path / "c.toml"
    good = DEFAULT_FILE.read_bytes()
    path.write_bytes(good + b"# caf\xe9\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert str(path) in message and f"byte {len(good) + 5}" in message and "UTF-8" in message
    assert "\n" not in message
    assert info.value.context["offset"] == len(good) + 5


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ('[command]\ncruise_speed_m_s = "2"\n', "command.cruise_speed_m_s"),
        ('[vehicle]\nstatus_text = "yes"\n', "vehicle.status_text"),
        ("[camera]\nwidth_px = 640.0\n", "camera.width_px"),
    ],
)
def test_the_file_has_strict_types_as_live_changes_do(tmp_path: Path, text: str, key: str) -> None:
    path = tmp_path / "c.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert key in str(info.value) and "\n" not in str(info.value)
    section, name = key.split(".")
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):  # the same rule for a live change
        apply_patch(CompanionConfig(), {section: {name: tomllib.loads(text)[section][name]}})


def test_a_whole_number_is_a_number_of_metres_in_the_file(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text("[command]\ncruise_speed_m_s = 2\n", encoding="utf-8")
    assert load_config(path).command.cruise_speed_m_s == 2.0


def test_the_flying_cruise_is_the_cruise_of_the_stack_that_flies() -> None:
    local = CompanionConfig()
    assert local.planner.kind == "local"
    assert local.flying_cruise_speed_m_s == local.planner.cruise_speed_m_s
    rules = CompanionConfig.model_validate({"planner": {"kind": "rules"}})
    assert rules.flying_cruise_speed_m_s == rules.command.cruise_speed_m_s
