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
        ({"planner": {"floor_m": 3.0}}, "floor_m (3.0) must be below ceiling_m (3.0)"),
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


def test_a_config_of_the_rule_stack_is_refused_in_one_line_naming_what_to_do(tmp_path: Path) -> None:
    """A config written for the removed rule stack names each removed setting and what replaces it, in
    one line, rather than "unknown key"; a setting that moved names its new place. Nothing is silently
    dropped, and a live change naming one is refused the same way."""
    old = tmp_path / "old.toml"
    old.write_text(
        "[command]\ncruise_speed_m_s = 0.7\nheading_hold_gain_per_s = 0.8\nline_hold_gain_per_m = 0.5\n"
        "[memory]\nduration_s = 30.0\n[detour]\nspeed_m_s = 0.5\n[planner]\nkind = \"rules\"\n",
        encoding="utf-8",
    )
    with pytest.raises(ConfigError) as info:
        load_config(old)
    message = str(info.value)
    assert "\n" not in message and str(old) in message
    assert "[detour]: removed with the rule stack; the local planner ([planner]) replaces it" in message
    assert "delete the section" in message
    assert "[memory]: removed with the rule stack" in message and "planner.block_px" in message
    assert "command.cruise_speed_m_s: moved to planner.cruise_speed_m_s" in message
    assert "planner.kind: removed: the local planner is the only decision layer" in message
    assert "command.heading_hold_gain_per_s, command.line_hold_gain_per_m: removed with the rule stack" in message
    assert "unknown key" not in message
    with pytest.raises(ConfigError, match=r"command\.max_yaw_rate_deg_s: moved to planner\.max_yaw_rate_deg_s"):
        apply_patch(CompanionConfig(), {"command": {"max_yaw_rate_deg_s": 60.0}})
    with pytest.raises(ConfigError, match=r"\[memory\]: removed with the rule stack"):
        parse_config({"memory": {"duration_s": 0.0}})
    with pytest.raises(ConfigError, match=r"command\.cruise_sped_m_s: unknown key"):  # a typo is still a typo
        parse_config({"command": {"cruise_sped_m_s": 1.0}})


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
    """planner.block_erode_px defaults to "auto", which the loader resolves for the backend: 1 px with
    the semi-global matcher's dense map, 0 with the others; a set value stays. No "auto" is left in a
    loaded config."""
    from companion.config import as_written, for_backend, semi_global_map

    cfg = parse_config({"stereo": {"backend": backend, "matcher": matcher}})
    assert semi_global_map(cfg.stereo, backend) is dense
    assert cfg.planner.block_erode_px == int(dense)
    assert cfg.stereo.backend == backend
    assert for_backend(cfg, backend) is cfg  # nothing left to resolve
    assert as_written(cfg)["planner"]["block_erode_px"] == "auto"
    fixed = parse_config({"stereo": {"backend": backend, "matcher": matcher}, "planner": {"block_erode_px": 2}})
    assert fixed.planner.block_erode_px == 2
    assert as_written(fixed)["planner"]["block_erode_px"] == 2


def test_a_patch_resolves_the_auto_settings_again_for_a_new_matcher() -> None:
    """A live change of matcher re-resolves the settings written "auto"; one set by the patch stays."""
    sgm = parse_config({"stereo": {"backend": "reference", "matcher": "sgm"}})
    assert sgm.planner.block_erode_px == 1
    assert apply_patch(sgm, {"stereo": {"matcher": "sad"}}).planner.block_erode_px == 0
    kept = apply_patch(sgm, {"planner": {"block_erode_px": 2}})
    assert apply_patch(kept, {"stereo": {"matcher": "sad"}}).planner.block_erode_px == 2


def test_the_default_config_resolves_auto_for_the_backend_this_machine_gets() -> None:
    from companion.config import concrete_backend, semi_global_map

    cfg = CompanionConfig()
    assert concrete_backend(cfg) in ("cupy", "cpu-sgm", "opencv-bm")
    dense = semi_global_map(cfg.stereo, concrete_backend(cfg))
    assert cfg.stereo.backend == "auto"  # the estimator resolves the backend itself
    assert cfg.planner.block_erode_px == int(dense)


def test_the_auto_map_options_need_a_concrete_backend_and_name_their_field_when_wrong() -> None:
    from companion.config import for_backend

    with pytest.raises(ValueError, match="concrete stereo.backend"):
        for_backend(CompanionConfig(), "auto")
    with pytest.raises(ConfigError, match="planner.block_erode_px"):
        parse_config({"planner": {"block_erode_px": "most"}})
    with pytest.raises(ConfigError, match="planner.block_erode_px"):
        parse_config({"planner": {"block_erode_px": 5}})


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
        ('[planner]\ncruise_speed_m_s = "2"\n', "planner.cruise_speed_m_s"),
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
    path.write_text("[planner]\ncruise_speed_m_s = 2\n", encoding="utf-8")
    assert load_config(path).planner.cruise_speed_m_s == 2.0
