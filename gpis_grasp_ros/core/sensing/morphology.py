"""Image and raster morphology shared by the stages: nearest pixels, hole filling, reconstruction, flooding."""

from __future__ import annotations

import cv2
import numpy as np


def nearest_pixel(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For every pixel (or raster cell) of ``mask`` (H x W bool, at least one True): the distance to the nearest
    True pixel (float32, pixels; 0 on them) and that pixel's (row, column) (H x W x 2 int)."""
    m = np.asarray(mask, dtype=bool)
    dist, nearest = cv2.distanceTransformWithLabels((~m).astype(np.uint8), cv2.DIST_L2, 5,
                                                    labelType=cv2.DIST_LABEL_PIXEL)
    seen = np.argwhere(m)  # in the (row-major) order of OpenCV's pixel labels
    return dist, seen[np.clip(nearest - 1, 0, len(seen) - 1)]


def _nearest_label(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For every raster cell: the label of the nearest labelled cell and the distance to it (cells)."""
    dist, near = nearest_pixel(labels > 0)
    return labels[near[..., 0], near[..., 1]], dist


def _reconstruct(marker: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Grey-level morphological reconstruction by dilation of ``marker`` under ``mask`` (8-connected)."""
    kernel = np.ones((3, 3), np.uint8)
    out = np.minimum(marker, mask).astype(np.float32)
    mask = mask.astype(np.float32)
    while True:
        nxt = np.minimum(cv2.dilate(out, kernel), mask)
        if np.array_equal(nxt, out):
            return out
        out = nxt


def _flood(markers: np.ndarray, dist: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Watershed of -``dist`` from ``markers`` inside ``mask`` by flooding: level by level from the highest
    distance down (half-cell steps), the labelled regions grow (8-neighbour dilations) into the unlabelled
    mask cells at or above the level, so each cell joins the blob it is deepest in. Only the mask's bounding box
    (and the one cell around it the dilations read) is flooded: nothing grows outside the mask."""
    result = np.zeros(mask.shape, np.int32)
    rows, cols = np.nonzero(mask)
    if rows.size == 0:
        return result
    box = np.s_[max(int(rows.min()) - 1, 0):int(rows.max()) + 2, max(int(cols.min()) - 1, 0):int(cols.max()) + 2]
    markers, dist, mask = markers[box], dist[box], mask[box]
    out = np.where(mask, markers, 0).astype(np.float32)
    kernel = np.ones((3, 3), np.uint8)
    levels = np.unique(np.floor(dist[mask & (markers == 0)] * 2.0) / 2.0)[::-1]
    for level in levels:
        allowed = mask & (dist >= level)
        while True:
            free = allowed & (out == 0)
            grown = cv2.dilate(out, kernel)
            take = free & (grown > 0)
            if not take.any():
                break
            out[take] = grown[take]
    result[box] = out.astype(np.int32)
    return result


def _filled(mask: np.ndarray) -> np.ndarray:
    """``mask`` (H x W) with every hole of its 8-connected regions filled (bool)."""
    out = np.zeros(mask.shape, np.uint8)
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, 1, thickness=cv2.FILLED)
    return out > 0
