"""The renderer's rasteriser: both eyes' targets, and one textured convex piece drawn into one of them.

Over the piece's pixel bounding box: inverse depth ``1/z`` is affine in the pixel coordinates for a
plane, so it is evaluated from the pixel rays' tables; the polygon is masked (``cv2.fillConvexPoly``,
1/16 px vertices), z-tested against the eye's inverse-depth buffer, and the texture is sampled through
the exact pixel -> texel homography (``cv2.warpPerspective``, bilinear, wrap) only inside the visible
part. A see-through face is laid over what lies behind it as a pixel integrates it (its texel is the
bar's grey times the bar's coverage of the pixel, and the rest of the pixel is what is behind), and
only where a bar covers most of a pixel is it in the depth buffer; a glossy face gets its highlight
added.
:func:`clip_polygon` is the Sutherland-Hodgman clip the renderer cuts pieces with.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from companion.core.geometry import StereoGeometry
from companion.sim.render.texture import BARS_ALPHA_THRESHOLD, BARS_TONE, TextureBank

#: Fixed-point bits for cv2.fillConvexPoly vertices (1/16 px).
_SHIFT = 4
_WARP_FLAGS = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP

Vec3 = tuple[float, float, float]


def clip_polygon(poly: list[Vec3], a: float, b: float, c: float, e: float) -> list[Vec3]:
    """Sutherland-Hodgman: the part of a convex polygon where ``a x + b y + c z + e >= 0``."""
    out: list[Vec3] = []
    prev = poly[-1]
    dp = a * prev[0] + b * prev[1] + c * prev[2] + e
    for cur in poly:
        dc = a * cur[0] + b * cur[1] + c * cur[2] + e
        if (dc >= 0.0) != (dp >= 0.0):
            t = dp / (dp - dc)
            x0, y0, z0 = prev
            out.append((x0 + t * (cur[0] - x0), y0 + t * (cur[1] - y0), z0 + t * (cur[2] - z0)))
        if dc >= 0.0:
            out.append(cur)
        prev, dp = cur, dc
    return out


class StereoRaster:
    """Both eyes' raster targets for one rig, drawn with textures of one bank.

    Buffers are allocated once; not thread-safe.

    Attributes:
        invz: per eye, the inverse depth of what is drawn, float32 ``(H, W)``, 1/m (0 = nothing).
        grey: per eye, the grey image, uint8 ``(H, W)``.
    """

    def __init__(self, geometry: StereoGeometry, textures: TextureBank) -> None:
        self.geometry = geometry
        self._textures = textures
        g = geometry
        w, h, f = g.width_px, g.height_px, g.focal_px
        self._xhat = ((np.arange(w, dtype=np.float64) - g.cx_px) / f).astype(np.float32)
        self._yhat = ((np.arange(h, dtype=np.float64) - g.cy_px) / f).astype(np.float32)
        # Per-eye inverse-depth buffers and grey targets, plus flat scratch reshaped per bounding box
        # (flat so that every (h, w) view is contiguous).
        self.invz: tuple[np.ndarray, np.ndarray] = (np.zeros((h, w), np.float32), np.zeros((h, w), np.float32))
        self.grey: tuple[np.ndarray, np.ndarray] = (np.zeros((h, w), np.uint8), np.zeros((h, w), np.uint8))
        self._scr_invz = np.empty(h * w, np.float32)
        self._scr_mask = np.empty(h * w, np.uint8)
        self._scr_vis = np.empty(h * w, np.uint8)
        self._scr_tex = np.empty(h * w, np.uint8)

    def clear(self) -> None:
        """Nothing drawn: every inverse depth 0, every grey 0."""
        for buf in self.invz:
            buf.fill(0.0)
        for buf in self.grey:
            buf.fill(0)

    def draw(
        self, us: list[float], vs: list[float], eye: int, p: list[float],
        tex: np.ndarray, tpm: float, s0: float, t0: float,
        alpha: bool = False, glare: tuple[float, float, float, float] | None = None,
    ) -> None:
        """Draw one clipped convex piece, given by its vertices' pixel coordinates, into one eye.

        ``p``: the piece's plane seen from this eye, 12 coefficients over the pixel ``(u, v, 1)``: its
        inverse depth, then the homogeneous texture coordinates ``s``, ``t`` (metres) and their ``w``;
        ``tex``: the texture at the piece's level of detail, ``tpm`` its texels per metre, ``(s0, t0)``
        the face's texture offset, texels.

        ``alpha``: a see-through face, drawn after everything behind it: each visible pixel becomes
        ``texel + (1 - coverage) · behind``, with the bar's coverage ``texel / BARS_TONE[0]`` (at most
        1), so that a bar thinner than a pixel is a faint unbroken line, as a camera sees it, not a
        dashed one; only texels at or over ``BARS_ALPHA_THRESHOLD`` enter the depth buffer (the pixel's
        depth is the bar's where the bar covers most of it); ``glare``: ``(u_px, v_px, sigma_px,
        peak_grey)`` of a highlight to add."""
        u0 = max(0, math.floor(min(us)))
        u1 = min(self.geometry.width_px, math.ceil(max(us)) + 1)
        if u0 >= u1:
            return
        v0 = max(0, math.floor(min(vs)))
        v1 = min(self.geometry.height_px, math.ceil(max(vs)) + 1)
        if v0 >= v1:
            return
        bw, bh = u1 - u0, v1 - v0
        n = bw * bh
        zbuf = self.invz[eye][v0:v1, u0:u1]

        # Inverse depth of the plane at every pixel centre of the box (affine in u, v).
        iz = self._scr_invz[:n].reshape(bh, bw)
        col = self._yhat[v0:v1] * np.float32(p[1])
        col += np.float32(p[2])
        np.add(col[:, None], self._xhat[u0:u1] * np.float32(p[0]), out=iz)

        mask = self._scr_mask[:n].reshape(bh, bw)
        mask.fill(0)
        sc = float(1 << _SHIFT)
        pts = np.array([(round((uu - u0) * sc), round((vv - v0) * sc)) for uu, vv in zip(us, vs)], np.int32)
        cv2.fillConvexPoly(mask, pts, 255, cv2.LINE_8, _SHIFT)
        vis = self._scr_vis[:n].reshape(bh, bw)
        cv2.compare(iz, zbuf, cv2.CMP_GT, dst=vis)
        cv2.bitwise_and(vis, mask, dst=vis)
        rx, ry, rw, rh = cv2.boundingRect(vis)
        if rw == 0:
            return

        # Pixel (x, y) of the visible sub-box -> texel: rows of M are (s, t, w) homogeneous.
        ox, oy = u0 + rx, v0 + ry
        ms0 = tpm * p[3] + s0 * p[9]
        ms1 = tpm * p[4] + s0 * p[10]
        ms2 = tpm * p[5] + s0 * p[11] + ms0 * ox + ms1 * oy
        mt0 = tpm * p[6] + t0 * p[9]
        mt1 = tpm * p[7] + t0 * p[10]
        mt2 = tpm * p[8] + t0 * p[11] + mt0 * ox + mt1 * oy
        mw0, mw1 = p[9], p[10]
        mw2 = p[11] + mw0 * ox + mw1 * oy
        sub = self._scr_tex[: rw * rh].reshape(rh, rw)
        size = float(self._textures.size)
        lim = self._textures.pad - 4
        # Warp tile by tile; each tile's texel range is moved by whole periods into the stored,
        # padded texture, which keeps OpenCV on its fast in-image path. Tiles whose texel range is
        # too wide for the padding are split; tiny ones fall back to BORDER_WRAP on one period.
        tiles = [(0, 0, rw, rh)]
        if lim < 16:  # (almost) no padding: wrap everything
            m = np.array([[ms0, ms1, ms2], [mt0, mt1, mt2], [mw0, mw1, mw2]])
            period = tex[: self._textures.size, : self._textures.size]
            cv2.warpPerspective(period, m, (rw, rh), dst=sub, flags=_WARP_FLAGS, borderMode=cv2.BORDER_WRAP)
            tiles = []
        while tiles:
            tx, ty, tw, th = tiles.pop()
            c2s = ms2 + ms0 * tx + ms1 * ty
            c2t = mt2 + mt0 * tx + mt1 * ty
            c2w = mw2 + mw0 * tx + mw1 * ty
            ss = []
            tt = []
            ok = True
            for x, y in ((0.0, 0.0), (tw - 1.0, 0.0), (0.0, th - 1.0), (tw - 1.0, th - 1.0)):
                w = c2w + mw0 * x + mw1 * y
                if w <= 1e-12:
                    ok = False
                    break
                ss.append((c2s + ms0 * x + ms1 * y) / w)
                tt.append((c2t + mt0 * x + mt1 * y) / w)
            fits = ok and max(ss) - min(ss) <= lim and max(tt) - min(tt) <= lim
            if not fits and (tw > 8 or th > 8):
                if ok and tw > 1 and th > 1:
                    # Split across the image axis along which the texel range grows fastest.
                    ext_x = max(
                        abs(ss[1] - ss[0]), abs(tt[1] - tt[0]), abs(ss[3] - ss[2]), abs(tt[3] - tt[2])
                    )
                    ext_y = max(
                        abs(ss[2] - ss[0]), abs(tt[2] - tt[0]), abs(ss[3] - ss[1]), abs(tt[3] - tt[1])
                    )
                    split_x = ext_x >= ext_y
                else:
                    split_x = tw >= th
                if split_x and tw > 1:
                    half = tw // 2
                    tiles.append((tx, ty, half, th))
                    tiles.append((tx + half, ty, tw - half, th))
                else:
                    half = th // 2
                    tiles.append((tx, ty, tw, half))
                    tiles.append((tx, ty + half, tw, th - half))
                continue
            if fits:
                ks = size * math.floor(min(ss) / size)
                kt = size * math.floor(min(tt) / size)
                src = tex
            else:
                ks = kt = 0.0
                src = tex[: self._textures.size, : self._textures.size]
            m = np.array(
                [
                    [ms0 - ks * mw0, ms1 - ks * mw1, c2s - ks * c2w],
                    [mt0 - kt * mw0, mt1 - kt * mw1, c2t - kt * c2w],
                    [mw0, mw1, c2w],
                ]
            )
            dst = sub[ty : ty + th, tx : tx + tw]
            cv2.warpPerspective(src, m, (tw, th), dst=dst, flags=_WARP_FLAGS, borderMode=cv2.BORDER_WRAP)
        vis_sub = vis[ry : ry + rh, rx : rx + rw]
        if glare is not None:
            self._add_glare(sub, ox, oy, glare)
        grey = self.grey[eye][oy : oy + rh, ox : ox + rw]
        if alpha:
            tex_f = sub.astype(np.float32)
            behind = grey.astype(np.float32) * np.maximum(0.0, 1.0 - tex_f * np.float32(1.0 / BARS_TONE[0]))
            cv2.copyTo(np.clip(np.rint(tex_f + behind), 0, 255).astype(np.uint8), vis_sub, dst=grey)
            vis_sub[sub < BARS_ALPHA_THRESHOLD] = 0  # mostly what is behind: its depth stays
        else:
            cv2.copyTo(sub, vis_sub, dst=grey)
        cv2.copyTo(iz, vis, dst=zbuf)

    @staticmethod
    def _add_glare(sub: np.ndarray, ox: int, oy: int, glare: tuple[float, float, float, float]) -> None:
        """Add a Gaussian highlight (saturating) to ``sub``, the uint8 block at image ``(ox, oy)``."""
        u, v, sigma, peak = glare
        rh, rw = sub.shape
        reach = 3.0 * sigma
        x0, x1 = max(0, math.floor(u - reach) - ox), min(rw, math.ceil(u + reach) + 1 - ox)
        y0, y1 = max(0, math.floor(v - reach) - oy), min(rh, math.ceil(v + reach) + 1 - oy)
        if x0 >= x1 or y0 >= y1:
            return
        gx = np.exp(-0.5 * ((np.arange(x0, x1, dtype=np.float32) + (ox - u)) / sigma) ** 2)
        gy = np.exp(-0.5 * ((np.arange(y0, y1, dtype=np.float32) + (oy - v)) / sigma) ** 2) * np.float32(peak)
        blob = np.rint(gy[:, None] * gx[None, :]).astype(np.uint8)
        region = sub[y0:y1, x0:x1]
        cv2.add(region, blob, dst=region)
