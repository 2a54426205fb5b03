"""Recorded stereo sequences read as left/right pairs: ASL/EuRoC folders and rosbags.

* **ASL/EuRoC** (``mav0/cam0/data.csv`` + ``mav0/cam0/data/*.png``, the same for ``cam1``; the folder
  given may be the one holding ``mav0`` or ``mav0`` itself): ``data.csv`` rows are
  ``timestamp_ns,filename``; ``cam0`` is the left eye. ``camN/sensor.yaml`` gives the calibration
  (:mod:`companion.calib.importers`).
* **rosbags** through the ``rosbags`` library (``pip install 'companion[recorded]'``): a ROS 1 ``.bag``,
  or a ROS 2 bag (its folder with ``metadata.yaml``, or the ``.db3``/``.mcap`` in it). Two image topics
  (``sensor_msgs/Image`` mono8, bgr8, rgb8, bgra8, rgba8, or ``sensor_msgs/CompressedImage``), named or
  found (a topic with ``left``/``cam0``/``infra1`` in its name and its ``right``/``cam1``/``infra2``
  twin; rectified ones first); the ``camera_info`` topics beside them give the calibration.

Pairs are matched by timestamp (the images' own ``header.stamp`` in a bag): a left and a right frame
within ``max_skew_ns`` make a pair; a frame with no partner is counted as unmatched and skipped. A
pause between pairs longer than 1.5 times the median period is a gap; :class:`SequenceReport` keeps
them for the user.
"""

from __future__ import annotations

import contextlib
import csv
import heapq
import logging
import re
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np

from companion.errors import CalibrationError, FrameError, InputError

__all__ = [
    "BAG_SUFFIXES",
    "AslSequence",
    "BagSequence",
    "PairMatcher",
    "SequenceReport",
    "StereoPair",
    "is_sequence",
    "open_sequence",
    "side_by_side",
]

log = logging.getLogger(__name__)

BAG_SUFFIXES: Final[tuple[str, ...]] = (".bag", ".db3", ".mcap")
_LEFT_RIGHT: Final[tuple[tuple[str, str], ...]] = (("left", "right"), ("cam0", "cam1"), ("infra1", "infra2"))
_IMAGE_TYPES: Final[tuple[str, ...]] = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")


@dataclass(frozen=True)
class StereoPair:
    """One matched pair.

    Attributes:
        timestamp_ns: the left frame's time, nanoseconds (the recording's clock).
        left, right: uint8 ``(H, W)`` grey or ``(H, W, 3)`` BGR images.
        index: 0-based count of pairs so far.
    """

    timestamp_ns: int
    left: np.ndarray
    right: np.ndarray
    index: int


@dataclass
class SequenceReport:
    """What reading a sequence found, beyond its pairs (filled in as it is read).

    Attributes:
        pairs: pairs delivered.
        unmatched_left, unmatched_right: frames with no partner within the skew, skipped.
        bad_frames: one line each: a frame that could not be decoded (skipped).
        gaps: ``(time_s from the first pair, length_s)`` of each pause longer than 1.5 median periods.
        period_s: the median time between pairs, seconds (None before three pairs).
    """

    pairs: int = 0
    unmatched_left: int = 0
    unmatched_right: int = 0
    bad_frames: list[str] = field(default_factory=list)
    gaps: list[tuple[float, float]] = field(default_factory=list)
    period_s: float | None = None
    _times_ns: list[int] = field(default_factory=list, repr=False)

    def add_pair_time(self, t_ns: int) -> None:
        self._times_ns.append(t_ns)
        self.pairs += 1

    def finish(self) -> None:
        """Compute the period and the gaps from the pairs' times."""
        t = np.asarray(self._times_ns, dtype=np.int64)
        if t.size < 3:
            return
        dt = np.diff(t) / 1e9
        self.period_s = float(np.median(dt))
        big = np.nonzero(dt > 1.5 * self.period_s)[0]
        self.gaps = [(float((t[i] - t[0]) / 1e9), float(dt[i])) for i in big]

    def summary(self) -> str:
        """One line for the user."""
        rate = f", {1.0 / self.period_s:.1f} Hz" if self.period_s else ""
        parts = [f"{self.pairs} pairs{rate}"]
        if self.unmatched_left or self.unmatched_right:
            parts.append(f"{self.unmatched_left} left and {self.unmatched_right} right frames with no partner")
        if self.gaps:
            longest = max(self.gaps, key=lambda g: g[1])
            parts.append(f"{len(self.gaps)} gaps (longest {longest[1]:.2f} s at {longest[0]:.1f} s)")
        if self.bad_frames:
            parts.append(f"{len(self.bad_frames)} undecodable frames skipped")
        return ", ".join(parts)


