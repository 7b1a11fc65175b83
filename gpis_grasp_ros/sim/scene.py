"""Simulated RGB-D camera (PrimeSense Carmine or RealSense D400) over planar objects on a table.

Produces the sensor streams of the paper's set-up (section III-B, Fig. 1): registered RGB and
depth from a head-mounted Carmine, 10 frames, transparent parts that show the table, specular
parts with no depth return, and Kinect-style noise, quantisation, drop-outs and projector shadows.
It also produces ground truth (occupancy, signed distance, centre of mass, outline) for the
simulated gripper and the evaluation, never for the perception pipeline.

Geometry (all lengths in metres)
--------------------------------
* Camera optical frame ``camera_rgb_optical_frame``: x right, y down, z along the optical axis
  toward the table. The table is the plane z = ``camera_height``; a table-plane point (X, Y)
  is the camera point (x=X, y=Y, z=camera_height). Object outlines are given in these (X, Y).
* The object is a right prism: its outline extruded ``height`` up from the table, so its top
  face is at depth ``camera_height - height``. Rays are traced through the prism, so walls facing
  the optical axis are seen at off-axis positions, exactly like a perspective camera.
* Intrinsics are VGA Carmine values (fx = fy = 570.3 px, cx = 319.5, cy = 239.5 on a 640 x 480
  sensor) cropped to a window around the object; the crop shifts (cx, cy) accordingly.
* The IR projector sits ``projector_baseline`` (0.075 m) along +x of the camera: table points
  whose line of sight to the projector is blocked by the object get no depth (projector shadow).

Camera pose, light, distractors, sensor (all default to the top-down Carmine scene above)
------------------------------------------------------------------------------------------
* **Table frame** T: the object outline's (X, Y) in the table plane, z into the table (away from
  the camera side; heights above the table are -z). The default camera is top-down: camera frame =
  T shifted by ``camera_height``.
* **Camera pose** (``camera_tilt``, ``camera_azimuth`` in degrees, ``camera_height`` = distance in m
  along the optical axis from the camera to the table point T(0, 0)): the camera looks at T(0, 0);
  ``camera_tilt`` is the angle between the optical axis and the downward table normal (0 =
  top-down; a PR2 head camera is at 45-55 degrees), the camera leaning back towards +Y (so the
  near table is at the bottom of the image), and ``camera_azimuth`` turns the whole rig about the
  table normal through T(0, 0). Camera axes in T: R_TC = Rz(azimuth) Rx(tilt); camera position
  C = R_TC (0, 0, -distance). Rays are traced in T, so any pose whose view of the table is not
  grazing works (validated: every pixel ray must meet the table, tilt < 80 degrees).
* **Ground truth in the table frame**: the grids' :class:`GridGeometry` carries
  ``rotation`` = R_TC^T (grid axes = T's axes in the camera frame) and ``z`` = the table plane's
  distance from the camera along T's z; grid (x, y) = T (X, Y) - C (X, Y). Centre of mass and
  outline are published as camera-frame 3D points on the table plane.
* **Light** (``light`` = (azimuth, elevation) in degrees of the direction towards the light in T,
  azimuth from +X towards +Y, elevation above the table): table points whose line to the light is
  blocked by a non-transparent object or distractor are in **shadow**: their colour is the table
  colour times ``1 - shadow_strength`` (darker, same chromaticity); depth is unaffected.
* **Distractors** (:class:`Distractor`): further right prisms on the table (own outline, height,
  colour, material). They are seen, cast shadows and occlude, but are not the target: the ground
  truth describes the main object only.
* **Sensor** (``sensor``): ``carmine`` (above) or ``realsense_d400`` (Intel D435 active stereo,
  depth aligned to the 640 x 480 colour camera: fx = fy = 615 px; depth noise
  :class:`noise_model.SensorModel` ``realsense_d400``, sigma_z = 3.8e-3 z^2 m, depth in 1 mm units;
  the right imager 0.05 m along +x plays the projector's role for occlusion holes; range 0.2-3 m).

Materials (:class:`MaterialRegion`, later regions override earlier ones, only inside the object)
------------------------------------------------------------------------------------------------
* ``opaque``      default object surface: depth noise from the axial model.
* ``transparent`` the IR pattern passes: depth is the table's; colour is the table's, tinted
  by ``TRANSPARENT_TINT`` (30 %) of the region's colour; 3 % refraction drop-outs.
* ``specular``    the pattern is reflected away: no depth (NaN); colour is a saturated,
  flickering metallic highlight pattern.
* ``dark``        low IR reflectance: 2.5x depth noise, 15 % drop-outs, colour darkened to 30 %.
* ``noisy``       rough / frosted surface: 4x depth noise, 5 % drop-outs.

Sensor model per frame: depth ~ N(z, sigma_z(z)^2) (``noise_model``), then the sensor's quantisation
(Carmine: :func:`disparity_quantise`, levels spaced by ``noise_model.quantisation_step``; D400: 1 mm);
random drop-outs (0.2 % everywhere, 30 % within one pixel of a depth edge > 4 mm, plus the
material rates); RGB is anti-aliased (3 x 3 samples per pixel) with a faint static texture and
N(0, 2^2) per-frame noise (specular pixels flicker with N(0, 25^2)).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from gpis_grasp_ros.core import noise_model
from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.data.topics import CAMERA_TOPICS, GROUND_TRUTH_TOPICS, TOPIC_TYPES, TOPICS

FRAME_ID = 'camera_rgb_optical_frame'
MATERIAL_KINDS: tuple[str, ...] = ('opaque', 'transparent', 'specular', 'dark', 'noisy')
_LABEL = {kind: i + 1 for i, kind in enumerate(MATERIAL_KINDS)}  # 0 = no object
L_OPAQUE, L_TRANSPARENT, L_SPECULAR, L_DARK, L_NOISY = (_LABEL[k] for k in MATERIAL_KINDS)

# Depth-noise multiplier and extra per-frame drop-out probability per label (index = label).
_NOISE_FACTOR = np.array([1.0, 1.0, 1.0, 1.0, 2.5, 4.0])
_DROPOUT = np.array([0.0, 0.0, 0.03, 1.0, 0.15, 0.05])
BASE_DROPOUT = 0.002
EDGE_DROPOUT = 0.30
EDGE_THRESHOLD_M = 0.004
TRANSPARENT_TINT = 0.30
RGB_NOISE_SIGMA = 2.0
SPECULAR_FLICKER_SIGMA = 25.0
MIN_RANGE_M = 0.35  # Carmine 1.09 working range 0.35 m ... 3.5 m
MAX_RANGE_M = 3.5
SENSORS: tuple[str, ...] = ('carmine', 'realsense_d400')
#: Working range (m) per sensor (D435: ~0.2 m minimum depth at 640 x 480, ~3 m useful range).
SENSOR_RANGE_M: dict[str, tuple[float, float]] = {'carmine': (MIN_RANGE_M, MAX_RANGE_M),
                                                  'realsense_d400': (0.2, 3.0)}
MAX_TILT_DEG = 80.0
DEFAULT_SHADOW_STRENGTH = 0.5
_HEIGHT_EPS_M = 1e-9
DEFAULT_START_NS = 1_432_598_400_000_000_000  # 2015-05-26T00:00:00Z (ICRA 2015), fixed for determinism



# =========================================================================== polygons
def polygon_area(poly: np.ndarray) -> float:
    """Signed area (m^2) of a closed polygon (N, 2); positive for counter-clockwise in (x, y)."""
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def polygon_centroid(poly: np.ndarray) -> np.ndarray:
    """Area centroid (x, y) in m of a simple polygon (uniform density: the centre of mass)."""
    x, y = poly[:, 0], poly[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    area = 0.5 * cross.sum()
    return np.array([np.sum((x + xn) * cross), np.sum((y + yn) * cross)]) / (6.0 * area)


def _orient(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """z of (b - a) x (c - a), broadcast over leading axes."""
    return (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0])


def _first_self_intersection(poly: np.ndarray) -> tuple[int, int] | None:
    """Indices (i, j) of two non-adjacent edges that touch or cross, or None for a simple polygon."""
    n = len(poly)
    a, b = poly, np.roll(poly, -1, axis=0)
    scale = float(np.ptp(poly, axis=0).max()) or 1.0
    eps = 1e-12 * scale * scale
    i, j = np.triu_indices(n, k=2)
    keep = ~((i == 0) & (j == n - 1))  # first and last edge share vertex 0
    i, j = i[keep], j[keep]
    if i.size == 0:
        return None
    p1, p2, p3, p4 = a[i], b[i], a[j], b[j]
    d1, d2 = _orient(p3, p4, p1), _orient(p3, p4, p2)
    d3, d4 = _orient(p1, p2, p3), _orient(p1, p2, p4)
    proper = (((d1 > eps) & (d2 < -eps)) | ((d1 < -eps) & (d2 > eps))) & \
             (((d3 > eps) & (d4 < -eps)) | ((d3 < -eps) & (d4 > eps)))

    def on_segment(p: np.ndarray, q: np.ndarray, r: np.ndarray, d: np.ndarray) -> np.ndarray:
        # r collinear with p-q and inside its bounding box
        lo, hi = np.minimum(p, q) - 1e-12 * scale, np.maximum(p, q) + 1e-12 * scale
        return (np.abs(d) <= eps) & np.all((r >= lo) & (r <= hi), axis=-1)

    touch = on_segment(p3, p4, p1, d1) | on_segment(p3, p4, p2, d2) | on_segment(p1, p2, p3, d3) | \
        on_segment(p1, p2, p4, d4)
    hit = np.flatnonzero(proper | touch)
    return (int(i[hit[0]]), int(j[hit[0]])) if hit.size else None


def validate_polygon(points: Any, what: str = 'polygon') -> np.ndarray:
    """Check and normalise a polygon: (N, 2) finite metres, >= 3 distinct vertices, non-zero area,
    not self-intersecting. Returns a float64 copy, counter-clockwise, without a repeated closing vertex.
    Raises ValueError with a message naming ``what``.
    """
    try:
        poly = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f'{what}: vertices must be numbers') from None
    if poly.size == 0:
        raise ValueError(f'{what} is empty: at least 3 vertices (x, y in metres) are needed')
    if poly.ndim != 2 or poly.shape[1] != 2:
        raise ValueError(f'{what} must be an (N, 2) array of x, y vertices in metres, got shape {poly.shape}')
    if not np.isfinite(poly).all():
        raise ValueError(f'{what} has non-finite vertices')
    # drop consecutive duplicates (including a closing vertex equal to the first)
    keep = np.any(np.abs(poly - np.roll(poly, 1, axis=0)) > 1e-12, axis=1)
    poly = poly[keep] if keep.any() else poly[:1]
    if len(poly) < 3:
        raise ValueError(f'{what} is degenerate: {len(poly)} distinct vertices, at least 3 are needed')
    scale = float(np.ptp(poly, axis=0).max())
    spread = np.linalg.svd(poly - poly.mean(axis=0), compute_uv=False)
    if scale <= 0 or spread[-1] <= 1e-9 * max(scale, 1e-12):
        raise ValueError(f'{what} is degenerate: all vertices lie on one line (zero area)')
    hit = _first_self_intersection(poly)
    if hit is not None:
        i, j = hit
        raise ValueError(f'{what} is self-intersecting: edge {i} ({poly[i].tolist()} -> '
                         f'{poly[(i + 1) % len(poly)].tolist()}) meets edge {j} ({poly[j].tolist()} -> '
                         f'{poly[(j + 1) % len(poly)].tolist()})')
    area = polygon_area(poly)
    if abs(area) < 1e-10:
        raise ValueError(f'{what} is degenerate: area {abs(area):.3g} m^2 (less than 1e-4 mm^2)')
    return poly if area > 0 else poly[::-1].copy()


def points_in_polygon(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Even-odd inside test of metric points (..., 2) against a polygon (N, 2); boolean (...)."""
    pts = np.asarray(points, dtype=np.float64)
    flat = pts.reshape(-1, 2)
    a, b = poly, np.roll(poly, -1, axis=0)
    inside = np.zeros(len(flat), dtype=bool)
    for start in range(0, len(flat), 8192):
        p = flat[start:start + 8192, None, :]
        y = p[..., 1]
        spans = (a[None, :, 1] <= y) != (b[None, :, 1] <= y)
        with np.errstate(divide='ignore', invalid='ignore'):
            xc = a[None, :, 0] + (y - a[None, :, 1]) * (b[None, :, 0] - a[None, :, 0]) / (b[None, :, 1] - a[None, :, 1])
        inside[start:start + 8192] = (np.count_nonzero(spans & (xc > p[..., 0]), axis=1) % 2) == 1
    return inside.reshape(pts.shape[:-1])


