"""The simulator's ZED: a :class:`~companion.interfaces.CameraSource` that renders the vehicle's view.

Each :meth:`SimCamera.read` renders one rectified side-by-side frame, uint8 ``(H, 2W, 3)`` BGR, from
the pose of the vehicle *now* (simulated time; the loop calls it at the camera rate), stamped with
the simulated time. Stereo is made non-ideal the way a real camera is: Gaussian sensor noise per eye
and frame, an auto-exposure gain that jumps every few seconds (both eyes), and a fixed small gain
mismatch between the eyes. All randomness comes from the flight seed (and ``sim.realization``), so
a flight is reproducible.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from companion.core.geometry import StereoGeometry
from companion.sim import realization_key
from companion.sim.render import Photometry, Pose, Scene, StereoRenderer, TextureBank
from companion.errors import CameraError
from companion.interfaces import Frame

#: Texture period used by the simulator's renderers (the renderer's default).
TEXTURE_SIZE = 1024


def make_texture_bank(seed: int = 0) -> TextureBank:
    """A texture bank to share between the renderers of many flights in one process (textures are
    generated lazily and cached; generating them is most of a renderer's start-up cost)."""
    return TextureBank(seed, TEXTURE_SIZE, pad=TEXTURE_SIZE // 2)


class SimCamera:
    """Renders what the vehicle sees.

    Args:
        geometry: the ideal rectified rig (eye size, focal, principal point, baseline).
        scene: the world.
        pose_at: returns ``(pose, time_s)`` of the vehicle now (e.g. a bound method of the vehicle).
        seed: flight seed (per-face texture offsets, noise and exposure draws).
        realization: ``sim.realization``: which draw of the noise, the exposure steps and the eyes'
            mismatch (:func:`~companion.sim.realization_key`); the textures stay the seed's.
        textures: a shared :class:`TextureBank` from :func:`make_texture_bank` (default: a new one
            like it; the images do not depend on whether the bank is shared).
        noise_std_grey: per-eye Gaussian noise, grey levels.
        exposure_step_interval_s: the gain jumps this often, seconds (0 = constant gain 1).
        exposure_gain_range: (low, high) of the uniform gain draw.
        eye_gain_mismatch: largest relative gain difference between the eyes.
        fail_after_s: from this simulated time on, :meth:`read` raises CameraError (a camera that
            stops delivering), or None.
    """

    name = "sim"

    def __init__(
        self,
        geometry: StereoGeometry,
        scene: Scene,
        pose_at: Callable[[], tuple[Pose, float]],
        *,
        seed: int = 0,
        realization: int = 0,
        textures: TextureBank | None = None,
        noise_std_grey: float = 0.0,
        exposure_step_interval_s: float = 0.0,
        exposure_gain_range: tuple[float, float] = (1.0, 1.0),
        eye_gain_mismatch: float = 0.0,
        fail_after_s: float | None = None,
    ) -> None:
        self.geometry = geometry
        self.scene = scene
        self._pose_at = pose_at
        self._seed = int(seed)
        # The random draws' key: the seed alone for realization 0 (the draws every earlier flight had)
        self._draws = realization_key(self._seed, realization)
        self._textures = textures
        self._noise = float(noise_std_grey)
        self._exp_interval = float(exposure_step_interval_s)
        self._gain_lo, self._gain_hi = (float(g) for g in exposure_gain_range)
        self._fail_after_s = fail_after_s
        rng = np.random.default_rng([*self._draws, 0xCA3E])
        m = float(eye_gain_mismatch) * float(rng.uniform(-1.0, 1.0))
        self._eye_gain = (1.0 + 0.5 * m, 1.0 - 0.5 * m)
        self._noise_rng = np.random.default_rng([*self._draws, 0x401E])
        self._renderer: StereoRenderer | None = None
        self._buffer: np.ndarray | None = None
        self._seq = 0

    @property
    def eye_size_px(self) -> tuple[int, int]:
        return (self.geometry.width_px, self.geometry.height_px)

    def open(self) -> None:
        """Build the renderer (textures are drawn from the shared bank as frames need them)."""
        if self._renderer is None:
            textures = self._textures if self._textures is not None else make_texture_bank()
            self._renderer = StereoRenderer(self.geometry, self.scene, seed=self._seed, textures=textures)

    def exposure_gain(self, time_s: float) -> float:
        """The auto-exposure gain at ``time_s``: piecewise constant, a pure function of the seed."""
        if self._exp_interval <= 0.0:
            return 1.0
        k = max(0, int(math.floor(time_s / self._exp_interval)))
        return float(np.random.default_rng([*self._draws, 0xE7, k]).uniform(self._gain_lo, self._gain_hi))

    def read(self) -> Frame:
        """Render the frame the camera captures now (simulated time).

        Raises:
            CameraError: not opened, or past ``fail_after_s``.
        """
        if self._renderer is None:
            raise CameraError("sim camera: read() before open()")
        pose, now_s = self._pose_at()
        if self._fail_after_s is not None and now_s >= self._fail_after_s:
            raise CameraError(f"sim camera: stopped delivering at t = {self._fail_after_s:.2f} s (simulated failure)")
        gain = self.exposure_gain(now_s)
        left = Photometry(gain=gain * self._eye_gain[0], noise_std=self._noise)
        right = Photometry(gain=gain * self._eye_gain[1], noise_std=self._noise)
        # A fresh array per frame: a consumer may keep frames (overlays, queues).
        image = self._renderer.render_side_by_side(
            pose, left=left, right=right, rng=self._noise_rng if self._noise > 0.0 else None
        )
        frame = Frame(image=image, timestamp_s=now_s, seq=self._seq)
        self._seq += 1
        return frame

    def close(self) -> None:
        self._renderer = None