class PairMatcher:
    """Pairs two time-ordered streams by timestamp: a left and a right item within ``max_skew_ns``.

    :meth:`push` items of either side as they come; it returns the pairs that became complete. An
    item older than the other side's oldest by more than the skew can never be matched and is dropped
    (counted in the report).
    """

    def __init__(self, max_skew_ns: int, report: SequenceReport) -> None:
        self.max_skew_ns = int(max_skew_ns)
        self.report = report
        self._q: tuple[deque[tuple[int, Any]], deque[tuple[int, Any]]] = (deque(), deque())

    def push(self, side: int, t_ns: int, item: Any) -> list[tuple[int, Any, Any]]:
        """Add an item of ``side`` (0 left, 1 right); returns ``[(t_ns, left, right), ...]``."""
        self._q[side].append((int(t_ns), item))
        out = []
        ql, qr = self._q
        while ql and qr:
            (tl, left), (tr, right) = ql[0], qr[0]
            if abs(tl - tr) <= self.max_skew_ns:
                ql.popleft()
                qr.popleft()
                out.append((tl, left, right))
            elif tl < tr:
                ql.popleft()
                self.report.unmatched_left += 1
            else:
                qr.popleft()
                self.report.unmatched_right += 1
        return out

    def finish(self) -> None:
        """Count what is left waiting as unmatched."""
        self.report.unmatched_left += len(self._q[0])
        self.report.unmatched_right += len(self._q[1])
        self._q[0].clear()
        self._q[1].clear()


