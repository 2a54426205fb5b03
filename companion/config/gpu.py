"""Config section of the CuPy backend: ``[gpu]`` in the TOML file.

Only read when ``stereo.backend`` resolves to ``cupy``. The matching rules themselves (disparities,
block size, uniqueness, texture) live in ``[stereo]`` and are shared with the CPU reference, which the
GPU path reproduces bit for bit.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from companion.config._base import StrictModel


class GpuConfig(StrictModel):
    """GPU backend options."""

    device_id: int = Field(default=0, ge=0, le=64, description="CUDA device ordinal.")
    zero_copy: bool = Field(
        default=False,
        description=(
            "Map the pinned host frame buffer into the GPU's address space and let the first kernel "
            "read the frame from it directly, with no host-to-device copy. Right on Jetsons (TX1, "
            "TX2, Xavier, Orin), where CPU and GPU share one DRAM; on a discrete GPU every read then "
            "crosses PCIe, so leave it off there."
        ),
    )
    use_cuda_graph: bool = Field(
        default=True,
        description=(
            "Replay the per-frame kernels and the result download as one captured CUDA graph (one "
            "launch instead of four or five); falls back to plain launches if capture fails."
        ),
    )
    disparity_preview_downsample: int = Field(
        default=4,
        ge=0,
        le=16,
        description=(
            "When a disparity image is asked for (overlays), return it downsampled by this factor, "
            "each cell the largest valid disparity of its block (the nearest surface), as a float32 "
            "image with NaN for none; 0 or 1 = the full-resolution disparity (a 2-byte-per-pixel "
            "download)."
        ),
    )
    camera_frame_buffers: int = Field(
        default=4,
        ge=0,
        le=16,
        description=(
            "Pinned host buffers a UVC camera decodes frames straight into, so that the GPU reads each "
            "frame with no host copy (about 0.25 ms less per 1280x720 frame on an H100 host; on a "
            "Jetson one memory copy of the frame less). A buffer is reused only once nothing holds its "
            "frame (up to four are in flight: being captured, waiting, being processed, being "
            "reported); when all are in use the camera decodes into memory of its own, as with 0 (off)."
        ),
    )
    register_frames: bool = Field(
        default=False,
        description=(
            "Page-lock the caller's frame (cudaHostRegister) for the time of its DMA instead of copying "
            "it into the pinned staging buffer; pays off where locking pages is cheaper than copying "
            "them (see docs/gpu_notes.md). Falls back to the staging copy when the frame is not "
            "C-contiguous or cannot be locked."
        ),
    )
    host_copy_engine: Literal["numpy", "opencv"] = Field(
        default="opencv",
        description=(
            "What copies a colour frame into the pinned staging buffer. opencv: cv2.cvtColor's "
            "BGR->RGB shuffle on OpenCV's own thread pool (all cores, no Python threads; the grey "
            "kernel then reads RGB order, with identical results); on an H100 host it moved a "
            "1280x720 frame 2-3x faster than one core. numpy: a plain copy (one core, or "
            "host_copy_threads)."
        ),
    )
    pipeline_bands: int = Field(
        default=2,
        ge=1,
        le=8,
        description=(
            "Upload and process a frame in this many row bands: while the host copies band k+1 into "
            "the pinned staging buffer, the GPU receives band k and matches every disparity row whose "
            "window it completes. 1 = copy, then upload, then compute."
        ),
    )
    host_copy_threads: int = Field(
        default=0,
        ge=0,
        le=32,
        description=(
            "Threads, the calling one included, that copy the frame's row bands into the pinned "
            "staging buffer and queue their DMA in parallel (NumPy and CuPy release the GIL); 0 or 1 = "
            "the calling thread alone. Worth it where one core copies slower than PCIe moves data."
        ),
    )
    rows_per_block: int = Field(
        default=0,
        ge=0,
        le=4096,
        description=(
            "Output rows one thread block of the disparity kernel walks down, px; 0 = sized so that "
            "one wave of blocks fills every multiprocessor (a tuning knob, not a behaviour)."
        ),
    )
    sgm_lanes_per_line: Literal[0, 4, 8, 16, 32] = Field(
        default=0,
        description=(
            "SGM kernels: lanes of a warp that own one image line (each lane then holds num_disparities "
            "/ (4 x lanes) groups of 4 disparities); 0 = min(32, num_disparities / 4). A tuning knob, not "
            "a behaviour: every setting gives the same results."
        ),
    )
    sgm_prefetch_steps: Literal[0, 2, 4] = Field(
        default=0,
        description=(
            "SGM path kernel: steps between a pixel's census loads and its path costs (more hides more "
            "memory latency, at the price of registers); 0 = the plan's choice: 4 where the kernel has "
            "fewer than 16 warps per SM of the GPU, else 2. A tuning knob, not a behaviour: every "
            "setting gives the same results."
        ),
    )
    stage_timing: bool = Field(
        default=False,
        description=(
            "Record CUDA events between stages and report per-stage GPU times (upload, grey/remap, "
            "disparity with regions, download) in the timings; costs a few event queries per frame "
            "and disables the CUDA graph."
        ),
    )
