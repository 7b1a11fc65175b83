"""Ground truth of a real capture: a target's footprint on the table and its exact signed distance.

The footprint is the object's orthographic shadow on the table plane, the part of the table a parallel-jaw
grasp from above closes on. From a target mask (the mask component containing a target pixel) and the depth
image of the true shape (e.g. the scene with opaque copies of transparent objects), construction in
docs/ground-truth.md:

1. every mask pixel gets its height above the table (its true depth; a pixel without a return takes the
   height of the nearest one with a return), and the one-pixel ring around the mask the height the surface
   reaches at the silhouette (linear extrapolation from inside: the base of a wall, the rim of a top);
2. each pixel's four corners are lifted to the surface (mean height of the pixels sharing the corner, not
   across a depth discontinuity) and projected onto the table: the pixels tile the projected visible
   surface, whose union is the footprint (its largest connected part);
3. its outline (rasterised finely, outer contour) is smoothed along its arc length at a few pixel footprints
   (a twiced Gaussian), which removes the mask's pixel staircase but does not shrink curved parts;
4. the SDF is the exact signed distance to that polygon (positive outside), so its finite differences are
   the outline's normals and not a raster's.

Every other labelled object whose footprint, built the same way, reaches the grid is an **obstacle** of the truth
(another component of the mask, or a part of the target's component that a depth discontinuity separates from it:
a touching object the mask merged): ``GroundTruth.obstacles`` holds the exact signed distance to the union of their
footprints, and a simulated jaw may neither start in one nor close on one, as in the planner's world
(:class:`~gpis_grasp_ros.core.sdf_bank.SdfBank`'s obstacles). Only what the mask labels is an obstacle (ClearGrasp
labels its transparent objects alone), and only one of at least the segmentation's minimum object area.

When the true depth is the capture's own depth, it is first registered to the mask: moved by the integer shift
that best overlays the mask on the depth's above-table pixels (:func:`mask_registration`). A structured-light
sensor's depth image is offset from the image its intrinsics and the label belong to by a few pixels; unmoved, the
truth would take the table's heights along one side of the mask (its pixels projected where their rays meet the
table) and miss the object's on the other. The footprint stays where the label (and the colour image) put it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.sensing import CameraIntrinsics, SensingParams, nearest_pixel
from gpis_grasp_ros.core.table_frame import TableFrame

if TYPE_CHECKING:
    from gpis_grasp_ros.data.rgbd_import import Capture

#: Outline smoothing scale sigma, in pixel footprints (docs/ground-truth.md: a one-pixel step of the mask's
#: staircase smoothed over sigma tilts the outline by at most atan(1 / (sqrt(2 pi) 3)) = 7.6 deg).
SMOOTHING_SIGMA_PIXELS = 3.0
#: Points further below the table than this are depth errors (m).
BELOW_TABLE_M = 0.005
#: Smallest height step (m) taken as a depth discontinuity: three times a 1-2 mm depth noise.
JUMP_FLOOR_M = 0.005
#: Largest label-to-depth misregistration searched (pixels, rows and columns): a structured-light sensor's depth is
#: offset from its image by a few pixels (about 4 px measured on a Kinect, Smisek et al. 2011); twice that.
MASK_REGISTRATION_RADIUS_PX = 8
#: Smallest footprint (m^2) of another labelled object that is an obstacle of the truth: the segmentation's minimum
#: object area (``SensingParams.min_object_area_m2``), so a label speck is judged as the perception treats a speck.
OBSTACLE_MIN_AREA_M2 = SensingParams.min_object_area_m2
#: Height (m) above the table from which a depth pixel sees an object when a mask is registered to the depth: the
#: segmentation's depth-evidence floor (``SensingParams.height_threshold``), at least twice the table's RMS.
MASK_REGISTRATION_HEIGHT_M = 0.003


@dataclass
class GroundTruth:
    """Target shape in the table frame: SDF (m, positive outside) and occupancy on ``geometry``."""

    sdf: np.ndarray
    occupancy: np.ndarray  # int8 0 / 100
    geometry: GridGeometry
    center_of_mass: np.ndarray  # (3,) camera frame, on the table plane (m)
    outline: np.ndarray  # (K, 3) camera frame, on the table plane (m)
    table: TableFrame
    depth_shift_px: tuple[int, int] = (0, 0)  # (rows, columns) the true depth was moved to register it to the mask
    #: (H, W) float32 signed distance (m) on ``geometry`` to the other labelled objects whose footprints reach the
    #: grid (None: none does); not part of the target, but the world its jaws move in
    obstacles: np.ndarray | None = None
    #: footprint parts of other labelled objects (other mask components, and parts of the target's component that a
    #: depth discontinuity separates from the target) that reach the grid; parts smaller than an object
    #: (:data:`OBSTACLE_MIN_AREA_M2`) and components that could not be built (no usable true-depth return on their
    #: mask, or under 10 pixels), both left out of ``obstacles``
    obstacle_objects: int = 0
    obstacles_small: int = 0
    obstacles_unbuilt: int = 0


def ground_truth_from_mask(capture: Capture, mask: np.ndarray, true_depth: np.ndarray, target_px: tuple[float, float],
                           table: TableFrame, resolution: float = 0.001, margin: float = 0.03,
                           frame_id: str = 'camera_color_optical_frame',
                           register_depth: bool | None = None) -> GroundTruth:
    """Ground truth of the mask component containing ``target_px`` (module docstring).

    Args:
        capture: the capture (for the intrinsics).
        mask: (H, W) bool or 0/255 mask of the objects (all of them).
        true_depth: (H, W) m depth of the true shape (NaN where unknown: the pixel's ray meets the table).
        target_px: (u, v) pixel on the target.
        table: table plane (camera frame) whose frame the ground truth uses.
        resolution, margin: ground-truth grid cell (m) and free margin around the shape (m).
        frame_id: frame of the grid (rgbd_import.FRAME_ID by default).
        register_depth: move the true depth onto the mask first (:func:`mask_registration`); None: when the true
            depth is the capture's own depth (the label was drawn on that capture). A separate true-shape capture
            (an opaque twin) is not registered: its offset from the mask may be the twin's placement.
    """
    intr = capture.intrinsics
    depth = np.asarray(true_depth, dtype=np.float64)
    labels = np.asarray(mask) > 0 if np.asarray(mask).dtype != bool else np.asarray(mask)
    if register_depth is None:
        register_depth = depth.shape == capture.depth.shape and bool(
            np.array_equal(depth, np.asarray(capture.depth, dtype=np.float64), equal_nan=True))
    shift = (0, 0)
    if register_depth:
        off = mask_registration(labels, depth, intr, table)
        shift = (-off[0], -off[1])
        depth = shifted(depth, *shift, fill=np.nan)
    _, components = cv2.connectedComponents(labels.astype(np.uint8), connectivity=8)
    target_label = _component_label(components, target_px)
    comp = components == target_label
    try:
        outline_xy, *beside = footprint_outlines(intr, comp, depth, table, resolution, target_px)
    except ValueError as exc:
        raise ValueError(f'the target has {exc}') from None
    lo = np.floor((outline_xy.min(axis=0) - margin) / resolution) * resolution
    hi = np.ceil((outline_xy.max(axis=0) + margin) / resolution) * resolution
    w, h = (int(round(c)) for c in (hi - lo) / resolution)
    geom = table.grid(float(lo[0]), float(lo[1]), resolution, w, h, frame_id)
    centres = geom.cell_centers()
    sdf = polygon_sdf(outline_xy, centres)
    inside = sdf < 0
    parts, unbuilt = list(beside), 0  # the other parts of the target's component (touching objects), then ...
    for label in range(1, int(components.max()) + 1):  # ... the other labelled objects
        if label != target_label:
            try:
                parts += footprint_outlines(intr, components == label, depth, table, resolution)
            except ValueError:
                unbuilt += 1
    obstacles, objects, small = None, 0, 0
    for part in parts:
        if abs(_signed_area(part)) < OBSTACLE_MIN_AREA_M2:
            small += 1
        elif np.all(part.max(axis=0) >= lo) and np.all(part.min(axis=0) <= hi):  # it reaches the grid
            objects += 1
            d = polygon_sdf(part, centres)
            obstacles = d if obstacles is None else np.minimum(obstacles, d)
    return GroundTruth(sdf=sdf.astype(np.float32), occupancy=np.where(inside, 100, 0).astype(np.int8), geometry=geom,
                       center_of_mass=geom.to_sensor(polygon_centroid(outline_xy)),
                       outline=geom.to_sensor(outline_xy), table=table, depth_shift_px=shift,
                       obstacles=None if obstacles is None else obstacles.astype(np.float32),
                       obstacle_objects=objects, obstacles_small=small, obstacles_unbuilt=unbuilt)


def footprint_outlines(intr: CameraIntrinsics, comp: np.ndarray, depth: np.ndarray, table: TableFrame,
                       resolution: float, anchor_px: tuple[float, float] | None = None) -> list[np.ndarray]:
    """Smoothed outlines (K, 2) (m, table frame, a vertex every ``resolution / 2``) of the footprint of one mask
    component ``comp`` with the true ``depth`` (steps 1-4 of the module docstring), one per connected part (a
    depth discontinuity separates touching objects of one component), largest first; with ``anchor_px`` (a pixel
    on the object) the part holding it first (the largest if none does).

    Raises:
        ValueError: the component has no return of the true shape, or fewer than 10 usable points."""
    vs, us = np.nonzero(comp)
    if vs.size < 10:
        raise ValueError('fewer than 10 usable ground-truth points on its mask component')
    # the work is the component's: its bounding box and a margin wider than the silhouette ring and the corners read
    margin = 4
    v0, v1 = max(int(vs.min()) - margin, 0), min(int(vs.max()) + margin + 1, comp.shape[0])
    u0, u1 = max(int(us.min()) - margin, 0), min(int(us.max()) + margin + 1, comp.shape[1])
    intr = CameraIntrinsics(intr.fx, intr.fy, intr.cx - u0, intr.cy - v0, u1 - u0, v1 - v0)
    comp, depth = comp[v0:v1, u0:u1], depth[v0:v1, u0:u1]
    if anchor_px is not None:
        anchor_px = (anchor_px[0] - u0, anchor_px[1] - v0)
    heights = _surface_heights(intr.rays(), comp, depth, table)
    comp = comp & (heights > -BELOW_TABLE_M)  # points below the table are depth errors
    if comp.sum() < 10:
        raise ValueError('fewer than 10 usable ground-truth points on its mask component')
    heights = np.where(comp, heights, np.nan)
    z = _target_depth(depth, comp, table)
    ext = _extend_to_silhouette(heights, comp)
    quads = _pixel_quads(intr, comp, ext, table, _wall_jump(intr, z, table))
    anchor_xy = None
    if anchor_px is not None:
        vs, us = np.nonzero(comp)
        u, v = (int(round(c)) for c in anchor_px)
        anchor_xy = quads[int(np.argmin((us - u) ** 2 + (vs - v) ** 2))].mean(axis=0)
    step = resolution / 4.0
    sigma = SMOOTHING_SIGMA_PIXELS * _pixel_footprint(intr, z, table)
    return [_resample_closed(_smooth_closed(part, step, sigma), resolution / 2.0)
            for part in _union_outlines(quads, step, anchor_xy)]


def mask_registration(mask: np.ndarray, depth: np.ndarray, intr: CameraIntrinsics, table: TableFrame,
                      radius: int = MASK_REGISTRATION_RADIUS_PX) -> tuple[int, int]:
    """Integer shift s = (rows, columns), at most ``radius`` each, by which the object ``mask`` (all its components:
    a misregistration is the sensor's, the same for every object) lies off the depth's objects; moving the depth
    by -s registers it to the mask.

    For each candidate s the depth is moved by -s and read on the rays of the pixels it lands on (at a 50° tilt the
    table's depth changes by ~1.3 mm per row, so a depth read on the wrong ray is not the table's); a pixel sees an
    object when it is more than max(MASK_REGISTRATION_HEIGHT_M, 2 x the table's RMS) above the table. The score is
    |A ∩ E| / (|A| + |E ∩ ring|): A the mask, E the object pixels, ring the band of ``radius`` pixels around A,
    where a registered depth shows table; without the ring, a shift that slides a neighbour under the mask would
    count as a gain. Ties (a flat or absent object) go to the smaller shift, so a registered depth stays put.
    """
    a = np.asarray(mask, dtype=bool)
    if not a.any():
        return 0, 0
    size = 2 * radius + 1
    ring = cv2.dilate(a.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))) > 0
    ring &= ~a
    rows, cols = np.nonzero(ring | a)
    r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    a, ring = a[r0:r1, c0:c1], ring[r0:r1, c0:c1]
    along = intr.rays()[r0:r1, c0:c1] @ table.n  # the height of depth z on each pixel's ray is z * along + offset
    z = np.where(np.isfinite(depth) & (depth > 0), depth, np.nan)
    pad = np.pad(z, radius, constant_values=np.nan)
    thr = max(MASK_REGISTRATION_HEIGHT_M, 2.0 * table.rms_m)
    area = float(a.sum())
    best, best_key = (0, 0), None
    for dv in range(-radius, radius + 1):
        for du in range(-radius, radius + 1):
            zs = pad[r0 + radius + dv:r1 + radius + dv, c0 + radius + du:c1 + radius + du]  # depth(p + s) at p
            with np.errstate(invalid='ignore'):
                e = zs * along + table.offset_m > thr
            score = float(np.count_nonzero(a & e)) / (area + float(np.count_nonzero(ring & e)))
            key = (score, -(dv * dv + du * du))
            if best_key is None or key > best_key:
                best, best_key = (dv, du), key
    return best


def shifted(image: np.ndarray, rows: int, cols: int, fill: float | bool = 0) -> np.ndarray:
    """``image`` moved down by ``rows`` and right by ``cols`` pixels; the pixels it leaves get ``fill``."""
    out = np.full_like(image, fill)
    h, w = image.shape[:2]
    if abs(rows) >= h or abs(cols) >= w:
        return out
    out[max(rows, 0):h + min(rows, 0), max(cols, 0):w + min(cols, 0)] = \
        image[max(-rows, 0):h + min(-rows, 0), max(-cols, 0):w + min(-cols, 0)]
    return out


def polygon_sdf(polygon: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Exact signed distance (m, positive outside) of ``points`` (..., 2) to the closed ``polygon`` (K, 2)."""
    poly = np.asarray(polygon, dtype=np.float64)
    pts = np.asarray(points, dtype=np.float64)
    origin = poly.min(axis=0)  # float32 contour for OpenCV: keep the coordinates small
    contour = ((poly - origin) * 1e3).astype(np.float32).reshape(-1, 1, 2)
    flat = (pts.reshape(-1, 2) - origin) * 1e3
    out = np.fromiter((cv2.pointPolygonTest(contour, (float(x), float(y)), True) for x, y in flat),
                      dtype=np.float64, count=flat.shape[0])
    return (-out * 1e-3).reshape(pts.shape[:-1])


def polygon_centroid(polygon: np.ndarray) -> np.ndarray:
    """Area centroid (2,) of a closed simple polygon (K, 2)."""
    p = np.asarray(polygon, dtype=np.float64)
    q = np.roll(p, -1, axis=0)
    cross = p[:, 0] * q[:, 1] - q[:, 0] * p[:, 1]
    return ((p + q) * cross[:, None]).sum(axis=0) / (3.0 * cross.sum())


def _component_label(labels: np.ndarray, target_px: tuple[float, float]) -> int:
    """The label (of ``cv2.connectedComponents``) of the mask component under ``target_px``."""
    u, v = (int(round(c)) for c in target_px)
    if not (0 <= v < labels.shape[0] and 0 <= u < labels.shape[1]) or labels[v, u] == 0:
        raise ValueError(f'target pixel ({u}, {v}) is not on the mask')
    return int(labels[v, u])


def _surface_heights(rays: np.ndarray, comp: np.ndarray, true_depth: np.ndarray, table: TableFrame) -> np.ndarray:
    """Height (m) above the table of the true surface at each pixel of the mask component ``comp`` (NaN elsewhere).

    A pixel with a return of the true shape is its ray at that depth. A pixel *without* one (a grazing or
    dark part of the opaque twin) still sees the object - the mask says so - at an unknown depth: it takes
    the height of the nearest pixel of the component with a return. Putting it where its ray meets the table
    would put it behind the object by up to H tan(tilt) (on the real lying bottle, 7-10 cm).

    Raises:
        ValueError: no pixel of the component has a return of the true shape."""
    z = np.where(np.isfinite(true_depth) & (true_depth > 0), true_depth, np.nan)
    valid = comp & np.isfinite(z)
    if not valid.any():
        raise ValueError('no return of the true shape (--gt-depth) on its mask component')
    heights = np.where(valid, (rays * np.nan_to_num(z)[..., None]) @ table.n + table.offset_m, np.nan)
    vs, us = np.nonzero(comp & ~valid)
    near = nearest_pixel(valid)[1][vs, us]
    heights[vs, us] = heights[near[:, 0], near[:, 1]]
    return heights


def _extend_to_silhouette(heights: np.ndarray, comp: np.ndarray) -> np.ndarray:
    """``heights`` on ``comp`` plus the 4-connected ring around it, each ring pixel the mean over its neighbours
    in ``comp`` of the height extrapolated linearly one pixel outwards (2 h(q) - h(q'), q' the next pixel
    inwards; h(q) if there is none), not below the table. A corner between the mask's last pixel and the ring
    then sits where the surface meets the silhouette: the base of a wall (its heights fall towards the table),
    the rim of a flat top (constant)."""
    pad = np.pad(heights, 2, constant_values=np.nan)
    inside = np.pad(comp, 2, constant_values=False)
    total = np.zeros(pad.shape)
    count = np.zeros(pad.shape)
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        q = np.roll(pad, (-dy, -dx), axis=(0, 1))  # the neighbour at (+dy, +dx)
        q2 = np.roll(pad, (-2 * dy, -2 * dx), axis=(0, 1))
        q_in = np.roll(inside, (-dy, -dx), axis=(0, 1))
        q2_in = np.roll(inside, (-2 * dy, -2 * dx), axis=(0, 1))
        est = np.where(q2_in, 2.0 * q - q2, q)
        use = ~inside & q_in
        total[use] += est[use]
        count[use] += 1
    ring = count > 0
    out = np.where(inside, pad, np.where(ring, total / np.maximum(count, 1), np.nan))
    return out[2:-2, 2:-2]


def _pixel_quads(intr: CameraIntrinsics, comp: np.ndarray, ext: np.ndarray, table: TableFrame,
                 jump_m: float) -> np.ndarray:
    """(K, 4, 2) table (x, y) of the corners of each pixel of ``comp``, each corner's ray at the mean height of
    the pixels sharing the corner (of ``ext``) that are within ``jump_m`` of the pixel's own: the surface is
    not bridged across a depth discontinuity (a mask pixel seeing the table behind a rim)."""
    vs, us = np.nonzero(comp)
    pad = np.pad(ext, 1, constant_values=np.nan)
    own = ext[vs, us]
    corners = []
    for dv, du in ((0, 0), (0, 1), (1, 1), (1, 0)):  # corner (v + dv - 1/2, u + du - 1/2), clockwise in the image
        around = np.stack([pad[vs + dv + a, us + du + b] for a in (0, 1) for b in (0, 1)], axis=1)
        ok = np.isfinite(around) & (np.abs(around - own[:, None]) <= jump_m)
        corners.append(np.where(ok, around, 0.0).sum(axis=1) / np.maximum(ok.sum(axis=1), 1))
    corner_h = np.stack(corners, axis=1)
    cv, cu = np.stack([vs, vs, vs + 1, vs + 1], axis=1), np.stack([us, us + 1, us + 1, us], axis=1)
    rays = np.stack([(cu - 0.5 - intr.cx) / intr.fx, (cv - 0.5 - intr.cy) / intr.fy, np.ones(cu.shape)], axis=-1)
    t = (corner_h - table.offset_m) / (rays @ table.n)
    return table.to_table(rays * t[..., None])[0]


def _union_outlines(quads: np.ndarray, step: float, target_xy: np.ndarray | None) -> list[np.ndarray]:
    """Outer boundaries (N, 2) (m, counter-clockwise in the table frame) of the connected parts of the quads' union,
    rasterised with cells of ``step`` m (OpenCV fills the cells whose centre is within half a cell of the polygon:
    the contour through them is unbiased), largest first; the part that holds ``target_xy`` (the largest if none
    does) first of all."""
    flat = quads.reshape(-1, 2)
    lo = flat.min(axis=0) - 4 * step
    w, h = (int(math.ceil(c)) + 8 for c in (flat.max(axis=0) - lo) / step)
    raster = np.zeros((h, w), np.uint8)
    shift = 4
    pts = np.round(((quads - lo) / step - 0.5) * (1 << shift)).astype(np.int32)
    cv2.fillPoly(raster, list(pts), 1, lineType=cv2.LINE_8, shift=shift)
    contours, _ = cv2.findContours(raster, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    chosen = sorted(contours, key=cv2.contourArea, reverse=True)
    if target_xy is not None:
        tx, ty = (float(c) for c in (target_xy - lo) / step - 0.5)
        holding = [c for c in chosen if cv2.pointPolygonTest(c, (tx, ty), False) >= 0]
        if holding:
            first = max(holding, key=cv2.contourArea)
            chosen = [first] + [c for c in chosen if c is not first]
    out = []
    for c in chosen:
        xy = lo + (c.reshape(-1, 2).astype(np.float64) + 0.5) * step
        if _signed_area(xy) < 0:
            xy = xy[::-1]
        out.append(_resample_closed(xy, step))
    return out


def _smooth_closed(xy: np.ndarray, step: float, sigma_m: float) -> np.ndarray:
    """Closed curve resampled every ``step`` m and smoothed along its arc length with the twiced Gaussian
    2 G - G * G (scale ``sigma_m``): a Gaussian alone pulls a curve of radius R in by sigma^2 / (2 R), the
    twiced kernel cancels that to second order and still removes the pixel staircase."""
    p = _resample_closed(xy, step)
    s = min(sigma_m / step, p.shape[0] / 8.0)
    g = gaussian_filter1d(p, s, axis=0, mode='wrap')
    return 2.0 * g - gaussian_filter1d(g, s, axis=0, mode='wrap')


def _resample_closed(xy: np.ndarray, step: float) -> np.ndarray:
    """Closed polyline (N, 2) → points equally spaced (about ``step`` m) along its arc length."""
    closed = np.vstack([xy, xy[:1]])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
    n = max(int(round(s[-1] / step)), 8)
    t = np.arange(n) * (s[-1] / n)
    return np.stack([np.interp(t, s, closed[:, k]) for k in range(2)], axis=1)


def _signed_area(xy: np.ndarray) -> float:
    q = np.roll(xy, -1, axis=0)
    return float(0.5 * (xy[:, 0] * q[:, 1] - q[:, 0] * xy[:, 1]).sum())


def _target_depth(depth: np.ndarray, comp: np.ndarray, table: TableFrame) -> float:
    z = depth[comp & np.isfinite(depth)]
    return float(np.median(z)) if z.size else table.offset_m


def _pixel_footprint(intr: CameraIntrinsics, z: float, table: TableFrame) -> float:
    """Largest extent (m) of one pixel on the table at depth ``z``: z / (f cos tilt)."""
    return z / min(intr.fx, intr.fy) / max(math.cos(math.radians(table.tilt_deg)), 0.3)


def _wall_jump(intr: CameraIntrinsics, z: float, table: TableFrame) -> float:
    """Largest height step (m) between neighbouring pixels on one surface: two pixels up a vertical wall,
    2 z / (f sin tilt), at least JUMP_FLOOR_M (depth noise). A larger step is a depth discontinuity; a smaller
    one bridged behind a rim moves the outline by under two pixel footprints."""
    sin_tilt = max(math.sin(math.radians(table.tilt_deg)), 0.05)
    return max(2.0 * z / min(intr.fx, intr.fy) / sin_tilt, JUMP_FLOOR_M)
