"""Soft per-pixel evidence of "not the table": depth (height above the plane) and a shadow-proof colour model."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
from numba import njit
from scipy.special import ndtr

from gpis_grasp_ros.core.median import median
from gpis_grasp_ros.core.sensing.camera import AveragedFrames
from gpis_grasp_ros.core.sensing.morphology import _filled
from gpis_grasp_ros.core.sensing.params import (
    CHROMA_CORE_PX,
    SensingParams,
)
from gpis_grasp_ros.core.sensing.pixel_kernels import mask_bounds, masked_rows, nan_to_num, norm_of
from gpis_grasp_ros.core.sensing.table import Measurement, TableFit


def shadow_line_distance(rgb: np.ndarray, table_rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance (0-255 units) of colours ``(..., 3)`` from the table's shadow line {alpha t, 0 <= alpha <= 1},
    and the brightness ratio alpha* = x.t / |t|^2 of each colour.

    A shadow scales the table colour t by alpha < 1 (same chromaticity) and is at distance ~0; a
    brighter colour is measured from t itself; a tint or another hue is off the line.
    """
    t = np.asarray(table_rgb, dtype=np.float64)
    ratio = (rgb @ t) / max(float(t @ t), 1e-9)
    if rgb.dtype != np.float64 or ratio.dtype != np.float64:
        alpha = np.clip(ratio, 0.0, 1.0)
        return norm_of([rgb[..., k] - alpha * t[k] for k in range(3)]), ratio  # |rgb - alpha t|
    dist = np.empty(ratio.shape)
    _shadow_line_distance(np.ascontiguousarray(rgb).reshape(-1, 3), np.ascontiguousarray(ratio).reshape(-1), t,
                          dist.reshape(-1))
    return dist, ratio


@njit(cache=True, nogil=True)
def _shadow_line_distance(rgb, ratio, t, out):
    """|rgb - alpha t| with alpha = np.clip(ratio, 0, 1), per colour, summed as ``norm_of``."""
    for k in range(ratio.size):
        a = ratio[k]
        if a < 0.0:
            a = 0.0
        elif a > 1.0:
            a = 1.0
        c0 = rgb[k, 0] - a * t[0]
        c1 = rgb[k, 1] - a * t[1]
        c2 = rgb[k, 2] - a * t[2]
        total = c0 * c0
        total = total + c1 * c1
        total = total + c2 * c2
        out[k] = math.sqrt(total)


