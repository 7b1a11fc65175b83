"""What defines one simulated recording: the object, its materials, distractors, camera, light and sensor.

Lengths in metres, angles in degrees, colours RGB 0..255; the frames are those of
:mod:`gpis_grasp_ros.sim.scene.view`.

* **Camera pose** (``camera_tilt``, ``camera_azimuth``, ``camera_height`` = distance along the optical
  axis from the camera to the table point T(0, 0)): the camera looks at T(0, 0); ``camera_tilt`` is
  the angle between the optical axis and the downward table normal (0 = top-down; a PR2 head camera
  is at 45-55 degrees), the camera leaning back towards +Y (so the near table is at the bottom of the
  image), and ``camera_azimuth`` turns the whole rig about the table normal through T(0, 0). Any pose
  whose view of the table is not grazing works (every pixel ray must meet the table, tilt < 80 degrees).
* **Light** (``light`` = (azimuth, elevation) of the direction towards the light in T, azimuth from +X
  towards +Y, elevation above the table): table points whose line to the light is blocked by a
  non-transparent object or distractor are in shadow: their colour is the table colour times
  ``1 - shadow_strength`` (darker, same chromaticity); depth is unaffected.
* **Distractors** (:class:`Distractor`): further right prisms on the table (own outline, height,
  colour, material). They are seen, cast shadows and occlude, but are not the target: the ground
  truth describes the main object only.
* **Sensor** (``sensor``): ``carmine`` (PrimeSense Carmine 1.09, VGA, fx = fy = 570.3 px, IR projector
  0.075 m along +x) or ``realsense_d400`` (Intel D435 active stereo, depth aligned to the 640 x 480
  colour camera: fx = fy = 615 px; the right imager 0.05 m along +x plays the projector's role for
  occlusion holes; range 0.2-3 m).

Materials (:class:`MaterialRegion`, later regions override earlier ones, only inside the object):

* ``opaque``      default object surface: depth noise from the axial model.
* ``transparent`` the IR pattern passes: depth is the table's; colour is the table's, tinted
  by ``TRANSPARENT_TINT`` (30 %) of the region's colour; 3 % refraction drop-outs.
* ``specular``    the pattern is reflected away: no depth (NaN); colour is a saturated,
  flickering metallic highlight pattern.
* ``dark``        low IR reflectance: 2.5x depth noise, 15 % drop-outs, colour darkened to 30 %.
* ``noisy``       rough / frosted surface: 4x depth noise, 5 % drop-outs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from gpis_grasp_ros.sim.scene.outlines import mask_to_polygon

FRAME_ID = 'camera_rgb_optical_frame'
MATERIAL_KINDS: tuple[str, ...] = ('opaque', 'transparent', 'specular', 'dark', 'noisy')
#: Surface label of each material kind; 0 = no object (the table).
MATERIAL_LABEL = {kind: i + 1 for i, kind in enumerate(MATERIAL_KINDS)}
L_OPAQUE, L_TRANSPARENT, L_SPECULAR, L_DARK, L_NOISY = (MATERIAL_LABEL[k] for k in MATERIAL_KINDS)
MIN_RANGE_M = 0.35  # Carmine 1.09 working range 0.35 m ... 3.5 m
MAX_RANGE_M = 3.5
SENSORS: tuple[str, ...] = ('carmine', 'realsense_d400')
#: Working range (m) per sensor (D435: ~0.2 m minimum depth at 640 x 480, ~3 m useful range).
SENSOR_RANGE_M: dict[str, tuple[float, float]] = {'carmine': (MIN_RANGE_M, MAX_RANGE_M),
                                                  'realsense_d400': (0.2, 3.0)}
MAX_TILT_DEG = 80.0
DEFAULT_SHADOW_STRENGTH = 0.5
DEFAULT_START_NS = 1_432_598_400_000_000_000  # 2015-05-26T00:00:00Z (ICRA 2015), fixed for determinism


@dataclass(frozen=True)
class MaterialRegion:
    """A surface-material region of the object: ``kind`` in :data:`MATERIAL_KINDS`, polygon (N, 2) in m,
    optional RGB ``color`` (default: the object colour). Only the part inside the object outline counts."""

    kind: str
    polygon: np.ndarray
    color: tuple[int, int, int] | None = None

    @staticmethod
    def box(kind: str, x0: float, y0: float, x1: float, y1: float,
            color: tuple[int, int, int] | None = None) -> MaterialRegion:
        """Axis-aligned box region with corners (x0, y0), (x1, y1) in m."""
        return MaterialRegion(kind, np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64), color)


@dataclass(frozen=True)
class CameraModel:
    """Carmine 1.09 VGA depth/RGB camera (registered): intrinsics in px, baseline in m."""

    fx: float = 570.3
    fy: float = 570.3
    cx: float = 319.5
    cy: float = 239.5
    width: int = 640
    height: int = 480
    projector_baseline: float = 0.075


#: Intel RealSense D435, depth aligned to the colour camera (640 x 480); the right IR imager is 50 mm along +x.
REALSENSE_D400_CAMERA = CameraModel(fx=615.0, fy=615.0, cx=319.5, cy=239.5, width=640, height=480,
                                    projector_baseline=0.050)


@dataclass(frozen=True)
class Distractor:
    """Another object on the table (not the target): outline (N, 2) m in the table frame, height (m),
    RGB colour and material kind (:data:`MATERIAL_KINDS`, whole object)."""

    outline: np.ndarray
    height: float = 0.03
    color: tuple[int, int, int] = (60, 130, 80)
    kind: str = 'opaque'

    @staticmethod
    def box(x: float, y: float, length: float, width: float, height: float, yaw_deg: float = 0.0,
            color: tuple[int, int, int] = (60, 130, 80), kind: str = 'opaque') -> Distractor:
        """Box centred at (x, y) m, ``length`` along its x axis, turned by ``yaw_deg`` (from +X towards +Y)."""
        t = math.radians(yaw_deg)
        r = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
        half = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * (length / 2.0, width / 2.0)
        return Distractor(half @ r.T + (x, y), height, color, kind)

    @staticmethod
    def cylinder(x: float, y: float, radius: float, height: float, color: tuple[int, int, int] = (60, 130, 80),
                 kind: str = 'opaque', n: int = 48) -> Distractor:
        """Upright cylinder (a can, a cup) of ``radius`` m centred at (x, y) m, as an n-gon."""
        a = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
        return Distractor(np.stack([x + radius * np.cos(a), y + radius * np.sin(a)], axis=1), height, color, kind)


@dataclass
class SceneSpec:
    """Everything that defines one simulated recording (lengths in m, angles in degrees, colours RGB 0..255).

    ``camera_height`` is the distance from the camera to the table point (0, 0) along the optical axis
    (the height above the table for the default top-down camera); see the module docstring for
    ``camera_tilt``, ``camera_azimuth``, ``light``, ``distractors`` and ``sensor``. ``camera`` defaults
    to the sensor's (Carmine VGA, or :data:`REALSENSE_D400_CAMERA`)."""

    outline: np.ndarray
    regions: Sequence[MaterialRegion] = ()
    height: float = 0.02
    table_color: tuple[int, int, int] = (186, 176, 160)
    object_color: tuple[int, int, int] = (70, 90, 150)
    camera_height: float = 0.7
    frames: int = 10
    seed: int = 0
    name: str = 'object'
    camera: CameraModel | None = None
    start_ns: int = DEFAULT_START_NS
    frame_rate: float = 30.0
    crop_margin_px: int = 16
    gt_resolution: float = 0.001
    gt_margin: float = 0.03
    camera_tilt: float = 0.0
    camera_azimuth: float = 0.0
    light: tuple[float, float] | None = None
    shadow_strength: float = DEFAULT_SHADOW_STRENGTH
    distractors: Sequence[Distractor] = ()
    sensor: str = 'carmine'

    def __post_init__(self) -> None:
        if self.camera is None:
            self.camera = REALSENSE_D400_CAMERA if self.sensor == 'realsense_d400' else CameraModel()

    @property
    def top_down(self) -> bool:
        """Whether the camera looks straight down (tilt 0, azimuth 0)."""
        return float(self.camera_tilt) == 0.0 and float(self.camera_azimuth) == 0.0

    @classmethod
    def from_mask(cls, mask: np.ndarray, mpp: float, **kwargs: Any) -> SceneSpec:
        """Scene of the single object in a binary ``mask`` with ``mpp`` metres per pixel, centred on
        the optical axis (see :func:`mask_to_polygon`); other fields as keyword arguments."""
        return cls(outline=mask_to_polygon(mask, mpp), **kwargs)



