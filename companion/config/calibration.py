"""Config of where the stereo geometry comes from (``[calibration]``)."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field

from companion.config._base import StrictModel


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
