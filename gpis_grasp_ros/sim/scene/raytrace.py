"""Ray casting through the scene's prisms: first hits, walls, see-through, projector shadows.

Rays are traced in the table frame T by marching each pixel ray from the tallest top down to the table
and sampling the surface-id raster, so any camera pose sees walls, occlusions and transparent parts
the way a perspective camera does.
"""

from __future__ import annotations

import math

import numpy as np

from gpis_grasp_ros.sim.scene.spec import L_TRANSPARENT
from gpis_grasp_ros.sim.scene.surfaces import HEIGHT_EPS_M, SurfaceRaster
from gpis_grasp_ros.sim.scene.view import CameraPose


class RayTracer:
    """Traces camera rays (slopes (..., 2)) of ``pose`` through ``surfaces``.

    ``band`` is the height (m) of the tallest top above the table (where marching starts),
    ``target_height`` the target's top (m), ``projector_baseline`` the projector's (D400: right
    imager's) offset along the camera's +x (m)."""

    CHUNK_SAMPLES = 4_000_000  # ray samples per block (bounds the tracer's memory)

    def __init__(self, pose: CameraPose, surfaces: SurfaceRaster, band: float, target_height: float,
                 projector_baseline: float) -> None:
        self.pose, self.surfaces = pose, surfaces
        self.band, self.target_height, self.projector_baseline = band, target_height, projector_baseline

    def _rows(self, rays: np.ndarray, k: int) -> list[slice]:
        """Row blocks of an (H, W, 2) ray array with about CHUNK_SAMPLES ray samples each."""
        per_row = max(1, int(np.prod(rays.shape[1:-1], dtype=np.int64)) * k)
        step = max(1, self.CHUNK_SAMPLES // per_row)
        return [slice(i, i + step) for i in range(0, rays.shape[0], step)]

    def trace(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """First hit of rays (H, W, 2) with the object and distractor prisms.

        Returns (surface id of the first non-transparent surface or 0 for the table, hit depth (m),
        is_wall, passed_transparent). Depths are marched from the tallest top to the table with a
        lateral step of at most two raster cells; a hit entered through a lower top face is placed
        exactly on that face.
        """
        dxy, dz = self.pose.ray_dirs(rays)
        cz = self.pose.c[2]
        t_top = (-self.surfaces.hmax - cz) / dz
        t_table = (0.0 - cz) / dz
        reach = float(np.max(np.abs(dxy) * (t_table - t_top)[..., None]))
        k = max(2, int(math.ceil(reach / (2 * self.surfaces.RESOLUTION))) + 1)
        out = [np.zeros(rays.shape[:-1], dtype=self.surfaces.ids.dtype), np.zeros(rays.shape[:-1]),
               np.zeros(rays.shape[:-1], dtype=bool), np.zeros(rays.shape[:-1], dtype=bool)]
        for rows in self._rows(rays, k):
            parts = self._block(dxy[rows], dz[rows], t_top[rows], t_table[rows], k)
            for o, p in zip(out, parts, strict=True):
                o[rows] = p
        return out[0], out[1], out[2], out[3]

    def _block(self, dxy: np.ndarray, dz: np.ndarray, t_top: np.ndarray, t_table: np.ndarray,
               k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        cxy, cz = self.pose.c[:2], self.pose.c[2]
        zs = np.linspace(t_top, t_table, k, axis=-1)
        ids = self.surfaces.lookup(cxy + dxy[..., None, :] * zs[..., :, None])  # (..., k)
        heights = -(cz + zs * dz[..., None])
        inside = self.surfaces.top_of_id[ids] >= heights - HEIGHT_EPS_M
        kinds = self.surfaces.kind_of_id[ids]
        solid = (kinds > 0) & (kinds != L_TRANSPARENT) & inside
        any_solid = solid.any(axis=-1)
        first = np.where(any_solid, np.argmax(solid, axis=-1), k - 1)
        hit = np.where(any_solid, np.take_along_axis(ids, first[..., None], axis=-1)[..., 0], 0)
        depth = np.where(any_solid, np.take_along_axis(zs, first[..., None], axis=-1)[..., 0], t_table)
        before = np.arange(k) < first[..., None]
        passed = np.any((kinds == L_TRANSPARENT) & inside & (before | ~any_solid[..., None]), axis=-1)
        # entered through a top face lower than the previous sample: put the hit on that face
        prev_h = np.take_along_axis(heights, np.maximum(first - 1, 0)[..., None], axis=-1)[..., 0]
        top_h = self.surfaces.top_of_id[hit]
        entered = any_solid & (first > 0) & (prev_h > top_h + HEIGHT_EPS_M)
        top_face = np.zeros_like(entered)
        if entered.any():
            t_face = (-top_h[entered] - cz) / dz[entered]
            face_id = self.surfaces.lookup(cxy + dxy[entered] * t_face[:, None])
            same = self.surfaces.obj_of_id[face_id] == self.surfaces.obj_of_id[hit[entered]]
            top_face[entered] = same
            depth[entered] = np.where(same, t_face, depth[entered])
        return hit, depth, any_solid & (first > 0) & ~top_face, passed

    def projector_shadow(self, rays: np.ndarray, label: np.ndarray) -> np.ndarray:
        """Table points (label 0) whose line to the IR projector (D400: the right imager) is blocked by a
        non-transparent object."""
        dxy, dz = self.pose.ray_dirs(rays)
        t_table = (0.0 - self.pose.c[2]) / dz
        table_pt = self.pose.c[:2] + dxy * t_table[..., None]
        proj_cam = np.array([self.projector_baseline, 0.0, 0.0])
        proj = self.pose.c + (proj_cam if self.pose.top_down else self.pose.r_tc @ proj_cam)
        travel = (proj[:2] - table_pt) * (self.band / -proj[2])  # lateral move up to the tallest top
        k = max(2, int(math.ceil(float(np.abs(travel).max()) / self.surfaces.RESOLUTION)) + 1)
        fractions = np.linspace(0.0, 1.0, k)[1:]
        blocked = np.zeros(rays.shape[:-1], dtype=bool)
        for rows in self._rows(rays, k):
            ids = self.surfaces.lookup(table_pt[rows][..., None, :] + travel[rows][..., None, :] * fractions[:, None])
            kinds = self.surfaces.kind_of_id[ids]
            inside = self.surfaces.top_of_id[ids] >= fractions * self.band - HEIGHT_EPS_M
            blocked[rows] = np.any((kinds > 0) & (kinds != L_TRANSPARENT) & inside, axis=-1)
        return blocked & (label == 0)

    def top_points(self, rays: np.ndarray) -> np.ndarray:
        """Table-frame (X, Y) where rays cross the plane of the target's top face."""
        dxy, dz = self.pose.ray_dirs(rays)
        t = (-self.target_height - self.pose.c[2]) / dz
        return self.pose.c[:2] + dxy * t[..., None]
