"""PNG figures of GPIS posteriors and grasps (OpenCV only; no matplotlib).

Pixel conventions: a grid of H x W cells drawn with ``scale`` pixels per cell is an image of
(H * scale) x (W * scale) pixels; cell (row, col) covers pixels [row * scale, (row + 1) * scale)
and metric (x, y) maps to the continuous pixel position ((x - origin_x) / res * scale,
(y - origin_y) / res * scale) (rows along +y as in :mod:`~gpis_grasp_ros.core.grid`).

Colour order: the drawing helpers work on OpenCV's BGR images; :func:`grasp_overlay` returns
RGB (ready for a ``sensor_msgs/Image`` with encoding ``rgb8``) and :func:`write_png` takes RGB or
grey images.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from gpis_grasp_ros.core.gpis import GpisPosterior
from gpis_grasp_ros.core.grid import GridGeometry

PANEL_PX = 300  # target panel size of save_gpis_figure
FONT = cv2.FONT_HERSHEY_SIMPLEX


def to_color(image_gray: np.ndarray, colormap: int | None = None) -> np.ndarray:
    """Grey image (uint8, or float scaled from its min..max) → BGR uint8; optional cv2 colormap."""
    img = np.asarray(image_gray)
    if img.dtype != np.uint8:
        f = np.nan_to_num(img.astype(np.float64))
        lo, hi = float(f.min()), float(f.max())
        img = np.zeros(f.shape, np.uint8) if hi <= lo else np.rint((f - lo) / (hi - lo) * 255).astype(np.uint8)
    if img.ndim == 3:
        return img.copy()
    if colormap is not None:
        return cv2.applyColorMap(img, colormap)
    return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)


def upscale(img: np.ndarray, factor: int) -> np.ndarray:
    """Nearest-neighbour zoom by an integer factor (each cell becomes factor x factor pixels)."""
    if factor < 1:
        raise ValueError(f'factor must be >= 1, got {factor}')
    if factor == 1:
        return img.copy()
    h, w = img.shape[:2]
    return cv2.resize(img, (w * factor, h * factor), interpolation=cv2.INTER_NEAREST)


def metric_to_pixel(geometry: GridGeometry, xy: np.ndarray, scale: float) -> np.ndarray:
    """Metric points ``(..., 2)`` (m) → continuous pixel coordinates ``(..., 2)`` as (px, py)."""
    xy = np.asarray(xy, dtype=np.float64)
    origin = np.array([geometry.origin_x, geometry.origin_y])
    return (xy - origin) / geometry.resolution * scale


def _pt(p: np.ndarray) -> tuple[int, int]:
    q = np.rint(np.asarray(p) - 0.5).astype(int)  # continuous position → index of the pixel containing it
    return int(q[0]), int(q[1])


def draw_grasp(img_bgr: np.ndarray, geometry: GridGeometry, jaw1_xy: np.ndarray, jaw2_xy: np.ndarray, scale: float,
               color: tuple[int, int, int] = (0, 0, 255), label: str | None = None,
               jaw_width_m: float | None = None, thickness: int = 2) -> np.ndarray:
    """Draw a parallel-jaw grasp in place: closing line g1-g2 and a jaw bar at each end.

    Jaw bars are perpendicular to the closing line, ``jaw_width_m`` long (default 2 cells).
    ``label`` is written next to jaw 1. Returns ``img_bgr`` for chaining.
    """
    g1 = np.asarray(jaw1_xy, dtype=np.float64).reshape(2)
    g2 = np.asarray(jaw2_xy, dtype=np.float64).reshape(2)
    axis = g2 - g1
    norm = float(np.linalg.norm(axis))
    perp = np.array([-axis[1], axis[0]]) / norm if norm > 0 else np.array([0.0, 1.0])
    half = 0.5 * (jaw_width_m if jaw_width_m is not None else 2.0 * geometry.resolution)
    p1, p2 = metric_to_pixel(geometry, np.stack([g1, g2]), scale)
    cv2.line(img_bgr, _pt(p1), _pt(p2), color, max(1, thickness - 1), cv2.LINE_AA)
    for g in (g1, g2):
        a, b = metric_to_pixel(geometry, np.stack([g - half * perp, g + half * perp]), scale)
        cv2.line(img_bgr, _pt(a), _pt(b), color, thickness + 1, cv2.LINE_AA)
    if label:
        x, y = _pt(p1)
        cv2.putText(img_bgr, label, (x + 4, y - 4), FONT, 0.4, color, 1, cv2.LINE_AA)
    return img_bgr


PALETTE_BGR = [(0, 0, 230), (0, 160, 0), (230, 90, 0), (0, 140, 255), (200, 0, 200), (160, 160, 0)]


def write_png(path: str | Path, img: np.ndarray) -> Path:
    """Write an RGB (H, W, 3) or grey (H, W) uint8 image as PNG (creating the folder); returns the path."""
    arr = np.asarray(img)
    if arr.dtype != np.uint8:
        arr = to_color(arr)[..., 0] if arr.ndim == 2 else np.clip(arr, 0, 255).astype(np.uint8)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), cv2.cvtColor(arr, cv2.COLOR_RGB2BGR) if arr.ndim == 3 else arr):
        raise OSError(f'could not write {out}')
    return out


def grasp_overlay(background: np.ndarray, geometry: GridGeometry, grasps: Sequence, scale: int = 8,
                  jaw_width_m: float | None = None) -> np.ndarray:
    """Grasps drawn over a grid image (e.g. GPIS-Blur) → RGB uint8 (H * scale, W * scale, 3).

    ``background`` is a grey or BGR image of the grid at any size (resized to the grid times
    ``scale``). Each grasp is ``(jaw1_xy, jaw2_xy)`` or ``(jaw1_xy, jaw2_xy, label)`` in metres,
    or an object with ``jaw1`` / ``jaw2`` (and optionally ``method`` and ``p_f``, used as label),
    such as a planner result. Colours cycle through a fixed palette.
    """
    h, w = geometry.shape
    img = to_color(background)
    if img.shape[:2] != (h * scale, w * scale):
        shrink = img.shape[0] > h * scale
        img = cv2.resize(img, (w * scale, h * scale), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    for i, grasp in enumerate(grasps):
        if isinstance(grasp, (tuple, list)):
            jaw1, jaw2 = grasp[0], grasp[1]
            label = grasp[2] if len(grasp) > 2 else None
        else:
            jaw1, jaw2 = grasp.jaw1, grasp.jaw2
            method, p_f = getattr(grasp, 'method', None), getattr(grasp, 'p_f', None)
            label = method if method else None
            if label and p_f is not None and np.isfinite(p_f):
                label = f'{label} P_F={p_f:.2f}'
        draw_grasp(img, geometry, np.asarray(jaw1, float)[:2], np.asarray(jaw2, float)[:2], scale,
                   PALETTE_BGR[i % len(PALETTE_BGR)], label, jaw_width_m)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _panel(img_bgr: np.ndarray, title: str, subtitle: str = '') -> np.ndarray:
    header = np.full((34, img_bgr.shape[1], 3), 255, np.uint8)
    cv2.putText(header, title, (5, 14), FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    if subtitle:
        cv2.putText(header, subtitle, (5, 29), FONT, 0.35, (60, 60, 60), 1, cv2.LINE_AA)
    return np.vstack([header, img_bgr])


def _zero_contour(mean: np.ndarray, scale: int) -> np.ndarray:
    """Pixels (upscaled) on the boundary between mu < 0 and mu >= 0 cells."""
    inside = upscale((mean < 0).astype(np.uint8), scale)
    edge = cv2.morphologyEx(inside, cv2.MORPH_GRADIENT, np.ones((2, 2), np.uint8))
    return edge.astype(bool)


def mean_image(posterior: GpisPosterior, scale: int) -> np.ndarray:
    """Posterior mean as a diverging colour image (blue inside, red outside) with the zero level set."""
    mu = posterior.mean
    bound = float(np.max(np.abs(mu))) or 1.0
    gray = np.rint((mu / bound * 0.5 + 0.5) * 255).astype(np.uint8)
    img = upscale(cv2.applyColorMap(gray, cv2.COLORMAP_JET), scale)
    img[_zero_contour(mu, scale)] = (255, 255, 255)
    return img


def std_image(posterior: GpisPosterior, scale: int) -> np.ndarray:
    """Posterior standard deviation sigma (eq. 2) on a 0..max colour scale."""
    return upscale(to_color(np.sqrt(posterior.variance), cv2.COLORMAP_VIRIDIS), scale)


def save_gpis_figure(path: str | Path, posterior: GpisPosterior, blur_image: np.ndarray | None = None) -> Path:
    """Write a PNG with the mean SDF, the posterior std and GPIS-Blur side by side; returns the path.

    ``blur_image`` is a :func:`~gpis_grasp_ros.core.blur.gpis_blur` image of any size; when omitted
    the figure has two panels.
    """
    h, w = posterior.geometry.shape
    scale = max(1, int(round(PANEL_PX / max(h, w))))
    mu = posterior.mean
    panels = [
        _panel(mean_image(posterior, scale), 'mean SDF (white: mu = 0)',
               f'{mu.min() * 1000:+.1f} .. {mu.max() * 1000:+.1f} mm'),
        _panel(std_image(posterior, scale), 'posterior std',
               f'0 .. {np.sqrt(posterior.variance.max()) * 1000:.2f} mm'),
    ]
    if blur_image is not None:
        blur = to_color(blur_image)
        blur = cv2.resize(blur, (w * scale, h * scale), interpolation=cv2.INTER_AREA
                          if blur.shape[0] > h * scale else cv2.INTER_LINEAR)
        panels.append(_panel(blur, 'GPIS-Blur', 'dark = object, grey = uncertain'))
    gap = np.full((panels[0].shape[0], 6, 3), 255, np.uint8)
    row = panels[0]
    for p in panels[1:]:
        row = np.hstack([row, gap, p])
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), row):
        raise OSError(f'could not write {out}')
    return out
