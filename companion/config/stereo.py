"""Config of the disparity computation (``[stereo]``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from companion.config._base import StrictModel

StereoBackend = Literal["auto", "opencv-bm", "opencv-sgbm", "reference", "cupy"]


class StereoConfig(StrictModel):
    """Disparity computation."""

    backend: StereoBackend = Field(
        default="auto",
        description=(
            "Disparity backend. auto: cupy when a CUDA device and CuPy are present, else opencv-bm. "
            "opencv-bm: OpenCV StereoBM on the CPU (fast). opencv-sgbm: OpenCV StereoSGBM (better, "
            "slower). reference: exact NumPy SAD block matching, the oracle the GPU must equal (slow). "
            "cupy: the CUDA kernels, same rules as reference."
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
        default=10,
        ge=0,
        le=100,
        description=(
            "Reject a match unless its cost beats every non-adjacent disparity's cost by this margin, "
            "percent (OpenCV's uniquenessRatio; the reference and cupy backends use the same rule)."
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
        return self
