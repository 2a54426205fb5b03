"""``companion demo``: the embedded default: fly one simulated course closed-loop and draw it."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from companion.errors import InputError

#: The demo's course (pitch, seed 1): a block across the whole view, its bottom 0.2 m under the vehicle's
#: top. Flown with the defaults (the local planner), the vehicle speeds up to about 2 m/s, sees the block
#: 2.2 m ahead, slows and descends under it (the fuzzy controller's "down", the paper's rule 2, is a term
#: of the planner's cost), passes with 0.26 m to spare, speeds up to 2.8 m/s and reaches the goal 11 m
#: on: an escape in one short, deterministic flight (6 s simulated).
#: The doorway (the paper's Fig. 10) shows neither: it is flown straight through.
DEMO_COURSE = ("pitch", 1)
#: Where the demo writes when no --out is given: relative to the working directory on purpose (it is
#: the user's "here"), resolved to an absolute path and printed.
DEFAULT_OUT = "companion-demo"


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``demo``."""
    p = sub.add_parser(
        "demo",
        help="fly one simulated course closed-loop (no hardware) and write its plot",
        description=(
            "Fly a simulated course closed-loop with the real pipeline: rendered ZED frames -> 9 region "
            "depths -> fuzzy decision -> setpoints -> a simulated multicopter. The default course (pitch, seed 1) "
            "puts a block across the way, too low to fly under at the start altitude: the vehicle (the "
            "local planner, up to 3 m/s) slows, escapes downward, passes under it and reaches the goal. Prints the decisions and the "
            "outcome, and writes the top-down and side-view plot and Fig. 10 overlay frames of the "
            "moments that tell (the first avoid, a brake if any, the nearest, the last) to the output "
            "directory."
        ),
    )
    p.add_argument("--out", type=Path, default=None, help=f"output directory (default ./{DEFAULT_OUT})")
    p.add_argument("--course", default=DEMO_COURSE[0], help=f"course kind (default {DEMO_COURSE[0]})")
    p.add_argument("--seed", type=int, default=DEMO_COURSE[1], help=f"course seed (default {DEMO_COURSE[1]})")
    p.add_argument("--config", type=Path, help="TOML config (default: built-in defaults)")
    p.add_argument("--verbose", action="store_true", help="also the controller's reasons (rules, memberships) per decision")
    from companion.cli.sim import add_view_options

    add_view_options(p)
    p.set_defaults(func=run)


class _OverlayPicker:
    """Keeps Fig. 10 overlays of a few telling frames: the first, the first of each AVOID or BRAKE
    episode (up to ``max_events``), the one with the nearest centre, and the last."""

    def __init__(self, layout: Any, near_m: float, far_m: float, max_disparity_px: float, max_events: int = 3):
        self.layout = layout
        self.near_m, self.far_m = near_m, far_m
        self.max_disp = max_disparity_px
        self.max_events = max_events
        self.first: tuple[str, Any] | None = None
        self.events: list[tuple[str, Any]] = []
        self.nearest: tuple[float, str, Any] | None = None
        self.last: tuple[str, Any] | None = None
        self._prev_kind: Any = None

    def __call__(self, frame: Any, result: Any) -> None:
        import math

        from companion.core.types import REGION_INDEX, DecisionKind

        kind = result.decision.kind
        label = f"t{frame.timestamp_s:05.2f}s_{kind.value}"
        if self.first is None:
            self.first = (label, self._snap(frame, result))
        elif kind is not DecisionKind.CLEAR and kind is not self._prev_kind and len(self.events) < self.max_events:
            self.events.append((label, self._snap(frame, result)))
        centre = float(result.refined.depth_m[REGION_INDEX["center"]])
        if not math.isnan(centre) and (self.nearest is None or centre < self.nearest[0]):
            self.nearest = (centre, label, self._snap(frame, result))
        self.last = (label, self._snap(frame, result))
        self._prev_kind = kind

    @staticmethod
    def _snap(frame: Any, result: Any) -> tuple[Any, Any]:
        """What drawing needs later (a copy of the frame: the camera may reuse its buffer); drawing
        waits until the flight is over, and only for the frames kept."""
        return frame.image.copy(), result

    def _draw(self, snap: tuple[Any, Any]) -> Any:
        import cv2

        from companion.core.overlay import draw_overlay
        from companion.core.regions import RegionLayout
        from companion.core.stereo import split_side_by_side

        image, result = snap
        left, _ = split_side_by_side(image)
        # Small simulated eyes: draw at twice the size so the labels stay legible.
        k = 2 if left.shape[1] < 600 else 1
        layout = RegionLayout(self.layout.row_edges * k, self.layout.col_edges * k)
        big = cv2.resize(left, None, fx=k, fy=k, interpolation=cv2.INTER_LINEAR)
        disp = result.disparity
        if disp is not None and k != 1:
            disp = cv2.resize(disp, None, fx=k, fy=k, interpolation=cv2.INTER_NEAREST)
        return draw_overlay(big, layout, result.shown_depths_m(), result.decision,
                            near_m=self.near_m, far_m=self.far_m, disparity=disp, max_disparity_px=self.max_disp,
                            filtered=result.filtered, legend=True)

    def images(self) -> list[tuple[str, Any]]:
        """(label, overlay image) of the frames kept, drawn now."""
        kept = [self.first] if self.first else []
        kept += self.events
        if self.nearest is not None:
            kept.append((self.nearest[1] + "_nearest", self.nearest[2]))
        if self.last is not None:
            kept.append((self.last[0] + "_last", self.last[1]))
        return [(label, self._draw(snap)) for label, snap in kept]


