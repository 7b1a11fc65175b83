"""Compiled (numba) loops of the occlusion stage: solid columns drawn into a depth buffer, the prism test
placing a no-return pixel on its ray, and the march that finds the table points under a seen surface.

They do per point what the array code around them would do with one temporary array per operation (the
same IEEE operations in the same order, so the same numbers), but point by point with early exits: a ray's
search stops at its first sample under the prism and a sample's test at its first pixel off the object. The
projections of a column's samples and of a segment's inner points are computed in a branch-free loop the
compiler vectorises, then tested. ``cam`` is (fx, fy, cx, cy) of :class:`~.camera.CameraIntrinsics`
(:func:`camera_vector`)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit


def camera_vector(intrinsics) -> np.ndarray:
    """(fx, fy, cx, cy) of a :class:`~.camera.CameraIntrinsics`, as the loops take it."""
    return np.array([intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy], dtype=np.float64)


def coarse_to_fine(n: int) -> np.ndarray:
    """The indices 0 .. n-1 of points along a segment, the middle first, then the middles of the halves, and so
    on: a segment that leaves the object does so at one place, found in a few tests in this order (a test of
    all the points gives the same answer in any order)."""
    order: list[int] = []
    spans = [(0, n - 1)]
    while spans:
        nxt = []
        for lo, hi in spans:
            if lo > hi:
                continue
            mid = (lo + hi) // 2
            order.append(mid)
            nxt += [(lo, mid - 1), (mid + 1, hi)]
        spans = nxt
    return np.asarray(order, dtype=np.int64)


@njit(cache=True, nogil=True, inline='always')
def _pixel(x, y, z, cam, width, height):
    """The image pixel (u, v) a camera-frame point projects onto (``CameraIntrinsics.pixel_index``), (-1, -1)
    when it lies behind the camera or outside the image."""
    if not z > 0.0:
        return -1, -1
    u = np.rint(cam[2] + cam[0] * x / z)
    v = np.rint(cam[3] + cam[1] * y / z)
    if not (u >= 0.0 and u < width and v >= 0.0 and v < height):  # also false for NaN
        return -1, -1
    return int(u), int(v)


@njit(cache=True, nogil=True, error_model='numpy')
def _fractions(m):
    """``k / den`` at [den, k] for den, k <= m: the divisions of a column's sample fractions, done once."""
    out = np.zeros((m + 1, m + 1))
    for den in range(1, m + 1):
        for k in range(m + 1):
            out[den, k] = k / den
    return out


@njit(cache=True, nogil=True, error_model='numpy')
def draw_columns(foot, h, n, normal, include_point, cam, zbuf, u0, v0, in_image):
    """Nearest depth of the solid columns over the pixels of ``zbuf`` (updated in place).

    Column i has ``n[i]`` samples ``foot[i] + (k / n[i] h[i]) normal`` (``k / (n[i] - 1)`` with
    ``include_point``), k = 0 .. n[i] - 1; a sample's pixel is ``CameraIntrinsics.pixel_index`` of it with
    ``in_image`` (zbuf is then the image, ``u0 = v0 = 0``), else its rounded projection minus (u0, v0), kept
    when it falls on zbuf. A column's projections are computed first, in a loop without branches (the compiler
    vectorises it; ``error_model='numpy'``: no zero-division branch, and no sample is divided by a zero depth
    that was not before), then drawn."""
    rows, cols = zbuf.shape
    m = 1
    for i in range(n.shape[0]):
        m = max(m, n[i])
    frac = _fractions(m)
    us = np.empty(m)
    vs = np.empty(m)
    zs = np.empty(m)
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    for i in range(foot.shape[0]):
        ni = n[i]
        row = frac[ni - 1 if include_point else ni]
        for k in range(ni):
            s = row[k] * h[i]
            x = foot[i, 0] + s * normal[0]
            y = foot[i, 1] + s * normal[1]
            z = foot[i, 2] + s * normal[2]
            us[k] = np.rint(cx + fx * x / z)
            vs[k] = np.rint(cy + fy * y / z)
            zs[k] = z
        for k in range(ni):
            z = zs[k]
            if in_image:  # _pixel
                if not (z > 0.0 and us[k] >= 0.0 and us[k] < cols and vs[k] >= 0.0 and vs[k] < rows):
                    continue
                u, v = int(us[k]), int(vs[k])
            else:
                u = int(us[k]) - u0
                v = int(vs[k]) - v0
                if u < 0 or u >= cols or v < 0 or v >= rows:
                    continue
            cur = zbuf[v, u]
            zbuf[v, u] = z if z < cur else cur  # a select: no branch that the depths decide


@njit(cache=True, nogil=True, inline='always')
def _on_object(x, y, z, cam, obj):
    u, v = _pixel(x, y, z, cam, obj.shape[1], obj.shape[0])
    return u >= 0 and obj[v, u]