def check_rgb(value: Any, what: str) -> tuple[int, int, int]:
    """``value`` as an (R, G, B) tuple of ints in 0..255; ValueError naming ``what`` otherwise."""
    try:
        c = tuple(int(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f'{what} must be three integers R,G,B in 0..255, got {value!r}') from None
    if len(c) != 3 or any(v < 0 or v > 255 for v in c):
        raise ValueError(f'{what} must be three integers R,G,B in 0..255, got {value!r}')
    return c  # type: ignore[return-value]


def validate_spec(s: SceneSpec) -> None:
    """Check the scalar fields of a spec (kinds, sensor, ranges, pose, light, counts, colours); ValueError
    with a message naming the field. Outlines and regions are checked when the scene is built."""
    for kind in [r.kind for r in s.regions] + [d.kind for d in s.distractors]:
        if kind not in MATERIAL_KINDS:
            raise ValueError(f"unknown material kind '{kind}'; expected one of {', '.join(MATERIAL_KINDS)}")
    if s.sensor not in SENSORS:
        raise ValueError(f"unknown sensor '{s.sensor}'; expected one of {', '.join(SENSORS)}")
    lo, hi = SENSOR_RANGE_M[s.sensor]
    if not (np.isfinite(s.camera_height) and lo < s.camera_height <= hi):
        raise ValueError(f'camera height must be in ({lo}, {hi}] m, got {s.camera_height}')
    if not (np.isfinite(s.height) and s.height > 0):
        raise ValueError(f'object height must be positive (m), got {s.height}')
    if s.top_down and s.camera_height - s.height < lo:
        raise ValueError(f'object top at {s.camera_height - s.height:.3f} m is closer than the sensor minimum '
                         f'range {lo} m')
    if not (np.isfinite(s.camera_tilt) and 0.0 <= s.camera_tilt < MAX_TILT_DEG):
        raise ValueError(f'camera tilt must be in [0, {MAX_TILT_DEG:.0f}) degrees from straight down, '
                         f'got {s.camera_tilt}')
    if not np.isfinite(s.camera_azimuth):
        raise ValueError(f'camera azimuth must be a finite angle (degrees), got {s.camera_azimuth}')
    if s.light is not None:
        light = np.asarray(s.light, dtype=np.float64).ravel()
        if light.shape != (2,) or not np.isfinite(light).all() or not 5.0 <= light[1] <= 90.0:
            raise ValueError(f'light must be (azimuth, elevation) in degrees with elevation in [5, 90], '
                             f'got {s.light!r}')
    if not (np.isfinite(s.shadow_strength) and 0.0 <= s.shadow_strength < 1.0):
        raise ValueError(f'shadow strength must be in [0, 1), got {s.shadow_strength}')
    for j, d in enumerate(s.distractors):
        if not (np.isfinite(d.height) and d.height > 0):
            raise ValueError(f'distractor {j} height must be positive (m), got {d.height}')
    if int(s.frames) != s.frames or s.frames < 1:
        raise ValueError(f'frames must be a positive integer, got {s.frames}')
    if int(s.seed) != s.seed or s.seed < 0:
        raise ValueError(f'seed must be a non-negative integer, got {s.seed}')
    if not s.frame_rate > 0:
        raise ValueError(f'frame rate must be positive (Hz), got {s.frame_rate}')
    check_rgb(s.table_color, 'table colour')
    check_rgb(s.object_color, 'object colour')
