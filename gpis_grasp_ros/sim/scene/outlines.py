"""Object outlines from files and masks: polygon CSV files (read and write) and binary mask images."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from gpis_grasp_ros.sim.scene.polygons import validate_polygon


def _clean_file_path(path: str | os.PathLike[str], what: str) -> Path:
    p = Path(path)
    if not p.exists():
        raise ValueError(f'{what} file not found: {p}')
    if not p.is_file():
        raise ValueError(f'{what} path is not a file: {p}')
    return p


def load_polygon_csv(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a polygon from a CSV file: one ``x,y`` vertex per line in metres.

    Blank lines and ``#`` comments are ignored, as is one non-numeric header line (e.g. ``x,y``).
    The polygon is validated (:func:`validate_polygon`); errors are ValueError with file:line.
    """
    p = _clean_file_path(path, 'polygon')
    rows: list[tuple[float, float]] = []
    header_seen = False
    for lineno, line in enumerate(p.read_text(encoding='utf8').splitlines(), start=1):
        text = line.split('#', 1)[0].strip()
        if not text:
            continue
        parts = [s for s in text.replace(';', ',').replace('\t', ',').replace(' ', ',').split(',') if s]
        try:
            values = [float(s) for s in parts]
        except ValueError:
            if not rows and not header_seen:
                header_seen = True
                continue
            raise ValueError(f"{p}:{lineno}: expected 'x,y' in metres, got '{line.strip()}'") from None
        if len(values) != 2:
            raise ValueError(f"{p}:{lineno}: expected 2 values 'x,y' in metres, got {len(values)}")
        rows.append((values[0], values[1]))
    return validate_polygon(np.array(rows, dtype=np.float64).reshape(-1, 2), what=f'polygon {p}')


def save_polygon_csv(path: str | os.PathLike[str], poly: np.ndarray, comment: str = '') -> None:
    """Write a polygon as ``x,y`` lines (metres, round-trip exact ``%.17g``)."""
    lines = [f'# {line}' for line in comment.splitlines()] + ['# x,y (m, table plane = camera x, y)']
    lines += [f'{x:.17g},{y:.17g}' for x, y in np.asarray(poly, dtype=np.float64)]
    Path(path).write_text('\n'.join(lines) + '\n', encoding='utf8')


def mask_to_polygon(mask: np.ndarray, mpp: float, center: tuple[float, float] = (0.0, 0.0),
                    tolerance_px: float = 0.5) -> np.ndarray:
    """Outline polygon (m) of the single object in a binary mask with ``mpp`` metres per pixel.

    The mask is centred on ``center`` (x, y) of the table plane (default: on the optical axis);
    mask rows run along +y. Holes are filled; the outline passes through boundary pixel centres and
    is simplified (Douglas-Peucker) to within ``tolerance_px`` pixels. Raises ValueError for an
    empty mask or several separate objects.
    """
    import cv2

    if not (np.isfinite(mpp) and mpp > 0):
        raise ValueError(f'metres per pixel must be positive, got {mpp}')
    m = np.asarray(mask)
    if m.ndim != 2:
        raise ValueError(f'mask must be a 2-D array, got shape {m.shape}')
    binary = (m > 0).astype(np.uint8)
    if not binary.any():
        raise ValueError('mask contains no object pixels (expected non-zero / white object pixels)')
    n_labels, _ = cv2.connectedComponents(binary, connectivity=8)
    if n_labels - 1 > 1:
        raise ValueError(f'mask contains {n_labels - 1} separate objects; exactly one is expected')
    contours, _ = cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    contour = max(contours, key=cv2.contourArea)
    contour = cv2.approxPolyDP(contour, float(tolerance_px), True).reshape(-1, 2).astype(np.float64)
    h, w = binary.shape
    xy = np.stack([(contour[:, 0] + 0.5 - w / 2.0) * mpp + center[0],
                   (contour[:, 1] + 0.5 - h / 2.0) * mpp + center[1]], axis=1)
    return validate_polygon(xy, what='mask outline')


def load_mask_png(path: str | os.PathLike[str], mpp: float) -> np.ndarray:
    """Object outline (m) from an image mask: pixels brighter than 127 (or opaque, if the image has
    an alpha channel that is not fully opaque) are the object. See :func:`mask_to_polygon`."""
    import cv2

    p = _clean_file_path(path, 'mask')
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f'mask {p} is not a readable image')
    if img.ndim == 3 and img.shape[2] == 4 and (img[..., 3] < 255).any():
        binary = img[..., 3] > 127
    else:
        grey = img if img.ndim == 2 else img[..., :3].mean(axis=2)
        binary = grey > (127 if img.dtype == np.uint8 else np.iinfo(img.dtype).max // 2
                         if np.issubdtype(img.dtype, np.integer) else 0.5)
    if not binary.any():
        raise ValueError(f'mask {p} contains no object pixels (expected white object on black)')
    return mask_to_polygon(binary, mpp)