@njit(cache=True, nogil=True, error_model='numpy')
def prism_heights(ray, ray_n, top_h, normal, offset, fractions, inner, cam, obj):
    """Height of each ray's first sample under the object's prism (0 where none), searched from the top down.

    Ray i is sampled at heights ``top_h[i] fractions[j]``; a sample's foot (where the ray is at that height,
    dropped onto the plane) is under the prism when the vertical segment from it up ``top_h[i]`` projects onto
    ``obj`` pixels at both ends and at the ``inner`` fractions of the way up. The inner points' projections are
    computed in a loop without branches (vectorised; ``error_model='numpy'``: a zero depth gives no exception,
    and such a point is off the object either way), then looked up in ``inner``'s order."""
    rows, cols = obj.shape
    fu, fv = cam[0], cam[1]
    cu, cv = cam[2], cam[3]
    pu = np.empty(inner.shape[0])
    pv = np.empty(inner.shape[0])
    pz = np.empty(inner.shape[0])
    out = np.zeros(ray.shape[0])
    for i in range(ray.shape[0]):
        lx = top_h[i] * normal[0]
        ly = top_h[i] * normal[1]
        lz = top_h[i] * normal[2]
        for j in range(fractions.shape[0]):
            hk = top_h[i] * fractions[j]
            t = (hk - offset) / ray_n[i]
            fx = ray[i, 0] * t - hk * normal[0]
            fy = ray[i, 1] * t - hk * normal[1]
            fz = ray[i, 2] * t - hk * normal[2]
            if not (_on_object(fx, fy, fz, cam, obj) and _on_object(fx + lx, fy + ly, fz + lz, cam, obj)):
                continue
            for m in range(inner.shape[0]):
                f = inner[m]
                z = fz + f * lz
                pu[m] = np.rint(cu + fu * (fx + f * lx) / z)
                pv[m] = np.rint(cv + fv * (fy + f * ly) / z)
                pz[m] = z
            under = True
            for m in range(inner.shape[0]):  # _on_object
                if not (pz[m] > 0.0 and pu[m] >= 0.0 and pu[m] < cols and pv[m] >= 0.0 and pv[m] < rows
                        and obj[int(pv[m]), int(pu[m])]):
                    under = False
                    break
            if under:
                out[i] = hk
                break
    return out


@njit(cache=True, nogil=True)
def under_prism(base, normal, heights, cam, sil):
    """Whether each table point ``base`` (K, 3) (camera frame) is under the prism whose image is ``sil``: the
    points ``base + h normal`` at every one of ``heights`` project onto ``sil`` pixels."""
    out = np.zeros(base.shape[0], dtype=np.bool_)
    for i in range(base.shape[0]):
        ok = True
        for h in heights:
            if not _on_object(base[i, 0] + h * normal[0], base[i, 1] + h * normal[1], base[i, 2] + h * normal[2],
                              cam, sil):
                ok = False
                break
        out[i] = ok
    return out


@njit(cache=True, nogil=True, inline='always')
def grid_point(x, y, h, rot, z0):
    """Sensor-frame point of grid point (x, y) at height h above the table: ``GridGeometry.to_sensor`` of a grid
    with rotation ``rot`` and ``z0``, summed term by term (the grid's BLAS product may round the last bit
    otherwise)."""
    lz = z0 - h
    return (x * rot[0, 0] + y * rot[0, 1] + lz * rot[0, 2],
            x * rot[1, 0] + y * rot[1, 1] + lz * rot[1, 2],
            x * rot[2, 0] + y * rot[2, 1] + lz * rot[2, 2])


@njit(cache=True, nogil=True)
def under_seen_surface(pts, heights, rot, z0, cam, foot_xy, above, tol):
    """Whether each table point ``pts`` (N, 2) (grid frame) lies under a surface the camera sees: at one of
    ``heights`` (tried in order, stopping at the first), the pixel looking at the point that high above it sees
    a surface (``above``) whose orthographic foot ``foot_xy`` (H, W, 2) is within ``tol`` of the point."""
    rows, cols = above.shape
    out = np.zeros(pts.shape[0], dtype=np.bool_)
    for i in range(pts.shape[0]):
        x = pts[i, 0]
        y = pts[i, 1]
        for h in heights:
            sx, sy, sz = grid_point(x, y, h, rot, z0)
            u, v = _pixel(sx, sy, sz, cam, cols, rows)
            if u < 0 or not above[v, u]:
                continue
            dx = foot_xy[v, u, 0] - x
            dy = foot_xy[v, u, 1] - y
            if math.sqrt(dx * dx + dy * dy) <= tol:  # NaN feet never are
                out[i] = True
                break
    return out
