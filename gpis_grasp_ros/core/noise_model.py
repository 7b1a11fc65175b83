"""Axial depth-noise model of a PrimeSense Carmine / Kinect v1 structured-light sensor.

Used both by the sensing pipeline (to weight measurements, paper section III-B) and by the
scene simulator that produces the shipped bags, so simulated data and the model agree.

Model (Nguyen, Izadi and Lovell, "Modeling Kinect Sensor Noise for Improved 3D Reconstruction
and Tracking", 3DIMPVT 2012, eq. 4, fitted for surfaces at 10-60 degrees to the optical axis):

    sigma_z(z) = 0.0012 + 0.0019 * (z - 0.4)^2      [m], z in metres (valid ~0.5 to 3 m)

Depth quantisation of the disparity-based sensor (Khoshelham and Elberink, "Accuracy and
Resolution of Kinect Depth Data for Indoor Mapping Applications", Sensors 2012): the depth step
between consecutive disparity levels grows with z^2,

    q(z) = 2.85e-3 * z^2                             [m]
"""

from __future__ import annotations

import numpy as np

SIGMA_Z_CONSTANT_M = 0.0012
SIGMA_Z_QUADRATIC_PER_M = 0.0019
SIGMA_Z_REFERENCE_DEPTH_M = 0.4
QUANTISATION_PER_M = 2.85e-3


def axial_sigma(depth_m: np.ndarray | float) -> np.ndarray:
    """Standard deviation (m) of one depth measurement at depth ``depth_m`` (m), Nguyen et al. 2012."""
    z = np.asarray(depth_m, dtype=np.float64)
    return SIGMA_Z_CONSTANT_M + SIGMA_Z_QUADRATIC_PER_M * (z - SIGMA_Z_REFERENCE_DEPTH_M) ** 2


def axial_variance(depth_m: np.ndarray | float) -> np.ndarray:
    """Variance (m^2) of one depth measurement at depth ``depth_m`` (m)."""
    return axial_sigma(depth_m) ** 2


def quantisation_step(depth_m: np.ndarray | float) -> np.ndarray:
    """Depth resolution (m) of the disparity quantisation at depth ``depth_m`` (m)."""
    z = np.asarray(depth_m, dtype=np.float64)
    return QUANTISATION_PER_M * z ** 2


def quantise(depth_m: np.ndarray) -> np.ndarray:
    """Round depths (m) to the sensor's depth levels; NaN (no return) stays NaN.

    The sensor measures disparity, proportional to 1/z, in integer steps, so the levels are evenly
    spaced in 1/z; with the step q(z) = k z^2 above that spacing is k (1/m):
    z_q = 1 / (k * round(1 / (k z))).
    """
    z = np.asarray(depth_m, dtype=np.float64)
    ok = np.isfinite(z) & (z > 0)
    k = QUANTISATION_PER_M
    n = np.round(1.0 / (k * np.where(ok, z, 1.0)))
    return np.where(ok & (n > 0), 1.0 / (k * np.maximum(n, 1.0)), np.nan)
