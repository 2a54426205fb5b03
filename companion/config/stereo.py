"""Config of the disparity computation (``[stereo]``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from companion.config._base import StrictModel

StereoBackend = Literal["auto", "opencv-bm", "opencv-sgbm", "reference", "cupy", "cpu-sgm"]
StereoMatcher = Literal["sgm", "sad"]


class StereoConfig(StrictModel):
    """Disparity computation."""

    backend: StereoBackend = Field(
        default="auto",
        description=(
            "Disparity backend. auto: cupy when a CUDA device and CuPy are present, else cpu-sgm where it "
            "keeps the camera's frame rate (cpu_sgm_cells_per_core_s), else opencv-bm. "
            "opencv-bm: OpenCV StereoBM on the CPU (fast). opencv-sgbm: OpenCV StereoSGBM (better, "
            "slower). reference: the exact NumPy matcher that `matcher` names, the oracle the GPU must "
            "equal bit for bit (slow: seconds per frame). cupy: the CUDA kernels, same rules as reference. "
            "cpu-sgm: the census + SGM rules of reference compiled for the CPU (Numba), equal to it bit "
            "for bit, threaded over cpu_threads."
        ),
    )
    matcher: StereoMatcher = Field(
        default="sgm",
        description=(
            "reference and cupy: the matching algorithm. sgm: census (9x7) costs, semi-global "
            "aggregation along sgm_paths paths, winner with the sgm_uniqueness_ratio_pct test, "
            "sub-pixel, a left-right check, a 3x3 median (every column matched, with the "
            "disparities it allows) and a near-range check (the pair shrunk 4 times, matched with half "
            "the disparities: where the full-size match finds nothing and the shrunk one a surface "
            "nearer than the range, the pixel reads the nearest measurable depth, not a wrong farther "
            "one). sad: SAD block matching (block_size_px, uniqueness_ratio_pct, "
            "texture_threshold_grey; the leftmost num_disparities + block_size_px/2 columns are never "
            "matched). The OpenCV backends ignore it; cpu-sgm is always sgm."
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
            "same rule). 5 rather than OpenCV's customary 10: on a plain wall 3 m ahead StereoBM then "
            "leaves about half the regions unknown instead of all of them, for slightly more bad pixels "
            "(with disp12_max_diff_px 1; docs/benchmarks.md)."
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
        description=(
            "Every matcher: the largest patch of disparity (pixels, connected, varying by at most "
            "speckle_range_px between neighbours) removed as a false match, a peak in Hirschmüller's "
            "terms; 0 = off. A surface is a large patch; on a plain wall the sensor's noise makes short "
            "streaks of matches at any depth (phantom obstacles), each its own small patch. The "
            "near-range check's shrunk pair removes patches of the same size in its own pixels: a "
            "streak's length is the matcher's, not the scene's."
        ),
    )
    speckle_range_px: int = Field(
        default=2,
        ge=0,
        le=64,
        description=(
            "Every matcher: the largest disparity step between neighbouring pixels of one patch, pixels "
            "(see speckle_window_px)."
        ),
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
    bm_scale_check: Literal["off", "agree", "no_conflict"] = Field(
        default="agree",
        description=(
            "opencv-bm: a second StereoBM on the pair at half size (half the disparities, the same "
            "settings) checks each full-size disparity d against twice the half-size one at the same "
            "place. agree: keep d only where the half-size match exists and is within "
            "bm_scale_check_tolerance_px of it; no_conflict: reject d only where the half-size match "
            "exists and differs; off: no check (where the half-size matcher's wider left band leaves it "
            "nothing, neither checks). A window over thin bars and what lies behind them (a fence, a "
            "grid) matches a wrong period at one size and not at the other; a true match agrees. agree "
            "removes most phantom near regions in front of bars and lowers Aloe's bad pixels, at "
            "slightly lower density and about 1.4 ms more a frame on 2 cores at 672x376 "
            "(docs/benchmarks.md)."
        ),
    )
    bm_scale_check_tolerance_px: float = Field(
        default=2.0,
        ge=0.5,
        le=16.0,
        description="opencv-bm, bm_scale_check: largest difference between d and twice the half-size disparity, full-size px.",
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
        description="Worker threads of the CPU backends (OpenCV's, and cpu-sgm's); 0 = all cores.",
    )
    cpu_sgm_cells_per_core_s: float = Field(
        default=100e6,
        ge=0.0,
        le=1e12,
        description=(
            "auto without CUDA: how much census + SGM matching one CPU core does per second, in pixels "
            "times disparities. auto picks cpu-sgm when camera width x height x num_disparities x "
            "camera.fps_hz is at most this times the threads it may use (cpu_threads, 0 = all cores; at "
            "most 2, the halves its paths run in), "
            "i.e. when it keeps the camera's frame rate with a quarter of each frame's time left for the "
            "rest of the pipeline; else opencv-bm. 0 = never."
        ),
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
