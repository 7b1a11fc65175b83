"""The chromaticity test of a clear body: each pixel's chromaticity against the table's, in the table's own spread.

A clear body seen through shows the table desaturated and tinted, at the table's depth and brightness: only its
chromaticity tells it from the table (:func:`chromaticity_distance`). :func:`frame_chromaticity` takes it once per
frame, when a stage first asks, so a window of the frame uses the whole frame's table statistics.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
from numba import njit

from gpis_grasp_ros.core.median import median
from gpis_grasp_ros.core.sensing.params import CHROMA_DARK, CHROMA_MIN_SIGMA, CHROMA_SMOOTH_PX


def chromaticity_distance(rgb: np.ndarray, train: np.ndarray, smooth_px: float = CHROMA_SMOOTH_PX,
                          dark: float = CHROMA_DARK) -> tuple[np.ndarray, float, float]:
    """Distance of each pixel's chromaticity from the table's, in robust sigmas of the table's own spread.

    Chromaticity c = (r, g, b) / (r + g + b) of the colour image smoothed with a Gaussian of ``smooth_px``
    pixels (demosaicing / JPEG noise): it ignores brightness, so a shadow or a highlight *of the table's
    colour* is at distance ~0, while the table seen *through* clear plastic - desaturated and tinted by the
    walls' reflections - is not. The table's chromaticity is the median over the training pixels ``train``
    (plane inliers); D = |c - c_table|, standardised as z = (D - median) / (1.4826 MAD) over the training
    pixels (at least ``CHROMA_MIN_SIGMA``: the smoothing halo of a coloured object on a noiseless table is
    not a body), so the test adapts to the table's texture (a mottled cloth, wood grain) and to the sensor; the
    spread grows as 1 / sqrt(brightness) for pixels darker than the table (the chromaticity noise of a shadow).
    Pixels darker than ``dark`` (sum of 0-255 RGB / 3) have no reliable chromaticity: z = 0.

    Returns z (H x W), and the median and MAD scale of D over the training pixels."""
    img = np.asarray(rgb, dtype=np.float32)
    if smooth_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), smooth_px, borderType=cv2.BORDER_REPLICATE)
    img = np.ascontiguousarray(img).reshape(-1, 3)
    train = np.ascontiguousarray(train, dtype=bool).reshape(-1)
    shape = np.shape(rgb)[:2]
    n = int(np.count_nonzero(train))
    if n < 20:
        return np.zeros(shape), 0.0, 1.0
    # the training pixels' chromaticities and brightness (total), then their distances from the median one
    samples = np.empty((4, n), np.float32)
    _chroma_samples(img, train, samples)
    c_table = np.array([median(samples[k]) for k in range(3)], dtype=np.float32)
    dist = np.empty(img.shape[0], np.float32)
    dist_train = np.empty(n, np.float32)
    _chroma_distance(img, train, c_table, dist, dist_train)
    med = float(median(dist_train))
    scale = max(CHROMA_MIN_SIGMA, 1.4826 * float(median(np.abs(dist_train - med))))
    # the chromaticity of a darker pixel is noisier (shot noise over less light): its spread is the table's
    # times sqrt(table brightness / pixel brightness), so a shadow is not flagged by its noise
    z = np.empty(img.shape[0])
    _chroma_z(img, dist, np.float32(float(median(samples[3]))), np.float32(scale), np.float32(med),
              np.float32(dark), z)
    return z.reshape(shape), med, scale


# The chromaticity's per-pixel passes, in float32 as the array code (total = (r + g) + b, chroma = colour /
# np.maximum(total, 1e-3), |chroma - c_table| summed as ``norm_of``, Python floats taken as float32).
@njit(cache=True, nogil=True, inline='always')
def _brightness(img, k):
    total = img[k, 0] + img[k, 1]
    total = total + img[k, 2]
    return total, (total if not total < np.float32(1e-3) else np.float32(1e-3))  # np.maximum: NaN kept


@njit(cache=True, nogil=True)
def _chroma_samples(img, train, out):
    j = 0
    for k in range(train.size):
        if train[k]:
            total, den = _brightness(img, k)
            for c in range(3):
                out[c, j] = img[k, c] / den
            out[3, j] = total
            j += 1


@njit(cache=True, nogil=True)
def _chroma_distance(img, train, c_table, dist, dist_train):
    j = 0
    for k in range(train.size):
        den = _brightness(img, k)[1]
        d0 = img[k, 0] / den - c_table[0]
        d1 = img[k, 1] / den - c_table[1]
        d2 = img[k, 2] / den - c_table[2]
        total = d0 * d0
        total = total + d1 * d1
        total = total + d2 * d2
        dist[k] = np.sqrt(total)
        if train[k]:
            dist_train[j] = dist[k]
            j += 1


@njit(cache=True, nogil=True)
def _chroma_z(img, dist, table_total, scale, med, dark, z):
    """z = (dist - med) / spread where total / 3 >= dark (0 elsewhere), spread = scale sqrt(max(1, table_total /
    max(total, 1e-3)))."""
    for k in range(dist.size):
        total, den = _brightness(img, k)
        ratio = table_total / den
        if not (ratio >= np.float32(1.0) or ratio != ratio):  # np.maximum(1.0, ratio): NaN kept
            ratio = np.float32(1.0)
        spread = scale * np.sqrt(ratio)
        z[k] = (dist[k] - med) / spread if total / np.float32(3.0) >= dark else 0.0


def frame_chromaticity(rgb: np.ndarray, train: np.ndarray) -> Callable[[], np.ndarray]:
    """The z-scores of :func:`chromaticity_distance` of ``rgb`` against the table pixels ``train``, computed on the
    first call and kept."""
    kept: list[np.ndarray] = []

    def z() -> np.ndarray:
        if not kept:
            kept.append(chromaticity_distance(rgb, train)[0])
        return kept[0]

    return z
