"""Frame plumbing before rectification: split a ZED side-by-side frame, convert to grey, check a pair.

Pure functions over NumPy arrays. Nothing here allocates a large array when the caller passes
``out=`` (the hot path), and :func:`split_side_by_side` never copies.
"""

from __future__ import annotations

import cv2
import numpy as np

from companion.errors import FrameError

__all__ = ["GREY_COEFFS_Q15", "check_pair", "split_side_by_side", "to_bgr", "to_grey"]

#: OpenCV's fixed-point BGR→grey weights for uint8 images, in units of 2**-15 (B, G, R):
#: round(0.114·2**15), round(0.587·2**15), round(0.299·2**15); they sum to exactly 2**15.
GREY_COEFFS_Q15: tuple[int, int, int] = (3735, 19235, 9798)


def _describe(a: np.ndarray) -> str:
    return f"shape {tuple(a.shape)} dtype {a.dtype}"


def split_side_by_side(frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split a ZED side-by-side frame into its left and right eye images.

    Args:
        frame: uint8 array ``(H, 2W)`` grey, ``(H, 2W, 2)`` YUYV (a UVC camera's bytes as they come:
            Y0 U Y1 V per two pixels, so ``[..., 0]`` is the luma), ``(H, 2W, 3)`` BGR or ``(H, 2W, 4)``
            BGRA; the left eye is columns ``[0, W)`` and the right eye columns ``[W, 2W)``.

    Returns:
        ``(left, right)``: two views into ``frame`` (no copy), each ``(H, W)`` or ``(H, W, C)`` with
        the frame's channels (alpha and chroma are dropped later, by :func:`to_grey`).

    Raises:
        FrameError: wrong dtype or number of dimensions/channels, an empty frame, an odd width, or
            (YUYV) an odd eye width, which would split a pixel pair's chroma between the eyes.
    """
    if not isinstance(frame, np.ndarray):
        raise FrameError(f"side-by-side frame must be a NumPy array, got {type(frame).__name__}")
    if frame.dtype != np.uint8:
        raise FrameError(f"side-by-side frame must be uint8, got {_describe(frame)}")
    if frame.ndim not in (2, 3) or (frame.ndim == 3 and frame.shape[2] not in (2, 3, 4)):
        raise FrameError(
            "side-by-side frame must be (H, 2W) grey, (H, 2W, 2) YUYV, (H, 2W, 3) BGR or (H, 2W, 4) BGRA, "
            f"got {_describe(frame)}"
        )
    height, width = frame.shape[:2]
    if height == 0 or width == 0:
        raise FrameError(f"side-by-side frame is empty: {_describe(frame)}")
    if width % 2:
        raise FrameError(
            f"side-by-side frame width {width} px is odd; it must hold two eyes of equal width ({_describe(frame)})"
        )
    half = width // 2
    if frame.ndim == 3 and frame.shape[2] == 2 and half % 2:
        raise FrameError(
            f"YUYV side-by-side frame's eyes are {half} px wide, an odd number: YUYV carries chroma per two "
            f"pixels, so each eye must be an even number of pixels wide ({_describe(frame)})"
        )
    return frame[:, :half], frame[:, half:]


def to_grey(image: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Convert one eye image to grey, exactly as ``cv2.cvtColor(..., COLOR_BGR2GRAY)`` does.

    For uint8 BGR (or BGRA, alpha ignored) OpenCV computes, per pixel, in integers::

        Y = (3735·B + 19235·G + 9798·R + 16384) >> 15

    (the weights 0.114, 0.587, 0.299 in Q15, :data:`GREY_COEFFS_Q15`, summing to 32768, with
    round-half-up). A GPU kernel using this formula matches the CPU bit for bit; the test suite checks
    the formula against cv2 on random data (OpenCV 5.0.0 matches it on all 2**24 BGR triples).

    A YUYV image (``(H, W, 2)``, a UVC camera's bytes undecoded) has its grey already: its luma,
    ``image[..., 0]``, is taken as it is. (It is the camera's Y, 16–235 for black to white in BT.601's
    video range; OpenCV's decoded BGR stretches that range by 255/219 first, so the same scene reads
    with 14 % less contrast here. Census and block matching compare pixels with their neighbours and
    do not depend on that scale.)

    Args:
        image: uint8 ``(H, W)`` grey (passed through), ``(H, W, 2)`` YUYV, ``(H, W, 3)`` BGR or
            ``(H, W, 4)`` BGRA; may be a non-contiguous view such as one half of a side-by-side frame.
        out: optional preallocated uint8 ``(H, W)`` array to write into (no allocation).

    Returns:
        uint8 ``(H, W)`` grey image: ``out`` when given; else a new array, or ``image`` itself when
        it is already grey (no copy).

    Raises:
        FrameError: ``image`` or ``out`` has the wrong dtype or shape.
    """
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
        got = _describe(image) if isinstance(image, np.ndarray) else type(image).__name__
        raise FrameError(f"image to convert to grey must be uint8, got {got}")
    luma = image.ndim == 3 and image.shape[2] == 2
    if image.ndim == 2 or luma:
        code = None
    elif image.ndim == 3 and image.shape[2] == 3:
        code = cv2.COLOR_BGR2GRAY
    elif image.ndim == 3 and image.shape[2] == 4:
        code = cv2.COLOR_BGRA2GRAY
    else:
        raise FrameError(
            f"image to convert to grey must be (H, W), (H, W, 2) YUYV, (H, W, 3) or (H, W, 4), got {_describe(image)}"
        )
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise FrameError(f"image to convert to grey is empty: {_describe(image)}")
    if out is not None and (out.dtype != np.uint8 or out.shape != image.shape[:2]):
        raise FrameError(f"grey output buffer must be uint8 {tuple(image.shape[:2])}, got {_describe(out)}")

    if code is None:
        grey = image[..., 0] if luma else image
        if out is None:
            return np.ascontiguousarray(grey) if luma else grey
        np.copyto(out, grey)
        return out
    result = cv2.cvtColor(image, code, dst=out)
    if out is not None and result is not out:
        # cv2 reallocates when it cannot write into dst as laid out (e.g. a strided view); keep the contract.
        np.copyto(out, result)
        return out
    return result


def to_bgr(image: np.ndarray) -> np.ndarray:
    """An image (one eye, or a whole side-by-side frame) in BGR, for what people look at: the preview, a
    recording, the calibration views. Not for the hot path: the pipeline needs only grey.

    Args:
        image: uint8 ``(H, W)`` grey, ``(H, W, 2)`` YUYV (``W`` even), ``(H, W, 3)`` BGR or ``(H, W, 4)``
            BGRA.

    Returns:
        uint8 ``(H, W, 3)`` BGR: ``image`` itself when it is BGR, else a new array (YUYV decoded as
        OpenCV's V4L2 capture decodes it, BT.601 video range).

    Raises:
        FrameError: any other dtype or shape, or a YUYV image of odd width.
    """
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
        got = _describe(image) if isinstance(image, np.ndarray) else type(image).__name__
        raise FrameError(f"image to show in colour must be uint8, got {got}")
    if image.ndim == 3 and image.shape[2] == 3:
        return image
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    if image.ndim == 3 and image.shape[2] == 2 and image.shape[1] % 2 == 0 and image.shape[0] > 0:
        return cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_YUV2BGR_YUYV)
    raise FrameError(
        f"image to show in colour must be (H, W), (H, W, 2) YUYV of even width, (H, W, 3) or (H, W, 4), "
        f"got {_describe(image)}"
    )


