"""The per-frame pipeline: side-by-side frame → 9 region depths → LUT → filter → fuzzy decision.

Two layers:

* a :class:`~companion.core.estimator.RegionEstimator` turns one ZED side-by-side frame into 9 raw
  region depths (split, grey, rectify, disparity, depth, robust minimum). This is the expensive part;
  its implementations (the CPU one in :mod:`companion.core.estimator`, the CuPy one in
  :mod:`companion.gpu`) share one contract and are built by a factory the caller passes in
  (:func:`companion.backends.make_pipeline` passes the backend registry's), so the core imports no
  backend.
* :class:`Pipeline` owns an estimator and the cheap, host-side stages that both share: the depth
  look-up table, the release filter and the avoidance controller. The estimator also reduces the
  disparity to blocks (``planner.block_px``), the local planner's map input (``near_blocks``).
  Where the estimator reports its device lost (a GPU fault that leaves CUDA unusable in the
  process), the pipeline builds the ``fallback`` estimator (the CPU engine) and matches with it
  from the next frame on, instead of losing every frame to the dead device.

Nothing here reads a clock for logic: the frame timestamp is passed in (it drives the filter). Stage
timings are instrumentation and use an injectable ``clock`` (default :func:`time.perf_counter`).
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from companion.config import CompanionConfig
from companion.core.estimator import Clock, EstimatorFactory, RegionEstimator
from companion.core.fuzzy.avoidance import AvoidanceController
from companion.core.geometry import StereoGeometry
from companion.core.lut import DepthLUT, median_filter, release_filter
from companion.core.obstacle import ObstacleDistance
from companion.core.types import Decision, RegionDepths
from companion.errors import BackendError

log = logging.getLogger(__name__)

#: Config sections whose change requires a new estimator (new maps, matcher or kernels). A change
#: elsewhere (LUT, controller, command) applies on the next frame with no rebuild.
ESTIMATOR_SECTIONS = ("calibration", "stereo", "regions", "gpu", "obstacle_distance")


@dataclass(frozen=True)
class FrameResult:
    """Everything the pipeline concluded from one frame.

    Attributes:
        timestamp_s: the frame's capture time (the caller's clock), seconds.
        raw: region depths from the estimator, metres (NaN unknown).
        refined: after the LUT and the release filter, metres (NaN unknown).
        decision: the controller's decision.
        timings_ms: stage -> milliseconds, plus ``total_ms``.
        disparity: float32 disparity image when asked for (for overlays), else None.
        measured: this frame's own region depths after the LUT, before the median and release
            filters, metres (NaN unknown): what the camera measured now.
        filtered: bool ``(9,)``: True where ``refined`` came out of the release filter (smoothing a
            receding obstacle, or a region coming back from unknown): a blend, no frame's measurement. A
            UI shows these as filtered. (The median over ``lut.median_frames`` picks one of the last
            frames' measurements, so it is not marked.)
        stand_in: bool ``(9,)``: True where ``refined`` is 0 m standing in for an unknown in the median
            window (unknown counts as near): not a depth at all, to be shown as unknown.
        near_blocks: float32 ``(ceil(H/b), ceil(W/b))`` the largest valid disparity of each
            ``planner.block_px`` block (px, NaN none; :mod:`companion.core.blocks`), a copy: the local
            planner's map input; None when the estimator computes none.
        geometry: the rectified rig the frame was seen with (the rays of ``near_blocks``).
        obstacle: the frame's OBSTACLE_DISTANCE bins (:class:`~companion.core.obstacle.ObstacleDistance`),
            or None when ``obstacle_distance.send`` is off or the estimator computes none.
    """

    timestamp_s: float
    raw: RegionDepths
    refined: RegionDepths
    decision: Decision
    timings_ms: dict[str, float] = field(default_factory=dict)
    disparity: np.ndarray | None = None
    measured: RegionDepths | None = None
    filtered: np.ndarray | None = None
    stand_in: np.ndarray | None = None
    obstacle: ObstacleDistance | None = None
    near_blocks: np.ndarray | None = None
    geometry: StereoGeometry | None = None

    def shown_depths_m(self) -> np.ndarray:
        """float64 ``(9,)``: ``refined`` with the median's stand-ins for unknown made NaN (unknown): the
        depths to show a person, metres."""
        out = np.array(self.refined.depth_m, dtype=np.float64)
        if self.stand_in is not None:
            out[self.stand_in] = np.nan
        return out


class Pipeline:
    """Frame → decision, for one camera resolution.

    Args:
        cfg: the whole configuration.
        width_px, height_px: size of one eye.
        make_estimator: builds the estimator for a config (now, unless ``estimator`` is given, and
            again when a change needs a new one); :func:`companion.backends.make_estimator`.
        estimator: an estimator to use instead of building one from ``cfg`` (tests, GPU sharing).
        fallback: builds the estimator to match with once the device is lost (a
            :class:`~companion.errors.BackendError` whose context says ``device_lost``), then and
            on every later rebuild; None: such an error is only raised.
        clock: timing clock for the per-stage figures.

    Attributes:
        device_lost: the error that lost the device, one line; None while it works.
    """

    def __init__(
        self,
        cfg: CompanionConfig,
        width_px: int,
        height_px: int,
        *,
        make_estimator: EstimatorFactory,
        estimator: RegionEstimator | None = None,
        fallback: EstimatorFactory | None = None,
        clock: Clock = time.perf_counter,
    ):
        self.width_px = width_px
        self.height_px = height_px
        self._clock = clock
        self._make_estimator = make_estimator
        self._fallback = fallback
        self.device_lost: str | None = None
        estimator = estimator or make_estimator(cfg, width_px, height_px, clock)
        self._filtered: np.ndarray | None = None
        self._history: deque[np.ndarray] = deque(maxlen=cfg.lut.median_frames - 1)
        self._last_timestamp_s: float | None = None
        self._install(cfg, estimator)

    @property
    def geometry(self) -> StereoGeometry:
        return self.estimator.geometry

    def _install(self, cfg: CompanionConfig, estimator: RegionEstimator) -> None:
        """Build the LUT and the controller for ``cfg``, then swap in everything at once (if a build
        raises, nothing has changed)."""
        lut = DepthLUT(cfg.lut.points_m)
        controller = AvoidanceController(cfg.controller)
        self.estimator, self._lut, self._controller = estimator, lut, controller
        self._release_tau_s = cfg.lut.release_time_constant_s
        self.config = cfg

    def reconfigure(self, cfg: CompanionConfig) -> list[str]:
        """Swap in a new, already validated config; returns the sections that changed.

        The LUT, filter and controller change on the next frame. A change to calibration, stereo,
        regions or gpu rebuilds the estimator (maps, matcher, kernels) before returning, so the
        next frame uses it. Everything is built before anything is swapped: if building raises,
        the old config stays in force.
        """
        changed = [
            name
            for name in type(cfg).model_fields
            if getattr(cfg, name) != getattr(self.config, name)
        ]
        estimator = self.estimator
        if any(s in changed for s in ESTIMATOR_SECTIONS):
            make = self._make_estimator if self.device_lost is None or self._fallback is None else self._fallback
            estimator = make(cfg, self.width_px, self.height_px, self._clock)
        self._install(cfg, estimator)
        if cfg.lut.median_frames - 1 != self._history.maxlen:
            self._history = deque(self._history, maxlen=cfg.lut.median_frames - 1)
        return changed

    def _fall_back(self, err: BackendError) -> None:
        """Swap in the fallback estimator after ``err`` lost the device (the frame itself is lost).

        Raises:
            BackendError: the fallback could not be built either (both causes in one line).
        """
        self.device_lost = str(err)
        old = self.estimator
        try:
            self.estimator = self._fallback(self.config, self.width_px, self.height_px, self._clock)
        except BackendError as build_err:
            raise BackendError(f"{err}; the fallback matcher could not be built: {build_err}", device_lost=True) from None
        log.error("%s: matching with %s from now on", err, self.estimator.name)
        closer = getattr(old, "close", None)
        if closer is not None:
            try:
                closer()
            except Exception as close_err:  # noqa: BLE001 - the lost device's threads; the fallback runs on
                log.error("releasing the lost backend failed: %s", close_err)

    def reset(self) -> None:
        """Forget the filter's memory (e.g. after a camera reconnect)."""
        self._filtered = None
        self._history.clear()
        self._last_timestamp_s = None

    def process(self, frame: np.ndarray, timestamp_s: float, want_disparity: bool = False) -> FrameResult:
        """Run the whole pipeline on one side-by-side frame captured at ``timestamp_s`` (seconds).

        Raises:
            FrameError: the frame has the wrong shape, dtype or size.
            BackendError: the estimator failed on this frame; where it lost its device and a
                ``fallback`` is given, the next frame is matched by the fallback estimator.
        """
        clock = self._clock
        t0 = clock()
        planner = self.config.planner
        erode = planner.block_erode_px
        try:
            est = self.estimator.estimate(
                frame,
                want_disparity=want_disparity,
                near_block_px=planner.block_px,
                near_erode_px=erode if isinstance(erode, int) else 0,  # a model built without validation: off
            )
        except BackendError as err:
            if err.context.get("device_lost") and self._fallback is not None and self.device_lost is None:
                self._fall_back(err)
            raise
        t1 = clock()
        looked_up = self._lut.apply(est.regions.depth_m)
        median = median_filter(self._history, looked_up, self.config.lut.median_frames)
        self._history.append(looked_up)
        # The LUT's output is > 0, so an exact 0 after the median is its stand-in for a recent unknown.
        stand_in = median == 0.0
        dt_s = 0.0 if self._last_timestamp_s is None else max(0.0, timestamp_s - self._last_timestamp_s)
        refined = release_filter(self._filtered, median, dt_s, self._release_tau_s)
        # Where the release filter changed the value it is a blend, no frame's measurement (the median
        # is one of the last frames' measurements). Unknown passes both filters at once (NaN in, NaN out).
        filtered = (refined != median) & ~np.isnan(median)
        stand_in &= refined == 0.0
        self._filtered = refined
        self._last_timestamp_s = timestamp_s
        t2 = clock()
        decision = self._controller.decide(refined)
        # The estimator reuses its block buffer for the next frame: the local planner gets its own.
        blocks = None if est.near_blocks is None else est.near_blocks.copy()
        t3 = clock()
        timings = dict(est.timings_ms)
        timings["lut_ms"] = (t2 - t1) * 1e3
        timings["fuzzy_ms"] = (t3 - t2) * 1e3
        timings["total_ms"] = (t3 - t0) * 1e3
        return FrameResult(
            timestamp_s=timestamp_s,
            raw=est.regions,
            refined=RegionDepths(depth_m=refined, valid_fraction=est.regions.valid_fraction),
            decision=decision,
            timings_ms=timings,
            disparity=est.disparity,
            measured=RegionDepths(depth_m=np.asarray(looked_up, dtype=np.float64), valid_fraction=est.regions.valid_fraction),
            filtered=filtered,
            stand_in=stand_in,
            obstacle=getattr(est, "obstacle", None),
            near_blocks=blocks,
            geometry=self.estimator.geometry,
        )
