"""Disparity and region quality of a matcher on a stereo pair with ground truth (``companion eval``).

Readers (pure functions of paths, no global state):

* :func:`read_pfm` / :func:`write_pfm`: the Portable Float Map of Middlebury's ``disp0.pfm``
  (bottom row first in the file, ``inf`` = unknown);
* :func:`read_middlebury_calib`: ``calib.txt`` (``cam0``, ``cam1``, ``doffs``, ``baseline`` in mm,
  ``width``, ``height``, ``ndisp``, ...);
* :func:`load_middlebury`: a Middlebury folder in one of three layouts: 2014/2021 (``im0.png``,
  ``im1.png``, ``disp0.pfm``, ``calib.txt``), 2005/2006 (``view1.png``, ``view5.png``, ``disp1.png``,
  uint8, 0 = unknown; at every size the PNG holds the full size's disparity, so at half and third size
  it is divided by 2 and 3: :func:`middlebury_2006_png_scale`) or OpenCV's sample copy of 2006 Aloe
  (``aloeL.jpg``, ``aloeR.jpg``, ``aloeGT.png``, full size);
* :func:`load_pair`: explicit left/right images with a disparity file (PFM, PNG, ``.npy``) or a depth
  file (PFM or ``.npy`` in metres, 16-bit PNG in millimetres) and a focal length and baseline.

Metrics, on a float32 disparity in pixels (NaN = no output) against the ground truth:

* **GT-known** pixels: the ground truth is finite and positive. **Matchable**: GT-known, and the match
  ``x - d_gt`` lies inside the right image and ``d_gt`` inside the searched range ``[0, D)``.
* **bad-k** = share of the output pixels (GT-known, resp. matchable) with ``|d - d_gt| > k``;
  **density** = output pixels / GT-known (resp. matchable) pixels; **too near** = share of the bad-2
  errors whose disparity is too large (the depth too near: phantom obstacles).
* **Verdicts** per region (:func:`region_verdict`): a **phantom** reads nearer than
  :data:`PHANTOM_RATIO` × the ground truth's depth; a **missed** near surface is one nearer than
  :data:`NEAR_SURFACE_M` that the output reads farther than its depth / :data:`PHANTOM_RATIO` and
  farther than the rig's nearest measurable depth ``f·B / (D - 1 + doffs)`` (a surface nearer than the
  rig can measure reads that depth at best); **unknown** has too few valid pixels (the controller
  treats it as near: safe, but it steers away).
* **Regions**: the 9-region robust minimum (:func:`~companion.core.regions.reduce_regions`, the
  configured percentile and minimum valid share) of the depth ``z = f·B / (d + doffs)`` from the output
  and from the ground truth, their difference, and each region's class from the controller's ``near``
  term (near when its membership is >= 0.5, unknown when the region is unknown, which the controller
  treats as near), plus the controller's decision from each.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from companion.config import CompanionConfig
from companion.core.depth import disparity_to_depth
from companion.core.fuzzy.avoidance import AvoidanceController
from companion.core.geometry import StereoGeometry
from companion.core.blocks import block_max
from companion.core.regions import reduce_regions, region_layout
from companion.core.types import REGION_NAMES
from companion.errors import InputError

#: A region reading nearer than this share of the ground truth's depth is a phantom obstacle.
PHANTOM_RATIO = 0.75
#: A real surface nearer than this, m, that a region reads farther than depth / PHANTOM_RATIO is missed.
NEAR_SURFACE_M = 1.0

#: Used when a pair has no calibration: a ZED-like rig, 90° horizontal field of view, 12 cm baseline.
ASSUMED_HFOV_DEG = 90.0
ASSUMED_BASELINE_M = 0.12


@dataclass(frozen=True)
class GroundTruthPair:
    """A rectified grey pair and its left-view ground truth.

    Attributes:
        left, right: uint8 ``(H, W)`` grey images.
        disparity: float32 ``(H, W)`` ground-truth disparity of the left image, px; NaN = unknown.
        focal_px, baseline_m: the rig (assumed when the source has none: see ``assumed``).
        doffs_px: ``cx_right - cx_left`` (Middlebury's doffs): depth ``z = f·B / (d + doffs)``.
        cx_px, cy_px: the left principal point, px.
        name: where it came from (one line).
        assumed: True when focal and baseline are the :data:`ASSUMED_HFOV_DEG` / :data:`ASSUMED_BASELINE_M` rig.
        ndisp: the source's disparity range if it states one (Middlebury's ``ndisp``), else None.
    """

    left: np.ndarray
    right: np.ndarray
    disparity: np.ndarray
    focal_px: float
    baseline_m: float
    doffs_px: float
    cx_px: float
    cy_px: float
    name: str
    assumed: bool = False
    ndisp: int | None = None

    @property
    def width_px(self) -> int:
        return int(self.left.shape[1])

    @property
    def height_px(self) -> int:
        return int(self.left.shape[0])

    def geometry(self) -> StereoGeometry:
        return StereoGeometry(self.width_px, self.height_px, self.focal_px, self.cx_px, self.cy_px, self.baseline_m)


# --------------------------------------------------------------------------------------------------
# readers


def read_pfm(path: str | Path) -> np.ndarray:
    """A one-channel PFM file as float32 ``(H, W)``, top row first.

    Raises:
        InputError: unreadable, not a grey PFM, or truncated.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as err:
        raise InputError(f"{path}: cannot read: {err.strerror or err}") from None
    # header: "Pf\n<w> <h>\n<scale>\n" (whitespace-separated tokens), then the raster
    m = re.match(rb"(P[Ff])\s+(\d+)\s+(\d+)\s+([-+0-9.eE]+)\s", data)
    if m is None:
        raise InputError(f"{path}: not a PFM file (no 'Pf <w> <h> <scale>' header)")
    if m.group(1) != b"Pf":
        raise InputError(f"{path}: a colour PFM ('PF'); a disparity or depth map has one channel ('Pf')")
    w, h, scale = int(m.group(2)), int(m.group(3)), float(m.group(4))
    n = w * h
    raster = data[m.end() :]
    if len(raster) < 4 * n:
        raise InputError(f"{path}: truncated PFM: {len(raster)} bytes for {w}x{h} floats")
    dtype = "<f4" if scale < 0 else ">f4"
    arr = np.frombuffer(raster[: 4 * n], dtype=dtype).reshape(h, w)
    return np.ascontiguousarray(arr[::-1]).astype(np.float32)


