"""Does the stereo setting work with the rig? The check run where a config meets the rig (the service
at its start and on every change, the tools that fly or process a config): :func:`check_rig_config`.

For the camera's eye size and the rig (the calibration file's rectified geometry, or the ideal rig), with
``f·B`` the focal length times the baseline and ``D`` the number of disparities:

* the **nearest depth the rig can measure** is ``z_min = f·B / (D - 1)`` (every message states it);
* **errors** (the setting cannot work): ``D - 1 >= W`` (no column could ever be matched); the safe window
  projected at the reference distance is wider or taller than the view (the centre region would be the
  whole image: "region wider than the view"); a block matcher (``opencv-bm``, ``opencv-sgbm``, or matcher
  ``sad``) whose never-matched left band (``D - 1 + b/2`` columns) reaches into the centre region; the
  rig measures nothing nearer than where the controller's ``near`` term reaches 0 (nothing could ever read
  near);
* **warnings** (it works, badly): ``z_min`` beyond the ``near`` term's full-membership edge (obstacles
  nearer than ``z_min`` cannot be measured); more disparities than the smallest multiple of 16 that
  reaches half of that edge (disparities for depths the controller does not distinguish: they cost time
  and, with block matching, add false matches at the largest disparities, read as phantom obstacles); a
  block matcher's band covering more than half of the left regions' columns (they read unknown, i.e.
  near, most of the time).

Pure: the geometry comes from :func:`~companion.core.rectifier.make_rectifier`, which reads the
calibration file when one is set.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

from companion.config import CompanionConfig
from companion.config.core import ControllerConfig, RegionsConfig, StereoConfig
from companion.core.geometry import StereoGeometry
from companion.core.rectifier import make_rectifier
from companion.errors import CompanionError, ConfigError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RigCheck:
    """The outcome of :func:`check_rig`.

    Attributes:
        nearest_depth_m: ``f·B / (D - 1)``, metres.
        errors: one line each; a non-empty list means the setting cannot work.
        warnings: one line each.
    """

    nearest_depth_m: float
    errors: tuple[str, ...]
    warnings: tuple[str, ...]


def rig_check_lines(result: RigCheck) -> list[str]:
    """The check's findings as every tool prints them (``process``, ``eval``, ``sim``, ``demo``, the
    service's log), one line each: ``rig check: error: ...`` / ``rig check: warning: ...``."""
    return [f"rig check: error: {m}" for m in result.errors] + [f"rig check: warning: {m}" for m in result.warnings]


def near_unmeasurable(result: RigCheck, controller: ControllerConfig) -> bool:
    """True when the rig cannot measure down to where the controller's 'near' is full: an obstacle
    nearer than :attr:`RigCheck.nearest_depth_m` has a disparity beyond the search, so it reads unknown,
    or (a false match at a smaller disparity) farther than it is; a region that reads far or clear
    then says nothing about what is nearer."""
    edges = _near_edges_m(controller)
    return edges is not None and result.nearest_depth_m > edges[0]


def _block_matcher(st: StereoConfig) -> str | None:
    """``"always"`` for a backend with the never-matched left band, ``"fallback"`` for auto (the CPU
    fallback opencv-bm has it), None for the SGM matcher."""
    if st.backend in ("opencv-bm", "opencv-sgbm"):
        return "always"
    if st.backend in ("reference", "cupy"):
        return "always" if st.matcher == "sad" else None
    if st.backend == "cpu-sgm":
        return None
    return "fallback"  # auto: cupy on a GPU, cpu-sgm or opencv-bm without one


def _near_edges_m(ctrl: ControllerConfig) -> tuple[float, float] | None:
    """Full-membership edge and zero edge of the 'near' term, metres (None for a shape without them)."""
    term = ctrl.input_terms.get("near")
    if term is None:
        return None
    p = term.params_m
    if term.shape == "left_shoulder":
        return p[0], p[1]
    if term.shape == "trapezoid":
        return p[2], p[3]
    if term.shape == "triangle":
        return p[1], p[2]
    return None


def _suggest_disparities(fb: float, depth_m: float) -> int:
    """The multiple of 16 that measures down to ``depth_m`` (at least 16, at most 256)."""
    return int(min(256, max(16, 16 * math.ceil((fb / depth_m + 1) / 16))))


