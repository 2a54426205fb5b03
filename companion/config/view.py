"""Config section of the live view and the flight recording: ``[view]`` in the TOML file.

The service publishes a small JPEG preview (the Fig. 10 overlay with the disparity inset) on
``preview_endpoint`` for ``companion view``, only while something subscribes, at most
``preview_rate_hz``; ``preview_width_px`` and ``preview_jpeg_quality`` set its size. With
``record_dir`` set, the service records its health messages (and every ``record_preview_every``-th
preview frame) there, bounded by ``record_max_mb``; ``companion review`` turns a recording into a report.

The endpoint and the recording folder take effect at the next start (:data:`VIEW_RESTART_FIELDS`);
the rate, size and quality apply live.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import Field, field_validator, model_validator

from companion.config._base import StrictModel

#: Fields of ``[view]`` that only a restart applies.
VIEW_RESTART_FIELDS: tuple[str, ...] = (
    "preview_endpoint",
    "preview_enabled",
    "record_dir",
    "record_max_mb",
    "record_preview_every",
)

_ZMQ_SCHEMES = ("tcp://", "ipc://", "inproc://")


def _is_loopback_tcp(endpoint: str) -> bool:
    host = endpoint.removeprefix("tcp://").rsplit(":", 1)[0].strip("[]")
    return host in ("127.0.0.1", "localhost", "::1") or host.startswith("127.")


class ViewConfig(StrictModel):
    """The live preview for `companion view` (published only while someone watches) and the flight recording."""

    preview_enabled: bool = Field(
        default=True,
        description=(
            "Bind the preview socket. Nothing is drawn or encoded until a viewer subscribes, so leaving "
            "it on costs the flight loop nothing (restart to change)."
        ),
    )
    preview_endpoint: str = Field(
        default="auto",
        min_length=1,
        max_length=200,
        description=(
            "ZeroMQ XPUB endpoint of the preview (JPEG frames for `companion view`). auto: "
            "ipc://<runtime dir>/preview.sock, mode 0660, beside the control socket (the camera's view is "
            "the service's group's, like the controls). Localhost or ipc:// only: `companion view` is what "
            "a phone connects to (restart to change)."
        ),
    )
    preview_rate_hz: float = Field(
        default=5.0, gt=0.0, le=30.0, description="Most preview frames per second (fewer when the camera is slower), Hz."
    )
    preview_width_px: int = Field(
        default=640, ge=160, le=1920, description="Width of the preview image, pixels (the height follows the camera's aspect)."
    )
    preview_jpeg_quality: int = Field(default=70, ge=10, le=95, description="JPEG quality of the preview, 10-95.")
    record_dir: Path | None = Field(
        default=None,
        description=(
            "Record each run of the service into a new folder under this absolute path: health.jsonl "
            "(every health message), preview/ (JPEG frames) and the config; `companion review` reads it. "
            "Unset: no recording (restart to change)."
        ),
    )
    record_max_mb: float = Field(
        default=200.0,
        gt=0.0,
        le=100_000.0,
        description=(
            "Largest size of one run's recording, megabytes: preview frames stop at 80 % of it, health "
            "lines at 100 % (restart to change)."
        ),
    )
    record_preview_every: int = Field(
        default=5,
        ge=0,
        le=1000,
        description=(
            "Keep every N-th preview frame in the recording (at 5 Hz, 5 = one a second); 0 = record "
            "health only, and the preview is then encoded only while a viewer watches (restart to change)."
        ),
    )

    @field_validator("preview_endpoint")
    @classmethod
    def _endpoint(cls, v: str) -> str:
        if v != "auto" and not v.startswith(_ZMQ_SCHEMES):
            raise ValueError(f"endpoint {v!r} must be 'auto' or start with one of {', '.join(_ZMQ_SCHEMES)}")
        if v.startswith("tcp://") and not _is_loopback_tcp(v):
            raise ValueError(
                f"preview_endpoint {v!r} is reachable from the network: bind it to 127.0.0.1 or ipc:// "
                "and let `companion view --host ...` (with its token) serve the network"
            )
        return v

    @field_validator("record_dir")
    @classmethod
    def _absolute(cls, v: Path | None) -> Path | None:
        if v is not None and not v.is_absolute():
            raise ValueError(f"record_dir must be an absolute path (the service's working directory is not yours), got {str(v)!r}")
        return v

    @model_validator(mode="after")
    def _check(self) -> ViewConfig:
        if self.record_dir is not None and self.record_preview_every > 0 and not self.preview_enabled:
            raise ValueError("record_preview_every > 0 records preview frames, which needs preview_enabled = true (or set it to 0)")
        return self
