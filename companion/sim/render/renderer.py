"""Synthetic rectified stereo renderer: textured convex faces, exact per-eye geometry, true depth.

How a frame is drawn (both eyes share one clipping pass; each eye has its own z-buffer):

1. Cull in one vectorised pass: back faces (seen from neither eye) and faces wholly outside one
   clip plane of the *union* frustum of the two eyes (near plane ``z >= z_near`` plus a guard band
   a few pixels outside the image), in the left camera frame.
2. Clip the survivors against those planes (Sutherland-Hodgman; only faces that cross a plane),
   then split big faces at fixed camera-depth slabs that select the texture level of detail.
   Camera depth ``z`` is the same for both eyes (they differ by a shift along camera x), so both eyes
   make identical LOD choices for every surface point.
3. Per eye and piece (:mod:`~companion.sim.render.raster`), over the piece's pixel bounding box:
   inverse depth ``1/z`` is affine in the pixel coordinates for a plane (``1/z = (n . r) / delta``
   with ``r = ((u-cx)/f, (v-cy)/f, 1)``); mask the polygon (``cv2.fillConvexPoly``), z-test against
   the eye's inverse-depth buffer, and sample the texture through the exact pixel -> texel homography
   (``cv2.warpPerspective``, bilinear, wrap) only inside the visible part.

Hard surfaces (:class:`~companion.sim.render.scene.Surface`): see-through bar faces are drawn after
every other face, back to front, each laid over what lies behind it as a pixel integrates it (a bar
thinner than a pixel is a faint unbroken line, as in a camera, not a dashed one), and in the depth
buffer only where a bar covers most of a pixel (texels from ``BARS_ALPHA_THRESHOLD``); a glossy face
adds the scene light's specular highlight, a Gaussian blob centred, in each eye, on the projection
of the light's mirror image in the face's plane (so the highlight moves with the eye and has the
disparity of that virtual image, not the surface's).

Pixel centres are at integer coordinates (:class:`~companion.core.geometry.StereoGeometry`), both
for the depth buffer and for the texture lookup, so a point seen by both eyes is sampled at the
same texture coordinate: the images are exact projections of one continuous textured surface, and
the disparity of a surface at depth ``Z`` is ``f * B / Z`` up to the texture interpolation (1/32 texel).
Polygon masks cover pixels within about half a pixel of the polygon, so silhouettes are exact to
about +-0.5 px; interiors are exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from companion.core.geometry import StereoGeometry
from companion.sim.render.faces import FaceArrays, scene_faces
from companion.core.pose import CAMERA_TO_BODY, Pose, _finite3
from companion.sim.render.raster import StereoRaster, Vec3, clip_polygon
from companion.sim.render.scene import Scene
from companion.sim.render.texture import BarPattern, Material, TextureBank

#: Extra pixels around the image inside the clip frustum: keeps clipped edges off the image.
_GUARD_PX = 4.0
#: Highest texture level of detail (a level-k texel spans 2**k level-0 texels).
_MAX_LEVEL = 12


@dataclass(frozen=True)
class Photometry:
    """Photometric effects for one eye, applied to the grey image before conversion to BGR.

    Attributes:
        gain: multiplies grey levels (exposure change), result saturated to [0, 255]; >= 0.
        noise_std: standard deviation of additive Gaussian noise, grey levels; >= 0. Needs an ``rng``.
    """

    gain: float = 1.0
    noise_std: float = 0.0

    def __post_init__(self) -> None:
        if not (self.gain >= 0.0 and math.isfinite(self.gain)):
            raise ValueError(f"Photometry.gain must be finite and >= 0, got {self.gain}")
        if not (self.noise_std >= 0.0 and math.isfinite(self.noise_std)):
            raise ValueError(f"Photometry.noise_std must be finite and >= 0, got {self.noise_std}")

    @property
    def is_identity(self) -> bool:
        return self.gain == 1.0 and self.noise_std == 0.0


_IDENTITY = Photometry()


@dataclass(frozen=True)
class RenderResult:
    """One rendered stereo pair.

    Attributes:
        left_bgr, right_bgr: rectified eye images, uint8 ``(H, W, 3)`` BGR (grey replicated).
        depth_m: ground-truth depth of the left eye, float32 ``(H, W)``, metres along the optical
            axis (camera z) at each pixel centre; +inf where no surface was drawn.
    """

    left_bgr: np.ndarray
    right_bgr: np.ndarray
    depth_m: np.ndarray

    def side_by_side(self) -> np.ndarray:
        """The ZED frame: uint8 ``(H, 2W, 3)``, left eye first."""
        return np.concatenate([self.left_bgr, self.right_bgr], axis=1)


class StereoRenderer:
    """Renders a :class:`Scene` as a rectified stereo pair with the left eye's true depth.

    Camera model: the left eye sits at the body pose plus ``camera_offset_frd_m`` (body frame) and
    looks along body x (camera x = body y right, camera y = body z down, camera z = body x forward);
    the right eye is ``geometry.baseline_m`` along camera +x. Both eyes use ``geometry``'s focal
    length and principal point.

    Textures are generated once per renderer, lazily per level of detail, from ``seed``; each face
    gets its own random texture offset. Buffers are allocated once; a renderer is not thread-safe.

    Args:
        geometry: the rectified rig (image size, focal, principal point, baseline).
        scene: what to draw.
        seed: texture seed: same seed, same images.
        texels_per_m: level-0 texture density, texels per metre (detail is the same on every
            surface; level ``k`` has ``texels_per_m / 2**k``).
        camera_offset_frd_m: left-eye position in the body frame (forward, right, down), metres.
        z_near_m: near clip distance along the optical axis, metres (> 0).
        texture_size: period of each texture image, texels (power of two >= 64).
        textures: an existing :class:`TextureBank` to draw textures from (and add to), e.g. one
            shared by the renderers of many simulator courses; ``texture_size`` is then ignored.
            ``seed`` still sets the per-face texture offsets.
    """

    def __init__(
        self,
        geometry: StereoGeometry,
        scene: Scene,
        seed: int = 0,
        *,
        texels_per_m: float = 512.0,
        camera_offset_frd_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
        z_near_m: float = 0.01,
        texture_size: int = 1024,
        textures: TextureBank | None = None,
    ) -> None:
        if not (texels_per_m > 0.0 and math.isfinite(texels_per_m)):
            raise ValueError(f"texels_per_m must be > 0, got {texels_per_m}")
        if not (z_near_m > 0.0 and math.isfinite(z_near_m)):
            raise ValueError(f"z_near_m must be > 0, got {z_near_m}")
        self.geometry = geometry
        self.scene = scene
        self.seed = int(seed)
        self.texels_per_m = float(texels_per_m)
        self.camera_offset_frd_m = np.asarray(_finite3("camera_offset_frd_m", camera_offset_frd_m))
        self.z_near_m = float(z_near_m)
        self._faces: FaceArrays = scene_faces(scene)
        # Padding half a period: most warps then fit the stored array (see StereoRaster.draw).
        if textures is None:
            textures = TextureBank(self.seed, texture_size, pad=texture_size // 2)
        self._textures = textures
        rng = np.random.default_rng([self.seed, 0xFACE])
        # Random per-face texture offsets decorrelate faces that share a texture image.
        self._tex_offset = rng.uniform(0.0, self._textures.size, (self._faces.n_faces, 2))
        fc = self._faces
        bars = fc.material == int(Material.BARS)
        # Bars start at each face's s origin, so a panel's front and back bars line up.
        self._tex_offset[bars, 0] = 0.0
        size = self._textures.size
        # Per face: its texture's pattern key (bars: the bar pattern; plain: the grain), whether its
        # texture has holes (see-through bars).
        bar_keys = [
            BarPattern.from_metres(sf.bar_period_m, sf.bar_width_m, sf.see_through, size, self.texels_per_m)
            if sf.kind == "bars" else None
            for sf in fc.surfaces
        ]
        plain_keys = [(round(10.0 * sf.grain_grey),) for sf in fc.surfaces]
        self._face_pattern: list[tuple[int, ...] | None] = []
        face_alpha: list[bool] = []
        for i, mat in zip(fc.surface.tolist(), fc.material.tolist()):
            key = bar_keys[i] if mat == Material.BARS else (plain_keys[i] if mat == Material.PLAIN else None)
            self._face_pattern.append(key)
            face_alpha.append(mat == Material.BARS and bool(key[2]))
        self._face_alpha = np.array(face_alpha, dtype=bool)  # see-through faces
        light = scene.light_ned_m
        gloss = np.array([sf.gloss for sf in fc.surfaces])[fc.surface]
        self._glossy = (gloss > 0.0) if light is not None else np.zeros(fc.n_faces, bool)

        g = geometry
        w, h, f = g.width_px, g.height_px, g.focal_px
        gx = (max(g.cx_px, w - 1 - g.cx_px) + _GUARD_PX) / f
        gy = (max(g.cy_px, h - 1 - g.cy_px) + _GUARD_PX) / f
        b = g.baseline_m
        # Union of both eyes' frusta in the left camera frame: a x + b y + c z + e >= 0.
        self._planes: tuple[tuple[float, float, float, float], ...] = (
            (0.0, 0.0, 1.0, -self.z_near_m),
            (1.0, 0.0, gx, 0.0),
            (-1.0, 0.0, gx, b),
            (0.0, 1.0, gy, 0.0),
            (0.0, -1.0, gy, 0.0),
        )
        self._plane_arr = np.array(self._planes, dtype=np.float64)
        # Camera depth where LOD level 1 starts: one level-0 texel per pixel.
        self._z_lod0 = f / self.texels_per_m
        self._raster = StereoRaster(geometry, self._textures)

    # ------------------------------------------------------------------ public API

    def render(
        self,
        pose: Pose,
        *,
        left: Photometry = _IDENTITY,
        right: Photometry = _IDENTITY,
        rng: np.random.Generator | None = None,
    ) -> RenderResult:
        """Render both eyes and the left eye's depth at ``pose`` (fresh arrays, safe to keep).

        Args:
            pose: vehicle body pose in NED.
            left, right: per-eye photometric effects (default: none).
            rng: noise source; required when either eye has ``noise_std > 0``.
        """
        self._rasterise(pose)
        depth = self._depth(np.empty(self._raster.invz[0].shape, np.float32))
        grey_l, grey_r = self._photometry(left, right, rng)
        return RenderResult(
            left_bgr=cv2.cvtColor(grey_l, cv2.COLOR_GRAY2BGR),
            right_bgr=cv2.cvtColor(grey_r, cv2.COLOR_GRAY2BGR),
            depth_m=depth,
        )

    def render_side_by_side(
        self,
        pose: Pose,
        out: np.ndarray | None = None,
        *,
        depth_out: np.ndarray | None = None,
        left: Photometry = _IDENTITY,
        right: Photometry = _IDENTITY,
        rng: np.random.Generator | None = None,
    ) -> np.ndarray:
        """Render a ZED side-by-side frame, uint8 ``(H, 2W, 3)`` BGR, left eye first.

        Args:
            pose: vehicle body pose in NED.
            out: optional destination, uint8 ``(H, 2W, 3)``; written in place and returned.
            depth_out: optional float32 ``(H, W)``: receives the left eye's depth (metres).
            left, right, rng: as in :meth:`render`.
        """
        h, w = self._raster.invz[0].shape
        if out is None:
            out = np.empty((h, 2 * w, 3), np.uint8)
        elif out.shape != (h, 2 * w, 3) or out.dtype != np.uint8:
            raise ValueError(f"out must be uint8 {(h, 2 * w, 3)}, got {out.dtype} {out.shape}")
        if depth_out is not None and (depth_out.shape != (h, w) or depth_out.dtype != np.float32):
            raise ValueError(f"depth_out must be float32 {(h, w)}, got {depth_out.dtype} {depth_out.shape}")
        self._rasterise(pose)
        if depth_out is not None:
            self._depth(depth_out)
        grey_l, grey_r = self._photometry(left, right, rng)
        cv2.cvtColor(grey_l, cv2.COLOR_GRAY2BGR, dst=out[:, :w])
        cv2.cvtColor(grey_r, cv2.COLOR_GRAY2BGR, dst=out[:, w:])
        return out

    def prepare_textures(self, max_depth_m: float | None = None) -> None:
        """Generate now every texture a frame can need out to ``max_depth_m`` (default: the world
        box's diagonal), instead of lazily during the first frames that need them."""
        if max_depth_m is None:
            sc = self.scene
            span = 2.0 * sc.backdrop_half_size_m
            max_depth_m = math.sqrt(2.0 * span * span + (sc.floor_z_m - sc.top_z_m) ** 2)
        top = self._level(float(max_depth_m))
        used = sorted(set(zip(self._faces.material.tolist(), self._face_pattern)), key=repr)
        for material, pattern in used:
            for level in range(top + 1):
                self._textures.get(material, level, pattern)

    def eye_positions_ned_m(self, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        """Optical centres of the left and right eye, float64 ``(3,)`` each, NED metres."""
        r_nb = pose.ned_from_body()
        c_l = np.asarray(pose.position_ned_m) + r_nb @ self.camera_offset_frd_m
        c_r = c_l + (r_nb @ CAMERA_TO_BODY)[:, 0] * self.geometry.baseline_m
        return c_l, c_r

    # ------------------------------------------------------------------ internals

    def _depth(self, out: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore"):
            np.reciprocal(self._raster.invz[0], out=out)
        return out

    def _photometry(
        self, left: Photometry, right: Photometry, rng: np.random.Generator | None
    ) -> tuple[np.ndarray, np.ndarray]:
        eyes = []
        for grey, ph in zip(self._raster.grey, (left, right)):
            if ph.is_identity:
                eyes.append(grey)
                continue
            img = grey.astype(np.float32)
            if ph.gain != 1.0:
                img *= np.float32(ph.gain)
            if ph.noise_std > 0.0:
                if rng is None:
                    raise ValueError("Photometry.noise_std > 0 needs an rng (numpy Generator)")
                img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(ph.noise_std)
            np.clip(np.rint(img, out=img), 0.0, 255.0, out=img)
            eyes.append(img.astype(np.uint8))
        return eyes[0], eyes[1]

    def _level(self, z: float) -> int:
        if z < self._z_lod0:
            return 0
        return min(_MAX_LEVEL, int(math.floor(math.log2(z / self._z_lod0))) + 1)

    def _lod_pieces(
        self, poly: list[Vec3], zmin: float, zmax: float
    ) -> list[tuple[list[Vec3], int]]:
        """Split a polygon at the camera-depth slab boundaries of the LOD levels (level ``k >= 1``
        covers ``z_lod0 * [2**(k-1), 2**k)``); each piece is textured at its slab's level, so a
        texel spans 1 to 2 pixels horizontally (never minified)."""
        k = self._level(zmin)
        k_far = self._level(zmax)
        if k_far == k:
            return [(poly, k)]
        pieces = []
        rest = poly
        while k < k_far:
            z_cut = self._z_lod0 * 2.0**k  # where level k + 1 starts
            near = clip_polygon(rest, 0.0, 0.0, -1.0, z_cut)
            if len(near) >= 3:
                pieces.append((near, k))
            rest = clip_polygon(rest, 0.0, 0.0, 1.0, -z_cut)
            if len(rest) < 3:
                return pieces
            k += 1
        pieces.append((rest, k))
        return pieces

    def _rasterise(self, pose: Pose) -> None:
        """Draw both eyes into the raster's ``grey`` and ``invz`` (inverse depth, 0 = nothing)."""
        g = self.geometry
        fc = self._faces
        f = g.focal_px
        r_nc = pose.ned_from_camera()
        r_cn = r_nc.T
        c_l, c_r = self.eye_positions_ned_m(pose)

        # --- vectorised culling and per-face constants
        side_l = fc.normal @ c_l - fc.offset  # > 0: the eye is on the visible side
        side_r = fc.normal @ c_r - fc.offset
        vc = (fc.verts - c_l) @ r_cn.T  # every vertex in the left camera frame
        dist = vc @ self._plane_arr[:, :3].T + self._plane_arr[:, 3]
        dmin = np.minimum.reduceat(dist, fc.starts, axis=0)
        dmax = np.maximum.reduceat(dist, fc.starts, axis=0)
        keep = ((side_l > 1e-9) | (side_r > 1e-9)) & np.all(dmax >= 0.0, axis=1)
        idx = np.flatnonzero(keep)
        self._raster.clear()
        if idx.size == 0:
            return
        # Front to back by nearest vertex: faces drawn later are often hidden, and skip texturing.
        # See-through faces last, back to front: each is laid over what lies behind it.
        zmin_all = np.minimum.reduceat(vc[:, 2], fc.starts)[idx]
        see_through = self._face_alpha[idx]
        idx = idx[np.lexsort((np.where(see_through, -zmin_all, zmin_all), see_through))]

        n_c = fc.normal[idx] @ r_cn.T
        es_c = fc.axis_s[idx] @ r_cn.T
        et_c = fc.axis_t[idx] @ r_cn.T
        origin = fc.origin[idx]
        # Row vectors of coefficients over r = K^-1 (u, v, 1) become coefficients over (u, v, 1).
        kinv = np.array([[1.0 / f, 0.0, -g.cx_px / f], [0.0, 1.0 / f, -g.cy_px / f], [0.0, 0.0, 1.0]])
        p_w = n_c @ kinv
        eye_params = []
        for c_eye in (c_l, c_r):
            delta = fc.offset[idx] - fc.normal[idx] @ c_eye  # < 0 for a face the eye sees
            sig_s = np.einsum("ij,ij->i", fc.axis_s[idx], c_eye - origin)
            sig_t = np.einsum("ij,ij->i", fc.axis_t[idx], c_eye - origin)
            # Texture coordinate (metres) times (n_c . r) is a_s . r: homogeneous, exact per ray.
            p_s = (sig_s[:, None] * n_c + delta[:, None] * es_c) @ kinv
            p_t = (sig_t[:, None] * n_c + delta[:, None] * et_c) @ kinv
            # An eye exactly in a face's plane (delta = 0) sees it edge-on: its row is inf/NaN, and
            # that face is not drawn for that eye (vis_* below), so the values are never used.
            with np.errstate(divide="ignore", invalid="ignore"):
                inv = 1.0 / delta
                # Negate so that the homogeneous w = -(n_c . r) > 0 on the visible side.
                params = np.concatenate([n_c * inv[:, None], -p_s, -p_t, -p_w], axis=1)
            eye_params.append(params.tolist())
        tex_offset = self._tex_offset[idx].tolist()
        vis_l = (side_l[idx] > 1e-9).tolist()
        vis_r = (side_r[idx] > 1e-9).tolist()
        inside = np.all(dmin[idx] >= 0.0, axis=1).tolist()
        starts = fc.starts[idx].tolist()
        counts = fc.counts[idx].tolist()
        materials = fc.material[idx].tolist()
        patterns = [self._face_pattern[i] for i in idx.tolist()]
        alphas = self._face_alpha[idx].tolist()
        glares = self._glares(idx, c_l, c_r, r_cn)

        # --- per face: clip, split by LOD, draw in each eye
        cx, cy, base = g.cx_px, g.cy_px, g.baseline_m
        fb = f * base
        for j in range(idx.size):
            s = starts[j]
            poly: list[Vec3] = list(map(tuple, vc[s : s + counts[j]].tolist()))
            if not inside[j]:
                for plane in self._planes:
                    poly = clip_polygon(poly, *plane)
                    if len(poly) < 3:
                        break
                if len(poly) < 3:
                    continue
            zs = [q[2] for q in poly]
            s_off, t_off = tex_offset[j]
            glare = glares.get(j)
            for piece, level in self._lod_pieces(poly, min(zs), max(zs)):
                tpm = self.texels_per_m / (1 << level)
                tex = self._textures.get(materials[j], level, patterns[j])
                # Project: v is the same in both eyes; the right eye's u is f*B/z smaller.
                fz = [f / q[2] for q in piece]
                us = [q[0] * k + cx for q, k in zip(piece, fz)]
                vs = [q[1] * k + cy for q, k in zip(piece, fz)]
                if vis_l[j]:
                    self._raster.draw(us, vs, 0, eye_params[0][j], tex, tpm, s_off, t_off, alphas[j],
                               None if glare is None else glare[0])
                if vis_r[j]:
                    us_r = [uu - fb / q[2] for uu, q in zip(us, piece)]
                    self._raster.draw(us_r, vs, 1, eye_params[1][j], tex, tpm, s_off, t_off, alphas[j],
                               None if glare is None else glare[1])

    def _glares(
        self, idx: np.ndarray, c_l: np.ndarray, c_r: np.ndarray, r_cn: np.ndarray
    ) -> dict[int, tuple[tuple[float, float, float, float] | None, tuple[float, float, float, float] | None]]:
        """The specular highlight of each glossy face among the drawn ``idx``: by position in
        ``idx``, per eye ``(u_px, v_px, sigma_px, peak_grey)`` or None where the light's mirror
        image lies behind that eye (or the light behind the face)."""
        out: dict[int, tuple] = {}
        light = self.scene.light_ned_m
        if light is None or not self._glossy.any():
            return out
        fc = self._faces
        g = self.geometry
        lp = np.asarray(light)
        for j in np.flatnonzero(self._glossy[idx]).tolist():
            i = int(idx[j])
            n, off = fc.normal[i], float(fc.offset[i])
            h = float(n @ lp) - off
            if h <= 0.0:  # the light is behind the face: no highlight
                continue
            sf = fc.surfaces[int(fc.surface[i])]
            mirror = lp - 2.0 * h * n
            sigma_px = g.focal_px * math.tan(math.radians(sf.gloss_spread_deg))
            per_eye = []
            for c_eye in (c_l, c_r):
                x, y, z = ((mirror - c_eye) @ r_cn.T).tolist()
                per_eye.append(
                    (g.focal_px * x / z + g.cx_px, g.focal_px * y / z + g.cy_px, sigma_px, sf.gloss) if z > 1e-6 else None
                )
            out[j] = (per_eye[0], per_eye[1])
        return out
