"""Axial depth-noise models of RGB-D sensors, and the effective number of independent frames.

Used both by the sensing pipeline (to weight measurements, paper section III-B) and by the
scene simulator that produces the shipped bags, so simulated data and the model agree.

Every model is a :class:`SensorModel` with

    sigma_z(z) = c0 + c1 * (z - z_ref)^2 + c2 * z^2          [m], z = depth along the optical axis (m)
    q(z)       = q2 * z^2 + q0                               [m], depth step of the quantisation

**carmine** (PrimeSense Carmine / Kinect v1 structured light, the paper's sensor, the default):
Nguyen, Izadi and Lovell, "Modeling Kinect Sensor Noise for Improved 3D Reconstruction and
Tracking", 3DIMPVT 2012, eq. 4 (surfaces at 10-60 degrees to the optical axis):
c0 = 0.0012 m, c1 = 0.0019 1/m, z_ref = 0.4 m, c2 = 0. Disparity quantisation (Khoshelham and
Elberink, Sensors 2012): q2 = 2.85e-3 1/m, q0 = 0.

**realsense_d400** (Intel RealSense D415/D435 active stereo): Intel's depth RMS error formula
(Intel RealSense "Tuning depth cameras for best performance" white paper, Grunnet-Jepsen et al.):

    RMS error = z^2 * subpixel / (focal_px * baseline)

with the D435's baseline 50 mm, a subpixel accuracy of 0.08 px and the depth focal length of
the 848 x 480 mode (~424 px, 87 degrees HFOV) - the resolution Intel recommends for depth -
gives c2 = 0.08 / (424 * 0.050) = 3.8e-3 1/m (3.8 mm at 1 m, 2.4 mm at 0.8 m, consistent with
the 2-4 mm seen on real D435 captures); c0 = c1 = 0. The depth image is delivered in 1 mm
units: q0 = 1e-3 m, q2 = 0.

**custom**: all five coefficients given by the user.

**Shadow of the second viewpoint** (``occluder_x_m``). A structured-light sensor measures a point only if its IR
projector lights it too, an active-stereo sensor only if its second imager sees it: table points hidden from that
second viewpoint by an object get no return - the projector (stereo) shadow beside the object, on the side away from
the viewpoint. ``occluder_x_m`` is its position along +x of the depth image's camera frame (m; 0 = no such shadow
modelled; ``occluder_y_m`` along +y, for a camera rolled about its optical axis: upside down, x = -0.075 for a
Carmine; rolled a quarter turn clockwise in the image, y = +0.075): **carmine** 0.075 (the projector of the
PrimeSense / Kinect v1 design, 7.5 cm from the IR camera), **realsense_d400** 0.050 (the D435's stereo baseline, the
right imager); the simulator puts its projector there too (``sim.scene.CameraModel.projector_baseline``). Checked on
the real D435 capture of ``bags/real`` with opaque objects: the table points the model hides from x = +0.050 m are
no-return pixels in 99 % of 2280 cases beyond what the camera itself cannot see (56 % of 3523 with the imager on the
other side; ``test/core/test_shadow.py``), see ``sensing.occlusion_shadow_pixels``.

Frames are averaged to reduce the noise (section III-B: 10 frames). The reduction is only as
large as the frames are independent: :func:`effective_frame_count` *measures* it from the
frame-to-frame depth differences (identical repeated frames count as one).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.stats import chi2

from gpis_grasp_ros.core.median import median

SIGMA_Z_CONSTANT_M = 0.0012
SIGMA_Z_QUADRATIC_PER_M = 0.0019
SIGMA_Z_REFERENCE_DEPTH_M = 0.4
QUANTISATION_PER_M = 2.85e-3

#: Intel D435: baseline (m), subpixel accuracy (px), depth focal length at 848 x 480 (px).
D435_BASELINE_M = 0.050
D435_SUBPIXEL_PX = 0.08
D435_DEPTH_FOCAL_PX = 424.0
D435_STEREO_PER_M = D435_SUBPIXEL_PX / (D435_DEPTH_FOCAL_PX * D435_BASELINE_M)
D435_DEPTH_UNIT_M = 0.001
#: x (m, depth camera frame) of the second viewpoint a return needs: Carmine's IR projector, the D435's right imager.
CARMINE_PROJECTOR_X_M = 0.075
D435_OCCLUDER_X_M = D435_BASELINE_M

SENSOR_MODELS = ('carmine', 'realsense_d400', 'custom')


@dataclass(frozen=True)
class SensorModel:
    """Axial noise sigma_z(z) = c0 + c1 (z - z_ref)^2 + c2 z^2 and quantisation q(z) = q2 z^2 + q0 (m)."""

    name: str = 'carmine'
    sigma_constant_m: float = SIGMA_Z_CONSTANT_M  # c0
    sigma_quadratic_per_m: float = SIGMA_Z_QUADRATIC_PER_M  # c1
    sigma_reference_depth_m: float = SIGMA_Z_REFERENCE_DEPTH_M  # z_ref
    sigma_stereo_per_m: float = 0.0  # c2
    quantisation_per_m: float = QUANTISATION_PER_M  # q2
    quantisation_constant_m: float = 0.0  # q0
    occluder_x_m: float = CARMINE_PROJECTOR_X_M  # x (m) of the projector / second imager; 0 = no shadow model
    occluder_y_m: float = 0.0  # y (m) of it: a camera rolled about its optical axis (a portrait mount)

    def __post_init__(self) -> None:
        values = (self.sigma_constant_m, self.sigma_quadratic_per_m, self.sigma_reference_depth_m,
                  self.sigma_stereo_per_m, self.quantisation_per_m, self.quantisation_constant_m)
        if not all(math.isfinite(v) and v >= 0 for v in values):
            raise ValueError(f'sensor model coefficients must be finite and >= 0, got {values}')
        for name in ('occluder_x_m', 'occluder_y_m'):
            value = getattr(self, name)
            if not (math.isfinite(value) and abs(value) <= 1.0):
                raise ValueError(f'sensor model: {name} must be a finite offset of at most 1 m, got {value}')
        if self.sigma_constant_m + self.sigma_quadratic_per_m + self.sigma_stereo_per_m <= 0:
            raise ValueError('sensor model: sigma_z would be 0 at every depth (give c0, c1 or c2 > 0)')

    @classmethod
    def named(cls, name: str) -> SensorModel:
        """The documented model ``'carmine'`` or ``'realsense_d400'``."""
        if name == 'carmine':
            return cls()
        if name == 'realsense_d400':
            return cls('realsense_d400', 0.0, 0.0, 0.0, D435_STEREO_PER_M, 0.0, D435_DEPTH_UNIT_M, D435_OCCLUDER_X_M)
        raise ValueError(f"unknown sensor model '{name}' (one of 'carmine', 'realsense_d400', or build a custom "
                         'SensorModel from coefficients)')

    def sigma(self, depth_m: np.ndarray | float) -> np.ndarray:
        """Standard deviation (m) of one depth measurement at depth ``depth_m`` (m)."""
        z = np.asarray(depth_m, dtype=np.float64)
        return (self.sigma_constant_m + self.sigma_quadratic_per_m * (z - self.sigma_reference_depth_m) ** 2
                + self.sigma_stereo_per_m * z ** 2)

    def variance(self, depth_m: np.ndarray | float) -> np.ndarray:
        """Variance (m^2) of one measurement, quantisation included: sigma_z^2 + q^2 / 12."""
        return self.sigma(depth_m) ** 2 + self.quantisation(depth_m) ** 2 / 12.0

    def quantisation(self, depth_m: np.ndarray | float) -> np.ndarray:
        """Depth step (m) of the sensor's quantisation at depth ``depth_m`` (m)."""
        z = np.asarray(depth_m, dtype=np.float64)
        return self.quantisation_per_m * z ** 2 + self.quantisation_constant_m


