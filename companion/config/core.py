"""Config sections of the perception and decision core (calibration → stereo → regions → LUT → fuzzy).

Every field has a type, a default, bounds, its unit in its name and a description. The defaults are
the paper's values where the paper gives one (near 0.75 m, far 2.25 m, a 0.5 m safe window at 1.5 m,
the seven rules, a 45°-rotated corner controller). The knobs the paper leaves open are tuned in the
closed-loop simulator (``companion sim --suite standard``, docs/benchmarks.md): the speed blend, yaw and
vertical rates, the release filter, the escape threshold, four side rules and course hold.
``config/paper.toml`` restores the paper's controller exactly (constant speed, no side rules, no
course hold) for comparison.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator, model_validator

from companion.config._base import StrictModel
from companion.core.fuzzy.rules import parse_antecedent
from companion.core.types import REGION_NAMES

#: A region's name (the same names, in the same order, as ``companion.core.types.REGION_NAMES``).
RegionName = Literal["up_left", "up", "up_right", "left", "center", "right", "down_left", "down", "down_right"]

# --------------------------------------------------------------------------------------------------
# Calibration


class CalibrationConfig(StrictModel):
    """Where the stereo geometry comes from."""

    file: Path | None = Field(
        default=None,
        description=(
            "Stereo calibration: a ZED factory file SN<serial>.conf, or an OpenCV stereo calibration "
            "(.yaml/.yml/.json/.npz with K1 D1 K2 D2 R T and image_size). Unset: the frames are taken "
            "as already rectified by an ideal rig described by ideal_hfov_deg and ideal_baseline_m "
            "(the simulator's camera)."
        ),
    )
    ideal_hfov_deg: float = Field(
        default=90.0,
        gt=10.0,
        lt=170.0,
        description="Horizontal field of view of the ideal rectified rig used when no file is set, degrees.",
    )
    ideal_baseline_m: float = Field(
        default=0.12,
        gt=0.01,
        le=1.0,
        description="Baseline of the ideal rig used when no file is set, metres (ZED: 0.12).",
    )
    rectify_alpha: float = Field(
        default=0.0,
        ge=-1.0,
        le=1.0,
        description=(
            "stereoRectify free scaling: 0 keeps only valid pixels (zoomed), 1 keeps all source pixels, "
            "-1 lets OpenCV choose."
        ),
    )


# --------------------------------------------------------------------------------------------------
# Stereo matching

StereoBackend = Literal["auto", "opencv-bm", "opencv-sgbm", "reference", "cupy"]
StereoMatcher = Literal["sgm", "sad"]


class StereoConfig(StrictModel):
    """Disparity computation."""

    backend: StereoBackend = Field(
        default="auto",
        description=(
            "Disparity backend. auto: cupy when a CUDA device and CuPy are present, else opencv-bm. "
            "opencv-bm: OpenCV StereoBM on the CPU (fast). opencv-sgbm: OpenCV StereoSGBM (better, "
            "slower). reference: the exact NumPy matcher that `matcher` names, the oracle the GPU must "
            "equal bit for bit (slow: seconds per frame). cupy: the CUDA kernels, same rules as reference."
        ),
    )
    matcher: StereoMatcher = Field(
        default="sgm",
        description=(
            "reference and cupy: the matching algorithm. sgm: census (9x7) costs, semi-global "
            "aggregation along sgm_paths paths, winner with the sgm_uniqueness_ratio_pct test, "
            "sub-pixel, a left-right check and a 3x3 median (every column matched, with the "
            "disparities it allows). sad: SAD block matching (block_size_px, uniqueness_ratio_pct, "
            "texture_threshold_grey; the leftmost num_disparities + block_size_px/2 columns are never "
            "matched). The OpenCV backends ignore it."
        ),
    )
    num_disparities: int = Field(
        default=64,
        ge=16,
        le=256,
        multiple_of=16,
        description="Disparity search range [0, num_disparities) in pixels; a multiple of 16 (OpenCV's rule).",
    )
    block_size_px: int = Field(
        default=9, ge=5, le=31, description="Side of the square matching window in pixels; odd."
    )
    uniqueness_ratio_pct: int = Field(
        default=5,
        ge=0,
        le=100,
        description=(
            "Reject a match unless its cost beats every non-adjacent disparity's cost by this margin, "
            "percent (OpenCV's uniquenessRatio; matcher sad of the reference and cupy backends uses the "
            "same rule). 5 (10 before 2026-11-23): on a plain wall 3 m ahead StereoBM left 15 of 27 "
            "regions unknown instead of 27, for 1.16 % bad-2 on Aloe instead of 1.00 % (with "
            "disp12_max_diff_px 1; docs/benchmarks.md)."
        ),
    )
    texture_threshold_grey: int = Field(
        default=3,
        ge=0,
        le=255,
        description=(
            "reference/cupy: reject a pixel whose window has a mean absolute horizontal grey-level "
            "difference below this (flat, textureless patches give no reliable match), grey levels."
        ),
    )
    bm_texture_threshold: int = Field(
        default=10,
        ge=0,
        le=100000,
        description="opencv-bm: OpenCV's textureThreshold (sum of |prefiltered| values over the window).",
    )
    bm_prefilter_type: Literal["xsobel", "normalized_response"] = Field(
        default="xsobel", description="opencv-bm: pre-filter applied to both images before matching."
    )
    bm_prefilter_size_px: int = Field(
        default=9, ge=5, le=255, description="opencv-bm: pre-filter window size for normalized_response, odd."
    )
    bm_prefilter_cap: int = Field(
        default=31, ge=1, le=63, description="opencv-bm/sgbm: clip of pre-filtered values."
    )
    speckle_window_px: int = Field(
        default=100,
        ge=0,
        le=10000,
        description="opencv-bm/sgbm: largest blob of disparity (pixels) still removed as speckle; 0 = off.",
    )
    speckle_range_px: int = Field(
        default=2,
        ge=0,
        le=64,
        description="opencv-bm/sgbm: disparity variation within a blob still counted as one blob, pixels.",
    )
    disp12_max_diff_px: int = Field(
        default=1,
        ge=-1,
        le=64,
        description=(
            "opencv-bm: OpenCV's left-right check (disp12MaxDiff): reject a pixel whose disparity differs "
            "by more than this from the right view's, px; -1 = off. On Aloe (docs/benchmarks.md) 1 halves "
            "StereoBM's bad-2 (2.1 -> 1.0 %) at the same density and speed. opencv-sgbm: the tolerance of "
            "sgbm_lr_check (OpenCV 5's StereoSGBM itself ignores disp12MaxDiff: measured identical)."
        ),
    )
    sgbm_lr_check: bool = Field(
        default=False,
        description=(
            "opencv-sgbm: mirrored left-right check: a second StereoSGBM on the mirrored pair gives the "
            "right view's disparity, and a pixel whose disparity differs from it by more than "
            "disp12_max_diff_px (1 when that is -1) is rejected. About doubles the matcher's time."
        ),
    )
    sgbm_mode: Literal["sgbm", "hh", "sgbm_3way", "hh4"] = Field(
        default="sgbm_3way", description="opencv-sgbm: path aggregation mode (sgbm_3way is the fastest)."
    )
    sgbm_p1: int = Field(
        default=0,
        ge=0,
        le=100000,
        description="opencv-sgbm: penalty for a disparity change of 1 between neighbours; 0 = 8·block².",
    )
    sgbm_p2: int = Field(
        default=0,
        ge=0,
        le=400000,
        description="opencv-sgbm: penalty for larger disparity changes; 0 = 32·block². Must exceed p1.",
    )
    cpu_threads: int = Field(
        default=0,
        ge=0,
        le=256,
        description="OpenCV worker threads for the CPU backends; 0 = all cores.",
    )
    sgm_paths: Literal[4, 8] = Field(
        default=4,
        description=(
            "matcher sgm: aggregation paths: 4 (left, right, up, down) or 8 (and the diagonals). On "
            "Aloe at full size (docs/benchmarks.md) 8 paths (with P1 8, P2 80) gave 3.1 % bad-2 where 4 "
            "gave 3.3 %, at the same density; on an H100 they cost about twice the aggregation time."
        ),
    )
    sgm_p1: int = Field(
        default=10,
        ge=0,
        le=192,
        description=(
            "matcher sgm: penalty for a disparity change of 1 px between neighbours along a path, in "
            "census-cost units (bits of the 62-bit census); below sgm_p2."
        ),
    )
    sgm_p2: int = Field(
        default=120,
        ge=1,
        le=193,
        description=(
            "matcher sgm: penalty for a larger disparity change (a depth edge), census-cost units; at "
            "most 193 so that every path cost fits one byte (62 + P2 <= 255). 10/120 measured best of "
            "the settings tried on Aloe (docs/benchmarks.md)."
        ),
    )
    sgm_uniqueness_ratio_pct: int = Field(
        default=10,
        ge=0,
        le=100,
        description=(
            "matcher sgm: reject a pixel unless its summed cost beats every disparity 2 px or more "
            "away by this margin, percent."
        ),
    )
    sgm_lr_max_diff_px: int = Field(
        default=1,
        ge=-1,
        le=16,
        description=(
            "matcher sgm: left-right check: reject a pixel whose disparity d differs by more than this "
            "from the right view's disparity at x - d (computed from the same summed costs), pixels; "
            "-1 = no check. Off, Aloe's bad-2 triples (3.9 % -> 11.7 % at half size with uniqueness 5, "
            "docs/benchmarks.md)."
        ),
    )
    sgm_median: bool = Field(
        default=True,
        description="matcher sgm: replace each valid disparity by the median of the valid ones in its 3x3 neighbourhood.",
    )

    @field_validator("block_size_px")
    @classmethod
    def _odd_block(cls, v: int) -> int:
        if v % 2 == 0:
            raise ValueError(f"block_size_px must be odd, got {v}")
        return v

    @field_validator("bm_prefilter_size_px")
    @classmethod
    def _odd_prefilter(cls, v: int) -> int:
        if v % 2 == 0:
            raise ValueError(f"bm_prefilter_size_px must be odd, got {v}")
        return v

    @model_validator(mode="after")
    def _sgbm_penalties(self) -> StereoConfig:
        if self.sgbm_p1 and self.sgbm_p2 and self.sgbm_p2 <= self.sgbm_p1:
            raise ValueError(f"sgbm_p2 ({self.sgbm_p2}) must be greater than sgbm_p1 ({self.sgbm_p1})")
        if self.sgm_p2 <= self.sgm_p1:
            raise ValueError(f"sgm_p2 ({self.sgm_p2}) must be greater than sgm_p1 ({self.sgm_p1})")
        return self


# --------------------------------------------------------------------------------------------------
# Regions


class RegionsConfig(StrictModel):
    """The nine regions and how each is reduced to one depth."""

    safe_window_width_m: float = Field(
        default=0.5,
        gt=0.05,
        le=10.0,
        description="Width of the safe window around the vehicle that defines the centre region, metres.",
    )
    safe_window_height_m: float = Field(
        default=0.5,
        gt=0.05,
        le=10.0,
        description="Height of the safe window that defines the centre region, metres.",
    )
    reference_distance_m: float = Field(
        default=1.5,
        gt=0.1,
        le=50.0,
        description=(
            "Distance at which the safe window is projected through the rectified focal length to size "
            "the centre region, metres (paper: 0.5 m at 1.5 m ≈ 150 px at f ≈ 450 px)."
        ),
    )
    robust_percentile_pct: float = Field(
        default=2.0,
        ge=0.0,
        le=50.0,
        description=(
            "Region depth = this low percentile of the region's valid depths, percent: the k-th "
            "nearest valid pixel with k = max(1, ceil(pct/100 · n_valid)). 0 = the raw minimum (the "
            "paper's choice, which one false match turns into a phantom obstacle)."
        ),
    )
    min_valid_fraction: float = Field(
        default=0.10,
        gt=0.0,
        le=1.0,
        description=(
            "A region with a smaller share of valid depth pixels than this is unknown, and the "
            "controller treats unknown as near."
        ),
    )
    max_depth_m: float = Field(
        default=20.0,
        gt=1.0,
        le=1000.0,
        description="Region depths beyond this (including matches at disparity 0) are reported as this, metres.",
    )


# --------------------------------------------------------------------------------------------------
# Look-up table


class LutConfig(StrictModel):
    """Depth refinement (paper section VI) and per-region temporal filter."""

    points_m: list[tuple[float, float]] = Field(
        default=[(0.2, 0.2), (40.0, 40.0)],
        min_length=2,
        max_length=256,
        description=(
            "Pairs (computed depth, true depth), metres, both strictly increasing. Depths are mapped "
            "piecewise-linearly and clamped to the table's ends. The default is the identity."
        ),
    )
    median_frames: int = Field(
        default=3,
        ge=1,
        le=9,
        description=(
            "Each region depth is the median of its last this many frames, odd (an unknown region "
            "counts at once and unknown history counts as near). 1 = off (the paper). 3: a false "
            "stereo match that lasts one frame (PX4 SITL: weak-texture patches matched 40 px off, "
            "read 0.4 m in open space) no longer swerves the vehicle, and a near region that drops out "
            "to far for one frame stays near, at the cost of seeing a suddenly appearing obstacle one "
            "frame later (67 ms at 15 Hz)."
        ),
    )
    release_time_constant_s: float = Field(
        default=1.0,
        ge=0.0,
        le=10.0,
        description=(
            "Low-pass time constant for a region depth that grows (an obstacle receding), seconds; "
            "0 = off. A depth that shrinks (an obstacle approaching) is never delayed. Simulator-tuned: "
            "an obstacle leaving the centre keeps the avoidance going a little longer, for margin."
        ),
    )

    @field_validator("median_frames")
    @classmethod
    def _odd_window(cls, v: int) -> int:
        if v % 2 == 0:
            raise ValueError(f"median_frames must be odd, got {v}")
        return v

    @field_validator("points_m")
    @classmethod
    def _monotone(cls, pts: list[tuple[float, float]]) -> list[tuple[float, float]]:
        for i in range(1, len(pts)):
            (c0, t0), (c1, t1) = pts[i - 1], pts[i]
            if not c1 > c0:
                raise ValueError(
                    f"computed depths must be strictly increasing: point {i} has {c1} m after {c0} m"
                )
            if not t1 > t0:
                raise ValueError(
                    f"true depths must be strictly increasing: point {i} has {t1} m after {t0} m"
                )
        for i, (c, t) in enumerate(pts):
            if c <= 0 or t <= 0:
                raise ValueError(f"depths must be positive: point {i} is ({c}, {t})")
        return pts


# --------------------------------------------------------------------------------------------------
# Fuzzy controller

MembershipShape = Literal["triangle", "trapezoid", "left_shoulder", "right_shoulder", "gaussian"]
_SHAPE_ARITY = {"triangle": 3, "trapezoid": 4, "left_shoulder": 2, "right_shoulder": 2, "gaussian": 2}


def _check_shape_params(shape: str, params: tuple[float, ...]) -> None:
    n = _SHAPE_ARITY[shape]
    if len(params) != n:
        raise ValueError(f"{shape} takes {n} parameters, got {len(params)}: {list(params)}")
    if shape == "gaussian":
        if params[1] <= 0:
            raise ValueError(f"gaussian sigma must be > 0, got {params[1]}")
        return
    if any(b < a for a, b in zip(params, params[1:])):
        raise ValueError(f"{shape} parameters must be non-decreasing, got {list(params)}")
    if shape in ("left_shoulder", "right_shoulder") and params[1] <= params[0]:
        raise ValueError(f"{shape} needs a < b, got {list(params)}")


class InputTerm(StrictModel):
    """A membership function over a region depth (metres).

    Shapes: triangle (a, b, c): 0 at a, 1 at b, 0 at c. trapezoid (a, b, c, d). left_shoulder (a, b):
    1 up to a, falling linearly to 0 at b. right_shoulder (a, b): 0 up to a, rising to 1 at b.
    gaussian (mean, sigma).
    """

    shape: MembershipShape = Field(description="Membership function shape.")
    params_m: tuple[float, ...] = Field(description="Shape parameters in metres (see the shape).")

    @model_validator(mode="after")
    def _check(self) -> InputTerm:
        _check_shape_params(self.shape, self.params_m)
        return self


class OutputTerm(StrictModel):
    """A membership function over a normalised output in [-1, 1] (same shapes as :class:`InputTerm`)."""

    shape: MembershipShape = Field(description="Membership function shape.")
    params: tuple[float, ...] = Field(description="Shape parameters, dimensionless, on [-1, 1].")

    @model_validator(mode="after")
    def _check(self) -> OutputTerm:
        _check_shape_params(self.shape, self.params)
        return self


class RuleConfig(StrictModel):
    """One Mamdani rule: ``when`` (a condition over region terms) ``then`` (output terms).

    ``when`` may use the placeholders ``{yaw_side}`` (the preferred horizontal side, a region and yaw
    term: left/right), ``{pitch_side}`` (up/down) and ``{corner_side}`` (the preferred corner, e.g.
    up_right); ``then`` values may use ``{yaw_side}`` and ``{pitch_side}``.
    """

    name: str = Field(min_length=1, max_length=64, description="Short unique name, shown in logs and health.")
    when: str = Field(min_length=1, max_length=500, description="Condition, e.g. 'center is near and up is far'.")
    then: dict[Literal["yaw", "pitch"], str] = Field(
        min_length=1, description="Output -> term, e.g. {yaw = 'left'}."
    )
    weight: float = Field(default=1.0, gt=0.0, le=1.0, description="Rule weight multiplying its strength.")
    doc: str = Field(default="", max_length=1000, description="Why the rule exists (free text).")

    @field_validator("when")
    @classmethod
    def _parse(cls, v: str) -> str:
        parse_antecedent(_substitute_placeholders(v, "right", "up"))
        return v


def _substitute_placeholders(text: str, yaw_side: str, pitch_side: str) -> str:
    return (
        text.replace("{yaw_side}", yaw_side)
        .replace("{pitch_side}", pitch_side)
        .replace("{corner_side}", f"{pitch_side}_{yaw_side}")
    )


def _t(shape: str, *p: float) -> dict:
    return {"shape": shape, "params": p}


def _i(shape: str, *p: float) -> dict:
    return {"shape": shape, "params_m": p}


def _default_input_terms() -> dict[str, InputTerm]:
    # Paper: below 0.75 m is near, above 2.25 m is far, linear between (a 1/3 scale on its 0–3 axis).
    return {
        "near": InputTerm(**_i("left_shoulder", 0.75, 2.25)),
        "far": InputTerm(**_i("right_shoulder", 0.75, 2.25)),
    }


def _default_yaw_terms() -> dict[str, OutputTerm]:
    return {
        "left": OutputTerm(**_t("trapezoid", -1.0, -1.0, -0.6, 0.0)),
        "straight": OutputTerm(**_t("triangle", -0.4, 0.0, 0.4)),
        "right": OutputTerm(**_t("trapezoid", 0.0, 0.6, 1.0, 1.0)),
    }


def _default_pitch_terms() -> dict[str, OutputTerm]:
    return {
        "down": OutputTerm(**_t("trapezoid", -1.0, -1.0, -0.6, 0.0)),
        "level": OutputTerm(**_t("triangle", -0.4, 0.0, 0.4)),
        "up": OutputTerm(**_t("trapezoid", 0.0, 0.6, 1.0, 1.0)),
    }


def _r(name: str, when: str, doc: str, **then: str) -> RuleConfig:
    return RuleConfig(name=name, when=when, then=then, doc=doc)


def _default_main_rules() -> list[RuleConfig]:
    return [
        _r("R1", "center is far", "Paper rule 1: centre clear, fly straight.", yaw="straight", pitch="level"),
        _r("R2", "center is near and up is near and down is far",
           "Paper rule 2: blocked ahead and above, free below: go down.", pitch="down"),
        _r("R3", "center is near and down is near and up is far",
           "Paper rule 3: blocked ahead and below, free above: go up.", pitch="up"),
        _r("R4", "center is near and right is near and left is far",
           "Paper rule 4: blocked ahead and right, free left: turn left.", yaw="left"),
        _r("R5", "center is near and left is near and right is far",
           "Paper rule 5: blocked ahead and left, free right: turn right.", yaw="right"),
        _r("R6", "center is near and {yaw_side} is far",
           "Paper rule 6 (preferred side): blocked ahead and the preferred side is free: turn to it. "
           "The paper prints 'right is near -> right', which would steer into the obstacle and cancel "
           "rule 4; read as the preference that breaks left/right ties (paper Fig. 9c).",
           yaw="{yaw_side}"),
        _r("R7", "center is near and {pitch_side} is far",
           "Paper rule 7 (preferred vertical): blocked ahead and the preferred vertical side is free: "
           "go that way (same reading as rule 6).",
           pitch="{pitch_side}"),
        _r("TIE", "center is near and up is near and down is near and left is far and right is far",
           "Tie rule (paper Fig. 9c): ahead, above and below blocked, both sides free: take the "
           "preferred side so the centroid never collapses to straight.",
           yaw="{yaw_side}"),
        # Not in the paper. The centre region is a cone (0.5 m at 1.5 m) narrower than the vehicle
        # closer in, so an obstacle within reach can sit in a side region while the centre reads far
        # (the paper's Fig. 11 failure): the side rules keep steering away from a near side until it
        # is passed. Their steering also pauses course hold (see command.hold_resume_delay_s).
        _r("S1", "center is far and left is near and right is far",
           "Side rule (not in the paper): centre clear but something near on the left: veer right.",
           yaw="right"),
        _r("S2", "center is far and right is near and left is far",
           "Side rule (not in the paper): centre clear but something near on the right: veer left.",
           yaw="left"),
        _r("S3", "center is far and up is near and down is far",
           "Side rule (not in the paper): centre clear but something near above: sink.",
           pitch="down"),
        _r("S4", "center is far and down is near and up is far",
           "Side rule (not in the paper): centre clear but something near below: climb.",
           pitch="up"),
    ]


def _default_corner_rules() -> list[RuleConfig]:
    # The main controller rotated by 45°: up -> up_right, right -> down_right, down -> down_left,
    # left -> up_left. Consulted only when the main controller finds no escape.
    return [
        _r("C1", "center is far", "Rotated rule 1: centre clear, fly straight.", yaw="straight", pitch="level"),
        _r("C2", "center is near and up_right is near and down_left is far",
           "Rotated rule 2: blocked up-right, free down-left: go down-left.", yaw="left", pitch="down"),
        _r("C3", "center is near and down_left is near and up_right is far",
           "Rotated rule 3: blocked down-left, free up-right: go up-right.", yaw="right", pitch="up"),
        _r("C4", "center is near and down_right is near and up_left is far",
           "Rotated rule 4: blocked down-right, free up-left: go up-left.", yaw="left", pitch="up"),
        _r("C5", "center is near and up_left is near and down_right is far",
           "Rotated rule 5: blocked up-left, free down-right: go down-right.", yaw="right", pitch="down"),
        _r("C6", "center is near and {corner_side} is far",
           "Rotated preference: blocked ahead and the preferred corner is free: go to it.",
           yaw="{yaw_side}", pitch="{pitch_side}"),
    ]


class ControllerConfig(StrictModel):
    """The Mamdani fuzzy controller: membership functions, operators and the rule bases."""

    and_method: Literal["min", "product"] = Field(default="min", description="Fuzzy AND (t-norm).")
    or_method: Literal["max", "probabilistic_sum"] = Field(default="max", description="Fuzzy OR (s-norm).")
    implication: Literal["min", "product"] = Field(
        default="min", description="How a rule's strength shapes its output set: clip (min) or scale (product)."
    )
    defuzzification: Literal["centroid", "mean_of_maximum", "bisector"] = Field(
        default="centroid", description="Defuzzification of the aggregated (max) output set."
    )
    output_resolution: int = Field(
        default=201, ge=21, le=10001, description="Samples of the output universe [-1, 1]."
    )
    input_terms: dict[str, InputTerm] = Field(
        default_factory=_default_input_terms,
        min_length=1,
        description="Terms over every region depth (metres). Paper: near below 0.75 m, far above 2.25 m.",
    )
    yaw_terms: dict[str, OutputTerm] = Field(
        default_factory=_default_yaw_terms, min_length=1, description="Terms of the yaw output (-1 left, +1 right)."
    )
    pitch_terms: dict[str, OutputTerm] = Field(
        default_factory=_default_pitch_terms, min_length=1, description="Terms of the pitch output (-1 down, +1 up)."
    )
    yaw_neutral_term: str = Field(default="straight", description="The yaw term that means 'no avoidance'.")
    pitch_neutral_term: str = Field(default="level", description="The pitch term that means 'no avoidance'.")
    preferred_yaw_side: Literal["left", "right"] = Field(
        default="right", description="Side taken when both are equally free ({yaw_side} in rules). Paper: right."
    )
    preferred_pitch_side: Literal["up", "down"] = Field(
        default="up", description="Vertical side taken when both are equally free ({pitch_side} in rules)."
    )
    main_rules: list[RuleConfig] = Field(
        default_factory=_default_main_rules, min_length=1, description="The main controller (centre + 4 sides)."
    )
    corner_rules: list[RuleConfig] = Field(
        default_factory=_default_corner_rules,
        description="The 45°-rotated controller over the corners, consulted when the main one finds no escape.",
    )
    unknown_depth_m: float = Field(
        default=0.0,
        ge=0.0,
        le=0.75,
        description="Depth fed to the controller for an unknown region, metres: unknown is treated as near.",
    )
    min_escape_strength: float = Field(
        default=0.2,
        gt=0.0,
        le=1.0,
        description=(
            "Strongest non-neutral rule below this means that controller found no escape (then the "
            "corner controller, then brake). Simulator-tuned: 0.05 crept toward flat faces on escapes "
            "of strength 0.07."
        ),
    )
    min_escape_command: float = Field(
        default=0.05,
        ge=0.0,
        le=1.0,
        description=(
            "An escape whose defuzzified |yaw| and |pitch| are both below this is no escape: opposing "
            "rules of equal strength (a flat wall filling the view) cancel to 'straight'."
        ),
    )
    brake_near_degree: float = Field(
        default=0.5,
        gt=0.0,
        le=1.0,
        description=(
            "With no escape from either controller, brake once the centre is at least this near "
            "(membership of the first input term, 'near')."
        ),
    )

    def substitute(self, text: str) -> str:
        """Replace ``{yaw_side}``, ``{pitch_side}`` and ``{corner_side}`` in a rule's text."""
        return _substitute_placeholders(text, self.preferred_yaw_side, self.preferred_pitch_side)

    @model_validator(mode="after")
    def _check_rules(self) -> ControllerConfig:
        regions = set(REGION_NAMES)
        out_terms = {"yaw": self.yaw_terms, "pitch": self.pitch_terms}
        if self.yaw_neutral_term not in self.yaw_terms:
            raise ValueError(f"yaw_neutral_term {self.yaw_neutral_term!r} is not one of {sorted(self.yaw_terms)}")
        if self.pitch_neutral_term not in self.pitch_terms:
            raise ValueError(
                f"pitch_neutral_term {self.pitch_neutral_term!r} is not one of {sorted(self.pitch_terms)}"
            )
        if "near" not in self.input_terms:
            raise ValueError("input_terms must define 'near' (used for braking and speed)")
        for label, rules in (("main_rules", self.main_rules), ("corner_rules", self.corner_rules)):
            seen: set[str] = set()
            for k, rule in enumerate(rules):
                where = f"{label}.{k} ({rule.name!r})"
                if rule.name in seen:
                    raise ValueError(f"{where}: duplicate rule name")
                seen.add(rule.name)
                ante = parse_antecedent(self.substitute(rule.when))
                for c in ante.clauses:
                    if c.variable not in regions:
                        raise ValueError(
                            f"{where}: unknown region {c.variable!r}; regions are {', '.join(REGION_NAMES)}"
                        )
                    if c.term not in self.input_terms:
                        raise ValueError(f"{where}: unknown term {c.term!r}; terms are {sorted(self.input_terms)}")
                for out, term in rule.then.items():
                    term = self.substitute(term)
                    if term not in out_terms[out]:
                        raise ValueError(f"{where}: {out} has no term {term!r}; terms are {sorted(out_terms[out])}")
        return self