def polygon_signed_distance(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Signed distance (m) from points (..., 2) to the polygon boundary: positive outside, negative inside."""
    pts = np.asarray(points, dtype=np.float64)
    flat = pts.reshape(-1, 2)
    a = poly
    ab = np.roll(poly, -1, axis=0) - a
    len2 = np.maximum(np.sum(ab * ab, axis=1), 1e-300)
    dist = np.empty(len(flat))
    for start in range(0, len(flat), 4096):
        p = flat[start:start + 4096, None, :]
        t = np.clip(np.sum((p - a) * ab, axis=-1) / len2, 0.0, 1.0)
        d = p - (a + t[..., None] * ab)
        dist[start:start + 4096] = np.sqrt(np.min(np.sum(d * d, axis=-1), axis=1))
    inside = points_in_polygon(flat, poly)
    return np.where(inside, -dist, dist).reshape(pts.shape[:-1])


def rasterise_polygon(poly: np.ndarray, geometry: GridGeometry) -> np.ndarray:
    """Boolean (H, W) grid: cell centres inside the polygon (even-odd rule, scanline, vectorised)."""
    centers_y = geometry.origin_y + (np.arange(geometry.height) + 0.5) * geometry.resolution
    centers_x = geometry.origin_x + (np.arange(geometry.width) + 0.5) * geometry.resolution
    a, b = poly, np.roll(poly, -1, axis=0)
    y = centers_y[:, None]
    spans = (a[None, :, 1] <= y) != (b[None, :, 1] <= y)
    with np.errstate(divide='ignore', invalid='ignore'):
        xc = a[None, :, 0] + (y - a[None, :, 1]) * (b[None, :, 0] - a[None, :, 0]) / (b[None, :, 1] - a[None, :, 1])
    xc = np.sort(np.where(spans, xc, np.inf), axis=1)
    k = int(spans.sum(axis=1).max(initial=0))
    if k == 0:
        return np.zeros(geometry.shape, dtype=bool)
    xc = xc[:, :k]
    count = np.sum(xc[:, None, :] < centers_x[None, :, None], axis=2)
    return (count % 2) == 1


# =========================================================================== inputs
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


# =========================================================================== scene description
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


@dataclass
class Frame:
    """One simulated frame: ``depth`` (H, W) float32 m (NaN = no return), ``rgb`` (H, W, 3) uint8,
    ``xyz`` (H, W, 3) float32 m in the optical frame (NaN = no return), ``stamp_ns``."""

    stamp_ns: int
    depth: np.ndarray
    rgb: np.ndarray
    xyz: np.ndarray


@dataclass
class GroundTruth:
    """Ground truth at the table plane: occupancy (H, W) int8 (100 object, 0 free), signed distance
    (H, W) float32 m (positive outside), their ``geometry`` (z = table depth), centre of mass (x, y, z)
    in m and the outline (N, 2) in m."""

    geometry: GridGeometry
    occupancy: np.ndarray
    sdf: np.ndarray
    center_of_mass: np.ndarray
    outline: np.ndarray


def disparity_quantise(depth_m: np.ndarray) -> np.ndarray:
    """Snap depths (m) to the structured-light sensor's depth levels (:func:`noise_model.quantise`).

    Levels are uniformly spaced in 1/z (the sensor measures disparity in fixed sub-pixel steps),
    so every output is one of a fixed set of levels (repeated values also compress well in the bags).
    """
    return noise_model.quantise(depth_m)


def _color(value: Any, what: str) -> tuple[int, int, int]:
    try:
        c = tuple(int(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f'{what} must be three integers R,G,B in 0..255, got {value!r}') from None
    if len(c) != 3 or any(v < 0 or v > 255 for v in c):
        raise ValueError(f'{what} must be three integers R,G,B in 0..255, got {value!r}')
    return c  # type: ignore[return-value]


def shadow_shift(light: tuple[float, float] | None) -> np.ndarray | None:
    """Table-frame shift (m per m of height) from an occluder point to its shadow on the table, for a light
    at (azimuth, elevation) degrees (module docstring); None without a light."""
    if light is None:
        return None
    az, el = (math.radians(float(v)) for v in light)
    return -np.array([math.cos(az), math.sin(az)]) * (math.cos(el) / math.sin(el))


def _smooth_field(rng: np.random.Generator, shape: tuple[int, int], sigma_px: float) -> np.ndarray:
    """Zero-mean, unit-std spatially correlated random field."""
    f = ndimage.gaussian_filter(rng.standard_normal(shape), sigma_px, mode='reflect')
    return (f - f.mean()) / max(float(f.std()), 1e-12)


# =========================================================================== the simulator
class Scene:
    """A validated scene with its static rendering (crop, ray hits, colours) precomputed.

    ``Scene(spec)`` raises ValueError for bad input. :meth:`frames` yields the noisy frames
    (deterministic for a given ``spec.seed``), :meth:`ground_truth` the exact shape, and
    :meth:`messages` everything as ROS messages via a :mod:`~gpis_grasp_ros.data.messages` factory.
    Rays are traced in the table frame T (module docstring); the top-down default reproduces the
    original top-down renderer bit for bit.
    """

    SUBSAMPLES = 3  # per pixel and axis, for anti-aliased colour
    RASTER_RES = 0.00025  # m, material raster used for ray tracing
    CHUNK_SAMPLES = 4_000_000  # ray samples per block (bounds the tracer's memory)

    def __init__(self, spec: SceneSpec) -> None:
        self.spec = spec
        self._validate()
        self.outline = validate_polygon(spec.outline, what='object outline')
        self.regions = [(r.kind, validate_polygon(r.polygon, what=f"region {i} ('{r.kind}')"))
                        for i, r in enumerate(spec.regions)]
        region_colors = [self.object_color if r.color is None else
                         np.array(_color(r.color, f"region {i} ('{r.kind}') colour"), dtype=np.float64)
                         for i, r in enumerate(spec.regions)]
        self.distractors = [(validate_polygon(d.outline, what=f'distractor {j} outline'), float(d.height), d.kind,
                             np.array(_color(d.color, f'distractor {j} colour'), dtype=np.float64))
                            for j, d in enumerate(spec.distractors)]
        # surface id 0 = no object, 1 = base object, 2 + i = region i, then one id per distractor
        n_main = 2 + len(self.regions)
        self._kind_of_id = np.array([0, L_OPAQUE] + [_LABEL[k] for k, _ in self.regions]
                                    + [_LABEL[d[2]] for d in self.distractors], dtype=np.uint8)
        self._color_of_id = np.array([self.table_color, self.object_color] + region_colors
                                     + [d[3] for d in self.distractors], dtype=np.float64)
        #: height (m) of each surface's top above the table; object index (0 table, 1 target, 2 + j distractor j)
        self._top_of_id = np.array([0.0] + [float(spec.height)] * (n_main - 1) + [d[1] for d in self.distractors])
        self._obj_of_id = np.array([0] + [1] * (n_main - 1) + [2 + j for j in range(len(self.distractors))])
        self.sensor_model = noise_model.SensorModel.named(spec.sensor)
        self.camera = spec.camera if spec.camera is not None else CameraModel()
        self._build_pose()
        self.top_depth = float(spec.camera_height - spec.height)
        hmax = max([float(spec.height)] + [d[1] for d in self.distractors])
        self._hmax = hmax
        self._band = float(spec.camera_height) - float(spec.camera_height - hmax)  # = hmax (as a depth difference)
        self._build_raster()
        self._build_crop()
        self._rng = np.random.default_rng(int(spec.seed))
        self._render_static()

    # ------------------------------------------------------------------ validation
    def _validate(self) -> None:
        s = self.spec
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
        self.table_color = np.array(_color(s.table_color, 'table colour'), dtype=np.float64)
        self.object_color = np.array(_color(s.object_color, 'object colour'), dtype=np.float64)

    # ------------------------------------------------------------------ camera pose
    def _build_pose(self) -> None:
        """Camera axes R_TC (columns, in the table frame T) and camera position C in T (m)."""
        s = self.spec
        d = float(s.camera_height)
        if s.top_down:
            r = np.eye(3)
            c = np.array([0.0, 0.0, -d])
        else:
            t, a = math.radians(float(s.camera_tilt)), math.radians(float(s.camera_azimuth))
            rx = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(t), -math.sin(t)], [0.0, math.sin(t), math.cos(t)]])
            rz = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
            r = rz @ rx
            c = r @ np.array([0.0, 0.0, -d])
        self._r_tc, self._c = r, c
        #: distance (m) of the table plane from the camera along T's z (the ground-truth grids' ``z``)
        self.table_depth = float(s.camera_height) if s.top_down else float(-c[2])

    @property
    def grid_rotation(self) -> tuple[float, ...]:
        """Row-major ``GridGeometry.rotation`` of table-frame grids: T's axes in the camera frame (R_TC^T)."""
        return tuple(float(v) for v in self._r_tc.T.ravel())

    def table_to_camera(self, xy: np.ndarray, height: np.ndarray | float = 0.0) -> np.ndarray:
        """Table-frame points ``(..., 2)`` (m) at ``height`` (m) above the table → camera frame ``(..., 3)``."""
        xy = np.asarray(xy, dtype=np.float64)
        h = np.broadcast_to(np.asarray(height, dtype=np.float64), xy.shape[:-1])
        g = np.concatenate([xy, (-h)[..., None]], axis=-1) - self._c
        return g if self.spec.top_down else g @ self._r_tc

    def _ray_dirs(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ray slopes (..., 2) in the camera → directions in T with unit optical-axis component:
        (lateral (..., 2), along T's z (...)); the camera-frame depth of C + t d is t."""
        if self.spec.top_down:
            return rays, np.ones(rays.shape[:-1])
        d = np.concatenate([rays, np.ones(rays.shape[:-1] + (1,))], axis=-1) @ self._r_tc.T
        return d[..., :2], d[..., 2]

    # ------------------------------------------------------------------ material raster
    def _shadow_shift(self) -> np.ndarray | None:
        return shadow_shift(self.spec.light)

    def _build_raster(self) -> None:
        res = self.RASTER_RES
        pts = np.concatenate([self.outline] + [d[0] for d in self.distractors])
        shift = self._shadow_shift()
        if shift is not None:
            pts = np.concatenate([pts, pts + self._hmax * shift])
        lo = np.floor(pts.min(axis=0) / res) * res - 2 * res
        hi = np.ceil(pts.max(axis=0) / res) * res + 2 * res
        w, h = (int(round(v)) for v in (hi - lo) / res)
        self._raster_geom = GridGeometry(float(lo[0]), float(lo[1]), res, w, h, self.table_depth, FRAME_ID)
        inside = rasterise_polygon(self.outline, self._raster_geom)
        n_ids = len(self._kind_of_id)
        ids = np.where(inside, 1, 0).astype(np.uint8 if n_ids < 250 else np.uint16)
        for i, (kind, poly) in enumerate(self.regions):
            cells = rasterise_polygon(poly, self._raster_geom) & inside
            if not cells.any():
                raise ValueError(f"region {i} ('{kind}') does not overlap the object outline")
            ids[cells] = i + 2
        for j, (poly, *_rest) in enumerate(self.distractors):
            cells = rasterise_polygon(poly, self._raster_geom)
            if (cells & (ids > 0)).any():
                raise ValueError(f'distractor {j} overlaps the object or another distractor')
            ids[cells] = 2 + len(self.regions) + j
        self._ids = ids
        self._shadow = None if shift is None else self._cast_shadow(shift)

    def _cast_shadow(self, shift: np.ndarray) -> np.ndarray:
        """Boolean raster of the table cells in the light's shadow: a cell p is dark when p - s * shift... i.e.
        some non-transparent column of top height >= s lies at p + s * |shift| towards the light, s in [0, top]."""
        res = self.RASTER_RES
        kinds = self._kind_of_id[self._ids]
        solid = (kinds > 0) & (kinds != L_TRANSPARENT)
        top = self._top_of_id[self._ids]
        shadow = np.zeros_like(solid)
        n = max(2, int(math.ceil(self._hmax * float(np.abs(shift).max()) / res)) + 1)
        done: set[tuple[int, int]] = set()
        for s in np.linspace(0.0, self._hmax, n):
            dc, dr = (int(round(v)) for v in s * shift / res)
            if (dc, dr) in done and s > 0:
                continue
            done.add((dc, dr))
            src = solid & (top >= s - _HEIGHT_EPS_M)
            h, w = src.shape
            shadow[max(dr, 0):h + min(dr, 0), max(dc, 0):w + min(dc, 0)] |= \
                src[max(-dr, 0):h - max(dr, 0), max(-dc, 0):w - max(dc, 0)]
        return shadow

    def _lookup(self, xy: np.ndarray, raster: np.ndarray | None = None) -> np.ndarray:
        """Surface id (or ``raster`` value) at metric table-plane points (..., 2); 0 outside the raster."""
        g = self._raster_geom
        values = self._ids if raster is None else raster
        col = np.floor((xy[..., 0] - g.origin_x) / g.resolution).astype(np.int64)
        row = np.floor((xy[..., 1] - g.origin_y) / g.resolution).astype(np.int64)
        ok = (col >= 0) & (col < g.width) & (row >= 0) & (row < g.height)
        out = np.zeros(xy.shape[:-1], dtype=values.dtype)
        out[ok] = values[row[ok], col[ok]]
        return out

    # ------------------------------------------------------------------ crop window
    def _build_crop(self) -> None:
        cam, margin = self.camera, int(self.spec.crop_margin_px)
        pts = [(self.outline, float(self.spec.height)), (self.outline, 0.0)]
        for poly, height, *_rest in self.distractors:
            pts += [(poly, height), (poly, 0.0)]
        shift = self._shadow_shift()
        if shift is not None:  # keep the target's shadow in view
            pts.append((self.outline + float(self.spec.height) * shift, 0.0))
        cams = [self.table_to_camera(xy, h) for xy, h in pts]
        zs = np.concatenate([c[:, 2] for c in cams])
        lo_range = SENSOR_RANGE_M[self.spec.sensor][0]
        if zs.min() < lo_range:
            raise ValueError(f'object top at {zs.min():.3f} m is closer than the sensor minimum range {lo_range} m')
        us = np.concatenate([cam.cx + cam.fx * c[:, 0] / c[:, 2] for c in cams])
        vs = np.concatenate([cam.cy + cam.fy * c[:, 1] / c[:, 2] for c in cams])
        if us.min() < 0 or vs.min() < 0 or us.max() > cam.width - 1 or vs.max() > cam.height - 1:
            raise ValueError('object is outside the camera field of view: at camera height '
                             f'{self.spec.camera_height} m it projects to u {us.min():.0f}..{us.max():.0f}, '
                             f'v {vs.min():.0f}..{vs.max():.0f} px of a {cam.width} x {cam.height} image; '
                             'move it toward the optical axis (x = y = 0) or raise the camera')
        self.u0 = max(0, int(math.floor(us.min())) - margin)
        self.v0 = max(0, int(math.floor(vs.min())) - margin)
        u1 = min(cam.width, int(math.ceil(us.max())) + margin + 1)
        v1 = min(cam.height, int(math.ceil(vs.max())) + margin + 1)
        self.width, self.height = u1 - self.u0, v1 - self.v0
        self.fx, self.fy = cam.fx, cam.fy
        self.cx, self.cy = cam.cx - self.u0, cam.cy - self.v0
        corners = np.array([[[-0.5, -0.5], [self.width - 0.5, -0.5]],
                            [[-0.5, self.height - 0.5], [self.width - 0.5, self.height - 0.5]]])
        corner_rays = (corners - (self.cx, self.cy)) / (self.fx, self.fy)
        _, dz = self._ray_dirs(corner_rays)
        if not (dz > 1e-3).all():
            raise ValueError('the camera view grazes the table: some pixel rays never meet the table plane; '
                             'reduce the camera tilt')

    @property
    def intrinsics(self) -> tuple[float, float, float, float, int, int]:
        """Cropped pinhole intrinsics ``(fx, fy, cx, cy, width, height)`` in px."""
        return self.fx, self.fy, self.cx, self.cy, self.width, self.height

    def pixel_rays(self, offset: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
        """(H, W, 2) ray slopes (x/z, y/z) through the pixel centres shifted by ``offset`` px."""
        u = np.arange(self.width) + offset[0]
        v = np.arange(self.height) + offset[1]
        return np.stack(np.meshgrid((u - self.cx) / self.fx, (v - self.cy) / self.fy), axis=-1)

    def table_points(self, rays: np.ndarray) -> np.ndarray:
        """Table-frame (X, Y) (m) where rays (..., 2) meet the table plane."""
        dxy, dz = self._ray_dirs(rays)
        t = (0.0 - self._c[2]) / dz
        return self._c[:2] + dxy * t[..., None]

    # ------------------------------------------------------------------ ray casting
    def _rows(self, rays: np.ndarray, k: int) -> list[slice]:
        """Row blocks of an (H, W, 2) ray array with about CHUNK_SAMPLES ray samples each."""
        per_row = max(1, int(np.prod(rays.shape[1:-1], dtype=np.int64)) * k)
        step = max(1, self.CHUNK_SAMPLES // per_row)
        return [slice(i, i + step) for i in range(0, rays.shape[0], step)]

    def _trace(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """First hit of rays (H, W, 2) with the object and distractor prisms.

        Returns (surface id of the first non-transparent surface or 0 for the table, hit depth (m),
        is_wall, passed_transparent). Depths are marched from the tallest top to the table with a
        lateral step of at most two raster cells; a hit entered through a lower top face is placed
        exactly on that face.
        """
        dxy, dz = self._ray_dirs(rays)
        cz = self._c[2]
        t_top = (-self._hmax - cz) / dz
        t_table = (0.0 - cz) / dz
        reach = float(np.max(np.abs(dxy) * (t_table - t_top)[..., None]))
        k = max(2, int(math.ceil(reach / (2 * self.RASTER_RES))) + 1)
        out = [np.zeros(rays.shape[:-1], dtype=self._ids.dtype), np.zeros(rays.shape[:-1]),
               np.zeros(rays.shape[:-1], dtype=bool), np.zeros(rays.shape[:-1], dtype=bool)]
        for rows in self._rows(rays, k):
            parts = self._trace_block(dxy[rows], dz[rows], t_top[rows], t_table[rows], k)
            for o, p in zip(out, parts, strict=True):
                o[rows] = p
        return out[0], out[1], out[2], out[3]

    def _trace_block(self, dxy: np.ndarray, dz: np.ndarray, t_top: np.ndarray, t_table: np.ndarray,
                     k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        cxy, cz = self._c[:2], self._c[2]
        zs = np.linspace(t_top, t_table, k, axis=-1)
        ids = self._lookup(cxy + dxy[..., None, :] * zs[..., :, None])  # (..., k)
        heights = -(cz + zs * dz[..., None])
        inside = self._top_of_id[ids] >= heights - _HEIGHT_EPS_M
        kinds = self._kind_of_id[ids]
        solid = (kinds > 0) & (kinds != L_TRANSPARENT) & inside
        any_solid = solid.any(axis=-1)
        first = np.where(any_solid, np.argmax(solid, axis=-1), k - 1)
        hit = np.where(any_solid, np.take_along_axis(ids, first[..., None], axis=-1)[..., 0], 0)
        depth = np.where(any_solid, np.take_along_axis(zs, first[..., None], axis=-1)[..., 0], t_table)
        before = np.arange(k) < first[..., None]
        passed = np.any((kinds == L_TRANSPARENT) & inside & (before | ~any_solid[..., None]), axis=-1)
        # entered through a top face lower than the previous sample: put the hit on that face
        prev_h = np.take_along_axis(heights, np.maximum(first - 1, 0)[..., None], axis=-1)[..., 0]
        top_h = self._top_of_id[hit]
        entered = any_solid & (first > 0) & (prev_h > top_h + _HEIGHT_EPS_M)
        top_face = np.zeros_like(entered)
        if entered.any():
            t_face = (-top_h[entered] - cz) / dz[entered]
            face_id = self._lookup(cxy + dxy[entered] * t_face[:, None])
            same = self._obj_of_id[face_id] == self._obj_of_id[hit[entered]]
            top_face[entered] = same
            depth[entered] = np.where(same, t_face, depth[entered])
        return hit, depth, any_solid & (first > 0) & ~top_face, passed

    def _projector_shadow(self, rays: np.ndarray, label: np.ndarray) -> np.ndarray:
        """Table points (label 0) whose line to the IR projector (D400: the right imager) is blocked by a
        non-transparent object."""
        dxy, dz = self._ray_dirs(rays)
        t_table = (0.0 - self._c[2]) / dz
        table_pt = self._c[:2] + dxy * t_table[..., None]
        proj_cam = np.array([self.camera.projector_baseline, 0.0, 0.0])
        proj = self._c + (proj_cam if self.spec.top_down else self._r_tc @ proj_cam)
        travel = (proj[:2] - table_pt) * (self._band / -proj[2])  # lateral move up to the tallest top
        k = max(2, int(math.ceil(float(np.abs(travel).max()) / self.RASTER_RES)) + 1)
        fractions = np.linspace(0.0, 1.0, k)[1:]
        blocked = np.zeros(rays.shape[:-1], dtype=bool)
        for rows in self._rows(rays, k):
            ids = self._lookup(table_pt[rows][..., None, :] + travel[rows][..., None, :] * fractions[:, None])
            kinds = self._kind_of_id[ids]
            inside = self._top_of_id[ids] >= fractions * self._band - _HEIGHT_EPS_M
            blocked[rows] = np.any((kinds > 0) & (kinds != L_TRANSPARENT) & inside, axis=-1)
        return blocked & (label == 0)

    # ------------------------------------------------------------------ static rendering
    def _render_static(self) -> None:
        rng = self._rng
        s = self.SUBSAMPLES
        offsets = (np.arange(s) + 0.5) / s - 0.5
        shape = (self.height, self.width)
        # static textures (drawn first so every frame's randomness follows in a fixed order)
        table_tex = 1.0 + 0.025 * _smooth_field(rng, shape, 6.0)
        object_tex = 1.0 + 0.03 * _smooth_field(rng, shape, 2.0)
        glint = _smooth_field(rng, shape, 1.5)
        metal = np.array([150.0, 152.0, 158.0]) * (1.0 + 0.12 * glint[..., None])
        highlight = np.clip((glint - 0.4) * 1.5, 0.0, 1.0)[..., None]  # ~1/3 of the surface, some saturated
        specular_rgb = metal + (255.0 - metal) * 1.5 * highlight

        colour = np.zeros(shape + (3,))
        spec_frac = np.zeros(shape)
        shadow_frac = np.zeros(shape)
        table = self.table_color * table_tex[..., None]
        for oy in offsets:
            for ox in offsets:
                rays = self.pixel_rays((ox, oy))
                hit, _, wall, passed = self._trace(rays)
                label = self._kind_of_id[hit]
                # tint of the first transparent surface along the ray (top-face point approximation)
                tint_id = self._lookup(self._top_points(rays))
                tint_id = np.where(self._kind_of_id[tint_id] == L_TRANSPARENT, tint_id, 1)
                lit = table
                if self._shadow is not None:  # cast shadow: darker, same chromaticity
                    dark = self._lookup(self.table_points(rays), self._shadow)
                    lit = table * np.where(dark, 1.0 - float(self.spec.shadow_strength), 1.0)[..., None]
                    shadow_frac += dark & (label == 0)
                tinted = (1 - TRANSPARENT_TINT) * lit + TRANSPARENT_TINT * self._color_of_id[tint_id]
                c = np.where(passed[..., None], tinted, lit)
                obj = self._color_of_id[hit] * object_tex[..., None] * np.where(wall, 0.65, 1.0)[..., None]
                c = np.where(np.isin(label, (L_OPAQUE, L_NOISY))[..., None], obj, c)
                c = np.where((label == L_DARK)[..., None], 0.3 * obj, c)
                c = np.where((label == L_SPECULAR)[..., None], specular_rgb * np.where(wall, 0.65, 1.0)[..., None], c)
                colour += c
                spec_frac += label == L_SPECULAR
        self._colour = colour / (s * s)
        self._spec_frac = spec_frac / (s * s)
        #: fraction of each pixel showing the table in the light's cast shadow (0 without a light)
        self.shadow_fraction = shadow_frac / (s * s)

        # depth from the pixel-centre ray (the sensor measures one depth per pixel)
        rays = self.pixel_rays()
        hit, depth, _, passed = self._trace(rays)
        label = self._kind_of_id[hit]
        shadow = self._projector_shadow(rays, label)
        clean = np.where((label == L_SPECULAR) | shadow, np.nan, depth)
        self._rays = rays
        self._label = np.where((label == 0) & passed, L_TRANSPARENT, label).astype(np.uint8)
        self._object = self._obj_of_id[hit]
        self._shadow_px = shadow
        self._clean_depth = clean
        self._edge = self._depth_edges(clean)

    def _top_points(self, rays: np.ndarray) -> np.ndarray:
        """Table-frame (X, Y) where rays cross the plane of the target's top face."""
        dxy, dz = self._ray_dirs(rays)
        t = (-float(self.spec.height) - self._c[2]) / dz
        return self._c[:2] + dxy * t[..., None]

    @staticmethod
    def _depth_edges(depth: np.ndarray) -> np.ndarray:
        """Pixels within one pixel of a depth jump > EDGE_THRESHOLD_M or of a no-return pixel."""
        valid = np.isfinite(depth)
        d = np.where(valid, depth, 0.0)
        jump = np.zeros(depth.shape, dtype=bool)
        for axis in (0, 1):
            big = (np.abs(np.diff(d, axis=axis)) > EDGE_THRESHOLD_M) | (np.diff(valid.astype(np.int8), axis=axis) != 0)
            lo = [slice(None)] * 2
            hi = [slice(None)] * 2
            lo[axis], hi[axis] = slice(None, -1), slice(1, None)
            jump[tuple(lo)] |= big
            jump[tuple(hi)] |= big
        return ndimage.binary_dilation(jump, iterations=1) & np.isfinite(depth)

    # ------------------------------------------------------------------ frames
    def stamp_ns(self, index: int) -> int:
        """Header stamp (ns) of frame ``index``: ``start_ns`` + (index + 1) / frame_rate.

        Frame 0 comes one period after ``start_ns``, when the ground truth is stamped."""
        return int(self.spec.start_ns) + int(round((index + 1) * 1e9 / self.spec.frame_rate))

    def quantise(self, depth_m: np.ndarray) -> np.ndarray:
        """The sensor's depth quantisation (Carmine: disparity levels; D400: 1 mm depth units)."""
        if self.spec.sensor == 'carmine':
            return disparity_quantise(depth_m)
        step = float(self.sensor_model.quantisation_constant_m)
        z = np.asarray(depth_m, dtype=np.float64)
        return np.round(z / step) * step if step > 0 else z

    def frames(self) -> Iterator[Frame]:
        """The ``spec.frames`` noisy frames in order (a fresh, deterministic pass on every call)."""
        state = self._rng.bit_generator.state
        rng = np.random.default_rng()
        rng.bit_generator.state = state
        shape = (self.height, self.width)
        clean = self._clean_depth
        valid = np.isfinite(clean)
        z0 = np.where(valid, clean, self.table_depth)
        sigma = self.sensor_model.sigma(z0) * _NOISE_FACTOR[self._label]
        p_drop = np.clip(BASE_DROPOUT + EDGE_DROPOUT * self._edge + _DROPOUT[self._label], 0.0, 1.0)
        for i in range(int(self.spec.frames)):
            noisy = z0 + sigma * rng.standard_normal(shape)
            drop = rng.random(shape) < p_drop
            depth = self.quantise(noisy)
            depth = np.where(valid & ~drop, depth, np.nan).astype(np.float32)
            rgb_f = self._colour + RGB_NOISE_SIGMA * rng.standard_normal(shape + (3,))
            rgb_f += (SPECULAR_FLICKER_SIGMA * self._spec_frac)[..., None] * rng.standard_normal(shape + (1,))
            rgb = np.clip(np.round(rgb_f), 0, 255).astype(np.uint8)
            xyz = np.concatenate([self._rays * depth[..., None], depth[..., None]], axis=-1).astype(np.float32)
            yield Frame(self.stamp_ns(i), depth, rgb, xyz)

    # ------------------------------------------------------------------ ground truth
    def ground_truth(self) -> GroundTruth:
        """Exact shape of the target on a ``gt_resolution`` grid in the table plane covering it plus
        ``gt_margin`` (m). The grid's pose (rotation, plane distance) is in its geometry; its (x, y) are
        table-frame coordinates minus the camera's (X, Y) (module docstring)."""
        res, margin = float(self.spec.gt_resolution), float(self.spec.gt_margin)
        if not res > 0 or margin < 0:
            raise ValueError(f'ground-truth resolution must be positive and margin >= 0, got {res}, {margin}')
        lo = np.floor((self.outline.min(axis=0) - margin) / res) * res
        hi = np.ceil((self.outline.max(axis=0) + margin) / res) * res
        w, h = (int(round(v)) for v in (hi - lo) / res)
        table_geom = GridGeometry(float(lo[0]), float(lo[1]), res, w, h, self.table_depth, FRAME_ID)
        occ = np.where(rasterise_polygon(self.outline, table_geom), 100, 0).astype(np.int8)
        sdf = polygon_signed_distance(table_geom.cell_centers(), self.outline).astype(np.float32)
        if self.spec.top_down:
            geom = table_geom
            com = np.append(polygon_centroid(self.outline), self.table_depth)
        else:
            geom = GridGeometry(float(lo[0] - self._c[0]), float(lo[1] - self._c[1]), res, w, h, self.table_depth,
                                FRAME_ID, self.grid_rotation)
            com = self.table_to_camera(polygon_centroid(self.outline))
        return GroundTruth(geom, occ, sdf, com, self.outline.copy())

    # ------------------------------------------------------------------ messages
    def describe(self) -> dict[str, Any]:
        """JSON-able summary of the scene (stored as bag metadata)."""
        s = self.spec
        out: dict[str, Any] = {
            'name': s.name, 'height_m': float(s.height), 'camera_height_m': float(s.camera_height),
            'frames': int(s.frames), 'seed': int(s.seed), 'table_color': [int(v) for v in self.table_color],
            'object_color': [int(v) for v in self.object_color],
            'regions': [r.kind for r in s.regions], 'intrinsics': list(self.intrinsics),
            'crop_offset_px': [self.u0, self.v0], 'frame_id': FRAME_ID, 'outline_vertices': len(self.outline),
        }
        if not s.top_down:
            out.update({'camera_tilt_deg': float(s.camera_tilt), 'camera_azimuth_deg': float(s.camera_azimuth),
                        'table_normal_camera': [float(v) for v in -self._r_tc[2]],
                        'table_distance_m': self.table_depth})
        if s.light is not None:
            out.update({'light_azimuth_elevation_deg': [float(v) for v in s.light],
                        'shadow_strength': float(s.shadow_strength)})
        if self.distractors:
            out['distractors'] = [{'kind': kind, 'height_m': height, 'color': [int(v) for v in color],
                                   'outline_m': np.round(poly, 6).tolist()}
                                  for poly, height, kind, color in self.distractors]
        if s.sensor != 'carmine':
            out['sensor'] = s.sensor
        return out

    def messages(self, f: Any) -> Iterator[tuple[str, str, int, Any]]:
        """``(topic, msgtype, t_ns, msg)`` in bag order: latched ground truth at ``start_ns``, then per
        frame the two CameraInfos, the RGB image, the depth image and the point cloud."""
        from gpis_grasp_ros.data import messages as cv

        t0 = int(self.spec.start_ns)
        gt = self.ground_truth()
        hdr = cv.header(f, t0, FRAME_ID)
        yield TOPICS['occupancy'], TOPIC_TYPES[TOPICS['occupancy']], t0, \
            cv.numpy_to_occupancy_grid(f, gt.occupancy, gt.geometry, hdr)
        yield TOPICS['sdf'], TOPIC_TYPES[TOPICS['sdf']], t0, cv.numpy_to_float_grid(f, gt.sdf, gt.geometry, hdr, 'm')
        yield TOPICS['com'], TOPIC_TYPES[TOPICS['com']], t0, cv.point_stamped(f, gt.center_of_mass, hdr)
        if self.spec.top_down:
            outline = cv.polygon_stamped(f, gt.outline, self.table_depth, hdr)
        else:
            pts = [f.new('geometry_msgs/msg/Point32', x=float(x), y=float(y), z=float(z))
                   for x, y, z in self.table_to_camera(gt.outline).astype(np.float32)]
            outline = f.new('geometry_msgs/msg/PolygonStamped', header=hdr,
                            polygon=f.new('geometry_msgs/msg/Polygon', points=pts))
        yield TOPICS['outline'], TOPIC_TYPES[TOPICS['outline']], t0, outline
        for frame in self.frames():
            t = frame.stamp_ns
            h = cv.header(f, t, FRAME_ID)
            info = cv.intrinsics_to_camera_info(f, *self.intrinsics, h)
            yield TOPICS['rgb_info'], TOPIC_TYPES[TOPICS['rgb_info']], t, info
            yield TOPICS['rgb'], TOPIC_TYPES[TOPICS['rgb']], t, cv.numpy_to_image(f, frame.rgb, 'rgb8', h)
            yield TOPICS['depth_info'], TOPIC_TYPES[TOPICS['depth_info']], t, info
            yield TOPICS['depth'], TOPIC_TYPES[TOPICS['depth']], t, cv.numpy_to_image(f, frame.depth, '32FC1', h)
            yield TOPICS['points'], TOPIC_TYPES[TOPICS['points']], t, \
                cv.xyz_rgb_to_pointcloud2(f, frame.xyz, frame.rgb, h)


def write_scene_bag(spec: SceneSpec, path: str | os.PathLike[str], overwrite: bool = False) -> Path:
    """Simulate ``spec`` and write it as an MCAP bag at ``path`` (``.mcap`` file or rosbag2 directory).

    Camera topics are recorded with sensor-data QoS, ground truth latched. All validation happens
    before anything is written; a failure while writing leaves no partial bag. Returns the path.
    """
    from gpis_grasp_ros.data import bagio
    from gpis_grasp_ros.data.messages import RosbagsFactory

    scene = Scene(spec)
    ts = bagio.get_typestore()
    meta = {'gpis_grasp_ros.sim.scene': json.dumps(scene.describe(), sort_keys=True)}
    with bagio.BagWriter(path, typestore=ts, custom_data=meta, overwrite=overwrite) as bag:
        for topic in GROUND_TRUTH_TOPICS:
            bag.add_topic(topic, TOPIC_TYPES[topic], bagio.LATCHED_QOS)
        for topic in CAMERA_TOPICS:
            bag.add_topic(topic, TOPIC_TYPES[topic], bagio.SENSOR_QOS)
        for topic, _msgtype, t_ns, msg in scene.messages(RosbagsFactory(ts)):
            bag.write(topic, t_ns, msg)
    return Path(path)
