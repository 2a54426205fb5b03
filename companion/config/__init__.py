"""The whole configuration: one TOML file validated by pydantic v2.

``load_config(path)`` reads and validates a file; ``parse_config(mapping)`` validates a mapping;
``apply_patch(config, patch)`` validates a partial update against a whole new model. All three raise
:class:`~companion.errors.ConfigError` whose message names the field path and the bad value; none of
them ever returns a half-valid config. The defaults of every model are the documented default file
``config/companion.toml`` (a test keeps the two equal), so the service runs with no file at all.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any, get_args

from pydantic import Field, PrivateAttr, ValidationError, model_validator

from companion.config._base import StrictModel
from companion.config.core import (
    CalibrationConfig,
    CommandConfig,
    ControllerConfig,
    InputTerm,
    LutConfig,
    OutputTerm,
    RegionsConfig,
    RuleConfig,
    StereoBackend,
    StereoConfig,
)
from companion.config.envelope import EnvelopeConfig, envelope_violations
from companion.config.gpu import GpuConfig
from companion.config.obstacle import ObstacleDistanceConfig
from companion.config.planner import PlannerConfig
from companion.config.removed import is_removed, removed_message
from companion.config.service import (
    BusConfig,
    CameraConfig,
    ServiceConfig,
    VehicleConfig,
)
from companion.config.sim import SimConfig
from companion.config.view import ViewConfig
from companion.devices import cpu_cores, cuda_available, numba_available
from companion.errors import ConfigError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on 3.10 only
    import tomli as tomllib

__all__ = [
    "BusConfig",
    "CalibrationConfig",
    "CameraConfig",
    "CommandConfig",
    "CompanionConfig",
    "ControllerConfig",
    "EnvelopeConfig",
    "GpuConfig",
    "InputTerm",
    "LutConfig",
    "ObstacleDistanceConfig",
    "OutputTerm",
    "RegionsConfig",
    "RuleConfig",
    "ServiceConfig",
    "SimConfig",
    "StereoConfig",
    "VehicleConfig",
    "ViewConfig",
    "apply_patch",
    "as_written",
    "concrete_backend",
    "for_backend",
    "load_bus_config",
    "load_config",
    "load_view_config",
    "parse_config",
    "semi_global_map",
]


class CompanionConfig(StrictModel):
    """Root of the configuration; one attribute per TOML table."""

    calibration: CalibrationConfig = Field(default_factory=CalibrationConfig)
    stereo: StereoConfig = Field(default_factory=StereoConfig)
    regions: RegionsConfig = Field(default_factory=RegionsConfig)
    lut: LutConfig = Field(default_factory=LutConfig)
    controller: ControllerConfig = Field(default_factory=ControllerConfig)
    command: CommandConfig = Field(default_factory=CommandConfig)
    planner: PlannerConfig = Field(default_factory=PlannerConfig)
    obstacle_distance: ObstacleDistanceConfig = Field(default_factory=ObstacleDistanceConfig)
    camera: CameraConfig = Field(default_factory=CameraConfig)
    vehicle: VehicleConfig = Field(default_factory=VehicleConfig)
    bus: BusConfig = Field(default_factory=BusConfig)
    service: ServiceConfig = Field(default_factory=ServiceConfig)
    gpu: GpuConfig = Field(default_factory=GpuConfig)
    sim: SimConfig = Field(default_factory=SimConfig)
    view: ViewConfig = Field(default_factory=ViewConfig)
    envelope: EnvelopeConfig = Field(default_factory=EnvelopeConfig)

    #: The settings written "auto" and resolved for the backend, as ("section", "field") pairs.
    _from_auto: frozenset[tuple[str, str]] = PrivateAttr(default=frozenset())

    @model_validator(mode="after")
    def _within_envelope(self) -> CompanionConfig:
        problems = envelope_violations(self)
        if problems:
            raise ValueError("outside the safety envelope: " + "; ".join(problems))
        return self

    @model_validator(mode="after")
    def _resolve_for_backend(self) -> CompanionConfig:
        """Every validated config flies its backend-dependent settings resolved (:func:`for_backend`
        with :func:`concrete_backend`): nothing downstream ever reads "auto"."""
        auto = frozenset((s, f) for s, f in AUTO_FOR_BACKEND if getattr(getattr(self, s), f) == "auto")
        if not auto:
            return self
        resolved = for_backend(self, concrete_backend(self))
        for section in {s for s, _ in auto}:
            # The model is frozen once validation returns; this is still validation.
            object.__setattr__(self, section, getattr(resolved, section))
        self._from_auto = auto
        return self


#: The settings whose "auto" means "as the backend's disparity map needs" (:func:`for_backend`).
AUTO_FOR_BACKEND: tuple[tuple[str, str], ...] = (("planner", "block_erode_px"),)


def _short_repr(value: Any, limit: int = 80) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def format_validation_error(err: ValidationError, source: str) -> str:
    """One line: ``source: field.path: message (got VALUE)`` per problem, joined by '; '. Settings that
    were removed (:mod:`companion.config.removed`) come first, together, each with what to do."""
    parts = []
    removed = []
    for e in err.errors(include_url=False):
        loc = ".".join(str(x) for x in e["loc"])
        msg = e["msg"].removeprefix("Value error, ")
        if e["type"] == "extra_forbidden":
            if is_removed(loc):
                removed.append(loc)
                continue
            msg = "unknown key (no such setting here; check the spelling)"
        value = e.get("input")
        # A whole-model check (e.g. rule cross-references) already names the item in its message.
        got = "" if e["type"] == "missing" or isinstance(value, dict) else f" (got {_short_repr(value)})"
        parts.append(f"{loc}: {msg}{got}" if loc else msg)  # a whole-config check names its fields
    if removed:
        parts.insert(0, removed_message(removed))
    return f"{source}: invalid config: " + "; ".join(parts)


def parse_config(data: Mapping[str, Any], source: str = "config") -> CompanionConfig:
    """Validate a mapping (e.g. parsed TOML) into a :class:`CompanionConfig`.

    Whether the stereo setting works with the rig is checked where the config meets the rig
    (:func:`companion.core.rig_check.check_rig_config`: the service, the tools that fly it).

    Raises:
        ConfigError: naming each bad field's path and value.
    """
    try:
        cfg = CompanionConfig.model_validate(dict(data))
    except ValidationError as err:
        raise ConfigError(format_validation_error(err, source), source=source) from None
    return cfg


#: The backends whose matcher follows ``stereo.matcher`` (the OpenCV ones are their own matchers).
_OWN_MATCHER_BACKENDS = ("cupy", "reference")


#: Threads the cpu-sgm engine's path aggregation (most of its work) runs on at most: two halves.
CPU_SGM_MAX_THREADS = 2


def cpu_sgm_keeps_rate(cfg: CompanionConfig, cores: int) -> bool:
    """Whether ``cpu-sgm`` keeps the camera's frame rate with ``cores`` CPU cores: camera pixels ×
    disparities × frames per second at most ``stereo.cpu_sgm_cells_per_core_s`` per thread it may
    use (``stereo.cpu_threads``, 0 = ``cores``; at most :data:`CPU_SGM_MAX_THREADS`). Pure: the
    caller counts the cores."""
    st, cam = cfg.stereo, cfg.camera
    threads = min(st.cpu_threads, cores) if st.cpu_threads > 0 else cores
    threads = max(1, min(threads, CPU_SGM_MAX_THREADS))
    work = cam.width_px * cam.height_px * st.num_disparities * cam.fps_hz
    return st.cpu_sgm_cells_per_core_s > 0 and work <= st.cpu_sgm_cells_per_core_s * threads


def concrete_backend(cfg: CompanionConfig) -> str:
    """The backend ``cfg.stereo.backend`` means on this machine: "auto" is cupy when CuPy sees a CUDA
    device, else cpu-sgm where Numba is installed and it keeps the camera's rate
    (:func:`cpu_sgm_keeps_rate`), else opencv-bm; any other name is itself. The same answer for the
    same config on the same machine (no timing)."""
    backend = cfg.stereo.backend
    if backend == "auto":
        if cuda_available():
            return "cupy"
        if numba_available() and cpu_sgm_keeps_rate(cfg, cpu_cores()):
            return "cpu-sgm"
        return "opencv-bm"
    return backend


def as_written(cfg: CompanionConfig) -> dict[str, Any]:
    """``cfg`` as JSON-ready tables, with the settings that were written "auto" (and resolved for the
    backend) back to "auto": what a patch merges into, so a change of backend or matcher resolves
    them again."""
    data = cfg.model_dump(mode="json")
    for section, name in cfg._from_auto:
        data[section][name] = "auto"
    return data


def semi_global_map(stereo: StereoConfig, backend: str) -> bool:
    """Whether ``backend`` (a concrete ``stereo.backend``, not "auto") with ``stereo`` makes the
    semi-global matcher's dense map, the one ``planner.block_erode_px = "auto"`` was measured to help
    (:func:`for_backend`)."""
    return backend == "cpu-sgm" or (backend in _OWN_MATCHER_BACKENDS and stereo.matcher == "sgm")


def for_backend(cfg: CompanionConfig, backend: str) -> CompanionConfig:
    """``cfg`` with ``planner.block_erode_px`` resolved where it is "auto": 1 px with the semi-global
    matcher's dense map (:func:`semi_global_map`), 0 with any other. The same object when nothing is
    "auto".

    The map decides: the SGM smears depth edges onto what is behind them, which the erosion corrects;
    StereoBM leaves holes, and its sparse near surfaces would be eroded away. Every validated
    :class:`CompanionConfig` is resolved this way for :func:`concrete_backend` of its backend.

    Raises:
        ValueError: ``backend`` is "auto" or names no backend.
    """
    if backend == "auto" or backend not in get_args(StereoBackend):
        raise ValueError(f"for_backend needs a concrete stereo.backend, got {backend!r}")
    if cfg.planner.block_erode_px != "auto":
        return cfg
    erode = 1 if semi_global_map(cfg.stereo, backend) else 0
    return cfg.model_copy(update={"planner": cfg.planner.model_copy(update={"block_erode_px": erode})})


def read_config_text(path: Path) -> str:
    """The text of config file ``path``, decoded as UTF-8.

    Raises:
        ConfigError: the file is missing or unreadable, or a byte is not UTF-8 (naming the file, the
            byte offset and its line).
    """
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise ConfigError(f"{path}: cannot read config: {err.strerror or err}", source=str(path)) from None
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as err:
        line = raw.count(b"\n", 0, err.start) + 1
        raise ConfigError(
            f"{path}: not UTF-8 text: byte {err.start} (line {line}) is {raw[err.start:err.start + 1]!r} "
            f"({err.reason}); save the file as UTF-8",
            source=str(path),
            offset=err.start,
        ) from None


def _read_toml(path: Path) -> dict[str, Any]:
    """The parsed TOML of config file ``path`` (ConfigError: unreadable, not UTF-8, not TOML)."""
    text = read_config_text(path)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path}: not valid TOML: {err}", source=str(path)) from None


def _strict_validate(model: type[StrictModel], data: Mapping[str, Any], source: str) -> Any:
    """``data`` (parsed TOML) validated by ``model`` with strict types, as :func:`apply_patch` validates
    a live change: a number must be a number (``"2"`` is not), a flag a boolean.

    Raises:
        ConfigError: naming each bad key, or a number that is not finite.
    """
    try:
        text = json.dumps(dict(data), allow_nan=False, default=str)
    except ValueError:
        raise ConfigError(f"{source}: invalid config: numbers must be finite (nan and inf are not)", source=source) from None
    try:
        return model.model_validate_json(text, strict=True)
    except ValidationError as err:
        raise ConfigError(format_validation_error(err, source), source=source) from None


def load_config(path: Path | str | None) -> CompanionConfig:
    """Read and validate a TOML config file; ``None`` gives the defaults. Types are strict, as in a
    live change (:func:`apply_patch`).

    Raises:
        ConfigError: the file is missing, unreadable, not UTF-8, not TOML, or invalid.
    """
    if path is None:
        return CompanionConfig()
    path = Path(path)
    return _strict_validate(CompanionConfig, _read_toml(path), str(path))


def _load_table(path: Path | str, name: str, model: type[StrictModel]) -> Any:
    """Table ``name`` of a TOML config file, validated alone by ``model`` (the rest of the file may be invalid).

    Raises:
        ConfigError: the file is missing, unreadable, not UTF-8, not TOML, or that table is invalid.
    """
    path = Path(path)
    data = _read_toml(path)
    table = data.get(name, {})
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: {name}: expected a table, got {type(table).__name__}", source=str(path))
    return _strict_validate(model, table, f"{path} [{name}]")


def load_bus_config(path: Path | str) -> BusConfig:
    """Only the ``[bus]`` table of a TOML config file: ``companion ctl``, ``watch`` and ``view`` find the
    service with it even when the rest of the file is invalid (when a user most needs status)."""
    return _load_table(path, "bus", BusConfig)


def load_view_config(path: Path | str) -> ViewConfig:
    """Only the ``[view]`` table of a TOML config file (``companion view``: where the preview is)."""
    return _load_table(path, "view", ViewConfig)


def _deep_merge(base: dict[str, Any], patch: Mapping[str, Any], path: str) -> dict[str, Any]:
    out = dict(base)
    for key, value in patch.items():
        if not isinstance(key, str):
            raise ConfigError(f"patch: key {key!r} at {path or '(root)'} is not a string")
        where = f"{path}.{key}" if path else key
        if isinstance(value, Mapping) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value, where)
        else:
            out[key] = value
    return out


def apply_patch(config: CompanionConfig, patch: Mapping[str, Any]) -> CompanionConfig:
    """Return a new config: ``config`` with ``patch`` deep-merged in (tables merge, lists replace).

    The whole result is validated with strict types, as JSON: a number must be a number (``"2.5"``
    and ``true`` are not), a flag a boolean. On error ``config`` is untouched and a ConfigError says
    which field.
    """
    if not isinstance(patch, Mapping):
        raise ConfigError(f"patch: expected a table/object, got {type(patch).__name__}")
    merged = _deep_merge(as_written(config), patch, "")
    try:
        text = json.dumps(merged, allow_nan=False, default=str)
    except ValueError:
        raise ConfigError("patch: invalid config: numbers must be finite (NaN and infinity are not)") from None
    try:
        cfg = CompanionConfig.model_validate_json(text, strict=True)
    except ValidationError as err:
        raise ConfigError(format_validation_error(err, "patch"), source="patch") from None
    return cfg