def side_by_side(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """The two eyes as one side-by-side frame: uint8 ``(H, 2W)`` when both are grey, else BGR
    ``(H, 2W, 3)``.

    Raises:
        FrameError: the eyes differ in size.
    """
    import cv2

    if left.shape[:2] != right.shape[:2]:
        raise FrameError(
            f"left is {left.shape[1]}x{left.shape[0]} but right is {right.shape[1]}x{right.shape[0]}"
        )
    if left.ndim != right.ndim:
        left = cv2.cvtColor(left, cv2.COLOR_GRAY2BGR) if left.ndim == 2 else left
        right = cv2.cvtColor(right, cv2.COLOR_GRAY2BGR) if right.ndim == 2 else right
    return np.ascontiguousarray(np.concatenate([left, right], axis=1))


# ------------------------------------------------------------------------------------------------ ASL


def _asl_root(path: Path) -> Path | None:
    """The folder holding ``cam0`` and ``cam1`` (``mav0``), or None."""
    for root in (path / "mav0", path):
        if (root / "cam0" / "data.csv").is_file() and (root / "cam1" / "data.csv").is_file():
            return root
    return None


def _read_data_csv(path: Path) -> list[tuple[int, Path]]:
    rows = []
    try:
        with path.open(encoding="utf-8", newline="") as f:
            for n, row in enumerate(csv.reader(f), start=1):
                if not row or row[0].lstrip().startswith("#"):
                    continue
                if len(row) < 2:
                    raise InputError(f"{path}:{n}: expected timestamp_ns,filename, got {','.join(row)!r}")
                try:
                    t = int(row[0].strip())
                except ValueError:
                    raise InputError(f"{path}:{n}: timestamp {row[0].strip()!r} is not an integer of nanoseconds") from None
                rows.append((t, path.parent / "data" / row[1].strip()))
    except OSError as err:
        raise InputError(f"{path}: cannot read it: {err.strerror or err}") from None
    rows.sort(key=lambda r: r[0])
    return rows


class AslSequence:
    """An ASL/EuRoC folder as stereo pairs (module doc).

    Args:
        path: the folder holding ``mav0``, or ``mav0``.
        max_skew_ns: the most a left and a right frame's times may differ to make a pair.

    Raises:
        InputError: not an ASL folder, or an unreadable ``data.csv``.
    """

    kind = "asl"

    def __init__(self, path: Path, max_skew_ns: int = 5_000_000) -> None:
        root = _asl_root(Path(path))
        if root is None:
            raise InputError(f"{path}: not an ASL/EuRoC folder (no mav0/cam0/data.csv and mav0/cam1/data.csv)")
        self.path = Path(path)
        self.root = root
        self.name = f"asl:{path}"
        self.max_skew_ns = int(max_skew_ns)
        self._left = _read_data_csv(root / "cam0" / "data.csv")
        self._right = _read_data_csv(root / "cam1" / "data.csv")
        if not self._left or not self._right:
            raise InputError(f"{path}: {'cam0' if not self._left else 'cam1'}/data.csv lists no frames")
        self.report = SequenceReport()
        self.topics = ("cam0", "cam1")

    @property
    def frame_count(self) -> int:
        """An upper bound of the pairs (the shorter eye's frames)."""
        return min(len(self._left), len(self._right))

    def calibration(self) -> Any:
        """The rig from ``cam0/sensor.yaml`` and ``cam1/sensor.yaml``, or None when they are absent.

        Raises:
            CalibrationError: they are there but wrong.
        """
        from companion.calib.importers import import_calibration

        files = [self.root / "cam0" / "sensor.yaml", self.root / "cam1" / "sensor.yaml"]
        if not all(f.is_file() for f in files):
            return None
        return import_calibration(files).calibration

    def _read(self, path: Path) -> np.ndarray | None:
        import cv2

        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None or image.dtype != np.uint8:
            why = "missing or not an image" if image is None else f"{image.dtype} pixels, not 8-bit"
            self.report.bad_frames.append(f"{path.name}: {why}")
            return None
        if image.ndim == 3 and image.shape[2] == 4:
            image = image[:, :, :3]
        return image

    def pairs(self) -> Iterator[StereoPair]:
        """The pairs in time order (decoded lazily); the report is complete when the iterator ends."""
        self.report = SequenceReport()
        matcher = PairMatcher(self.max_skew_ns, self.report)
        merged = heapq.merge(((t, 0, p) for t, p in self._left), ((t, 1, p) for t, p in self._right))
        for t, side, p in merged:
            for t_pair, lp, rp in matcher.push(side, t, p):
                left, right = self._read(lp), self._read(rp)
                if left is None or right is None:
                    continue
                self.report.add_pair_time(t_pair)
                yield StereoPair(t_pair, left, right, self.report.pairs - 1)
        matcher.finish()
        self.report.finish()

    def close(self) -> None:
        """Nothing to release (files are opened one at a time)."""


# ------------------------------------------------------------------------------------------------ rosbags


def _bag_paths(path: Path) -> list[Path]:
    """What AnyReader opens: a ROS 1 ``.bag`` file, or a ROS 2 bag's folder."""
    if path.is_dir():
        if not (path / "metadata.yaml").is_file():
            raise InputError(f"{path}: not a ROS 2 bag (no metadata.yaml) nor an ASL folder (no mav0/cam0/data.csv)")
        return [path]
    if path.suffix.lower() == ".bag":
        return [path]
    if path.suffix.lower() in (".db3", ".mcap"):
        if (path.parent / "metadata.yaml").is_file():
            return [path.parent]
        raise InputError(f"{path}: a ROS 2 bag is read from its folder with metadata.yaml, which is not beside it")
    raise InputError(f"{path}: not a recording this reader knows (an ASL folder, a .bag, or a ROS 2 bag folder)")


def _stamp_ns(msg: Any, fallback_ns: int) -> int:
    stamp = getattr(getattr(msg, "header", None), "stamp", None)
    if stamp is None:
        return fallback_ns
    sec = getattr(stamp, "sec", getattr(stamp, "secs", 0))
    nsec = getattr(stamp, "nanosec", getattr(stamp, "nsecs", 0))
    t = int(sec) * 1_000_000_000 + int(nsec)
    return t if t > 0 else fallback_ns


def decode_image(msg: Any, msgtype: str) -> np.ndarray:
    """A ``sensor_msgs/Image`` (mono8, bgr8, rgb8, bgra8, rgba8) or ``CompressedImage`` as uint8 grey
    ``(H, W)`` or BGR ``(H, W, 3)``.

    Raises:
        FrameError: another encoding, or data that does not fit the message's size.
    """
    import cv2

    data = np.frombuffer(bytes(msg.data) if not isinstance(msg.data, np.ndarray) else msg.data, dtype=np.uint8)
    if msgtype.endswith("CompressedImage"):
        image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
        if image is None or image.dtype != np.uint8:
            raise FrameError(f"a compressed image ({msg.format or 'no format'}) that OpenCV cannot decode to 8 bits")
        return image[:, :, :3] if image.ndim == 3 and image.shape[2] == 4 else image
    enc = str(msg.encoding).lower()
    channels = {"mono8": 1, "8uc1": 1, "bgr8": 3, "rgb8": 3, "8uc3": 3, "bgra8": 4, "rgba8": 4, "8uc4": 4}.get(enc)
    if channels is None:
        raise FrameError(f"image encoding {msg.encoding!r} is not one the replay reads (mono8, bgr8, rgb8, bgra8, rgba8)")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if step < w * channels or data.size < h * step:
        raise FrameError(f"a {w}x{h} {msg.encoding} image with step {step} holds {data.size} bytes")
    rows = data[: h * step].reshape(h, step)[:, : w * channels]
    if channels == 1:
        return np.ascontiguousarray(rows)
    image = rows.reshape(h, w, channels)
    if enc.startswith("rgb"):
        return cv2.cvtColor(image, cv2.COLOR_RGB2BGR if channels == 3 else cv2.COLOR_RGBA2BGR)
    return np.ascontiguousarray(image[:, :, :3])


def pick_topics(image_topics: list[str]) -> tuple[str, str] | None:
    """The left and right image topics among ``image_topics``, or None when they cannot be told."""
    pairs = []
    for topic in image_topics:
        for left, right in _LEFT_RIGHT:
            if left in topic:
                twin = topic.replace(left, right)
                if twin in image_topics and twin != topic:
                    pairs.append((topic, twin))
    if not pairs:
        return None
    # Rectified, then grey, then the shortest names: the ZED wrapper's left/image_rect_gray first.
    pairs.sort(key=lambda p: ("rect" not in p[0], not re.search(r"gr[ae]y|mono", p[0]), len(p[0]), p[0]))
    return pairs[0]


class BagSequence:
    """A rosbag's two image topics as stereo pairs (module doc).

    Args:
        path: a ``.bag``, a ROS 2 bag folder, or the ``.db3``/``.mcap`` in one.
        left_topic, right_topic: the image topics; None = found (:func:`pick_topics`).
        max_skew_ns: the most a left and a right frame's stamps may differ to make a pair.

    Raises:
        InputError: the rosbags library is missing, the bag cannot be read, or the topics are not there.
    """

    kind = "rosbag"

    def __init__(
        self, path: Path, left_topic: str | None = None, right_topic: str | None = None, max_skew_ns: int = 5_000_000
    ) -> None:
        try:
            from rosbags.highlevel import AnyReader
        except ImportError:
            raise InputError(
                f"{path}: reading rosbags needs the rosbags library: pip install 'companion[recorded]'"
            ) from None
        self.path = Path(path)
        self.name = f"rosbag:{path}"
        self.max_skew_ns = int(max_skew_ns)
        self.report = SequenceReport()
        self._reader_cls = AnyReader
        self._paths = _bag_paths(self.path)
        with self._open() as reader:
            types = {c.topic: c.msgtype for c in reader.connections}
            counts = {t: 0 for t in types}
            for c in reader.connections:
                counts[c.topic] += c.msgcount
        images = sorted(t for t, m in types.items() if m in _IMAGE_TYPES)
        if (left_topic is None) != (right_topic is None):
            raise InputError("give both --left-topic and --right-topic, or neither")
        if left_topic is None:
            found = pick_topics(images)
            if found is None:
                raise InputError(
                    f"{path}: cannot tell the left and right image topics apart among {', '.join(images) or 'no image topics'}; "
                    "name them (--left-topic, --right-topic)"
                )
            left_topic, right_topic = found
        for topic in (left_topic, right_topic):
            if topic not in types:
                raise InputError(f"{path}: no topic {topic} (image topics: {', '.join(images) or 'none'})")
            if types[topic] not in _IMAGE_TYPES:
                raise InputError(f"{path}: {topic} is {types[topic]}, not sensor_msgs/Image or CompressedImage")
        assert right_topic is not None
        self.topics = (left_topic, right_topic)
        self._types = types
        self._counts = counts

    @contextlib.contextmanager
    def _open(self) -> Iterator[Any]:
        try:
            reader = self._reader_cls(self._paths)
            reader.open()
        except Exception as exc:  # rosbags raises its own error types per format; one line names the file
            raise InputError(f"{self.path}: cannot read the bag: {type(exc).__name__}: {exc}") from None
        try:
            yield reader
        finally:
            reader.close()

    @property
    def frame_count(self) -> int:
        """An upper bound of the pairs (the shorter topic's messages)."""
        return min(self._counts[self.topics[0]], self._counts[self.topics[1]])

    def _info_topic(self, image_topic: str) -> str:
        # image_transport's compressed topics are <image topic>/compressed (or compressedDepth, theora).
        base = re.sub(r"/(compressed|compressedDepth|theora)$", "", image_topic)
        return base.rsplit("/", 1)[0] + "/camera_info"

    def calibration(self) -> Any:
        """The rig from the first message of the ``camera_info`` topic beside each image topic, or None
        when there are none.

        Raises:
            CalibrationError: they are there but do not describe a stereo rig the pipeline can rectify.
        """
        from companion.calib.importers import camera_info_calibration

        topics = [self._info_topic(t) for t in self.topics]
        if not all(self._types.get(t) == "sensor_msgs/msg/CameraInfo" for t in topics):
            return None
        first: dict[str, Any] = {}
        with self._open() as reader:
            conns = [c for c in reader.connections if c.topic in topics]
            for conn, _t, raw in reader.messages(connections=conns):
                if conn.topic not in first:
                    msg = reader.deserialize(raw, conn.msgtype)
                    first[conn.topic] = {
                        name: getattr(msg, name) for name in ("k", "d", "r", "p", "K", "D", "R", "P", "width", "height", "distortion_model")
                        if hasattr(msg, name)
                    }
                if len(first) == 2:
                    break
        if len(first) < 2:
            return None
        calib, swapped = camera_info_calibration(first[topics[0]], first[topics[1]], topics[0], topics[1])
        if swapped:
            raise CalibrationError(
                f"{self.path}: {topics[1]} has no baseline in P but {topics[0]} has: the image topics are the wrong way "
                f"round; give --left-topic {self.topics[1]} --right-topic {self.topics[0]}"
            )
        return calib

    def pairs(self) -> Iterator[StereoPair]:
        """The pairs in time order (decoded lazily); the report is complete when the iterator ends."""
        self.report = SequenceReport()
        matcher = PairMatcher(self.max_skew_ns, self.report)
        side_of = {self.topics[0]: 0, self.topics[1]: 1}
        with self._open() as reader:
            conns = [c for c in reader.connections if c.topic in side_of]
            for conn, t_bag, raw in reader.messages(connections=conns):
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                except Exception as exc:  # a damaged message is one bad frame, not the end of the replay
                    self.report.bad_frames.append(f"{conn.topic} at {t_bag} ns: cannot deserialize ({type(exc).__name__})")
                    continue
                for t_pair, lm, rm in matcher.push(side_of[conn.topic], _stamp_ns(msg, t_bag), (conn.msgtype, msg)):
                    try:
                        left, right = decode_image(lm[1], lm[0]), decode_image(rm[1], rm[0])
                    except FrameError as err:
                        self.report.bad_frames.append(f"pair at {t_pair} ns: {err}")
                        continue
                    self.report.add_pair_time(t_pair)
                    yield StereoPair(t_pair, left, right, self.report.pairs - 1)
        matcher.finish()
        self.report.finish()

    def close(self) -> None:
        """Nothing held between reads (the bag is opened for each pass)."""


# ------------------------------------------------------------------------------------------------ entry


def is_sequence(path: Path) -> bool:
    """True for what :func:`open_sequence` reads: an ASL folder, a ``.bag``/``.db3``/``.mcap``, or a ROS 2
    bag's folder."""
    path = Path(path)
    if path.is_dir():
        return _asl_root(path) is not None or (path / "metadata.yaml").is_file()
    return path.suffix.lower() in BAG_SUFFIXES


def open_sequence(
    path: Path, *, left_topic: str | None = None, right_topic: str | None = None, max_skew_ms: float = 5.0
) -> AslSequence | BagSequence:
    """An ASL folder or a rosbag as stereo pairs.

    Raises:
        InputError: no such path, or not a recording of either kind (one line saying what was looked for).
    """
    path = Path(path).expanduser()
    if not path.exists():
        raise InputError(f"{path}: no such file or folder")
    skew_ns = int(round(max_skew_ms * 1e6))
    if path.is_dir() and _asl_root(path) is not None:
        if left_topic is not None or right_topic is not None:
            raise InputError(f"{path}: an ASL folder has no topics (cam0 is left, cam1 right); leave out --left-topic/--right-topic")
        return AslSequence(path, skew_ns)
    return BagSequence(path, left_topic, right_topic, skew_ns)
