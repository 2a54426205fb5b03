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

Two materials are *hard* on purpose (the surfaces real stereo fails on): ``PLAIN`` (a painted wall:
smooth shading of a few grey levels and a faint grain, :func:`plain_field`) and ``BARS`` (vertical
bars of a regular period, :func:`bars_texture`; a see-through variant whose gaps are holes, grey 0).
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
    PLAIN = 3  #: a plain painted wall or cabinet: bright, smooth, nearly textureless
    BARS = 4  #: vertical bars of a regular period (needs a :class:`BarPattern`)


#: (mean grey level, standard deviation in grey levels) of each noise material, in Material order.
_MATERIAL_TONE: tuple[tuple[float, float], ...] = (
    (122.0, 48.0),  # OBSTACLE
    (108.0, 44.0),  # GROUND
    (168.0, 30.0),  # SKY
)

#: PLAIN: mean grey and std of the smooth shading (grey levels); the grain's std is the surface's
#: (its pattern key, in tenths of a grey level). The shading varies over ``size / 16`` texels and
#: more (tens of centimetres to metres): almost no gradient within a matching window; the grain, at
#: the texel scale, is about the camera's default sensor noise (2 grey levels, independent per eye),
#: so matching a plain wall is largely matching noise, as on a real one (tools/hard_surface_study.py
#: measures it).
PLAIN_TONE = (182.0, 5.0)
#: BARS: the bars' mean grey and the std of their shading and grain; an opaque pattern's gaps are
#: this fraction of the bars' grey (a shadowed recess).
BARS_TONE = (150.0, 6.0, 1.5)
BARS_GAP_FRACTION = 0.35
#: See-through bars: a texel is ``coverage × grey`` (0 in a gap; bilinear interpolation keeps that at a
#: bar's edge); a pixel sampled below this is mostly what lies behind and keeps that depth (a bar
#: covering at least about half of it gives the pixel the bar's depth).
BARS_ALPHA_THRESHOLD = 60

#: Gaussian blur of the finished noise, texels: takes the texel-to-texel white noise off the pixel
#: Nyquist frequency (like a lens would), so that matching at half-pixel disparities does not alias.
_BLUR_TEXELS = 0.5
#: Coarsest lattice of the noise pyramid, texels.
_COARSE_PX = 8


def _check_size(size: int) -> None:
    """Raise ValueError unless ``size`` (texels) is a power of two >= 64."""
    if size < 64 or size & (size - 1):
        raise ValueError(f"texture size must be a power of two >= 64, got {size}")


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
    _check_size(size)
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


def plain_field(rng: np.random.Generator, size: int) -> tuple[np.ndarray, np.ndarray]:
    """The two parts of a plain surface, float32 ``(size, size)`` each, zero mean, unit std, periodic:
    smooth shading (the noise pyramid's coarse octaves only, from 8 texels up to ``size / 16``) and
    grain (white noise blurred by 0.7 texel).

    Args:
        rng: Source of randomness (the only one used).
        size: Side in texels, a power of two >= 64.
    """
    _check_size(size)
    n = _COARSE_PX
    acc = rng.standard_normal((n, n), dtype=np.float32)
    while n < size:
        acc = _periodic_pyr_up(acc)
        n *= 2
        if n <= size // 16:
            acc += rng.standard_normal((n, n), dtype=np.float32) * 0.5
    acc -= acc.mean()
    acc /= acc.std()
    grain = rng.standard_normal((size, size), dtype=np.float32)
    wrapped = cv2.copyMakeBorder(grain, 4, 4, 4, 4, cv2.BORDER_WRAP)
    grain = cv2.GaussianBlur(wrapped, (0, 0), 0.7)[4:-4, 4:-4]
    grain -= grain.mean()
    grain /= grain.std()
    return acc, grain


