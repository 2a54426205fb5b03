"""Synthetic stereo renderer: textured boxes, pillars, ground and backdrop; exact rectified stereo
pairs with the left eye's ground-truth depth. Pure core (NumPy/OpenCV only). ``target``: flat boards
(chessboard, ChArUco, any texture) seen by raw, distorted cameras, for calibration.

Public API::

    from companion.sim.render import StereoRenderer, Scene, Box, Pillar, Pose
"""

from __future__ import annotations

from companion.core.pose import CAMERA_TO_BODY, Pose
from companion.sim.render.renderer import (
    Photometry,
    RenderResult,
    StereoRenderer,
    bench_render,
    bench_scene,
)
from companion.sim.render.scene import Box, Obstacle, Pillar, Scene, corridor_scene
from companion.sim.render.target import PlanarTarget, TargetCamera, chessboard_target
from companion.sim.render.texture import Material, TextureBank

__all__ = [
    "CAMERA_TO_BODY",
    "Box",
    "Material",
    "Obstacle",
    "Photometry",
    "Pillar",
    "PlanarTarget",
    "Pose",
    "RenderResult",
    "Scene",
    "StereoRenderer",
    "TargetCamera",
    "TextureBank",
    "bench_render",
    "bench_scene",
    "chessboard_target",
    "corridor_scene",
]
