"""The table plane and the table frame, from a depth image seen by a tilted camera.

Frames and units (metres throughout):

* **Camera (sensor) frame**: the optical frame of the depth image, x right, y down, z along the
  optical axis. A pixel (u, v) with depth z is the point ((u - cx) z / fx, (v - cy) z / fy, z).
* **Table plane**: n . p + d = 0 with the unit normal n pointing to the camera side, so d > 0 is
  the camera's distance from the plane and h(p) = n . p + d is the height of p above the table.
* **Table frame** (:class:`TableFrame`): rotation R whose columns are the table frame's axes in
  the camera frame: z_t = -n (into the table, like the optical axis of a top-down camera and a
  gripper's approach), x_t = the camera's x axis projected into the plane, y_t = z_t x x_t. A
  camera point p has table coordinates (x, y) = (R^T p)[:2] and height d - (R^T p)[2]. A
  top-down camera (n = -z) gives R = I, so the table frame is the camera frame shifted along z.
  This is exactly :class:`~gpis_grasp_ros.core.grid.GridGeometry`'s pose (``rotation`` = R,
  ``z`` = d); grids in the table frame lie in the plane.

:func:`fit_table_plane` is a robust plane fit over the whole valid cloud (MSAC, Torr and
Zisserman 2000: RANSAC with a truncated quadratic cost), the inlier band taken from the sensor's
noise model at each point's depth, followed by least-squares refinement on the inliers. Random
triples are tried until an all-inlier triple is 99.9 % likely given the best plane's inlier
fraction w (log(0.001) / log(1 - w^3) triples, Fischler and Bolles 1981; at least
``min_iterations``, at most ``iterations``). The largest plane seen wins; a tilt (angle between
the optical axis and -n) above ``max_tilt_deg`` means the plane is seen edge-on and is rejected.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.noise_model import SensorModel


@dataclass(frozen=True)
class TableFrame:
    """Table plane n . p + d = 0 (camera frame, n unit towards the camera, d > 0 in m) and its frame."""

    normal: tuple[float, float, float]
    offset_m: float
    inlier_fraction: float = 1.0  # fraction of the fitted points within the inlier band (1 if given)
    rms_m: float = 0.0  # RMS point-to-plane distance of the inliers (m; 0 if given)

    @classmethod
    def from_plane(cls, a: float, b: float, c: float, d: float, **kwargs: float) -> TableFrame:
        """Plane a x + b y + c z + d = 0 (camera frame, m) → normalised, normal towards the camera."""
        coef = np.array([a, b, c, d], dtype=np.float64)
        if not np.isfinite(coef).all():
            raise ValueError(f'table plane must be 4 finite numbers (a, b, c, d), got {coef.tolist()}')
        norm = float(np.linalg.norm(coef[:3]))
        if norm < 1e-12:
            raise ValueError(f'table plane normal (a, b, c) must not be zero, got {coef.tolist()}')
        coef = coef / norm
        if coef[3] < 0:  # the camera (origin) must be on the positive side: n . 0 + d > 0
            coef = -coef
        if coef[3] <= 0:
            raise ValueError('table plane passes through the camera centre (d = 0)')
        return cls(tuple(float(v) for v in coef[:3]), float(coef[3]), **kwargs)

    @property
    def n(self) -> np.ndarray:
        """Unit normal (3,) in the camera frame, towards the camera."""
        return np.asarray(self.normal, dtype=np.float64)

    @property
    def tilt_deg(self) -> float:
        """Angle (deg) between the optical axis and the direction into the table (-n); 0 = top-down."""
        return float(np.degrees(np.arccos(np.clip(-self.n[2], -1.0, 1.0))))

    @property
    def rotation(self) -> np.ndarray:
        """R (3 x 3): table axes as columns in the camera frame (z = -n, x = camera x projected)."""
        z = -self.n
        x = np.array([1.0, 0.0, 0.0]) - z[0] * z
        if np.linalg.norm(x) < 1e-6:  # camera x along the normal (edge-on): use camera y instead
            x = np.array([0.0, 1.0, 0.0]) - z[1] * z
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        return np.stack([x, y, z], axis=1)

    def height(self, points: np.ndarray) -> np.ndarray:
        """Height (m) above the table of camera-frame points ``(..., 3)`` (positive towards the camera)."""
        return np.asarray(points, dtype=np.float64) @ self.n + self.offset_m

    def to_table(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame points ``(..., 3)`` → (table (x, y) of their orthographic foot ``(..., 2)``, height)."""
        return self.grid(0.0, 0.0, 1.0, 1, 1).from_sensor(points)

    def to_camera(self, xy: np.ndarray, height: float | np.ndarray = 0.0) -> np.ndarray:
        """Table (x, y) ``(..., 2)`` at ``height`` above the plane → camera-frame points ``(..., 3)``."""
        return self.grid(0.0, 0.0, 1.0, 1, 1).to_sensor(xy, height)

    def ray_intersection(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where camera rays ``(..., 3)`` (through the origin) meet the plane: (points (..., 3), hit mask).

        Rays parallel to the plane or pointing away from it do not hit (NaN points)."""
        rays = np.asarray(rays, dtype=np.float64)
        denom = rays @ self.n
        hit = denom < -1e-9
        if rays.ndim < 2:
            t = np.where(hit, -self.offset_m / np.where(hit, denom, -1.0), np.nan)
            return rays * t[..., None], hit
        points = np.empty(rays.shape)
        _ray_points(np.ascontiguousarray(rays).reshape(-1, 3), np.ascontiguousarray(denom).reshape(-1),
                    np.ascontiguousarray(hit).reshape(-1), -self.offset_m, points.reshape(-1, 3))
        return points, hit

    def grid(self, origin_x: float, origin_y: float, resolution: float, width: int, height: int,
             frame_id: str = '') -> GridGeometry:
        """A grid in the table plane with the given table-frame corner (m) and cell size (m)."""
        return GridGeometry(float(origin_x), float(origin_y), float(resolution), int(width), int(height),
                            float(self.offset_m), frame_id, tuple(float(v) for v in self.rotation.ravel()))

    def plane_coefficients(self) -> tuple[float, float, float, float]:
        """(a, b, c, d) with a x + b y + c z + d = 0, (a, b, c) = n."""
        return (*self.normal, self.offset_m)


@njit(cache=True, nogil=True)
def _ray_points(rays, denom, hit, neg_offset, out):
    """``rays * t`` with ``t = -offset / denom`` where the ray hits the plane, NaN where not (one pass)."""
    for k in range(denom.size):
        t = neg_offset / denom[k] if hit[k] else np.nan
        for c in range(3):
            out[k, c] = rays[k, c] * t


def _plane_from_three(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Planes through point triples ``(K, 3, 3)`` → (unit normals (K, 3), offsets (K,)); degenerate → 0 normal."""
    nrm = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    length = np.linalg.norm(nrm, axis=1)
    ok = length > 1e-12
    nrm = np.where(ok[:, None], nrm / np.where(ok, length, 1.0)[:, None], 0.0)
    d = -np.einsum('ij,ij->i', nrm, p[:, 0])
    return nrm, d


def _refine(points: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, float]:
    """Weighted total-least-squares plane through ``points`` (K, 3)."""
    w = weights / weights.sum()
    centroid = w @ points
    centred = (points - centroid) * np.sqrt(w)[:, None]
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    normal = vt[-1]
    return normal, float(-normal @ centroid)


@njit(cache=True, nogil=True)
def _usable_points(cloud, mask, out):
    """``out`` = ``mask`` and the point finite and in front of the camera (z > 0), for every row of ``cloud``."""
    for k in range(cloud.shape[0]):
        x, y, z = cloud[k, 0], cloud[k, 1], cloud[k, 2]
        out[k] = mask[k] and np.isfinite(x) and np.isfinite(y) and np.isfinite(z) and z > 0


def fit_table_plane(points: np.ndarray, model: SensorModel, *, band_sigmas: float = 3.0, band_floor_m: float = 0.002,
                    iterations: int = 300, min_iterations: int = 50, max_points: int = 10000,
                    score_points: int = 2000, min_inlier_fraction: float = 0.2, max_tilt_deg: float = 75.0,
                    seed: int = 0, mask: np.ndarray | None = None) -> TableFrame:
    """Robust plane fit (MSAC + least squares) to camera-frame points ``(K, 3)`` (m), or to those of an organised
    cloud ``(H, W, 3)`` where ``mask`` ``(H, W)`` holds (the same fit as of ``points[mask]``: the sample is drawn
    among the mask's pixels before their points are gathered).

    The inlier band of a point at depth z is max(band_floor_m, band_sigmas sigma_z(z)) of the
    sensor ``model``; the floor covers real tables that are not flat to the sensor's noise (cloth,
    wood grain) and the model's calibration error. The deterministic (``seed``) sample of at most
    ``max_points`` points is searched with up to ``iterations`` random triples (adaptive stop, see
    the module docstring), each scored on the first ``score_points`` of them (a random subset: the
    MSAC cost only has to rank the candidates); the best (lowest MSAC cost) plane is refined by weighted
    total least squares on its inliers among all the sampled points, three times.

    Raises:
        ValueError: fewer than 100 points; no plane holds ``min_inlier_fraction`` of the points;
            the plane is seen edge-on (tilt above ``max_tilt_deg``).
    """
    cloud = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    if mask is not None and np.size(mask) != cloud.shape[0]:
        raise ValueError(f'mask {np.shape(mask)} does not match the cloud {np.shape(points)}')
    keep = np.empty(cloud.shape[0], dtype=bool)
    _usable_points(cloud, np.ones(cloud.shape[0], dtype=bool) if mask is None else
                   np.ascontiguousarray(mask, dtype=bool).reshape(-1), keep)
    rows = np.flatnonzero(keep)  # the usable points, in order
    if rows.size < 100:
        raise ValueError(f'only {rows.size} valid depth points: cannot estimate the table plane '
                         '(give table_plane, or check the depth image)')
    rng = np.random.default_rng(seed)
    if rows.size > max_points:
        rows = rows[rng.choice(rows.size, max_points, replace=False)]
    pts = cloud[rows]
    band = np.maximum(band_floor_m, band_sigmas * model.sigma(pts[:, 2]))
    triples = pts[rng.integers(0, pts.shape[0], size=(iterations, 3))]
    subset = rng.permutation(pts.shape[0])[:score_points]
    score, score_band = pts[subset], band[subset]
    normals, offsets = _plane_from_three(triples)
    best_cost, best, needed = math.inf, None, iterations
    chunk = 25
    for s in range(0, iterations, chunk):
        if s >= needed:
            break
        nrm, off = normals[s:s + chunk], offsets[s:s + chunk]
        good = np.linalg.norm(nrm, axis=1) > 0
        if not good.any():
            continue
        resid = score @ nrm[good].T + off[good][None, :]  # (K, C)
        cost = np.minimum((resid / score_band[:, None]) ** 2, 1.0).sum(axis=0)
        j = int(np.argmin(cost))
        if cost[j] < best_cost:
            best_cost, best = float(cost[j]), (nrm[good][j], float(off[good][j]))
            # adaptive stop (Fischler and Bolles): enough triples for a 99.9 % chance of an all-inlier one
            w = float(np.mean(np.abs(resid[:, j]) <= score_band))
            needed = max(min_iterations, int(math.ceil(math.log(1e-3) / math.log(max(1e-12, 1.0 - w ** 3)))))
    if best is None:
        raise ValueError('depth points are collinear: cannot estimate the table plane')
    normal, offset = best
    inlier = np.abs(pts @ normal + offset) <= band
    for _ in range(3):
        if inlier.sum() < 3:
            break
        normal, offset = _refine(pts[inlier], 1.0 / band[inlier] ** 2)
        inlier = np.abs(pts @ normal + offset) <= band
    fraction = float(inlier.mean())
    if fraction < min_inlier_fraction:
        raise ValueError(f'no table plane found: the best plane holds only {fraction:.0%} of the valid depth points '
                         f'(need {min_inlier_fraction:.0%}); give table_plane or a region of interest')
    resid = pts[inlier] @ normal + offset
    frame = TableFrame.from_plane(*normal, offset, inlier_fraction=fraction,
                                  rms_m=float(np.sqrt(np.mean(resid ** 2))))
    if frame.tilt_deg > max_tilt_deg:
        raise ValueError(f'the dominant plane is seen at {frame.tilt_deg:.0f} degrees from the optical axis (more than '
                         f'{max_tilt_deg:.0f}): a wall or a table seen edge-on, not a table to segment on')
    return frame