CARMINE = SensorModel()


def axial_sigma(depth_m: np.ndarray | float) -> np.ndarray:
    """Standard deviation (m) of one Carmine depth measurement at depth ``depth_m`` (m), Nguyen et al. 2012."""
    return CARMINE.sigma(depth_m)


def axial_variance(depth_m: np.ndarray | float) -> np.ndarray:
    """Variance (m^2) of one Carmine depth measurement at depth ``depth_m`` (m)."""
    return axial_sigma(depth_m) ** 2


def quantisation_step(depth_m: np.ndarray | float) -> np.ndarray:
    """Carmine depth resolution (m) of the disparity quantisation at depth ``depth_m`` (m)."""
    return CARMINE.quantisation(depth_m)


def quantise(depth_m: np.ndarray) -> np.ndarray:
    """Round depths (m) to the Carmine's depth levels; NaN (no return) stays NaN.

    The sensor measures disparity, proportional to 1/z, in integer steps, so the levels are evenly
    spaced in 1/z; with the step q(z) = k z^2 above that spacing is k (1/m):
    z_q = 1 / (k * round(1 / (k z))).
    """
    z = np.asarray(depth_m, dtype=np.float64)
    ok = np.isfinite(z) & (z > 0)
    k = QUANTISATION_PER_M
    n = np.round(1.0 / (k * np.where(ok, z, 1.0)))
    return np.where(ok & (n > 0), 1.0 / (k * np.maximum(n, 1.0)), np.nan)