def check_pair(left: np.ndarray, right: np.ndarray) -> None:
    """Check that the two eye images of a pair have the same shape and dtype.

    Raises:
        FrameError: naming both sizes (``W x H``) and dtypes when they differ.
    """

    def size(a: np.ndarray) -> str:
        ch = f"x{a.shape[2]}" if a.ndim == 3 else ""
        return f"{a.shape[1]}x{a.shape[0]}{ch} {a.dtype}" if a.ndim >= 2 else f"shape {tuple(a.shape)} {a.dtype}"

    if left.shape != right.shape or left.dtype != right.dtype:
        raise FrameError(f"left and right images differ: left is {size(left)}, right is {size(right)}")


def split_frame(frame: np.ndarray, width_px: int, height_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Split a side-by-side frame and check each eye is ``width_px`` x ``height_px``.

    The one validation every estimator runs first (CPU and GPU alike).

    Returns:
        ``(left, right)`` views into ``frame``.

    Raises:
        FrameError: the frame is malformed (see :func:`split_side_by_side`), the eyes differ, or the
            eye size is not the configured one.
    """
    left, right = split_side_by_side(frame)
    check_pair(left, right)
    if left.shape[:2] != (height_px, width_px):
        raise FrameError(
            f"frame eye size {left.shape[1]}x{left.shape[0]} differs from the configured {width_px}x{height_px}"
        )
    return left, right
