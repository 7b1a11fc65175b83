"""GPIS-Blur visualisation (paper section IV, Fig. 2).

For S joint samples f_i ~ N(mu, Sigma) on the grid (:meth:`GpisPosterior.sample`):

    m_i(x_j) = sum_{x_k in N(x_j)} I(f_i(x_k) <= 0),     z_i(x_j) = 1 if m_i(x_j) > 0 else 0

N(x_j) is the (2k + 1) x (2k + 1) window of cells centred on x_j (k = ``neighborhood``; k = 0
is the cell alone), so z_i is sample i's object region {f_i <= 0} dilated by k cells: its
outer rim marks the zero crossing. The z_i are averaged into p(x_j) in [0, 1] (the fraction
of sampled shapes that reach x_j), drawn as intensity 255 (1 - p) so that certain object is
black and certain free space white, like the dark shapes of the paper's Fig. 1 and 2; the
image is optionally upsampled (bilinear, on the averaged image) and then histogram-equalised
(``cv2.equalizeHist``) to stretch the grey levels of uncertain regions. Equalisation is
monotonic, so certain object stays darkest and certain free space lightest.

Samples are drawn and thresholded in chunks, so memory is bounded by ``chunk`` x H x W.
"""

from __future__ import annotations

import cv2
import numpy as np

from gpis_grasp_ros.core.gpis import GpisPosterior


def _dilate_any(mask: np.ndarray, k: int) -> np.ndarray:
    """Logical OR over a (2k+1) x (2k+1) window for a stack of masks ``(n, H, W)`` (separable)."""
    if k <= 0:
        return mask
    n, h, w = mask.shape
    padded = np.zeros((n, h + 2 * k, w), dtype=bool)
    padded[:, k:k + h] = mask
    rows = np.zeros((n, h, w), dtype=bool)
    for d in range(2 * k + 1):
        rows |= padded[:, d:d + h]
    padded = np.zeros((n, h, w + 2 * k), dtype=bool)
    padded[:, :, k:k + w] = rows
    out = np.zeros((n, h, w), dtype=bool)
    for d in range(2 * k + 1):
        out |= padded[:, :, d:d + w]
    return out


def zero_crossing_frequency(posterior: GpisPosterior, n_samples: int = 1000, rng: np.random.Generator | None = None,
                            neighborhood: int = 1, chunk: int = 250) -> np.ndarray:
    """Average of the indicators z_i over ``n_samples`` joint samples → ``(H, W)`` float in [0, 1]."""
    if n_samples < 1:
        raise ValueError(f'n_samples must be >= 1, got {n_samples}')
    if neighborhood < 0:
        raise ValueError(f'neighborhood must be >= 0 cells, got {neighborhood}')
    rng = np.random.default_rng(0) if rng is None else rng
    total = np.zeros(posterior.geometry.shape)
    for start in range(0, n_samples, chunk):
        m = min(chunk, n_samples - start)
        z = _dilate_any(posterior.sample(m, rng) <= 0.0, neighborhood)
        total += z.sum(axis=0)
    return total / n_samples


def gpis_blur(posterior: GpisPosterior, n_samples: int = 1000, rng: np.random.Generator | None = None,
              neighborhood: int = 1, upsample: int = 1, equalize: bool = True) -> np.ndarray:
    """GPIS-Blur image (section IV): uint8 ``(H * upsample, W * upsample)``, dark = object.

    Args:
        posterior: GPIS posterior to visualise.
        n_samples: number S of joint shape samples (the paper uses 1000).
        rng: random generator (default: seeded with 0, so images are reproducible).
        neighborhood: half-width k (cells) of the window N(x_j).
        upsample: integer zoom factor (bilinear interpolation of the equalised image).
        equalize: apply histogram equalisation (the paper's contrast enhancement).
    """
    if upsample < 1:
        raise ValueError(f'upsample must be >= 1, got {upsample}')
    freq = zero_crossing_frequency(posterior, n_samples, rng, neighborhood)
    img = np.clip(np.rint((1.0 - freq) * 255.0), 0, 255).astype(np.uint8)
    if equalize:
        img = equalize_uncertain(img)
    if upsample > 1:
        h, w = img.shape
        img = cv2.resize(img, (w * upsample, h * upsample), interpolation=cv2.INTER_LINEAR)
    return img


def equalize_uncertain(img: np.ndarray) -> np.ndarray:
    """Histogram-equalise the grey pixels (1..254) of a uint8 image; 0 and 255 are kept (see above)."""
    out = img.copy()
    grey = (img > 0) & (img < 255)
    values = img[grey]
    if values.size == 0 or values.min() == values.max():
        return out
    eq = cv2.equalizeHist(values.reshape(1, -1)).ravel().astype(np.float64)
    out[grey] = np.clip(np.rint(1.0 + eq * (253.0 / 255.0)), 1, 254).astype(np.uint8)
    return out