def distinct_frames(depth_frames: np.ndarray) -> np.ndarray:
    """Indices of the frames that are not an exact repeat of an earlier frame: every return the same and no return
    (NaN, inf or <= 0, however encoded) where the other has none."""
    frames = np.ascontiguousarray(depth_frames, dtype=np.float64)
    flat = frames.reshape(frames.shape[0], -1)
    keep: list[int] = []
    for i in range(flat.shape[0]):
        if not any(_same_returns(flat[i], flat[j]) for j in keep):
            keep.append(i)
    return np.asarray(keep, dtype=np.int64)


@njit(cache=True, nogil=True)
def _same_returns(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two flat depth frames hold the same returns (stops at the first difference)."""
    for k in range(a.size):
        x, y = a[k], b[k]
        x_ok = np.isfinite(x) and x > 0.0
        y_ok = np.isfinite(y) and y > 0.0
        if x_ok != y_ok or (x_ok and x != y):
            return False
    return True


@njit(cache=True, nogil=True)
def _temporal_moments(flat: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sample variance (ddof 1) and mean over the frames ``idx`` of the pixels of ``flat`` (N, P) with a return in
    all of them, in pixel order: what ``values.var(axis=0, ddof=1)`` and ``values.mean(axis=0)`` give for
    ``values = flat[idx][:, ok]`` (the same sums in the same order: frame after frame)."""
    n = idx.size
    npx = flat.shape[1]
    # frame after frame, each frame's row read in order (every pixel summed; those without a return dropped after)
    ok = np.ones(npx, dtype=np.bool_)
    total = np.zeros(npx)
    for j in range(n):
        row = flat[idx[j]]
        for p in range(npx):
            x = row[p]
            ok[p] &= (x > 0.0) & (x < np.inf)  # finite and > 0
            total[p] = x if j == 0 else total[p] + x
    count = 0
    for p in range(npx):
        count += ok[p]
    mean_all = total / n
    q = np.zeros(npx)
    for j in range(n):
        row = flat[idx[j]]
        if j == 0:
            for p in range(npx):
                d = row[p] - mean_all[p]
                q[p] = d * d
        else:
            for p in range(npx):
                d = row[p] - mean_all[p]
                q[p] += d * d
    s2 = np.empty(count)
    mean = np.empty(count)
    k = 0
    for p in range(npx):
        if ok[p]:
            s2[k] = q[p] / (n - 1)
            mean[k] = mean_all[p]
            k += 1
    return s2, mean


def effective_frame_count(depth_frames: np.ndarray, model: SensorModel, min_pixels: int = 50) -> float:
    """Number of *independent* frames the average of ``depth_frames`` ``(N, H, W)`` (m) is worth.

    Exact repeats are removed first (:func:`distinct_frames`). For the remaining n frames the
    temporal variance of each pixel valid in all of them is compared with the sensor model's
    variance at that depth: n_eff = 1 + (n - 1) min(1, median(s_t^2) / (b_n median(sigma_model^2))),
    b_n = median(chi2_{n-1}) / (n - 1) the median's bias for Gaussian noise.
    Independent frames with the modelled noise give n_eff ~ n; frames that repeat one measurement
    (a paused driver, a still image played in a loop, strong temporal filtering) give n_eff ~ 1,
    so the averaged variance sigma^2 / n_eff is not under-estimated. With fewer than
    ``min_pixels`` such pixels the frames are counted as independent (n) - nothing was measured.
    A pixel has a return where its depth is finite and > 0 (NaN, inf and <= 0 are no return).
    """
    frames = np.ascontiguousarray(depth_frames, dtype=np.float64)
    idx = distinct_frames(frames)
    n = int(idx.size)
    if n <= 1:
        return 1.0
    s2, mean = _temporal_moments(frames.reshape(frames.shape[0], -1), idx)
    if s2.size < min_pixels:
        return float(n)
    model_var = model.variance(mean)
    # the median of a sample variance of n Gaussian values is chi2_{n-1} median / (n - 1) of the variance
    unbias = float(chi2.ppf(0.5, n - 1) / (n - 1))
    ratio = float(median(s2) / unbias / max(float(median(model_var)), 1e-18))
    return float(1.0 + (n - 1) * min(1.0, ratio))