class BarPattern(tuple):
    """The key of a bar texture: ``(periods, duty_permille, see_through)``.

    ``periods`` bars fill one level-0 texture tile (``size`` texels), so every level's image stays
    periodic; ``duty_permille`` is the bar width over the period, in thousandths.
    """

    __slots__ = ()

    def __new__(cls, periods: int, duty_permille: int, see_through: bool) -> BarPattern:
        if not (1 <= int(periods) and 0 < int(duty_permille) < 1000):
            raise ValueError(f"bar pattern needs periods >= 1 and 0 < duty_permille < 1000, got {periods}, {duty_permille}")
        return super().__new__(cls, (int(periods), int(duty_permille), bool(see_through)))

    @classmethod
    def from_metres(
        cls, period_m: float, width_m: float, see_through: bool, size: int, texels_per_m: float
    ) -> BarPattern:
        """The pattern nearest bars of ``period_m`` and ``width_m`` on a texture of ``size`` texels
        drawn at ``texels_per_m`` (the period snaps to ``size / texels_per_m / periods``)."""
        periods = max(1, round(size / (texels_per_m * period_m)))
        duty = min(999, max(1, round(1000.0 * width_m / period_m)))
        return cls(periods, duty, see_through)


def bars_texture(rng: np.random.Generator, size: int, level: int, pattern: BarPattern) -> np.ndarray:
    """A bar texture at LOD ``level``: uint8 ``(size, size)``, periodic, bars along the columns (s).

    Each texel column's bar coverage is exact (the area of the periodic box function over the
    texel), so bars thinner than a texel fade instead of aliasing. See-through: ``coverage × bar``
    (0 = hole); opaque: the gap grey blended with the bar grey by coverage.
    """
    periods, duty_permille, see_through = pattern
    period = size / (periods * 2.0**level)  # texels
    width = period * duty_permille / 1000.0

    def covered(x: np.ndarray) -> np.ndarray:  # bar length in [0, x), bars at [m p, m p + w)
        return np.floor(x / period) * width + np.minimum(np.mod(x, period), width)

    edges = np.arange(size + 1, dtype=np.float64)
    coverage = np.diff(covered(edges)).astype(np.float32)  # (size,) in [0, 1]
    mean, shade_std, grain_std = BARS_TONE
    shade, grain = plain_field(rng, size)
    bar = mean + shade_std * shade + grain_std * grain
    if see_through:
        img = bar * coverage[None, :]
    else:
        img = bar * (BARS_GAP_FRACTION + (1.0 - BARS_GAP_FRACTION) * coverage[None, :])
    return np.clip(img, 0.0, 255.0).round().astype(np.uint8)


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
        _check_size(size)
        if not 0 <= pad <= size:
            raise ValueError(f"texture pad must be in [0, {size}], got {pad}")
        self.seed = int(seed)
        self.size = int(size)
        self.pad = int(pad)
        self._cache: dict[tuple[int, int], np.ndarray] = {}

    def get(self, material: int, level: int, pattern: tuple[int, ...] | None = None) -> np.ndarray:
        """The padded texture of ``material`` at LOD ``level``: uint8 ``(size + pad, size + pad)``.

        ``get(...)[:size, :size]`` is one period (use it with ``BORDER_WRAP``). ``BARS`` needs its
        :class:`BarPattern`, ``PLAIN`` its grain as ``(tenths of a grey level,)``; the others none.
        """
        material = Material(int(material))
        if (material in (Material.BARS, Material.PLAIN)) != (pattern is not None):
            raise ValueError(f"material {material.name} {'needs' if pattern is None else 'takes no'} pattern")
        key = (int(material), int(level)) if pattern is None else (int(material), int(level), *pattern)
        tex = self._cache.get(key)
        if tex is None:
            seed = [self.seed, key[0], key[1], 0x7E47]
            if pattern is not None:
                seed += [int(v) for v in pattern]
            rng = np.random.default_rng(seed)
            if material is Material.BARS:
                assert pattern is not None
                period = bars_texture(rng, self.size, int(level), pattern)
            elif material is Material.PLAIN:
                assert pattern is not None
                mean, shade_std = PLAIN_TONE
                grain_std = int(pattern[0]) / 10.0
                shade, grain = plain_field(rng, self.size)
                period = np.clip(mean + shade_std * shade + grain_std * grain, 0.0, 255.0).round().astype(np.uint8)
            else:
                mean, std = _MATERIAL_TONE[material]
                field = noise_field(rng, self.size)
                period = np.clip(field * std + mean, 0.0, 255.0).round().astype(np.uint8)
            tex = cv2.copyMakeBorder(period, 0, self.pad, 0, self.pad, cv2.BORDER_WRAP)
            tex.setflags(write=False)
            self._cache[key] = tex
        return tex