def check_rig(
    geometry: StereoGeometry, stereo: StereoConfig, regions: RegionsConfig, controller: ControllerConfig
) -> RigCheck:
    """Errors and warnings for this stereo setting on this rig (module doc)."""
    w, h = geometry.width_px, geometry.height_px
    D = stereo.num_disparities
    fb = geometry.focal_baseline_px_m
    z_min = fb / (D - 1)
    rig = (
        f"{w}x{h} px, f = {geometry.focal_px:.0f} px, B = {geometry.baseline_m:.3f} m, "
        f"{D} disparities: the nearest depth this rig can measure is {z_min:.2f} m"
    )
    errors: list[str] = []
    warnings: list[str] = []
    if D - 1 >= w:
        errors.append(f"stereo.num_disparities = {D} is not below the {w} px image width ({rig})")
    f = geometry.focal_px
    win_w = f * regions.safe_window_width_m / regions.reference_distance_m
    win_h = f * regions.safe_window_height_m / regions.reference_distance_m
    if win_w > w - 2 or win_h > h - 2:
        errors.append(
            f"regions: the safe window {regions.safe_window_width_m} x {regions.safe_window_height_m} m at "
            f"{regions.reference_distance_m} m is {win_w:.0f} x {win_h:.0f} px, wider or taller than the "
            f"{w} x {h} px view: the centre region would be the whole image ({rig})"
        )
    c0 = max(1, int(math.floor(geometry.cx_px - (win_w - 1) / 2.0 + 0.5)))
    kind = _block_matcher(stereo)
    band = D - 1 + stereo.block_size_px // 2
    if kind is not None and not errors:
        who = "block matching" if kind == "always" else "the CPU fallback (opencv-bm) of backend auto"
        best = max(16, 16 * ((c0 - stereo.block_size_px // 2) // 16))
        if band > c0:
            msg = (
                f"stereo.num_disparities = {D}: {who} never matches the leftmost {band} columns, which reach "
                f"into the centre region (columns {c0}..): the centre would read unknown (near); use at most "
                f"{best} disparities, or matcher sgm ({rig})"
            )
            (errors if kind == "always" else warnings).append(msg)
        elif band > c0 / 2:
            warnings.append(
                f"stereo.num_disparities = {D}: {who} never matches the leftmost {band} of the left regions' "
                f"{c0} columns: they read unknown (near) most of the time ({rig})"
            )
    edges = _near_edges_m(controller)
    if edges is not None:
        full, zero = edges
        if z_min >= zero:
            errors.append(
                f"the rig measures nothing nearer than {z_min:.2f} m, beyond {zero} m where the controller's "
                f"'near' ends: nothing could ever read near; use at least {_suggest_disparities(fb, full)} "
                f"disparities ({rig})"
            )
        elif z_min > full:
            n = _suggest_disparities(fb, full)
            warnings.append(
                f"obstacles nearer than {z_min:.2f} m cannot be measured (the controller's 'near' is full from "
                f"{full} m); {n} disparities would reach {fb / (n - 1):.2f} m ({rig})"
            )
        elif _suggest_disparities(fb, full / 2) < D:
            # more disparities than the smallest multiple of 16 that reaches half the full-near edge
            n = _suggest_disparities(fb, full / 2)
            warnings.append(
                f"stereo.num_disparities = {D} searches down to {z_min:.2f} m, less than half the {full} m "
                f"where the controller's 'near' is full: the largest disparities cost time and, with block "
                f"matching, add false matches read as phantom obstacles; {n} would reach "
                f"{fb / (n - 1):.2f} m ({rig})"
            )
    return RigCheck(nearest_depth_m=z_min, errors=tuple(errors), warnings=tuple(warnings))


def check_rig_config(cfg: CompanionConfig, source: str = "config") -> list[str]:
    """Check the stereo setting against the rig at the camera's eye size.

    The rig is the calibration file's rectified geometry, or the ideal rig without one; a calibration
    that cannot be loaded here is left to the estimator, which reports it. See
    :func:`check_rig` for the rules.

    Returns:
        The warnings (each also logged).

    Raises:
        ConfigError: the setting cannot work (one line per problem, each naming the nearest depth).
    """
    try:
        geometry = make_rectifier(cfg.calibration, cfg.camera.width_px, cfg.camera.height_px).geometry
    except (CompanionError, OSError, ValueError) as err:
        log.debug("%s: rig not checked (calibration not loadable here: %s)", source, err)
        return []
    result = check_rig(geometry, cfg.stereo, cfg.regions, cfg.controller)
    if result.errors:  # in the words every tool prints (rig_check_lines)
        raise ConfigError(f"{source}: rig check: error: " + "; ".join(result.errors), source=source)
    for w in result.warnings:
        log.warning("%s: rig check: warning: %s", source, w)
    return list(result.warnings)
