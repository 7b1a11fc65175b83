"""The simulated scene: a validated :class:`SceneSpec` composed into a view, surfaces, tracer and images.

``Scene(spec)`` validates everything before rendering (ValueError naming the bad input), renders the
static images once, then gives the noisy frames (deterministic for a given ``spec.seed``) and the exact
ground truth of the target (occupancy, signed distance, centre of mass, outline) for the simulated
gripper and the evaluation, never for the perception pipeline.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from gpis_grasp_ros.core import noise_model
from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.sim.scene.polygons import (
    polygon_centroid,
    polygon_signed_distance,
    rasterise_polygon,
    validate_polygon,
)
from gpis_grasp_ros.sim.scene.raytrace import RayTracer
from gpis_grasp_ros.sim.scene.render import render_static
from gpis_grasp_ros.sim.scene.sensor import Frame, noisy_frames
from gpis_grasp_ros.sim.scene.spec import FRAME_ID, CameraModel, SceneSpec, check_rgb, validate_spec
from gpis_grasp_ros.sim.scene.surfaces import SurfaceRaster, shadow_shift
from gpis_grasp_ros.sim.scene.view import CameraPose, ImageWindow


@dataclass
class GroundTruth:
    """Ground truth at the table plane: occupancy (H, W) int8 (100 object, 0 free), signed distance
    (H, W) float32 m (positive outside), their ``geometry`` (z = table depth), centre of mass (x, y, z)
    in m and the outline (N, 2) in m; ``obstacles`` (H, W) float32 m, the signed distance to the distractors
    (None without any): the world the jaws move in, as a real capture's truth has its other objects."""

    geometry: GridGeometry
    occupancy: np.ndarray
    sdf: np.ndarray
    center_of_mass: np.ndarray
    outline: np.ndarray
    obstacles: np.ndarray | None = None