# --------------------------------------------------------------------------------------------------
# Command mapping


class CommandConfig(StrictModel):
    """How a decision becomes a body-frame velocity setpoint, and when frames are too old to trust."""

    cruise_speed_m_s: float = Field(
        default=0.7,
        ge=0.0,
        le=15.0,
        description=(
            "Forward speed when the way is clear, m/s (paper: constant). With PX4's default velocity "
            "response (~0.85 s lag) 1 m/s collided in the simulator and in PX4 SITL where 0.7 did not; "
            "raise it only on a vehicle tuned to respond faster."
        ),
    )
    avoid_speed_fraction: float = Field(
        default=0.1,
        ge=0.0,
        le=1.0,
        description=(
            "Forward speed while the centre is fully near, as a share of the cruise speed, blended "
            "linearly with the centre's near degree. 1 = the paper's constant speed; simulator-tuned "
            "0.1 leaves time to turn before the obstacle."
        ),
    )
    avoid_speed_regions: list[RegionName] = Field(
        default=[],
        max_length=9,
        description=(
            "Regions whose 'near' degree also slows the vehicle (the largest of them and the centre's "
            "drives the avoid_speed_fraction blend); [] = the centre only (the default). "
            "[\"left\", \"right\"] slows while a box passes beside the vehicle: in the simulator it "
            "raised the clearances but cost goals (timeouts in corridors), and in PX4 SITL it did not "
            "stop a flank clip; see docs/benchmarks.md."
        ),
    )
    max_yaw_rate_deg_s: float = Field(
        default=90.0,
        ge=0.0,
        le=360.0,
        description=(
            "Yaw rate commanded at fuzzy yaw ±1, deg/s (the default output terms defuzzify to at most "
            "±0.63, so 90 gives up to 57 deg/s)."
        ),
    )
    max_vertical_speed_m_s: float = Field(
        default=0.8, ge=0.0, le=5.0, description="Vertical speed commanded at fuzzy pitch ±1, m/s."
    )
    stale_frame_timeout_s: float = Field(
        default=0.5,
        gt=0.0,
        le=10.0,
        description="A newest frame older than this gives a zero-velocity setpoint (state degraded), seconds.",
    )
    failsafe_timeout_s: float = Field(
        default=5.0,
        gt=0.0,
        le=120.0,
        description="A newest frame older than this makes the service leave offboard to Hold (state failsafe), seconds.",
    )
    # Course hold (goal seeking). Not in the paper, whose controller only avoids: a vehicle that yawed
    # away never came back. Applies only when the caller passes the errors to setpoint_for.
    heading_hold_gain_per_s: float = Field(
        default=0.8,
        ge=0.0,
        le=10.0,
        description=(
            "Course hold: on a CLEAR decision, yaw back toward the heading at engagement at this rate "
            "per radian of heading error, 1/s (0 = off: the paper's behaviour)."
        ),
    )
    max_heading_hold_rate_deg_s: float = Field(
        default=20.0, ge=0.0, le=360.0, description="Course hold: largest yaw rate it commands, deg/s."
    )
    turn_back_angle_deg: float = Field(
        default=100.0,
        ge=0.0,
        le=180.0,
        description=(
            "Course hold, turning back: facing more than this many degrees away from the heading course "
            "hold aims at (line included), on a CLEAR decision past hold_resume_delay_s, the vehicle "
            "stops going forward and turns toward the course in place at max_heading_hold_rate_deg_s, "
            "whatever its side regions read (a turn in place moves it toward nothing, and the obstacle "
            "memory guards its flanks); 180 = off. Without it a vehicle that had turned around in a "
            "corridor (PX4 SITL, corridor-0) flew back out of it: the walls beside it read nearer than "
            "hold_clear_depth_m, so course hold never turned it."
        ),
    )
    line_hold_gain_per_m: float = Field(
        default=0.5,
        ge=0.0,
        le=10.0,
        description=(
            "Course hold, line: also steer back to the line through the engagement point along the "
            "engagement heading: the heading aimed at turns toward the line by atan(this × cross-track "
            "distance), per metre (0 = off: hold the heading only, and drift sideways with the "
            "autopilot's heading-estimate error)."
        ),
    )
    max_line_hold_angle_deg: float = Field(
        default=30.0, ge=0.0, le=89.0, description="Course hold, line: the largest turn toward the line, degrees."
    )
    line_hold_lateral_gain_per_s: float = Field(
        default=1.0,
        ge=0.0,
        le=10.0,
        description=(
            "Course hold, line, sideways: also fly sideways back toward the line at this speed per metre "
            "of cross-track distance, 1/s (0 = off: the paper never flies sideways). Turning back takes "
            "seconds; a multicopter that drifts sideways (wind, or PX4 SITL's ~0.2 m/s velocity-estimate "
            "error) is brought back at once, and the camera keeps looking ahead."
        ),
    )
    max_line_hold_lateral_speed_m_s: float = Field(
        default=0.3, ge=0.0, le=2.0, description="Course hold, line, sideways: the largest sideways speed it commands, m/s."
    )
    line_hold_lateral_clear_depth_m: float = Field(
        default=1.0,
        ge=0.0,
        le=50.0,
        description=(
            "Course hold, line, sideways: only toward a side whose region (left, right) is at least this "
            "deep, metres; unknown blocks it. Nearer than hold_clear_depth_m, because a slow sideways "
            "step is not a turn toward the side: approaching a wall with a doorway, both sides read the "
            "wall ~2 m ahead and the vehicle must still line up with the gap."
        ),
    )
    altitude_hold_gain_per_s: float = Field(
        default=0.5,
        ge=0.0,
        le=10.0,
        description=(
            "Course hold: on a CLEAR decision, climb or descend back toward the altitude at engagement "
            "at this speed per metre of altitude error, 1/s (0 = off)."
        ),
    )
    max_altitude_hold_speed_m_s: float = Field(
        default=0.3, ge=0.0, le=5.0, description="Course hold: largest vertical speed it commands, m/s."
    )
    hold_resume_delay_s: float = Field(
        default=1.5,
        ge=0.0,
        le=60.0,
        description=(
            "Course hold resumes only after the decisions have been CLEAR and straight this long, "
            "seconds: an obstacle just passed is beside or below the vehicle, out of the camera's view. "
            "The heading part (and turning back) counts decisions that do not turn, the altitude part "
            "ones that neither turn nor climb (a slight climb away from the ground must not keep a "
            "vehicle facing away from its course from turning back)."
        ),
    )
    hold_resume_distance_m: float = Field(
        default=1.5,
        ge=0.0,
        le=50.0,
        description=(
            "Overhead memory, metres (0 = off): no climb at all (by a rule or by course hold) until the "
            "vehicle has flown this far (horizontally) since the up region last read nearer than "
            "hold_clear_depth_m, and course hold's altitude part also waits this far after the "
            "decisions turned CLEAR and straight. The camera cannot see straight up: under a block, "
            "rules that climb away from the ground (and a hold that waited only for a time) flew the "
            "vehicle into the block's rear edge (simulator and PX4 SITL)."
        ),
    )
    brake_hold_gain_per_s: float = Field(
        default=1.0,
        ge=0.0,
        le=10.0,
        description=(
            "Brake position and heading hold: while braking, command a velocity back to where the brake "
            "began, this gain times the distance, and a yaw rate back to the heading it began with, this "
            "gain times the angle (capped at max_heading_hold_rate_deg_s), per second (0 = plain zero "
            "velocity and yaw rate). Zero velocity lets a real multicopter drift with its "
            "velocity-estimate error (PX4 SITL: into the obstacle within 20 s), and PX4 keeps turning "
            "~0.4 s after a zero yaw rate, which can open a false escape; holding both does not."
        ),
    )
    brake_hold_max_speed_m_s: float = Field(
        default=0.3, ge=0.0, le=2.0, description="Brake position hold: the largest speed it commands, m/s."
    )
    no_progress_timeout_s: float = Field(
        default=20.0,
        ge=0.0,
        le=600.0,
        description=(
            "Progress watchdog, seconds (0 = off): engaged with course hold, when the vehicle has not got "
            "progress_step_m farther along the course (the line from where it was engaged, along the "
            "heading it had then) for this long, the service stops trying: it holds position (as a "
            "brake does), its state becomes paused with the reason, and it waits for the pilot (resume "
            "tries again, or take over). A vehicle circling in front of an obstacle it cannot get past, "
            "or following a wall away from the only opening, only spends battery near obstacles."
        ),
    )
    progress_step_m: float = Field(
        default=1.0,
        gt=0.0,
        le=50.0,
        description=(
            "Progress watchdog: how much farther along the course (metres) counts as progress and "
            "restarts no_progress_timeout_s."
        ),
    )
    hold_clear_depth_m: float = Field(
        default=2.25,
        ge=0.0,
        le=50.0,
        description=(
            "Course hold turns (climbs, descends) toward a side only while that side's region (left, "
            "right, up, down) is at least this deep, metres; unknown blocks it."
        ),
    )

    @model_validator(mode="after")
    def _order(self) -> CommandConfig:
        if self.failsafe_timeout_s <= self.stale_frame_timeout_s:
            raise ValueError(
                f"failsafe_timeout_s ({self.failsafe_timeout_s}) must exceed stale_frame_timeout_s "
                f"({self.stale_frame_timeout_s})"
            )
        return self


