"""Planar convex faces of a scene, as flat arrays the renderer can cull in one vectorised pass."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.sim.render.scene import TEXTURED, Box, Pillar, Scene, Surface
from companion.sim.render.texture import Material


@dataclass(frozen=True)
class FaceArrays:
    """Every face of a scene. Face ``i`` owns vertices ``verts[starts[i] : starts[i] + counts[i]]``.

    Attributes:
        verts: float64 ``(Nv, 3)``, NED metres, each face's vertices in cyclic order (convex).
        starts, counts: int64 ``(Nf,)``.
        normal: float64 ``(Nf, 3)``, unit, pointing to the side the face is seen from.
        offset: float64 ``(Nf,)``: the plane is ``normal . p = offset``; a camera at ``c`` sees the
            face iff ``normal . c > offset``.
        origin, axis_s, axis_t: float64 ``(Nf, 3)``: texture frame; texture coordinates (metres) of a
            point ``p`` on the face are ``axis_s . (p - origin)`` and ``axis_t . (p - origin)``.
        material: int64 ``(Nf,)``, :class:`Material` values.
        surface: int64 ``(Nf,)``, index into ``surfaces`` of the face's :class:`Surface` (its bar
            pattern, see-through, gloss).
        surfaces: the distinct surfaces, ``surfaces[0]`` the default :data:`TEXTURED`.
    """

    verts: np.ndarray
    starts: np.ndarray
    counts: np.ndarray
    normal: np.ndarray
    offset: np.ndarray
    origin: np.ndarray
    axis_s: np.ndarray
    axis_t: np.ndarray
    material: np.ndarray
    surface: np.ndarray
    surfaces: tuple[Surface, ...]

    @property
    def n_faces(self) -> int:
        return int(self.starts.shape[0])


class _Builder:
    def __init__(self) -> None:
        self.verts: list[np.ndarray] = []
        self.counts: list[int] = []
        self.normal: list[np.ndarray] = []
        self.origin: list[np.ndarray] = []
        self.axis_s: list[np.ndarray] = []
        self.axis_t: list[np.ndarray] = []
        self.material: list[int] = []
        self.surface: list[int] = []
        self.surfaces: list[Surface] = [TEXTURED]
        self._surface_index: dict[Surface, int] = {TEXTURED: 0}
        self._current_surface = 0

    def polygon(self, verts: np.ndarray, normal: np.ndarray, axis_s: np.ndarray, material: int) -> None:
        verts = np.asarray(verts, dtype=np.float64)
        normal = np.asarray(normal, dtype=np.float64)
        axis_s = np.asarray(axis_s, dtype=np.float64)
        self.verts.append(verts)
        self.counts.append(verts.shape[0])
        self.normal.append(normal)
        self.origin.append(verts[0])
        self.axis_s.append(axis_s)
        self.axis_t.append(np.cross(normal, axis_s))
        self.material.append(int(material))
        self.surface.append(self._current_surface)

    def quad(
        self, centre: np.ndarray, normal: np.ndarray, axis_s: np.ndarray, axis_t: np.ndarray,
        half_s: float, half_t: float, material: int,
    ) -> None:
        corners = [(-1, -1), (1, -1), (1, 1), (-1, 1)]
        verts = np.array([centre + a * half_s * axis_s + b * half_t * axis_t for a, b in corners])
        self.polygon(verts, normal, axis_s, material)

    def box(self, box: Box) -> None:
        c = np.asarray(box.centre_ned_m)
        ax = box.axes()
        half = 0.5 * np.asarray(box.size_m)
        surface = box.surface
        index = self._surface_index.setdefault(surface, len(self.surfaces))
        if index == len(self.surfaces):
            self.surfaces.append(surface)
        self._current_surface = index
        # Side faces have a horizontal s axis (bars vary along s: vertical bars); top and bottom of
        # a bar box are plain (a rail's top).
        side = {"textured": Material.OBSTACLE, "plain": Material.PLAIN, "bars": Material.BARS}[surface.kind]
        for k in range(3):
            s_axis, t_axis = (1, 2) if k == 0 else ((0, 2) if k == 1 else (0, 1))
            material = side if k < 2 or surface.kind != "bars" else Material.PLAIN
            for sign in (1.0, -1.0):
                n = sign * ax[k]
                self.quad(c + half[k] * n, n, ax[s_axis], ax[t_axis], half[s_axis], half[t_axis], material)
        self._current_surface = 0

    def pillar(self, p: Pillar) -> None:
        c = np.asarray(p.centre_ned_m)
        step = 2.0 * math.pi / p.sides
        half_edge = p.radius_m * math.tan(math.pi / p.sides)
        down = np.array([0.0, 0.0, 1.0])
        for j in range(p.sides):
            n = np.array([math.cos(j * step), math.sin(j * step), 0.0])
            tangent = np.array([-n[1], n[0], 0.0])
            self.quad(c + p.radius_m * n, n, tangent, down, half_edge, 0.5 * p.height_m, Material.OBSTACLE)
        r_vertex = p.radius_m / math.cos(math.pi / p.sides)
        ang = (np.arange(p.sides) + 0.5) * step
        ring = np.stack([r_vertex * np.cos(ang), r_vertex * np.sin(ang), np.zeros_like(ang)], axis=1)
        east = np.array([1.0, 0.0, 0.0])
        top = c + ring - np.array([0.0, 0.0, 0.5 * p.height_m])
        bottom = c + ring + np.array([0.0, 0.0, 0.5 * p.height_m])
        self.polygon(top, -down, east, Material.OBSTACLE)
        self.polygon(bottom[::-1], down, east, Material.OBSTACLE)

    def world_box(self, scene: Scene) -> None:
        """Inward-facing faces of the backdrop box (the floor is the ground when there is one)."""
        cn, ce = scene.backdrop_centre_ne_m
        r = scene.backdrop_half_size_m
        z0, z1 = scene.top_z_m, scene.floor_z_m
        zc, hz = 0.5 * (z0 + z1), 0.5 * (z1 - z0)
        ex, ey, ez = np.eye(3)
        floor_mat = Material.GROUND if scene.ground else Material.SKY
        top_mat = Material.OBSTACLE if scene.ceiling_altitude_m is not None else Material.SKY
        self.quad(np.array([cn, ce, z1]), -ez, ex, ey, r, r, floor_mat)
        self.quad(np.array([cn, ce, z0]), ez, ex, ey, r, r, top_mat)
        self.quad(np.array([cn + r, ce, zc]), -ex, ey, ez, r, hz, Material.SKY)
        self.quad(np.array([cn - r, ce, zc]), ex, ey, ez, r, hz, Material.SKY)
        self.quad(np.array([cn, ce + r, zc]), -ey, ex, ez, r, hz, Material.SKY)
        self.quad(np.array([cn, ce - r, zc]), ey, ex, ez, r, hz, Material.SKY)

    def build(self) -> FaceArrays:
        counts = np.asarray(self.counts, dtype=np.int64)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        normal = np.asarray(self.normal)
        origin = np.asarray(self.origin)
        arrays = FaceArrays(
            verts=np.concatenate(self.verts, axis=0),
            starts=starts,
            counts=counts,
            normal=normal,
            offset=np.einsum("ij,ij->i", normal, origin),
            origin=origin,
            axis_s=np.asarray(self.axis_s),
            axis_t=np.asarray(self.axis_t),
            material=np.asarray(self.material, dtype=np.int64),
            surface=np.asarray(self.surface, dtype=np.int64),
            surfaces=tuple(self.surfaces),
        )
        for a in (arrays.verts, arrays.starts, arrays.counts, arrays.normal, arrays.offset,
                  arrays.origin, arrays.axis_s, arrays.axis_t, arrays.material, arrays.surface):
            a.setflags(write=False)
        return arrays


def scene_faces(scene: Scene) -> FaceArrays:
    """All faces of ``scene``: the world box's six first, then each obstacle's (boxes 6, pillars n+2)."""
    b = _Builder()
    b.world_box(scene)
    for ob in scene.obstacles:
        if isinstance(ob, Box):
            b.box(ob)
        else:
            b.pillar(ob)
    return b.build()
