"""Synthetic stereo renderer: textured boxes, pillars, ground and backdrop, and the hard surfaces
(plain walls, bars, glare: :class:`Surface`); exact rectified stereo pairs with the left eye's
ground-truth depth. Pure core (NumPy/OpenCV only). ``target``: flat boards
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
)
from companion.sim.render.scene import TEXTURED, Box, Obstacle, Pillar, Scene, Surface, corridor_scene
from companion.sim.render.target import PlanarTarget, TargetCamera, chessboard_target
from companion.sim.render.texture import BarPattern, Material, TextureBank

__all__ = [
    "CAMERA_TO_BODY",
    "TEXTURED",
    "BarPattern",
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
    "Surface",
    "TargetCamera",
    "TextureBank",
    "chessboard_target",
    "corridor_scene",
]