# --------------------------------------------------------------------------------------------------
# Obstacle memory and the out-of-view guard


class MemoryConfig(StrictModel):
    """Obstacle memory: what the camera saw near, kept for a few seconds in the local (NED) frame, so
    that an obstacle the vehicle turned away from or flew past still keeps it away. The camera sees
    only ahead (ZED: ~±44°), and a multicopter drifts with its position estimate's error (PX4 SITL:
    ~0.2 m/s), sideways into what it no longer sees. Not in the paper."""

    duration_s: float = Field(
        default=30.0,
        ge=0.0,
        le=300.0,
        description=(
            "How long a point seen near is remembered after it was last seen, seconds; 0 = off (the "
            "paper). Long enough to outlast a brake, a hold or a turn in place in a dead end (an "
            "obstacle beside the vehicle is out of view the whole time: 17 s in one simulated dead "
            "end), short because the memory lives in the vehicle's position estimate, which drifts "
            "against the world."
        ),
    )
    max_depth_m: float = Field(
        default=2.5,
        gt=0.0,
        le=10.0,
        description=(
            "Only cells nearer than this are remembered, metres. Far enough that a wall 1 m to the "
            "side is remembered: the leftmost num_disparities columns are never matched, so a side "
            "wall first shows at ~32° off the heading, 1.6 times its lateral distance ahead."
        ),
    )
    grid_rows: int = Field(default=6, ge=1, le=64, description="Rows of the image's memory cells.")
    grid_cols: int = Field(
        default=24,
        ge=1,
        le=128,
        description=(
            "Columns of the image's memory cells: each cell gives at most one remembered point per "
            "frame, at its robust nearest depth, on the ray of the block that depth came from."
        ),
    )
    block_px: int = Field(
        default=4,
        ge=1,
        le=16,
        description=(
            "The disparity image is first reduced to the largest valid disparity of each block of this "
            "many pixels square (the GPU does this on the device: it must be a multiple of "
            "gpu.disparity_preview_downsample there), then cells are reduced from blocks."
        ),
    )
    robust_percentile_pct: float = Field(
        default=25.0,
        ge=0.0,
        le=100.0,
        description=(
            "A cell's disparity is the k-th largest of its blocks' with k = max(1, ceil(pct/100 · "
            "valid blocks)): something near must fill this share of a cell to be remembered. Each "
            "block is already its nearest pixel, so a small patch of false matches fills many blocks; "
            "at 5 % a weak-texture patch matched wrong for 2 frames of 3 was remembered and pushed a "
            "simulated vehicle into a pillar."
        ),
    )
    min_valid_fraction: float = Field(
        default=0.1,
        ge=0.0,
        le=1.0,
        description=(
            "A cell with fewer valid blocks than this fraction gives no point (unknown ahead is the "
            "regions' business: the controller treats it as near)."
        ),
    )
    confirm_frames: int = Field(
        default=3,
        ge=1,
        le=9,
        description=(
            "A cell's depth is the median of its last this many frames, odd, a cell seen nothing in "
            "counting as far: a false match that lasts one frame is not remembered."
        ),
    )
    guard_distance_m: float = Field(
        default=0.6,
        gt=0.0,
        le=5.0,
        description=(
            "A remembered point out of the camera's view (or nearer than it can see) this near to the "
            "vehicle's centre, horizontally, pushes the vehicle away (and stops its motion toward it when "
            "on its path, keep_out_m), metres. Default: the 0.25 m vehicle plus 0.35 m, below the 0.66 m a centred vehicle has "
            "to either side of a 0.82 m doorway gap."
        ),
    )
    keep_out_m: float = Field(
        default=0.35,
        gt=0.0,
        le=5.0,
        description=(
            "A guarding point within this of the path ahead (the line of the commanded velocity) stops "
            "the motion toward it, metres: the 0.25 m vehicle plus 0.1 m. Points farther from the path "
            "only push, so that passing between two pillars is not stalled."
        ),
    )
    guard_gain_per_s: float = Field(
        default=1.5,
        ge=0.0,
        le=10.0,
        description=(
            "The push away: this gain times how far inside guard_distance_m the point is, per second "
            "(m/s per metre); 0 = only stop the motion toward it."
        ),
    )
    max_guard_speed_m_s: float = Field(
        default=0.5, ge=0.0, le=2.0, description="The largest speed the push commands, m/s."
    )
    counter_velocity_fraction: float = Field(
        default=0.5,
        ge=0.0,
        le=2.0,
        description=(
            "While the vehicle is still moving toward a guarding point on the path it actually flies "
            "(its velocity lags the setpoint: ~0.85 s with PX4), the setpoint moves away from it at "
            "this fraction of that closing speed (with the push, at most max_guard_speed_m_s), so the "
            "lag does not carry it in (0 = only stop commanding toward it). Dimensionless. Default 0.5: "
            "with PX4 SITL the vehicle pushed off one jamb of a 1.1-1.3 m doorway slid on into the "
            "other (2 collisions in 14 doorway flights at 0, none in 18 at 0.5); 1 shoves the vehicle "
            "sideways, where the camera does not see either (a kinematic collision)."
        ),
    )
    hold_clear_m: float = Field(
        default=1.0,
        ge=0.0,
        le=5.0,
        description=(
            "Course hold neither turns nor slides toward a side with a remembered point within this "
            "of the vehicle, horizontally, and not more than keep_out_m behind it, metres (0 = off): "
            "an obstacle just passed is beside it, out of view (PX4 SITL: turning back toward the "
            "line right after a box, the vehicle swung into the box's rear corner)."
        ),
    )
    gap_centering_gain_per_s: float = Field(
        default=0.0,
        ge=0.0,
        le=10.0,
        description=(
            "Gap centering: with remembered points on both sides of the vehicle, abreast or up to "
            "gap_lookahead_m ahead, less than gap_max_width_m apart sideways (a doorway, two pillars), "
            "a CLEAR decision flies sideways toward the middle between the nearest of each side at "
            "this speed per metre off it, 1/s, instead of the line hold's sideways step (0 = off). "
            "Off by default: at 1 it raised PX4 SITL's doorway clearances from 0.01-0.08 m to "
            "0.10-0.25 m, but a false near point in the memory made a false gap, and with the guard's "
            "push away from the same point it slid a forest flight into a pillar (1 collision in 27 "
            "flights); the kinematic suite gave 100 % with and without drift."
        ),
    )
    max_gap_centering_speed_m_s: float = Field(
        default=0.3, ge=0.0, le=2.0, description="Gap centering: the largest sideways speed it commands, m/s."
    )
    gap_max_width_m: float = Field(
        default=2.0,
        gt=0.0,
        le=10.0,
        description=(
            "Gap centering: only a gap narrower than this (sideways, between the nearest remembered "
            "points left and right) is centred in, metres; wider ones leave room for course hold."
        ),
    )
    gap_lookahead_m: float = Field(
        default=1.5,
        gt=0.0,
        le=10.0,
        description=(
            "Gap centering: points up to this far ahead of the vehicle (and abreast, down to keep_out_m "
            "behind) count as its sides, metres: far enough to line up with a doorway before its "
            "jambs leave the view, near enough not to centre on what lies beyond a turn."
        ),
    )
    height_band_m: float = Field(
        default=0.4,
        gt=0.0,
        le=5.0,
        description=(
            "Only points within this much of the vehicle's altitude guard it, metres (the ground and "
            "what is overhead are the regions' business)."
        ),
    )

    @field_validator("confirm_frames")
    @classmethod
    def _odd_confirm(cls, v: int) -> int:
        if v % 2 == 0:
            raise ValueError(f"confirm_frames must be odd, got {v}")
        return v