@dataclass(frozen=True)
class ColourModel:
    """Table colour model learnt from the plane's inliers (robust statistics: median and 1.4826 MAD)."""

    table_rgb: np.ndarray  # (3,) median colour t of the training pixels (0-255)
    threshold: float  # shadow-line distance above which a colour is not the table's
    sigma: float  # width of the soft ramp of the test
    dark_ratio: float  # brightness ratio below which a colour on the shadow line is "darker than the table"

    def evidence(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """p_c (probability of "not the table") and the brightness ratio of colours ``rgb``."""
        dist, ratio = shadow_line_distance(rgb, self.table_rgb)
        return ndtr((dist - self.threshold) / self.sigma), ratio


def _colour_model(rgb: np.ndarray, train: np.ndarray, params: SensingParams) -> ColourModel:
    """Table colour model from the training pixels ``train`` of the colour image.

    t = median colour; threshold = max(``color_threshold_min``, median + ``color_mad_factor`` MAD) of
    the training pixels' shadow-line distances, ramp max(2, MAD); colours darker than the table's
    own texture (ratio below median - max(0.1, ``color_mad_factor`` MAD)) are "darker than the table".
    Robust statistics, because the plane's inliers include the table seen *through* clear objects."""
    samples = masked_rows(rgb, train) if rgb.ndim == 3 else rgb[train]
    if samples.shape[0] > 50000:
        samples = samples[np.random.default_rng(0).choice(samples.shape[0], 50000, replace=False)]
    if params.table_color is not None:
        table_rgb = np.asarray(params.table_color, dtype=np.float64).reshape(3)
    else:
        table_rgb = np.median(samples, axis=0)
    dist, ratio = shadow_line_distance(samples, table_rgb)
    mad = 1.4826 * float(median(np.abs(dist - median(dist))))
    c_thr = (float(params.color_threshold) if params.color_threshold > 0
             else max(params.color_threshold_min, float(median(dist)) + params.color_mad_factor * mad))
    c_sigma = float(params.color_sigma) if params.color_sigma > 0 else max(2.0, mad)
    ratio_mad = 1.4826 * float(median(np.abs(ratio - median(ratio))))
    dark_ratio = float(median(ratio)) - max(0.1, params.color_mad_factor * ratio_mad)
    return ColourModel(table_rgb, c_thr, c_sigma, dark_ratio)


def _colour_evidence(rgb_mean: np.ndarray, inlier: np.ndarray,
                     params: SensingParams) -> tuple[ColourModel, np.ndarray, np.ndarray]:
    """Table colour model trained on the plane's inliers, per-pixel colour evidence p_c and brightness ratio."""
    img = rgb_mean.astype(np.float32).astype(np.float64)
    model = _colour_model(img, inlier, params)
    p_c, ratio = model.evidence(img)
    return model, p_c, ratio


def _morph_clean(prob: np.ndarray, size: int) -> np.ndarray:
    """Grey-level opening then closing of a probability map (removes specks, fills pinholes)."""
    if size <= 1:
        return prob
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    img = prob.astype(np.float32)
    img = cv2.morphologyEx(img, cv2.MORPH_OPEN, kernel, borderType=cv2.BORDER_REPLICATE)
    img = cv2.morphologyEx(img, cv2.MORPH_CLOSE, kernel, borderType=cv2.BORDER_REPLICATE)
    return img.astype(np.float64)


class Evidence(NamedTuple):
    """Per-pixel soft evidence, cleaned."""

    p_d: np.ndarray  # (H, W) probability of "above the table" from depth
    p_c: np.ndarray  # (H, W) probability of "not the table's colour"
    colour: ColourModel


def soft_evidence(frames: AveragedFrames, fit: TableFit, meas: Measurement, params: SensingParams) -> Evidence:
    """p_d = Phi((h - h_thr) / s_h) and the colour test p_c, each cleaned by a grey-level opening then closing;
    a colour darker than the table on its shadow line defers to depth."""
    p_d = np.where(frames.valid, ndtr((nan_to_num(meas.height) - fit.h_thr) / meas.s_h), 0.0)
    colour, p_c, c_ratio = _colour_evidence(frames.rgb_mean, fit.support, params)
    p_d = _morph_clean(p_d, params.morph_kernel_px)
    p_c = _morph_clean(p_c, params.morph_kernel_px)
    # darker than the table on its shadow line: shadow or a dark object of the table's hue - colour
    # cannot tell, so it defers to depth (no evidence either way, no disagreement)
    p_c = np.where((c_ratio < colour.dark_ratio) & (p_c < 0.5), p_d, p_c)
    return Evidence(p_d, p_c, colour)


def combine(ev: Evidence, missing_px: np.ndarray, params: SensingParams) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel occupancy o, the inverse-variance combination of the two masks (missing = object), and the
    disagreement rho = |p_d - p_c| (0 where missing)."""
    p_d, p_c = np.asarray(ev.p_d), np.asarray(ev.p_c)
    if p_d.dtype != np.float64 or p_c.dtype != np.float64 or p_d.shape != p_c.shape:
        v_d = p_d * (1.0 - p_d) + params.depth_floor_variance
        v_c = p_c * (1.0 - p_c) + params.color_floor_variance
        occ = (p_d / v_d + p_c / v_c) / (1.0 / v_d + 1.0 / v_c)
        return np.where(missing_px, 1.0, occ), np.where(missing_px, 0.0, np.abs(p_d - p_c))
    p_d, p_c = np.ascontiguousarray(p_d), np.ascontiguousarray(p_c)
    missing = np.broadcast_to(np.asarray(missing_px, dtype=bool), p_d.shape)
    occ, rho = np.empty(p_d.shape), np.empty(p_d.shape)
    _combine(p_d.reshape(-1), p_c.reshape(-1), np.ascontiguousarray(missing).reshape(-1),
             float(params.depth_floor_variance), float(params.color_floor_variance), occ.reshape(-1), rho.reshape(-1))
    return occ, rho


@njit(cache=True, nogil=True, error_model='numpy')
def _combine(p_d, p_c, missing, floor_d, floor_c, occ, rho):
    """:func:`combine` per pixel, in the array code's order of operations."""
    for k in range(p_d.size):
        if missing[k]:
            occ[k] = 1.0
            rho[k] = 0.0
            continue
        d, c = p_d[k], p_c[k]
        v_d = d * (1.0 - d) + floor_d
        v_c = c * (1.0 - c) + floor_c
        occ[k] = (d / v_d + c / v_c) / (1.0 / v_d + 1.0 / v_c)
        rho[k] = abs(d - c)


def chromatic_extension(target_px: np.ndarray, candidate: np.ndarray, chroma_z: np.ndarray, z_min: float,
                        core_px: int = CHROMA_CORE_PX) -> np.ndarray:
    """Pixels of a clear target seen only as a change of the table's chromaticity, grown from the target.

    A transparent object lying on the table returns the table's depth through its body, and its colour
    test (:func:`shadow_line_distance`) passes only where it is specular; the body is seen as the table's
    colour desaturated by the plastic. ``chroma_z`` (:func:`chromaticity_distance`) > ``z_min`` marks such
    pixels among the ``candidate`` pixels (table-level, not another object's evidence), opened with a 3 x 3
    disc (isolated texture specks go); the result is the 8-connected regions of them that touch the
    target's pixels ``target_px`` and hold a disc of ``core_px`` pixels (a band of mixed pixels along an
    opaque object's seen edge does not). The region is grown in the image from the target, so chromatic
    pixels elsewhere (texture, other clear objects) never become evidence; other objects' evidence pixels
    are not candidates, so the growth stops at them. Limits: a clear object standing on a table of its
    own tint is not seen this way, and the region leaks along chromatic table pixels that touch the body
    (the base of another clear object seen through, behind it) - the threshold bounds how far."""
    grow = ((chroma_z > z_min) & candidate & ~target_px).astype(np.uint8)
    grow = cv2.morphologyEx(grow, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))) > 0
    if not grow.any():
        return np.zeros_like(grow)
    n, lab = cv2.connectedComponents(grow.astype(np.uint8), connectivity=8)
    touching = cv2.dilate(target_px.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    # a band along the target's seen edge (mixed pixels, a shading rim) has no core: only regions holding a
    # disc of ``core_px`` pixels are a body seen through
    core = cv2.erode(grow.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (core_px, core_px)),
                     borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
    keep = np.zeros(n, dtype=bool)
    keep[np.unique(lab[touching & grow])] = True
    has_core = np.zeros(n, dtype=bool)
    has_core[np.unique(lab[core])] = True
    keep &= has_core
    keep[0] = False
    # gaps enclosed by the body and the target (a label, a highlight) are body too
    return _filled(keep[lab] | target_px) & candidate & ~target_px


def _bounded_extension(target_px: np.ndarray, extension: np.ndarray, params: SensingParams) -> np.ndarray:
    """The chromatic extension, or nothing when it reaches the image (or pixel ROI) border: a region that
    runs out of the image is not the enclosed body of the target (the table's own colour changing)."""
    if not extension.any():
        return extension
    h, w = extension.shape
    b = params.border_px
    u_lo, v_lo, u_hi, v_hi = (0, 0, w - 1, h - 1) if params.roi_px is None else \
        (max(0, params.roi_px[0]), max(0, params.roi_px[1]), min(w - 1, params.roi_px[2]), min(h - 1, params.roi_px[3]))
    v_min, v_max, u_min, u_max = mask_bounds(extension)
    if u_min < u_lo + b or v_min < v_lo + b or u_max > u_hi - b or v_max > v_hi - b:
        return np.zeros_like(extension)
    return extension
