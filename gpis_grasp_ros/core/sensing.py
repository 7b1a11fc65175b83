"""From RGBD frames to an occupancy grid and an SDF noise map (paper section III-B).

Pipeline (one call, :func:`segment_frames`):

1. **Averaging.** Depth is averaged per pixel over the frames with a valid return (finite,
   > 0); the number of valid returns ``n`` is kept. Colour is averaged over all frames.
2. **Table.** A plane z(u, v) = a u + b v + c is fitted to the valid depths of an image border
   band by least squares with iterative outlier rejection (3 x 1.4826 MAD, at least 3 sigma of
   the sensor), unless ``table_depth_m`` is given. The table colour is the per-channel median of
   the border band, unless given. (The camera looks down at the table, objects lie inside.)
3. **Masks (soft).** Height above the table h = z_table - z_mean. The depth evidence is the
   probability that the true height exceeds ``height_threshold`` given the averaged sensor
   noise, p_d = Phi((h - h_thr) / s_h) with s_h^2 = (sigma_z^2 + q^2 / 12) / n (Carmine axial
   model and disparity quantisation, :mod:`~gpis_grasp_ros.core.noise_model`). The colour evidence
   is p_c = Phi((|rgb - rgb_table| - c_thr) / c_sigma) (Euclidean RGB distance, 0-255 units);
   unless set (> 0), both adapt to the table's texture seen in the border band: c_thr = max(20,
   median + 5 MAD) and c_sigma = max(2, MAD) of the border distances, so faintly tinted
   transparent parts (distance ~20-30 on the shipped bags' table) still register or at least
   raise the noise map, while plain table pixels stay at p_c ~ 0.
   Both maps are cleaned by a grey-level morphological opening then closing (OpenCV). The hard
   masks ``depth_mask`` / ``rgb_mask`` are p > 0.5.
4. **Occupancy.** The two masks are combined with inverse-variance weights, each mask's
   variance being its Bernoulli variance p (1 - p) plus a floor that encodes how much that
   sensor is trusted (depth more than colour by default, so a transparent part seen only in
   colour does not enter the *mean* shape, as for Object A in the paper):
   o = (p_d / v_d + p_c / v_c) / (1 / v_d + 1 / v_c). Pixels without any valid return are
   **missing** and count as object (o = 1), as in the paper. Connected components of the
   evidence (o, p_d or p_c > 0.5, or missing) smaller than ``min_object_area_px`` or than
   ``min_component_fraction`` of the largest are discarded as clutter / specks (occupancy 0;
   weak or discarded evidence still raises the noise map through rho below).
5. **Grid.** The kept evidence's bounding box plus ``margin`` of its larger side on
   every side gives a square of side S in the table plane, resampled to M x M square cells
   (``grid_size``, default 25). A pixel (u, v) at table depth z_t is at x = (u - cx) z_t / fx,
   y = (v - cy) z_t / fy (camera frame, metres); cells are averaged from bilinearly
   interpolated pixel maps on an s x s sub-grid per cell (s >= pixels per cell), so coarse and
   fine grids both integrate the image. A cell is missing when more than
   ``missing_cell_fraction`` of its area has no valid return (excluded from GPIS training,
   ``train_mask``). Cells outside the (cropped) image are ``observed = False`` and assumed to be
   table: free, trained with SDF variance ``unobserved_variance_m2`` - the object is assumed to
   lie inside the image, and leaving them untrained would let the negative prior mean invent
   object there.

Noise map. The GP observes the *signed distance*, so the map is the variance (m^2) of each
cell's SDF value, the sum of these documented terms:

* depth:          mean over the cell of s_z^2 / n (axial noise of the averaged depth, m^2). A
  surface seen with axial error s_z is localised laterally to about the same error, so it is
  used 1:1 as an SDF error (the paper's "noise map based on a noise model of the Primesense").
* disagreement:   ``disagreement_variance_m2`` x rho, rho = |mean p_d - mean p_c| over the
  cell's valid pixels, in [0, 1]: the two masks disagree about the cell (averaging first means
  that a boundary cell half covered in both masks, or a one-pixel edge misalignment, does not
  count); plus the same variance x the missing fraction of partly missing (still trained)
  cells. The ``noise_px`` debug map is the pixel version, s_z^2 / n + variance x |p_d - p_c|.
* propagation:    the SDF at a cell depends on the occupancy of the cells holding its nearest
  surface, not only on its own. For every connected component U_c of uncertain cells (missing,
  or rho > ``uncertainty_threshold``) the SDF is computed with U_c as object (f_obj) and as free
  (f_free); the cell's value is uncertain by Delta = f_obj - f_free, a Bernoulli choice with
  variance q (1 - q) Delta^2, q = 1/2 (``alternative_weight`` = 0.25); a component that is the
  only object evidence is skipped ("free" would mean no object at all). This error is the *same*
  for all cells that depend on U_c, but the GP noise is independent per cell, and n cells with
  a shared error would average it away as if it had variance / n. The term is therefore
  multiplied by n_eff = min(#affected training cells, pi (l_e / res)^2), the number of cells
  sharing the error within ``error_correlation_length_m`` l_e (an effective-sample-size
  correction). Far from any uncertain cell f_obj = f_free and the term vanishes; next to a
  transparent or specular part it keeps the GPIS uncertain there (section III-B (a), (b)).
* discretisation (off by default, ``discretisation_weight``): resolution^2 / 12. The grid's
  boundary quantisation is a systematic, spatially correlated error; entered as white noise
  it lets maximum likelihood choose a longer length scale that makes the GPIS over-confident
  inside missing regions, so it is not used unless asked for.

Missing cells (excluded from training) carry at least ``disagreement_variance_m2`` so that the
published map never shows them as reliable; the GP does not use these values.

All points are metric (x, y) in the camera frame at the table depth; see
:class:`~gpis_grasp_ros.core.grid.GridGeometry` for the array conventions.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.special import ndtr

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.noise_model import axial_variance, quantisation_step
from gpis_grasp_ros.core.sdf import signed_distance


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels: x = (u - cx) z / fx, y = (v - cy) z / fy (u = column, v = row)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        if not (math.isfinite(self.fx) and math.isfinite(self.fy) and self.fx > 0 and self.fy > 0):
            raise ValueError(f'focal lengths must be positive pixels, got fx={self.fx}, fy={self.fy}')
        if not (math.isfinite(self.cx) and math.isfinite(self.cy)):
            raise ValueError('principal point must be finite')
        if self.width < 1 or self.height < 1:
            raise ValueError(f'image size must be positive, got {self.width} x {self.height}')


@dataclass(frozen=True)
class SensingParams:
    """Settings of :func:`segment_frames` (lengths in metres, colours in 0-255 RGB units)."""

    grid_size: int = 25  # M, cells per side of the square grid
    margin: float = 0.2  # free margin on each side, fraction of the object's larger bbox side
    table_depth_m: float | None = None  # known table depth (fronto-parallel); None = fit a plane to the border
    table_color: tuple[float, float, float] | None = None  # known table RGB; None = median of the border
    border_px: int = 8  # width of the image border band used to estimate the table
    height_threshold: float = 0.003  # depth mask: height above the table (~6 sigma of a 10-frame average)
    color_threshold: float = 0.0  # RGB mask: distance from the table colour; <= 0 = adaptive (docstring)
    color_threshold_min: float = 20.0  # adaptive threshold: max(this, median + color_mad_factor x MAD of border)
    color_mad_factor: float = 5.0
    color_sigma: float = 0.0  # width of the soft colour ramp; <= 0 = adaptive, max(2, MAD of the border)
    depth_floor_variance: float = 0.02  # trust of the depth mask in the inverse-variance weights
    color_floor_variance: float = 0.05  # trust of the RGB mask (higher = trusted less)
    morph_kernel_px: int = 3  # opening/closing kernel (ellipse) of the mask clean-up, 0 = off
    min_valid_returns: int = 1  # fewer valid returns than this = missing pixel
    min_object_area_px: int = 30  # smaller evidence components are discarded
    min_component_fraction: float = 0.05  # ... and components smaller than this x the largest
    missing_cell_fraction: float = 0.5  # a cell is missing above this fraction of missing area
    uncertainty_threshold: float = 0.5  # rho above which a cell's occupancy is uncertain
    unobserved_variance_m2: float = 1e-5  # SDF variance of grid cells outside the image (assumed table)
    disagreement_variance_m2: float = 1e-4  # SDF variance (m^2) per unit disagreement rho
    alternative_weight: float = 0.25  # weight of (f_obj - f_free)^2 in the SDF noise
    error_correlation_length_m: float = 0.01  # extent over which propagated SDF errors are shared (m)
    discretisation_weight: float = 0.0  # weight of resolution^2 / 12 in the SDF noise (0 = off, see docstring)

    def __post_init__(self) -> None:
        if self.grid_size < 3:
            raise ValueError(f'grid_size must be >= 3, got {self.grid_size}')
        if self.margin < 0:
            raise ValueError('margin must be >= 0')
        if self.border_px < 1:
            raise ValueError('border_px must be >= 1')
        if not self.height_threshold > 0:
            raise ValueError(f'height_threshold must be a positive number of metres, got {self.height_threshold}')
        if self.depth_floor_variance <= 0 or self.color_floor_variance <= 0:
            raise ValueError('mask floor variances must be positive')


@dataclass
class SensingResult:
    """Output of :func:`segment_frames`: grid maps (M x M) plus pixel maps (H x W) for debugging."""

    occupancy: np.ndarray  # (M, M) float in [0, 1], probability of object
    noise_variance: np.ndarray  # (M, M) m^2, observation-noise variance of each cell's SDF value
    missing: np.ndarray  # (M, M) bool, mostly no valid depth return (object in occupancy, not trained)
    geometry: GridGeometry  # z = table depth (m)
    table_depth: float  # m, table plane depth at the grid centre
    train_mask: np.ndarray  # (M, M) bool, cells used to train the GPIS (= not missing)
    observed: np.ndarray  # (M, M) bool, cells covered by the image (the others are assumed table)
    uncertain: np.ndarray  # (M, M) bool, missing or masks disagree (rho > uncertainty_threshold)
    disagreement: np.ndarray  # (M, M) float rho in [0, 1]
    table_color: np.ndarray  # (3,) RGB
    color_threshold: float  # RGB distance threshold used (given or adaptive)
    # pixel level
    mean_depth: np.ndarray  # (H, W) m, NaN where missing
    valid_count: np.ndarray  # (H, W) int, valid returns per pixel
    height: np.ndarray  # (H, W) m above the table, NaN where missing
    depth_mask: np.ndarray  # (H, W) bool
    rgb_mask: np.ndarray  # (H, W) bool
    missing_mask: np.ndarray  # (H, W) bool
    object_mask: np.ndarray  # (H, W) bool, kept evidence components
    occupancy_px: np.ndarray  # (H, W) float
    noise_px: np.ndarray  # (H, W) m^2, depth + disagreement terms, NaN where missing
    disagreement_px: np.ndarray  # (H, W) float rho
    bbox_px: tuple[int, int, int, int]  # (u_min, v_min, u_max, v_max) of the object, inclusive
    intrinsics: CameraIntrinsics

    @property
    def sdf(self) -> np.ndarray:
        """Signed distance (m) of the occupancy (>= 0.5 is object), :func:`~gpis_grasp_ros.core.sdf.signed_distance`."""
        return signed_distance(self.occupancy, self.geometry.resolution)


# ----------------------------------------------------------------------------------------------
# input handling

def _as_frames(frames: np.ndarray | Sequence[np.ndarray], name: str, channels: int | None) -> np.ndarray:
    try:
        arr = np.asarray(frames)
    except ValueError as exc:  # ragged list of frames
        raise ValueError(f'{name}: frames have different shapes ({exc})') from None
    if arr.dtype == object:
        raise ValueError(f'{name}: frames have different shapes')
    want = 3 if channels is None else 4
    if arr.ndim == want - 1:
        arr = arr[None]
    if arr.ndim != want or (channels is not None and arr.shape[-1] != channels):
        shape = '(N, H, W)' if channels is None else f'(N, H, W, {channels})'
        raise ValueError(f'{name}: expected shape {shape} (or one frame without N), got {arr.shape}')
    if arr.shape[0] == 0 or arr.shape[1] == 0 or arr.shape[2] == 0:
        raise ValueError(f'{name}: no frames or empty images, got shape {arr.shape}')
    return arr


def frames_from_clouds(xyz: np.ndarray, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, CameraIntrinsics]:
    """Organized XYZRGB clouds → ``(rgb_frames, depth_frames, intrinsics)``.

    Depth is z (m; NaN where the point is invalid). The intrinsics are recovered by least
    squares from the pinhole model u = fx x / z + cx, v = fy y / z + cy over all valid points
    (u = column index, v = row index).

    Args:
        xyz: ``(N, H, W, 3)`` float points in the camera optical frame (m), NaN = no return.
        rgb: ``(N, H, W, 3)`` uint8 colours.
    """
    pts = _as_frames(xyz, 'xyz', 3)
    col = _as_frames(rgb, 'rgb', 3)
    if not np.issubdtype(pts.dtype, np.floating):
        raise ValueError(f'xyz must be floating point metres, got dtype {pts.dtype}')
    if col.dtype != np.uint8:
        raise ValueError(f'rgb must be uint8, got dtype {col.dtype}')
    if pts.shape != col.shape:
        raise ValueError(f'xyz {pts.shape} and rgb {col.shape} must have the same shape')
    n, h, w, _ = pts.shape
    x, y, z = (pts[..., i].astype(np.float64) for i in range(3))
    valid = np.isfinite(x) & np.isfinite(y) & np.isfinite(z) & (z > 0)
    if valid.sum() < 3:
        raise ValueError('clouds have fewer than 3 valid points: cannot recover the intrinsics')
    u = np.broadcast_to(np.arange(w, dtype=np.float64)[None, None, :], (n, h, w))[valid]
    v = np.broadcast_to(np.arange(h, dtype=np.float64)[None, :, None], (n, h, w))[valid]
    xz, yz = x[valid] / z[valid], y[valid] / z[valid]

    def fit(a: np.ndarray, b: np.ndarray, axis: str) -> tuple[float, float]:
        if np.ptp(a) <= 0:
            raise ValueError(f'valid points span a single {axis} ray direction: cannot recover the intrinsics')
        design = np.stack([a, np.ones_like(a)], axis=1)
        (f, c), *_ = np.linalg.lstsq(design, b, rcond=None)
        return float(f), float(c)

    fx, cx = fit(xz, u, 'x')
    fy, cy = fit(yz, v, 'y')
    depth = np.where(valid, z, np.nan)
    return col, depth, CameraIntrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=w, height=h)


def _fit_table_plane(depth: np.ndarray, border: np.ndarray) -> np.ndarray:
    """Robust least-squares plane z = a u + b v + c (m) through the valid border depths → (H, W)."""
    h, w = depth.shape
    vv, uu = np.nonzero(border & np.isfinite(depth))
    if vv.size < 20:
        raise ValueError(f'only {vv.size} valid depth returns in the image border: cannot estimate the table '
                         '(crop the image with some table around the object, or give table_depth_m)')
    zz = depth[vv, uu]
    design = np.stack([uu, vv, np.ones_like(uu)], axis=1).astype(np.float64)
    inlier = np.ones(zz.size, dtype=bool)
    coef = np.array([0.0, 0.0, float(np.median(zz))])
    for _ in range(5):
        if inlier.sum() < 3:
            break
        coef, *_ = np.linalg.lstsq(design[inlier], zz[inlier], rcond=None)
        resid = zz - design @ coef
        mad = 1.4826 * np.median(np.abs(resid[inlier] - np.median(resid[inlier])))
        tol = max(3.0 * mad, 3.0 * float(math.sqrt(axial_variance(coef[2]))))
        new = np.abs(resid) <= tol
        if np.array_equal(new, inlier):
            break
        inlier = new
    u_grid, v_grid = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    return coef[0] * u_grid + coef[1] * v_grid + coef[2]


def _morph_clean(prob: np.ndarray, size: int) -> np.ndarray:
    """Grey-level opening then closing of a probability map (removes specks, fills pinholes)."""
    if size <= 1:
        return prob
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    img = prob.astype(np.float32)
    img = cv2.morphologyEx(img, cv2.MORPH_OPEN, kernel, borderType=cv2.BORDER_REPLICATE)
    img = cv2.morphologyEx(img, cv2.MORPH_CLOSE, kernel, borderType=cv2.BORDER_REPLICATE)
    return img.astype(np.float64)


def _keep_components(evidence: np.ndarray, params: SensingParams) -> np.ndarray:
    """Evidence components large enough to be (part of) the object."""
    count, labels, stats, _ = cv2.connectedComponentsWithStats(evidence.astype(np.uint8), connectivity=8)
    if count <= 1:
        return np.zeros_like(evidence, dtype=bool)
    areas = stats[1:, cv2.CC_STAT_AREA]
    keep_min = max(params.min_object_area_px, params.min_component_fraction * areas.max())
    keep = np.zeros(count, dtype=bool)
    keep[1:] = areas >= keep_min
    return keep[labels]


def _cell_average(maps: list[np.ndarray], intr: CameraIntrinsics, geometry: GridGeometry,
                  z_table: float) -> tuple[list[np.ndarray], np.ndarray]:
    """Average pixel maps over each grid cell's area (bilinear sub-sampling), plus the in-image fraction."""
    m_w, m_h, res = geometry.width, geometry.height, geometry.resolution
    px_per_cell = res * max(intr.fx, intr.fy) / z_table
    s = max(2, int(math.ceil(px_per_cell)))
    offs = (np.arange(s) + 0.5) / s
    xs = geometry.origin_x + (np.arange(m_w)[:, None] + offs[None, :]).ravel() * res
    ys = geometry.origin_y + (np.arange(m_h)[:, None] + offs[None, :]).ravel() * res
    map_u = (intr.cx + xs * intr.fx / z_table).astype(np.float32)
    map_v = (intr.cy + ys * intr.fy / z_table).astype(np.float32)
    map_x, map_y = np.meshgrid(map_u, map_v)

    def sample(img: np.ndarray) -> np.ndarray:
        out = cv2.remap(img.astype(np.float32), map_x, map_y, interpolation=cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        return out.astype(np.float64).reshape(m_h, s, m_w, s)

    inside_sub = sample(np.ones((intr.height, intr.width)))
    inside = inside_sub.mean(axis=(1, 3))
    out = []
    for img in maps:
        sub = sample(img)
        total = sub.sum(axis=(1, 3))
        weight = inside_sub.sum(axis=(1, 3))
        out.append(np.where(weight > 0, total / np.maximum(weight, 1e-12), 0.0))
    return out, inside


def _propagation_variance(occ_bin: np.ndarray, uncertain: np.ndarray, train: np.ndarray, geometry: GridGeometry,
                          params: SensingParams) -> np.ndarray:
    """SDF variance (m^2) induced by uncertain cells on every cell's distance (module docstring)."""
    out = np.zeros(geometry.shape)
    if not uncertain.any():
        return out
    res = geometry.resolution
    n_local = math.pi * (params.error_correlation_length_m / res) ** 2
    count, labels = cv2.connectedComponents(uncertain.astype(np.uint8), connectivity=8)
    # if the component is all there is, "free" means no surface in the grid: distances of the grid size
    for c in range(1, count):
        comp = labels == c
        rest = occ_bin & ~comp
        if not rest.any():  # the component is the only object evidence: "free" would mean no object at all
            continue
        delta = signed_distance(occ_bin | comp, res) - signed_distance(rest, res)
        affected = int(np.count_nonzero((np.abs(delta) > 1e-12) & train))
        n_eff = max(1.0, min(float(affected), n_local))
        out += params.alternative_weight * n_eff * delta ** 2
    return out


# ----------------------------------------------------------------------------------------------
# main entry point

def segment_frames(rgb_frames: np.ndarray | Sequence[np.ndarray], depth_frames: np.ndarray | Sequence[np.ndarray],
                   intrinsics: CameraIntrinsics, params: SensingParams = SensingParams(),
                   frame_id: str = '') -> SensingResult:
    """Segment an object from N RGBD frames into an M x M occupancy grid and SDF noise map (III-B).

    Args:
        rgb_frames: ``(N, H, W, 3)`` uint8 RGB images (or one ``(H, W, 3)`` image).
        depth_frames: ``(N, H, W)`` float depth in metres, NaN (or <= 0) = no return.
        intrinsics: pinhole intrinsics of the (registered) images, pixels.
        params: thresholds and grid settings (see :class:`SensingParams`).
        frame_id: sensor frame stored in the returned geometry.

    Returns:
        :class:`SensingResult`; see the module docstring for every map.

    Raises:
        ValueError: wrong dtype or shape, no valid depth, no table in the border, no object.
    """
    if not isinstance(intrinsics, CameraIntrinsics):
        raise ValueError(f'intrinsics must be a CameraIntrinsics, got {type(intrinsics).__name__}')
    rgb = _as_frames(rgb_frames, 'rgb_frames', 3)
    depth_in = _as_frames(depth_frames, 'depth_frames', None)
    if rgb.dtype != np.uint8:
        raise ValueError(f'rgb_frames must be uint8, got dtype {rgb.dtype}')
    if not np.issubdtype(depth_in.dtype, np.floating):
        raise ValueError(f'depth_frames must be floating point metres, got dtype {depth_in.dtype} '
                         '(convert 16-bit millimetre depth with depth / 1000.0 and 0 -> NaN)')
    if rgb.shape[:3] != depth_in.shape:
        raise ValueError(f'rgb_frames {rgb.shape[:3]} and depth_frames {depth_in.shape} differ in number of '
                         'frames or image size')
    n_frames, h, w = depth_in.shape
    if (h, w) != (intrinsics.height, intrinsics.width):
        raise ValueError(f'images are {w} x {h} but the intrinsics are for {intrinsics.width} x {intrinsics.height}')

    # 1. averaging over valid returns
    depth = depth_in.astype(np.float64)
    valid = np.isfinite(depth) & (depth > 0)
    count = valid.sum(axis=0)
    if count.max() == 0:
        raise ValueError('depth_frames contain no valid return (all NaN or <= 0)')
    z_sum = np.where(valid, depth, 0.0).sum(axis=0)
    missing_px = count < max(1, params.min_valid_returns)
    with np.errstate(invalid='ignore', divide='ignore'):
        z_mean = np.where(missing_px, np.nan, z_sum / np.maximum(count, 1))
    rgb_mean = rgb.astype(np.float64).mean(axis=0)

    # 2. table plane and colour from the border band
    b = min(params.border_px, max(1, min(h, w) // 4))
    border = np.zeros((h, w), dtype=bool)
    border[:b, :] = border[-b:, :] = border[:, :b] = border[:, -b:] = True
    if params.table_depth_m is not None:
        if not (math.isfinite(params.table_depth_m) and params.table_depth_m > 0):
            raise ValueError(f'table_depth_m must be positive metres, got {params.table_depth_m}')
        z_table_px = np.full((h, w), float(params.table_depth_m))
    else:
        z_table_px = _fit_table_plane(z_mean, border)
    if params.table_color is not None:
        table_rgb = np.asarray(params.table_color, dtype=np.float64).reshape(3)
    else:
        table_rgb = np.median(rgb_mean[border], axis=0)

    # 3. soft depth and colour evidence
    height = z_table_px - z_mean
    z_safe = np.where(missing_px, z_table_px, z_mean)
    var_z = (axial_variance(z_safe) + quantisation_step(z_safe) ** 2 / 12.0) / np.maximum(count, 1)
    p_d = np.where(missing_px, 0.0, ndtr((np.nan_to_num(height) - params.height_threshold) / np.sqrt(var_z)))
    color_dist = np.linalg.norm(rgb_mean - table_rgb[None, None, :], axis=-1)
    # adaptive threshold and ramp: above the table's own colour variation (texture, shading, noise)
    border_dist = color_dist[border]
    mad = 1.4826 * float(np.median(np.abs(border_dist - np.median(border_dist))))
    c_thr = (float(params.color_threshold) if params.color_threshold > 0
             else max(params.color_threshold_min, float(np.median(border_dist)) + params.color_mad_factor * mad))
    c_sigma = float(params.color_sigma) if params.color_sigma > 0 else max(2.0, mad)
    p_c = ndtr((color_dist - c_thr) / c_sigma)
    p_d = _morph_clean(p_d, params.morph_kernel_px)
    p_c = _morph_clean(p_c, params.morph_kernel_px)

    # 4. inverse-variance combination, missing = object, clutter removal
    v_d = p_d * (1.0 - p_d) + params.depth_floor_variance
    v_c = p_c * (1.0 - p_c) + params.color_floor_variance
    occ = (p_d / v_d + p_c / v_c) / (1.0 / v_d + 1.0 / v_c)
    rho = np.abs(p_d - p_c)  # pixel-level disagreement (debug map); the grid uses cell averages below
    occ = np.where(missing_px, 1.0, occ)
    rho = np.where(missing_px, 0.0, rho)
    evidence = (occ > 0.5) | (p_d > 0.5) | (p_c > 0.5)
    if params.morph_kernel_px > 1:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (params.morph_kernel_px, params.morph_kernel_px))
        evidence = cv2.morphologyEx(evidence.astype(np.uint8), cv2.MORPH_OPEN, kernel).astype(bool)
    object_mask = _keep_components(evidence, params)
    if not object_mask.any():
        raise ValueError(f'no object found: no region of at least {params.min_object_area_px} px is more than '
                         f'{params.height_threshold * 1000:.1f} mm above the table, differs from the table colour '
                         f'by more than {c_thr:.0f}, or lacks depth')
    occ = np.where(object_mask, occ, 0.0)  # clutter leaves the shape; its disagreement rho stays in the noise
    noise_px = np.where(missing_px, np.nan, var_z + params.disagreement_variance_m2 * rho)

    # 5. square metric grid around the object, in the table plane
    vs, us = np.nonzero(object_mask)
    u0, u1, v0, v1 = int(us.min()), int(us.max()), int(vs.min()), int(vs.max())
    z_t = float(z_table_px[(v0 + v1) // 2, (u0 + u1) // 2])
    x0, x1 = (u0 - 0.5 - intrinsics.cx) * z_t / intrinsics.fx, (u1 + 0.5 - intrinsics.cx) * z_t / intrinsics.fx
    y0, y1 = (v0 - 0.5 - intrinsics.cy) * z_t / intrinsics.fy, (v1 + 0.5 - intrinsics.cy) * z_t / intrinsics.fy
    side = max(x1 - x0, y1 - y0) * (1.0 + 2.0 * params.margin)
    m = params.grid_size
    geometry = GridGeometry(origin_x=0.5 * (x0 + x1) - side / 2, origin_y=0.5 * (y0 + y1) - side / 2,
                            resolution=side / m, width=m, height=m, z=z_t, frame_id=frame_id)
    var_depth_px = np.where(missing_px, 0.0, var_z)
    valid_px = (~missing_px).astype(np.float64)
    (occ_c, pd_c, pc_c, miss_c, var_c, valid_c), inside = _cell_average(
        [occ, p_d * valid_px, p_c * valid_px, missing_px.astype(np.float64), var_depth_px, valid_px],
        intrinsics, geometry, z_t)
    observed = inside >= 0.5  # the rest of the grid lies outside the (cropped) image: assumed table
    occupancy = np.clip(np.where(observed, occ_c, 0.0), 0.0, 1.0)
    missing = observed & (miss_c > params.missing_cell_fraction)
    # cell disagreement from the cell-averaged evidence: a boundary cell half covered in both masks
    # agrees (0.5 vs 0.5), a transparent cell (depth 0, colour 1) does not
    with np.errstate(invalid='ignore', divide='ignore'):
        rho_c = np.abs(pd_c - pc_c) / valid_c
    disagreement = np.where(observed & (valid_c > 0), np.clip(np.nan_to_num(rho_c), 0.0, 1.0), 0.0)
    depth_var = np.where(valid_c > 0, var_c / np.maximum(valid_c, 1e-12), 0.0)

    # SDF noise: depth + discretisation + disagreement + propagation (module docstring)
    uncertain = missing | (disagreement > params.uncertainty_threshold)
    noise = (depth_var + params.discretisation_weight * geometry.resolution ** 2 / 12.0
             + params.disagreement_variance_m2 * disagreement
             + params.disagreement_variance_m2 * np.where(missing, 0.0, miss_c))
    occ_bin = occupancy >= 0.5
    if not occ_bin.any():
        raise ValueError('no object found: the object evidence is too weak for any grid cell to be occupied '
                         '(lower grid_size or the thresholds)')
    noise = np.where(observed, noise, params.unobserved_variance_m2)
    noise = noise + _propagation_variance(occ_bin, uncertain, ~missing, geometry, params)
    train_mask = ~missing
    noise = np.where(train_mask, noise, np.maximum(noise, params.disagreement_variance_m2))  # unused by the GP
    return SensingResult(
        occupancy=occupancy, noise_variance=noise, missing=missing, geometry=geometry, table_depth=z_t,
        train_mask=train_mask, observed=observed, uncertain=uncertain, disagreement=disagreement,
        table_color=table_rgb, color_threshold=c_thr, mean_depth=z_mean, valid_count=count.astype(np.int64),
        height=height,
        depth_mask=p_d > 0.5, rgb_mask=p_c > 0.5, missing_mask=missing_px, object_mask=object_mask,
        occupancy_px=occ, noise_px=noise_px, disagreement_px=rho, bbox_px=(u0, v0, u1, v1), intrinsics=intrinsics)