def write_pfm(path: str | Path, array: np.ndarray) -> None:
    """Write float32 ``(H, W)`` (top row first) as a little-endian one-channel PFM."""
    a = np.asarray(array, dtype="<f4")
    if a.ndim != 2:
        raise ValueError(f"PFM needs a 2-D array, got shape {a.shape}")
    h, w = a.shape
    Path(path).write_bytes(f"Pf\n{w} {h}\n-1.0\n".encode() + np.ascontiguousarray(a[::-1]).tobytes())


def read_middlebury_calib(path: str | Path) -> dict[str, Any]:
    """Middlebury ``calib.txt``: ``cam0``/``cam1`` as float64 ``(3, 3)``, the other keys as numbers.

    Raises:
        InputError: unreadable, a line that is not ``key=value``, or no ``cam0`` / ``baseline``.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise InputError(f"{path}: cannot read: {err.strerror or err}") from None
    out: dict[str, Any] = {}
    for i, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line:
            continue
        if "=" not in line:
            raise InputError(f"{path}:{i}: expected key=value, got {line!r}")
        key, value = (s.strip() for s in line.split("=", 1))
        try:
            if value.startswith("["):
                rows = [r.split() for r in value.strip("[]").split(";")]
                out[key] = np.array([[float(v) for v in r] for r in rows], dtype=np.float64)
            else:
                num = float(value)
                out[key] = int(num) if num.is_integer() and "." not in value else num
        except ValueError:
            raise InputError(f"{path}:{i}: cannot read {key} = {value!r}") from None
    for key in ("cam0", "baseline"):
        if key not in out:
            raise InputError(f"{path}: no {key}")
    if np.shape(out["cam0"]) != (3, 3):
        raise InputError(f"{path}: cam0 must be a 3x3 matrix")
    return out


def _read_grey(path: Path) -> np.ndarray:
    if path.is_dir():
        raise InputError(f"{path}: a folder, not an image file (for a Middlebury folder: --middlebury)")
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise InputError(f"{path}: not a readable image")
    return img


def _load_numpy(path: Path, what: str) -> np.ndarray:
    """A 2-D array from ``.npy``, or from an ``.npz`` holding one array (or one named ``what``).

    Raises:
        InputError: not readable by NumPy, pickled objects, several arrays and none named ``what``, or
            not 2-D.
    """
    try:
        loaded = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as err:
        raise InputError(f"{path}: not a NumPy {what} array ({err})") from None
    if isinstance(loaded, np.ndarray):
        arr = loaded
    else:
        with loaded:
            names = list(loaded.files)
            if what in names:
                arr = loaded[what]
            elif len(names) == 1:
                arr = loaded[names[0]]
            else:
                raise InputError(f"{path}: an .npz of {len(names)} arrays ({', '.join(names)}); name the {what} one '{what}'")
    if arr.ndim != 2 or arr.dtype.kind not in "iuf":
        raise InputError(f"{path}: a {what} must be one 2-D array of numbers, got {arr.dtype} {arr.shape}")
    return arr.astype(np.float32)


def _read_disparity(path: Path, png_scale: float) -> np.ndarray:
    """Disparity file -> float32 px, NaN unknown (PFM: inf/NaN/<= 0; PNG: 0; .npy/.npz: NaN/<= 0)."""
    if path.is_dir():
        raise InputError(f"{path}: a folder, not a disparity file (PFM, PNG, .npy or .npz)")
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".pfm":
        d = read_pfm(path)
    elif suffix in (".npy", ".npz"):
        d = _load_numpy(path, "disparity")
    else:
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None or raw.ndim != 2:
            raise InputError(
                f"{path}: not a disparity file eval reads (a one-channel PNG, PFM, .npy or .npz of disparities in px)"
            )
        d = raw.astype(np.float32) / np.float32(png_scale)
    d = d.astype(np.float32)
    d[~np.isfinite(d) | (d <= 0)] = np.nan
    return d


def _read_depth(path: Path, png_mm: bool) -> np.ndarray:
    """Depth file -> float32 metres, NaN unknown (PFM/.npy in metres; 16-bit PNG in millimetres)."""
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".pfm":
        z = read_pfm(path)
    elif suffix in (".npy", ".npz"):
        z = _load_numpy(path, "depth")
    else:
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None or raw.ndim != 2:
            raise InputError(f"{path}: not a one-channel depth image")
        z = raw.astype(np.float32) / (np.float32(1000.0) if png_mm else np.float32(1.0))
    z = z.astype(np.float32)
    z[~np.isfinite(z) | (z <= 0)] = np.nan
    return z


def _assumed_focal(width_px: int) -> float:
    return (width_px / 2.0) / math.tan(math.radians(ASSUMED_HFOV_DEG) / 2.0)


def middlebury_2006_png_scale(width_px: int) -> float:
    """PNG units per pixel of a 2005/2006 ``disp1.png`` at this image width: the PNGs hold the full
    size's disparity (full size is 1240–1390 px wide, half 620–695, third 413–465), so 1, 2 or 3; 1
    for a width no release has."""
    if 550 <= width_px < 1000:
        return 2.0
    if 350 <= width_px < 550:
        return 3.0
    return 1.0


def load_middlebury(directory: str | Path) -> GroundTruthPair:
    """A Middlebury pair from its folder (2014/2021, 2005/2006, or OpenCV's Aloe sample; module doc).

    Without ``calib.txt`` the rig is assumed (:data:`ASSUMED_HFOV_DEG`, :data:`ASSUMED_BASELINE_M`).

    Raises:
        InputError: no known layout in the folder, or an unreadable file.
    """
    d = Path(directory)
    if not d.is_dir():
        raise InputError(f"{d}: not a folder")
    layouts = (
        ("im0.png", "im1.png", "disp0.pfm", "Middlebury 2014/2021"),
        ("view1.png", "view5.png", "disp1.png", "Middlebury 2005/2006"),
        ("aloeL.jpg", "aloeR.jpg", "aloeGT.png", "Middlebury 2006 Aloe (OpenCV sample)"),
    )
    for ln, rn, gn, what in layouts:
        if (d / ln).is_file() and (d / rn).is_file() and (d / gn).is_file():
            left, right = _read_grey(d / ln), _read_grey(d / rn)
            scale = middlebury_2006_png_scale(left.shape[1]) if ln == "view1.png" else 1.0
            gt = _read_disparity(d / gn, png_scale=scale)
            if scale != 1.0:
                what += f" ({'half' if scale == 2.0 else 'third'} size: disparity = PNG / {scale:.0f})"
            break
    else:
        raise InputError(
            f"{d}: no Middlebury layout found (im0.png/im1.png/disp0.pfm, view1.png/view5.png/disp1.png, "
            "or aloeL.jpg/aloeR.jpg/aloeGT.png)"
        )
    if left.shape != right.shape or gt.shape != left.shape:
        raise InputError(f"{d}: left {left.shape}, right {right.shape} and ground truth {gt.shape} differ in size")
    h, w = left.shape
    calib = d / "calib.txt"
    if calib.is_file():
        c = read_middlebury_calib(calib)
        cam0 = c["cam0"]
        return GroundTruthPair(
            left, right, gt, float(cam0[0, 0]), float(c["baseline"]) / 1000.0, float(c.get("doffs", 0.0)),
            float(cam0[0, 2]), float(cam0[1, 2]), f"{what}: {d}", False,
            int(c["ndisp"]) if "ndisp" in c else None,
        )
    return GroundTruthPair(
        left, right, gt, _assumed_focal(w), ASSUMED_BASELINE_M, 0.0, (w - 1) / 2.0, (h - 1) / 2.0,
        f"{what}: {d}", True,
    )


def load_pair(
    left: str | Path,
    right: str | Path,
    *,
    disparity: str | Path | None = None,
    depth: str | Path | None = None,
    calib: str | Path | None = None,
    focal_px: float | None = None,
    baseline_m: float | None = None,
    doffs_px: float = 0.0,
    disparity_png_scale: float = 1.0,
    depth_png_mm: bool = True,
) -> GroundTruthPair:
    """Explicit files: left/right images and a disparity or a depth ground truth.

    A depth file needs the rig (``calib`` or ``focal_px`` and ``baseline_m``) to become disparity
    (``d = f·B / z - doffs``). Without a rig a disparity pair is scored against the assumed one.

    Raises:
        InputError: unreadable files, sizes that differ, neither or both of disparity and depth, or a
            depth file without a rig.
    """
    if (disparity is None) == (depth is None):
        raise InputError("give exactly one ground truth: a disparity file or a depth file")
    lp, rp = Path(left), Path(right)
    li, ri = _read_grey(lp), _read_grey(rp)
    if li.shape != ri.shape:
        raise InputError(f"{lp} ({li.shape[1]}x{li.shape[0]}) and {rp} ({ri.shape[1]}x{ri.shape[0]}) differ in size")
    h, w = li.shape
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    ndisp = None
    if calib is not None:
        c = read_middlebury_calib(calib)
        focal_px, baseline_m = float(c["cam0"][0, 0]), float(c["baseline"]) / 1000.0
        doffs_px = float(c.get("doffs", doffs_px))
        cx, cy = float(c["cam0"][0, 2]), float(c["cam0"][1, 2])
        ndisp = int(c["ndisp"]) if "ndisp" in c else None
    assumed = focal_px is None or baseline_m is None
    if depth is not None and assumed:
        raise InputError("a depth ground truth needs the rig: --calib, or --focal-px and --baseline-m")
    f = _assumed_focal(w) if focal_px is None else float(focal_px)
    b = ASSUMED_BASELINE_M if baseline_m is None else float(baseline_m)
    if depth is not None:
        z = _read_depth(Path(depth), depth_png_mm)
        gt = (np.float32(f * b) / z - np.float32(doffs_px)).astype(np.float32)
        gt[~np.isfinite(gt) | (gt <= 0)] = np.nan
        src = Path(depth)
    else:
        assert disparity is not None
        gt = _read_disparity(Path(disparity), disparity_png_scale)
        src = Path(disparity)
    if gt.shape != li.shape:
        raise InputError(f"{src}: ground truth {gt.shape[1]}x{gt.shape[0]} differs from the images' {w}x{h}")
    return GroundTruthPair(li, ri, gt, f, b, float(doffs_px), cx, cy, f"{lp.name} / {rp.name} / {src.name}", assumed,
                           ndisp)


def rescale(pair: GroundTruthPair, scale: float) -> GroundTruthPair:
    """The pair at ``scale`` (e.g. 0.5): images by area averaging, the ground truth by nearest sampling
    times ``scale``, focal length, doffs and principal point scaled (pixel centres at integers)."""
    if scale == 1.0:
        return pair
    if not 0.05 <= scale <= 1.0:
        raise InputError(f"scale must be in [0.05, 1], got {scale}")
    h, w = pair.left.shape
    nw, nh = max(1, round(w * scale)), max(1, round(h * scale))
    left = cv2.resize(pair.left, (nw, nh), interpolation=cv2.INTER_AREA)
    right = cv2.resize(pair.right, (nw, nh), interpolation=cv2.INTER_AREA)
    gt = cv2.resize(pair.disparity, (nw, nh), interpolation=cv2.INTER_NEAREST) * np.float32(scale)
    sx, sy = nw / w, nh / h
    return replace(
        pair, left=left, right=right, disparity=gt.astype(np.float32), focal_px=pair.focal_px * sx,
        doffs_px=pair.doffs_px * sx, cx_px=(pair.cx_px + 0.5) * sx - 0.5, cy_px=(pair.cy_px + 0.5) * sy - 0.5,
        name=f"{pair.name} at scale {scale:g}", ndisp=None if pair.ndisp is None else math.ceil(pair.ndisp * sx),
    )


def suggested_num_disparities(pair: GroundTruthPair) -> int:
    """``ndisp`` rounded up to a multiple of 16, else the smallest multiple of 16 above the largest
    ground-truth disparity; between 16 and 256."""
    if pair.ndisp is not None:
        n = int(pair.ndisp)
    else:
        n = math.floor(float(np.nanmax(pair.disparity))) + 1
    return int(min(256, max(16, 16 * math.ceil(n / 16))))


# --------------------------------------------------------------------------------------------------
# metrics


def disparity_metrics(disparity: np.ndarray, gt: np.ndarray, num_disparities: int) -> dict[str, float]:
    """bad-1, bad-2, density and the too-near share (module doc) over GT-known and matchable pixels.

    Args:
        disparity: float32 ``(H, W)`` output, px, NaN = none.
        gt: float32 ``(H, W)`` ground truth, px, NaN = unknown.
        num_disparities: the searched range ``D``.

    Returns:
        ``{"known_px", "matchable_px", "bad1_known", "bad2_known", "density_known", "too_near_known",
        "bad1_matchable", "bad2_matchable", "density_matchable", "too_near_matchable",
        "mean_abs_err_known"}``; shares in [0, 1] (NaN when there is nothing to count).
    """
    if disparity.shape != gt.shape:
        raise ValueError(f"disparity {disparity.shape} and ground truth {gt.shape} differ in shape")
    h, w = gt.shape
    known = np.isfinite(gt) & (gt > 0)
    xs = np.arange(w, dtype=np.float32)[None, :]
    matchable = known & (xs - gt >= 0) & (gt < num_disparities)
    out = np.isfinite(disparity)
    err = disparity - gt
    res: dict[str, float] = {"known_px": float(known.sum()), "matchable_px": float(matchable.sum())}
    for label, mask in (("known", known), ("matchable", matchable)):
        sel = out & mask
        n = int(sel.sum())
        e = err[sel]
        res[f"density_{label}"] = n / max(1, int(mask.sum()))
        res[f"bad1_{label}"] = float((np.abs(e) > 1).mean()) if n else math.nan
        res[f"bad2_{label}"] = float((np.abs(e) > 2).mean()) if n else math.nan
        bad = np.abs(e) > 2
        res[f"too_near_{label}"] = float((e[bad] > 0).mean()) if bad.any() else math.nan
    res["mean_abs_err_known"] = float(np.abs(err[out & known]).mean()) if (out & known).any() else math.nan
    return res


def map_block_report(
    disparity: np.ndarray,
    gt: np.ndarray,
    block_px: int,
    near_px: float,
    left: np.ndarray | None = None,
    jump_px: float = 1.0,
    band_px: int = 6,
    plain_grey: float = 4.0,
) -> dict[str, float]:
    """The local planner's map input (:func:`~companion.core.blocks.block_max`: each block's nearest
    disparity) from ``disparity`` against the same reduction of the ground truth.

    A block is **too near** when its disparity exceeds the ground truth's largest in the block by more
    than 1 px (nearer than every surface in it): what narrows a door on the local map. It lies
    **at a jump** when it touches a pixel within ``band_px`` of a ground-truth disparity jump of more
    than ``jump_px`` between neighbours (a foreground edge smeared onto what is behind it); else, with
    ``left``, on a **plain** surface when the block's texture (mean ``|horizontal grey difference|``)
    is below ``plain_grey``. A block whose ground truth is at least ``near_px`` (a surface near enough
    to remember) is **seen** when the output is within 1 px of it or nearer.

    Args:
        disparity: float32 ``(H, W)`` output, px, NaN = none.
        gt: float32 ``(H, W)`` ground truth, px, NaN = unknown.
        block_px: the map's block side, px.
        near_px: ground-truth disparity of the farthest surface that counts as near, px.
        left: uint8 ``(H, W)`` the left image, for the plain/textured split; None: no split.
        jump_px, band_px, plain_grey: see above; px, px, grey levels.

    Returns:
        ``{"blocks", "too_near", "too_near_at_jump", "too_near_plain", "too_near_textured", "near",
        "near_seen"}``, counts of blocks (the split of ``too_near`` off jumps is NaN without ``left``).
    """
    if disparity.shape != gt.shape:
        raise ValueError(f"disparity {disparity.shape} and ground truth {gt.shape} differ in shape")
    g = np.where(np.isfinite(gt), gt, np.nan).astype(np.float32)
    jump = np.zeros(g.shape, np.uint8)
    with np.errstate(invalid="ignore"):
        jump[:, 1:] |= np.abs(np.diff(g, axis=1)) > jump_px
        jump[1:, :] |= np.abs(np.diff(g, axis=0)) > jump_px
    k = 2 * int(band_px) + 1
    band = cv2.dilate(jump, np.ones((k, k), np.uint8)).astype(np.float32)
    out_b = block_max(disparity, block_px)
    gt_b = block_max(g, block_px)
    at_jump = block_max(band, block_px) > 0
    valid = np.isfinite(out_b)
    with np.errstate(invalid="ignore"):
        too_near = valid & (out_b > np.nan_to_num(gt_b, nan=-np.inf) + 1.0)
        near = np.nan_to_num(gt_b, nan=-1.0) >= near_px
        seen = near & (np.nan_to_num(out_b, nan=-np.inf) >= gt_b - 1.0)
    res = {
        "blocks": float(valid.sum()),
        "too_near": float(too_near.sum()),
        "too_near_at_jump": float((too_near & at_jump).sum()),
        "too_near_plain": math.nan,
        "too_near_textured": math.nan,
        "near": float(near.sum()),
        "near_seen": float(seen.sum()),
    }
    if left is not None:
        diff = np.zeros(left.shape, np.float32)
        diff[:, 1:] = np.abs(np.diff(left.astype(np.float32), axis=1))
        plain = _block_mean(diff, block_px) < plain_grey
        off = too_near & ~at_jump
        res["too_near_plain"] = float((off & plain).sum())
        res["too_near_textured"] = float((off & ~plain).sum())
    return res


def _block_mean(a: np.ndarray, b: int) -> np.ndarray:
    """Mean of each ``b × b`` block of a float32 image (partial edge blocks: over the whole block, zeros
    outside), float32 ``(ceil(H/b), ceil(W/b))``."""
    h, w = a.shape
    oh, ow = -(-h // b), -(-w // b)
    pad = np.zeros((oh * b, ow * b), np.float32)
    pad[:h, :w] = a
    return pad.reshape(oh, b, ow, b).mean(axis=(1, 3), dtype=np.float64).astype(np.float32)


def depth_from_disparity(disparity: np.ndarray, focal_baseline_px_m: float, doffs_px: float = 0.0) -> np.ndarray:
    """``z = f·B / (d + doffs)`` (float32, NaN where ``d`` is NaN; see :func:`disparity_to_depth`)."""
    d = disparity if doffs_px == 0.0 else disparity + np.float32(doffs_px)
    return disparity_to_depth(d, focal_baseline_px_m)


def region_verdict(gt_depth_m: float, depth_m: float, nearest_m: float = 0.0) -> str:
    """``"phantom"``, ``"missed"``, ``"unknown"`` or ``""`` for one region's output depth against its
    ground truth's, metres, NaN = unknown; ``nearest_m``: the rig's nearest measurable depth, which a
    nearer surface reads at best (module doc)."""
    if math.isnan(depth_m):
        return "unknown"
    if math.isnan(gt_depth_m):
        return ""
    if depth_m < PHANTOM_RATIO * gt_depth_m:
        return "phantom"
    if gt_depth_m < NEAR_SURFACE_M and depth_m > max(gt_depth_m / PHANTOM_RATIO, nearest_m * (1.0 + 1e-6)):
        return "missed"
    return ""


def region_report(
    disparity: np.ndarray, pair: GroundTruthPair, cfg: CompanionConfig
) -> dict[str, Any]:
    """Per-region robust minimum depth from the output and from the ground truth, their classes and the
    controller's decision from each (module doc).

    Returns:
        ``{"regions": [{"name", "gt_depth_m", "depth_m", "error_m", "gt_valid", "valid", "gt_class",
        "class", "verdict"}, ...], "gt_decision": {...}, "decision": {...}, "class_agreement": int}``.
    """
    geometry = pair.geometry()
    layout = region_layout(geometry, cfg.regions)
    fb = geometry.focal_baseline_px_m
    out = reduce_regions(depth_from_disparity(disparity, fb, pair.doffs_px), layout, cfg.regions)
    ref = reduce_regions(depth_from_disparity(pair.disparity, fb, pair.doffs_px), layout, cfg.regions)
    ctrl = AvoidanceController(cfg.controller)

    def classes(depth: np.ndarray) -> list[str]:
        res = ctrl.main_system.infer(ctrl.prepare(depth))
        names = []
        for i, name in enumerate(REGION_NAMES):
            near = float(res.memberships[ctrl.main_system.atom(name, "near")])
            names.append("unknown" if math.isnan(depth[i]) else ("near" if near >= 0.5 else "far"))
        return names

    def decision(depth: np.ndarray) -> dict[str, Any]:
        dec = ctrl.decide(depth)
        return {"kind": dec.kind.value, "yaw": dec.yaw, "pitch": dec.pitch, "reason": dec.reason}

    gc, bc = classes(ref.depth_m), classes(out.depth_m)
    nearest_m = fb / (cfg.stereo.num_disparities - 1 + pair.doffs_px)
    rows = []
    for i, name in enumerate(REGION_NAMES):
        g, b = float(ref.depth_m[i]), float(out.depth_m[i])
        rows.append({
            "name": name, "gt_depth_m": g, "depth_m": b, "error_m": b - g,
            "gt_valid": float(ref.valid_fraction[i]), "valid": float(out.valid_fraction[i]),
            "gt_class": gc[i], "class": bc[i], "verdict": region_verdict(g, b, nearest_m),
        })
    return {
        "regions": rows,
        "gt_decision": decision(ref.depth_m),
        "decision": decision(out.depth_m),
        "class_agreement": sum(a == b for a, b in zip(gc, bc)),
    }
