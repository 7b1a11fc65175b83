"""Ground truth from a mask and a true depth (gpis_grasp_ros.data.ground_truth) on analytic shapes.

Upright prisms (a disc, an ellipse, boxes) standing on a table, ray-cast at the resolutions and tilts of the
real captures (PrimeSense 640 x 480, f 525, 13 deg; D435 1280 x 720, f 921, 50 deg, depth in whole mm): the
truth's outline normals and its SDF's finite-difference normals follow the analytic outline's, and its
footprint is the analytic one. ``python test/data/test_ground_truth.py`` prints the figures of the
``ground_truth_from_mask`` importable from ``rgbd_import`` (docs/ground-truth.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import pytest
from scipy.ndimage import label as components
from scipy.spatial import cKDTree

from gpis_grasp_ros.core.sdf import sdf_gradient
from gpis_grasp_ros.core.sensing import CameraIntrinsics
from gpis_grasp_ros.core.table_frame import TableFrame
from gpis_grasp_ros.data import ground_truth as gt
from gpis_grasp_ros.data import rgbd_import as ri

PRIMESENSE = CameraIntrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
D435 = CameraIntrinsics(921.0, 921.0, 642.0, 359.0, 1280, 720)
CORNER_EXCLUSION_M = 0.006  # box outline points this close to a corner are not scored (the corners are rounded)


@dataclass(frozen=True)
class Prism:
    """An upright prism on the table: an ellipse (semi-axes a, b) or a box (half sizes a, b), yawed, H tall."""

    kind: str
    a: float
    b: float
    height: float
    yaw_deg: float
    camera: CameraIntrinsics
    tilt_deg: float
    distance: float  # m along the optical axis to the table
    offset: tuple[float, float] = (0.004, -0.007)  # object centre from the optical axis's foot (m, table frame)
    depth_step: float = 0.0  # depth quantisation (m; 0 = none)

    @property
    def table(self) -> TableFrame:
        t = math.radians(self.tilt_deg)
        return TableFrame.from_plane(0.0, -math.sin(t), -math.cos(t), self.distance)

    @property
    def centre(self) -> np.ndarray:
        return self.table.to_table(np.array([0.0, 0.0, self.distance]))[0] + np.asarray(self.offset)

    def _local(self, xy: np.ndarray) -> np.ndarray:
        c, s = math.cos(math.radians(self.yaw_deg)), math.sin(math.radians(self.yaw_deg))
        d = np.asarray(xy, dtype=np.float64) - self.centre
        return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], axis=-1)

    def inside(self, xy: np.ndarray) -> np.ndarray:
        q = self._local(xy)
        if self.kind == 'ellipse':
            return (q[..., 0] / self.a) ** 2 + (q[..., 1] / self.b) ** 2 <= 1.0
        return (np.abs(q[..., 0]) <= self.a) & (np.abs(q[..., 1]) <= self.b)

    def render(self) -> tuple[np.ndarray, np.ndarray]:
        """Ray-cast (depth (H, W) m, mask (H, W) bool) of the prism on the table."""
        table, rays = self.table, self.camera.rays()
        local = rays @ table.rotation  # a point t * ray: table (x, y) = t local[:2], height d - t local[2]
        az = local[..., 2]
        lo, hi = (table.offset_m - self.height) / az, table.offset_m / az  # height in [0, H]
        c, s = math.cos(math.radians(self.yaw_deg)), math.sin(math.radians(self.yaw_deg))
        ax, ay = c * local[..., 0] + s * local[..., 1], -s * local[..., 0] + c * local[..., 1]
        cx, cy = (float(v) for v in self._local(np.zeros(2)) * -1.0)
        if self.kind == 'ellipse':
            alpha = (ax / self.a) ** 2 + (ay / self.b) ** 2
            beta = ax * cx / self.a ** 2 + ay * cy / self.b ** 2
            gamma = (cx / self.a) ** 2 + (cy / self.b) ** 2 - 1.0
            disc = np.sqrt(np.maximum(beta ** 2 - alpha * gamma, 0.0))
            ok = beta ** 2 - alpha * gamma >= 0
            lo = np.maximum(lo, np.where(ok, (beta - disc) / alpha, np.inf))
            hi = np.minimum(hi, (beta + disc) / alpha)
        else:
            for comp, centre, half in ((ax, cx, self.a), (ay, cy, self.b)):
                with np.errstate(divide='ignore', invalid='ignore'):
                    t1, t2 = (centre - half) / comp, (centre + half) / comp
                inside = np.abs(centre) <= half
                lo = np.maximum(lo, np.where(comp == 0, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2)))
                hi = np.minimum(hi, np.where(comp == 0, np.inf, np.maximum(t1, t2)))
        mask = lo <= hi
        depth = np.where(mask, lo, table.offset_m / az)
        if self.depth_step:
            depth = np.round(depth / self.depth_step) * self.depth_step
        return depth, mask

    def outline(self, spacing: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
        """Points (N, 2) on the analytic outline (box corners excluded) and their outward unit normals."""
        c, s = math.cos(math.radians(self.yaw_deg)), math.sin(math.radians(self.yaw_deg))
        if self.kind == 'ellipse':
            th = np.linspace(0.0, 2 * np.pi, int(2 * np.pi * max(self.a, self.b) / spacing), endpoint=False)
            q = np.stack([self.a * np.cos(th), self.b * np.sin(th)], axis=1)
            nq = np.stack([np.cos(th) / self.a, np.sin(th) / self.b], axis=1)
        else:
            parts, normals = [], []
            for (sx, sy), half_along, half_across in (((1, 0), self.b, self.a), ((0, 1), self.a, self.b)):
                along = np.arange(-half_along + CORNER_EXCLUSION_M, half_along - CORNER_EXCLUSION_M, spacing)
                for sign in (1.0, -1.0):
                    n = sign * np.array([sx, sy], dtype=np.float64)
                    tangent = np.array([sy, sx], dtype=np.float64)
                    parts.append(n * half_across + along[:, None] * tangent)
                    normals.append(np.broadcast_to(n, (along.size, 2)))
            q, nq = np.vstack(parts), np.vstack(normals)
        rot = np.array([[c, -s], [s, c]])
        nq = nq / np.linalg.norm(nq, axis=1, keepdims=True)
        return q @ rot.T + self.centre, nq @ rot.T


CASES = [
    Prism('ellipse', 0.015, 0.015, 0.02, 0.0, PRIMESENSE, 13.0, 0.8),  # 3 cm disc, the fewest pixels
    Prism('ellipse', 0.04, 0.04, 0.06, 0.0, PRIMESENSE, 13.0, 0.6),
    Prism('box', 0.03, 0.02, 0.05, 20.0, PRIMESENSE, 13.0, 0.7),
    Prism('ellipse', 0.04, 0.02, 0.03, 35.0, PRIMESENSE, 13.0, 0.7),
    Prism('ellipse', 0.015, 0.015, 0.06, 0.0, D435, 50.0, 1.0, depth_step=0.001),
    Prism('ellipse', 0.04, 0.04, 0.02, 0.0, D435, 50.0, 0.6, depth_step=0.001),
    Prism('box', 0.015, 0.025, 0.02, 4.0, D435, 50.0, 0.6, depth_step=0.001),  # nearly axis-aligned: long steps
    Prism('box', 0.04, 0.03, 0.06, 45.0, D435, 50.0, 0.8, depth_step=0.001),
    Prism('ellipse', 0.03, 0.015, 0.04, 70.0, D435, 50.0, 0.8, depth_step=0.001),
]


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-12)
    return np.degrees(np.arccos(np.clip((a * b).sum(axis=-1), -1.0, 1.0)))


def figures(prism: Prism, truth: ri.GroundTruth) -> dict[str, float]:
    """Footprint IoU, P90 of the outline's and of the SDF gradient's angle to the analytic normals (deg)."""
    g = truth.geometry
    centres = g.cell_centers()
    occ = truth.sdf < 0
    true_in = prism.inside(centres)
    iou = float((occ & true_in).sum() / (occ | true_in).sum())
    pts, normals = prism.outline()
    tree = cKDTree(pts)
    # SDF normals: central differences at the cells within one cell of the analytic outline
    grad, defined = sdf_gradient(truth.sdf.astype(np.float64), g.resolution)
    dist, idx = tree.query(centres.reshape(-1, 2))
    near = (dist.reshape(g.shape) < g.resolution) & defined.all(axis=-1)
    sdf_err = _angles_deg(grad[near], normals[idx.reshape(g.shape)[near]])
    # outline normals: the polygon's vertex normals (central differences) at its vertices
    xy = truth.table.to_table(truth.outline)[0]
    tangent = np.roll(xy, -1, axis=0) - np.roll(xy, 1, axis=0)
    vnorm = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1) * (1.0 if _area(xy) > 0 else -1.0)
    d, j = tree.query(xy)
    keep = d < 0.002
    out_err = _angles_deg(vnorm[keep], normals[j[keep]])
    return {'iou': iou, 'sdf_p90': float(np.percentile(sdf_err, 90)), 'outline_p90': float(np.percentile(out_err, 90)),
            'scored': int(near.sum())}


def _area(xy: np.ndarray) -> float:
    q = np.roll(xy, -1, axis=0)
    return float(0.5 * (xy[:, 0] * q[:, 1] - q[:, 0] * xy[:, 1]).sum())


def _truth(prism: Prism) -> ri.GroundTruth:
    depth, mask = prism.render()
    capture = ri.Capture(np.zeros((*depth.shape, 3), np.uint8), depth, prism.camera)
    v, u = np.nonzero(mask)
    k = int(np.argmin((u - u.mean()) ** 2 + (v - v.mean()) ** 2))
    return ri.ground_truth_from_mask(capture, mask, np.where(mask, depth, np.nan), (u[k], v[k]), prism.table)


@pytest.mark.parametrize('prism', CASES, ids=lambda p: f'{p.kind}-{p.camera.width}-{p.distance}-{p.yaw_deg:g}')
def test_truth_follows_the_analytic_outline(prism):
    f = figures(prism, _truth(prism))
    assert f['iou'] >= 0.97, f
    assert f['sdf_p90'] <= 5.0, f
    assert f['outline_p90'] <= 5.0, f


def _own_depth_capture(prism: Prism, noise_m: float = 0.0, seed: int = 0):
    """(capture, mask, target pixel) of ``prism`` whose depth (the table included) is also the true depth."""
    depth, mask = prism.render()
    if noise_m:
        depth = depth + np.random.default_rng(seed).normal(0.0, noise_m, depth.shape)
    capture = ri.Capture(np.zeros((*depth.shape, 3), np.uint8), depth, prism.camera)
    v, u = np.nonzero(mask)
    k = int(np.argmin((u - u.mean()) ** 2 + (v - v.mean()) ** 2))
    return capture, mask, (float(u[k]), float(v[k]))


def _displaced(capture: ri.Capture, rows: int, cols: int) -> ri.Capture:
    return ri.Capture(capture.rgb, gt.shifted(capture.depth, rows, cols, fill=np.nan), capture.intrinsics)


@pytest.mark.parametrize('prism', CASES, ids=lambda p: f'{p.kind}-{p.camera.width}-{p.distance}-{p.yaw_deg:g}')
def test_a_depth_displaced_from_its_label_is_moved_back(prism):
    """A depth image displaced by a few pixels from the image its label and intrinsics belong to (a
    structured-light sensor's depth is offset from its infrared image) is moved back by that shift when it is the
    capture's own depth, and the truth is the registered scene's; a registered depth is not moved. Shifts drawn
    at random (seeded) within the searched radius, 1 mm depth noise on the PrimeSense cases. At 13° the shift is
    found exactly (the truth bit for bit); at 50° a wall's foot below the evidence height (3 mm) spans
    3 mm sin 50° / 0.7-1.1 mm = 2-3 pixel rows that read as table, so the estimate may be one row short (the truth
    still the analytic footprint)."""
    rng = np.random.default_rng(int(prism.distance * 100 + prism.yaw_deg))
    noise = 0.001 if prism.camera is PRIMESENSE else 0.0
    capture, mask, (u, v) = _own_depth_capture(prism, noise)
    ref = ri.ground_truth_from_mask(capture, mask, capture.depth, (u, v), prism.table)
    assert ref.depth_shift_px == (0, 0)
    assert figures(prism, ref)['iou'] >= 0.97
    for dv, du in [tuple(int(c) for c in rng.integers(-6, 7, 2)) for _ in range(3)]:
        moved = _displaced(capture, dv, du)
        truth = ri.ground_truth_from_mask(moved, mask, moved.depth, (u, v), prism.table)
        if prism.tilt_deg < 20.0:
            assert truth.depth_shift_px == (-dv, -du)
            assert np.array_equal(truth.sdf, ref.sdf) and truth.geometry == ref.geometry
        else:
            assert abs(truth.depth_shift_px[0] + dv) <= 1 and truth.depth_shift_px[1] == -du, (dv, du, truth)
            assert figures(prism, truth)['iou'] >= 0.97


def test_depth_registration_is_not_drawn_onto_a_touching_neighbour():
    """Two boxes side by side, only the first labelled (its neighbour unlabelled, as clutter the label missed):
    the depth is moved back onto the label, not slid so that the neighbour fills it (a score without the ring
    around the label would count that as a gain); a separate true-shape capture is never registered unless asked."""
    a = Prism('box', 0.02, 0.015, 0.04, 0.0, PRIMESENSE, 13.0, 0.7, offset=(-0.021, 0.0))
    b = Prism('box', 0.02, 0.015, 0.04, 0.0, PRIMESENSE, 13.0, 0.7, offset=(0.0205, 0.0))
    (da, ma), (db, _) = a.render(), b.render()
    capture = ri.Capture(np.zeros((*da.shape, 3), np.uint8), np.minimum(da, db), PRIMESENSE)
    label = ma & (da <= db)
    v, u = np.nonzero(label)
    k = int(np.argmin((u - u.mean()) ** 2 + (v - v.mean()) ** 2))
    for dv, du in ((0, 0), (0, 4), (3, -2), (0, -5)):
        moved = _displaced(capture, dv, du)
        truth = ri.ground_truth_from_mask(moved, label, moved.depth, (u[k], v[k]), a.table)
        assert truth.depth_shift_px == (-dv, -du)
    moved = _displaced(capture, 0, 4)
    other = moved.depth.copy()  # the same depth as if from a separate capture (one pixel differs)
    other[0, 0] = 0.5
    assert ri.ground_truth_from_mask(moved, label, other, (u[k], v[k]), a.table).depth_shift_px == (0, 0)
    forced = ri.ground_truth_from_mask(moved, label, other, (u[k], v[k]), a.table, register_depth=True)
    assert forced.depth_shift_px == (0, -4)


def test_a_flat_label_is_not_moved():
    """Nothing above the table under or around the label (a sheet of paper): no evidence, no shift."""
    prism = Prism('box', 0.03, 0.02, 0.0, 10.0, PRIMESENSE, 13.0, 0.7)
    depth, _ = prism.render()
    rays = prism.camera.rays()
    on_table = rays * (prism.table.offset_m / (rays @ -prism.table.n))[..., None]
    label = prism.inside(prism.table.to_table(on_table)[0])
    assert label.sum() > 500
    assert gt.mask_registration(label, depth, PRIMESENSE, prism.table) == (0, 0)



@pytest.mark.parametrize('camera, tilt, distance, step', [(PRIMESENSE, 13.0, 0.7, 0.0), (D435, 50.0, 0.7, 0.001)],
                         ids=['primesense-13', 'd435-50'])
def test_other_labelled_objects_are_the_truths_obstacles(camera, tilt, distance, step):
    """A labelled neighbour 15 mm from the target is an obstacle of the truth: the obstacle distance's negative part
    is the neighbour's analytic footprint (IoU >= 0.9 on the grid's cells it reaches) and it is positive on the
    target; the target's own truth is the one built with the neighbour unlabelled, bit for bit. A labelled speck
    under the minimum object area is not an obstacle, nor is a labelled object beyond the grid."""
    a = Prism('ellipse', 0.02, 0.02, 0.04, 0.0, camera, tilt, distance, offset=(-0.03, 0.0), depth_step=step)
    b = Prism('box', 0.012, 0.025, 0.03, 0.0, camera, tilt, distance, offset=(0.017, 0.0), depth_step=step)
    speck = Prism('ellipse', 0.003, 0.003, 0.01, 0.0, camera, tilt, distance, offset=(-0.075, 0.0), depth_step=step)
    far = Prism('box', 0.02, 0.02, 0.03, 0.0, camera, tilt, distance, offset=(-0.03, -0.11), depth_step=step)
    renders = [p.render() for p in (a, b, speck, far)]
    depth = np.minimum.reduce([d for d, _ in renders])
    visible = [m & (d <= depth) for d, m in renders]
    capture = ri.Capture(np.zeros((*depth.shape, 3), np.uint8), depth, camera)
    v, u = np.nonzero(visible[0])
    k = int(np.argmin((u - u.mean()) ** 2 + (v - v.mean()) ** 2))
    true_depth = np.where(np.logical_or.reduce(visible), depth, np.nan)
    alone = ri.ground_truth_from_mask(capture, visible[0], true_depth, (u[k], v[k]), a.table)
    assert alone.obstacles is None and alone.obstacle_objects == 0
    truth = ri.ground_truth_from_mask(capture, np.logical_or.reduce(visible), true_depth, (u[k], v[k]), a.table)
    assert np.array_equal(truth.sdf, alone.sdf) and truth.geometry == alone.geometry
    assert (truth.obstacle_objects, truth.obstacles_small, truth.obstacles_unbuilt) == (1, 1, 0)
    centres = truth.geometry.cell_centers()
    expected, got = b.inside(centres), truth.obstacles < 0
    assert expected.sum() > 300
    assert (expected & got).sum() / (expected | got).sum() >= 0.9
    assert truth.obstacles[truth.sdf < 0].min() > 0.005  # the target is no obstacle of its own
    inside_b = b.inside(centres)
    assert truth.obstacles[inside_b].min() < -0.008  # the neighbour's middle is deep inside it (half width 12 mm)



def test_an_object_the_mask_merged_with_the_target_is_an_obstacle():
    """A 15 mm box 6 mm in front of the 45 mm tall target on the table: at 13 deg the target's image touches it, so
    the label has one component for both; the depth discontinuity between them separates their footprints. The part
    holding the target pixel is the truth (IoU 0.94 with the target's analytic footprint), the other part an
    obstacle (IoU 0.91 with its box, whose far side the target hides)."""
    a = Prism('box', 0.02, 0.015, 0.045, 0.0, PRIMESENSE, 13.0, 0.7, offset=(0.0, 0.0))
    b = Prism('box', 0.02, 0.015, 0.015, 0.0, PRIMESENSE, 13.0, 0.7, offset=(0.0, -0.036))
    (da, ma), (db, mb) = a.render(), b.render()
    depth = np.minimum(da, db)
    mask = (ma & (da <= depth)) | (mb & (db <= depth))
    assert components(mask, structure=np.ones((3, 3)))[1] == 1  # one component in the label
    capture = ri.Capture(np.zeros((*depth.shape, 3), np.uint8), depth, PRIMESENSE)
    v, u = np.nonzero(ma & (da <= depth))
    k = int(np.argmin((u - u.mean()) ** 2 + (v - v.mean()) ** 2))
    truth = ri.ground_truth_from_mask(capture, mask, np.where(mask, depth, np.nan), (u[k], v[k]), a.table)
    centres = truth.geometry.cell_centers()

    def iou(x: np.ndarray, y: np.ndarray) -> float:
        return float((x & y).sum() / (x | y).sum())

    assert truth.obstacle_objects == 1
    assert iou(truth.sdf < 0, a.inside(centres)) >= 0.93
    assert iou(truth.obstacles < 0, b.inside(centres)) >= 0.9
    assert truth.obstacles[a.inside(centres)].min() > 0.003  # the target's cells are not the obstacle's


def test_label_specks_are_no_objects():
    """A label with 150 one-to-four-pixel specks scattered over the table (a noisy mask): none is an object of the
    truth (each is under 10 pixels: not built), and the target's truth is the one of the clean label bit for bit."""
    prism = CASES[2]
    depth, mask = prism.render()
    capture = ri.Capture(np.zeros((*depth.shape, 3), np.uint8), depth, prism.camera)
    v, u = np.nonzero(mask)
    k = int(np.argmin((u - u.mean()) ** 2 + (v - v.mean()) ** 2))
    clean = ri.ground_truth_from_mask(capture, mask, np.where(mask, depth, np.nan), (u[k], v[k]), prism.table)
    rng = np.random.default_rng(4)
    noisy = mask.copy()
    far = cv2.dilate(mask.astype(np.uint8), np.ones((41, 41), np.uint8)) == 0
    fv, fu = np.nonzero(far[2:-2, 2:-2])
    for i in rng.choice(fv.size, 150, replace=False):
        h, w = (int(x) for x in rng.integers(1, 3, 2))
        noisy[fv[i] + 2:fv[i] + 2 + h, fu[i] + 2:fu[i] + 2 + w] = True
    n_specks = components(noisy & ~mask, structure=np.ones((3, 3)))[1]
    truth = ri.ground_truth_from_mask(capture, noisy, np.where(noisy | mask, depth, np.nan), (u[k], v[k]),
                                      prism.table)
    assert np.array_equal(truth.sdf, clean.sdf) and truth.obstacles is None
    assert truth.obstacles_unbuilt == n_specks > 100 and truth.obstacle_objects == 0


if __name__ == '__main__':
    for case in CASES:
        res = figures(case, _truth(case))
        size = f'{2e2 * case.a:4.1f} x {2e2 * case.b:4.1f} x {1e2 * case.height:3.1f} cm'
        print(f'{case.kind:7s} {size}  yaw {case.yaw_deg:4.0f}'
              f'  {case.camera.width} px {case.tilt_deg:3.0f} deg {case.distance:.1f} m  IoU {res["iou"]:.3f}'
              f'  SDF normals P90 {res["sdf_p90"]:5.1f} deg  outline normals P90 {res["outline_p90"]:5.1f} deg')