def run(args: argparse.Namespace) -> int:
    import time

    import cv2

    from companion.cli.process import _near_far_m
    from companion.cli.sim import describe_flight, write_plot
    from companion.config import load_config
    from companion.core.geometry import StereoGeometry
    from companion.core.regions import region_layout
    from companion.sim.courses import make_course
    from companion.sim.loop import LogKind, fly

    out_dir = (args.out if args.out is not None else Path.cwd() / DEFAULT_OUT).expanduser().resolve()
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(f"{out_dir}: cannot create the output directory: {err.strerror or err}") from None
    cfg = load_config(args.config)
    from companion.sim.loop import simulated_rig_check_lines

    for line in simulated_rig_check_lines(cfg):  # the simulated rig's, not the camera's
        print(f"companion demo: {line}", file=sys.stderr)
    course = make_course(args.course, args.seed)
    sim = cfg.sim
    geometry = StereoGeometry.ideal(
        sim.eye_width_px, sim.eye_height_px, cfg.calibration.ideal_hfov_deg, cfg.calibration.ideal_baseline_m
    )
    near_m, far_m = _near_far_m(cfg)
    picker = _OverlayPicker(region_layout(geometry, cfg.regions), near_m, far_m, float(cfg.stereo.num_disparities))

    bridge = None
    t0 = time.perf_counter()
    if args.view:
        from companion.cli.sim import print_view_urls
        from companion.view.simbridge import fly_with_view

        print(f"companion demo: flying {course.name} ({course.description}) closed-loop, in real time for the view")
        result, bridge = fly_with_view(course, cfg, host=args.view_host, port=args.view_port,
                                       title=f"companion demo: {course.name}", on_frame=picker, on_urls=print_view_urls)
    else:
        print(f"companion demo: flying {course.name} ({course.description}) closed-loop, in simulated time")
        result = fly(course, cfg, on_frame=picker, want_disparity=True)
    wall = time.perf_counter() - t0

    # The decisions as they changed (frame by frame: what the pipeline concluded and why).
    fl = result.frame_log
    assert fl is not None
    from companion.core.words import decision_words

    print("\n  time   north   east   alt  decision  yaw    pitch  what it does" + ("  [the controller's reason]" if args.verbose else ""))
    prev = None
    for i in range(len(fl.t_s)):
        key = (int(fl.kind[i]), fl.reason[i].split(" (")[0].split(":")[0])
        if key == prev:
            continue
        prev = key
        n, e, z = fl.position_ned_m[i]
        print(f"{fl.t_s[i]:6.2f}s {n:6.2f} {e:+6.2f} {-z:5.2f}  {LogKind(int(fl.kind[i])).name.lower():8s} "
              f"{fl.yaw[i]:+.2f}  {fl.pitch[i]:+.2f}  "
              f"{decision_words(LogKind(int(fl.kind[i])).name, fl.yaw[i], fl.pitch[i], fl.region_depths_m[i])}"
              + (f"  [{fl.reason[i]}]" if args.verbose else ""))
    print()
    for line in describe_flight(result):
        print(line)

    for stale in out_dir.glob("overlay_t*.png"):  # this command's own files from an earlier run
        stale.unlink()
    plot_path = out_dir / "flight.png"
    write_plot(result, plot_path, side_view=True)
    written = [plot_path]
    for label, image in picker.images():
        path = out_dir / f"overlay_{label}.png"
        if not cv2.imwrite(str(path), image):
            raise InputError(f"{path}: cannot write the overlay")
        written.append(path)
    print(f"\nwrote {len(written)} images to {out_dir}:")
    for path in written:
        print(f"  {path.name}")
    print(f"demo finished in {wall:.1f} s")
    if bridge is not None:
        from companion.cli.sim import finish_view

        finish_view(bridge, args.view_linger_s)
    return 0