class Scene:
    """A validated scene with its static rendering precomputed.

    Parts: ``pose`` (:class:`CameraPose`), ``window`` (:class:`ImageWindow`, the cropped image),
    ``surfaces`` (:class:`SurfaceRaster`), ``tracer`` (:class:`RayTracer`) and ``static`` (the
    noise-free images, :class:`~gpis_grasp_ros.sim.scene.render.StaticImage`). :meth:`frames` yields
    the noisy frames, :meth:`ground_truth` the exact shape.
    """

    def __init__(self, spec: SceneSpec) -> None:
        self.spec = spec
        validate_spec(spec)
        self.table_color = np.array(check_rgb(spec.table_color, 'table colour'), dtype=np.float64)
        self.object_color = np.array(check_rgb(spec.object_color, 'object colour'), dtype=np.float64)
        self.outline = validate_polygon(spec.outline, what='object outline')
        self.regions = [(r.kind, validate_polygon(r.polygon, what=f"region {i} ('{r.kind}')"))
                        for i, r in enumerate(spec.regions)]
        region_colors = [self.object_color if r.color is None else
                         np.array(check_rgb(r.color, f"region {i} ('{r.kind}') colour"), dtype=np.float64)
                         for i, r in enumerate(spec.regions)]
        self.distractors = [(validate_polygon(d.outline, what=f'distractor {j} outline'), float(d.height), d.kind,
                             np.array(check_rgb(d.color, f'distractor {j} colour'), dtype=np.float64))
                            for j, d in enumerate(spec.distractors)]
        self.sensor_model = noise_model.SensorModel.named(spec.sensor)
        self.camera = spec.camera if spec.camera is not None else CameraModel()
        self.pose = CameraPose(spec)
        self.table_depth = self.pose.table_depth
        self.top_depth = float(spec.camera_height - spec.height)
        hmax = max([float(spec.height)] + [d[1] for d in self.distractors])
        band = float(spec.camera_height) - float(spec.camera_height - hmax)  # = hmax (as a depth difference)
        shift = shadow_shift(spec.light)
        self.surfaces = SurfaceRaster(self.outline, float(spec.height), self.regions, region_colors,
                                      self.distractors, self.table_color, self.object_color, self.table_depth,
                                      hmax, shift)
        in_view = [(self.outline, float(spec.height)), (self.outline, 0.0)]
        for poly, height, *_rest in self.distractors:
            in_view += [(poly, height), (poly, 0.0)]
        if shift is not None:  # keep the target's shadow in view
            in_view.append((self.outline + float(spec.height) * shift, 0.0))
        self.window = ImageWindow(self.pose, self.camera, spec, in_view)
        self.tracer = RayTracer(self.pose, self.surfaces, band, float(spec.height), self.camera.projector_baseline)
        self._rng = np.random.default_rng(int(spec.seed))
        self.static = render_static(self._rng, self.window, self.tracer, self.table_color,
                                    float(spec.shadow_strength))
        #: fraction of each pixel showing the table in the light's cast shadow (0 without a light)
        self.shadow_fraction = self.static.shadow_fraction

    @property
    def intrinsics(self) -> tuple[float, float, float, float, int, int]:
        """Cropped pinhole intrinsics ``(fx, fy, cx, cy, width, height)`` in px."""
        return self.window.intrinsics

    def stamp_ns(self, index: int) -> int:
        """Header stamp (ns) of frame ``index``: ``start_ns`` + (index + 1) / frame_rate.

        Frame 0 comes one period after ``start_ns``, when the ground truth is stamped."""
        return int(self.spec.start_ns) + int(round((index + 1) * 1e9 / self.spec.frame_rate))

    def frames(self) -> Iterator[Frame]:
        """The ``spec.frames`` noisy frames in order (a fresh, deterministic pass on every call)."""
        stamps = [self.stamp_ns(i) for i in range(int(self.spec.frames))]
        yield from noisy_frames(self.static, self._rng.bit_generator.state, self.spec.sensor, self.sensor_model,
                                self.table_depth, stamps)

    def ground_truth(self) -> GroundTruth:
        """Exact shape of the target on a ``gt_resolution`` grid in the table plane covering it plus
        ``gt_margin`` (m). The grid's pose (rotation, plane distance) is in its geometry; its (x, y) are
        table-frame coordinates minus the camera's (X, Y) (:mod:`~gpis_grasp_ros.sim.scene.view`)."""
        res, margin = float(self.spec.gt_resolution), float(self.spec.gt_margin)
        if not res > 0 or margin < 0:
            raise ValueError(f'ground-truth resolution must be positive and margin >= 0, got {res}, {margin}')
        lo = np.floor((self.outline.min(axis=0) - margin) / res) * res
        hi = np.ceil((self.outline.max(axis=0) + margin) / res) * res
        w, h = (int(round(v)) for v in (hi - lo) / res)
        table_geom = GridGeometry(float(lo[0]), float(lo[1]), res, w, h, self.table_depth, FRAME_ID)
        occ = np.where(rasterise_polygon(self.outline, table_geom), 100, 0).astype(np.int8)
        sdf = polygon_signed_distance(table_geom.cell_centers(), self.outline).astype(np.float32)
        obstacles = None
        if self.distractors:
            obstacles = np.minimum.reduce([polygon_signed_distance(table_geom.cell_centers(), poly)
                                           for poly, *_rest in self.distractors]).astype(np.float32)
        if self.spec.top_down:
            geom = table_geom
            com = np.append(polygon_centroid(self.outline), self.table_depth)
        else:
            c = self.pose.c
            geom = GridGeometry(float(lo[0] - c[0]), float(lo[1] - c[1]), res, w, h, self.table_depth,
                                FRAME_ID, self.pose.grid_rotation)
            com = self.pose.table_to_camera(polygon_centroid(self.outline))
        return GroundTruth(geom, occ, sdf, com, self.outline.copy(), obstacles)

    def describe(self) -> dict[str, Any]:
        """JSON-able summary of the scene (stored as bag metadata)."""
        s = self.spec
        out: dict[str, Any] = {
            'name': s.name, 'height_m': float(s.height), 'camera_height_m': float(s.camera_height),
            'frames': int(s.frames), 'seed': int(s.seed), 'table_color': [int(v) for v in self.table_color],
            'object_color': [int(v) for v in self.object_color],
            'regions': [r.kind for r in s.regions], 'intrinsics': list(self.intrinsics),
            'crop_offset_px': [self.window.u0, self.window.v0], 'frame_id': FRAME_ID,
            'outline_vertices': len(self.outline),
        }
        if not s.top_down:
            out.update({'camera_tilt_deg': float(s.camera_tilt), 'camera_azimuth_deg': float(s.camera_azimuth),
                        'table_normal_camera': [float(v) for v in -self.pose.r_tc[2]],
                        'table_distance_m': self.table_depth})
        if s.light is not None:
            out.update({'light_azimuth_elevation_deg': [float(v) for v in s.light],
                        'shadow_strength': float(s.shadow_strength)})
        if self.distractors:
            out['distractors'] = [{'kind': kind, 'height_m': height, 'color': [int(v) for v in color],
                                   'outline_m': np.round(poly, 6).tolist()}
                                  for poly, height, kind, color in self.distractors]
        if s.sensor != 'carmine':
            out['sensor'] = s.sensor
        return out
