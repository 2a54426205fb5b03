"""Procedural surface textures for the synthetic stereo renderer.

Every texture is a square, *periodic* (tileable) uint8 grey image: multi-scale value noise (white
noise at every octave, summed through a periodic Gaussian pyramid) plus thresholded blobs that give
sharp edges. Periodic so that a face larger than the texture can sample it with ``BORDER_WRAP``
without seams.

Level of detail: level ``k`` is drawn at ``texels_per_m / 2**k`` texels per metre and is used at
the camera depths where one of its texels spans 1 to 2 pixels (the renderer never minifies). Levels
are *independent* noise images (not a mip chain of one image), so that (a) every viewing distance
sees the same texture richness and (b) the world-space period grows with distance: a level repeats
every ``size`` texels, i.e. every 1000-2000 pixels in the image at the depths it is used at, far more
than any disparity search range (no periodic false matches).
"""

from __future__ import annotations

import enum

import cv2
import numpy as np


class Material(enum.IntEnum):
    """Surface families: they differ in brightness, contrast and noise stream."""

    OBSTACLE = 0  #: boxes, pillars, the ceiling: full contrast
    GROUND = 1  #: the ground plane: a little darker
    SKY = 2  #: the backdrop (walls and top of the world box): brighter, moderate contrast


#: (mean grey level, standard deviation in grey levels) of each material, in Material order.
_MATERIAL_TONE: tuple[tuple[float, float], ...] = (
    (122.0, 48.0),  # OBSTACLE
    (108.0, 44.0),  # GROUND
    (168.0, 30.0),  # SKY
)

#: Gaussian blur of the finished noise, texels: takes the texel-to-texel white noise off the pixel
#: Nyquist frequency (like a lens would), so that matching at half-pixel disparities does not alias.
_BLUR_TEXELS = 0.5
#: Coarsest lattice of the noise pyramid, texels.
_COARSE_PX = 8


def _periodic_pyr_up(a: np.ndarray) -> np.ndarray:
    """Double a periodic float32 ``(n, n)`` image to ``(2n, 2n)`` keeping it periodic (wrap padding)."""
    padded = cv2.copyMakeBorder(a, 2, 2, 2, 2, cv2.BORDER_WRAP)
    return cv2.pyrUp(padded)[4:-4, 4:-4]


def noise_field(rng: np.random.Generator, size: int) -> np.ndarray:
    """A periodic multi-scale noise field, float32 ``(size, size)``, zero mean, unit std.

    White noise is added at every octave from ``8`` texels up to ``size``; a copy of the field at
    ``size / 16`` resolution is upsampled and thresholded into blobs with hard edges (the kind of
    edge a block matcher locks onto), and added on top; a 0.5-texel Gaussian takes the energy off
    the texel Nyquist frequency.

    Args:
        rng: Source of randomness (the only one used).
        size: Side in texels, a power of two >= 64.
    """
    if size < 64 or size & (size - 1):
        raise ValueError(f"texture size must be a power of two >= 64, got {size}")
    n = _COARSE_PX
    acc = rng.standard_normal((n, n), dtype=np.float32)
    blob_src: np.ndarray | None = None
    while n < size:
        acc = _periodic_pyr_up(acc)
        n *= 2
        # Fine octaves slightly stronger: keeps per-pixel contrast where the texture is magnified.
        acc += rng.standard_normal((n, n), dtype=np.float32) * (0.55 if n < size else 0.8)
        if n == size // 16:
            blob_src = acc.copy()
    assert blob_src is not None
    blob = blob_src
    while blob.shape[0] < size:
        blob = _periodic_pyr_up(blob)
    acc += np.where(blob > 0.0, np.float32(1.0), np.float32(-1.0))
    wrapped = cv2.copyMakeBorder(acc, 4, 4, 4, 4, cv2.BORDER_WRAP)  # keeps the blur periodic
    acc = cv2.GaussianBlur(wrapped, (0, 0), _BLUR_TEXELS)[4:-4, 4:-4]
    acc -= acc.mean()
    acc /= acc.std()
    return acc


class TextureBank:
    """Lazily generated, cached textures: one periodic image per (material, level).

    Each image is stored *padded*: uint8 ``(size + pad, size + pad)`` with
    ``stored[i, j] = texture[i % size, j % size]``, so that a lookup whose texel range spans at most
    ``pad`` texels can be shifted by whole periods to lie inside the array (OpenCV's warp takes its
    fast path inside the image; wrapped lookups near the border are several times slower).

    Deterministic: the image for (material, level) depends only on ``(seed, material, level, size)``,
    not on the order in which images are first asked for. Owned by one renderer (no module state).

    Args:
        seed: Texture seed.
        size: Period of every texture image, texels (power of two >= 64).
        pad: Extra wrapped texels stored after each period, 0 <= pad <= size.
    """

    def __init__(self, seed: int, size: int = 1024, pad: int = 256) -> None:
        if size < 64 or size & (size - 1):
            raise ValueError(f"texture size must be a power of two >= 64, got {size}")
        if not 0 <= pad <= size:
            raise ValueError(f"texture pad must be in [0, {size}], got {pad}")
        self.seed = int(seed)
        self.size = int(size)
        self.pad = int(pad)
        self._cache: dict[tuple[int, int], np.ndarray] = {}

    def get(self, material: int, level: int) -> np.ndarray:
        """The padded texture of ``material`` at LOD ``level``: uint8 ``(size + pad, size + pad)``.

        ``get(...)[:size, :size]`` is one period (use it with ``BORDER_WRAP``).
        """
        key = (int(material), int(level))
        tex = self._cache.get(key)
        if tex is None:
            rng = np.random.default_rng([self.seed, key[0], key[1], 0x7E47])
            mean, std = _MATERIAL_TONE[Material(key[0])]
            field = noise_field(rng, self.size)
            period = np.clip(field * std + mean, 0.0, 255.0).round().astype(np.uint8)
            tex = cv2.copyMakeBorder(period, 0, self.pad, 0, self.pad, cv2.BORDER_WRAP)
            tex.setflags(write=False)
            self._cache[key] = tex
        return tex
