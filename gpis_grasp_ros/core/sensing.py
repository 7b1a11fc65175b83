"""From RGBD frames of a tabletop to a target's occupancy grid and SDF noise map (paper section III-B).

Pipeline (one call, :func:`segment_frames`), for a camera looking down at a table at any tilt
(0-60 degrees; the paper's PR2 head camera):

1. **Averaging.** Depth is averaged per pixel over the frames with a valid return (finite,
   > 0); the number of valid returns ``n`` is kept. Colour is averaged over all frames. The frames
   are worth n_eff <= N independent measurements, *measured* from their frame-to-frame depth
   differences (:func:`~gpis_grasp_ros.core.noise_model.effective_frame_count`: identical
   repeated frames count as one); a pixel's averaged variance is sigma_z^2 / (n n_eff / N).
2. **Table frame** (:mod:`~gpis_grasp_ros.core.table_frame`). Every valid pixel is back-projected
   to a camera-frame point (m); a robust plane fit (MSAC, inlier band from the sensor model
   ``sensor``) over the whole cloud gives the table normal n (towards the camera) and offset d,
   unless ``table_plane`` (a, b, c, d) or ``table_depth_m`` (fronto-parallel) is given. Heights
   are measured along n. The table's colour model is learnt from the plane's inliers.
3. **Evidence (soft).** Depth: p_d = Phi((h - h_thr) / s_h), h the height above the plane,
   s_h the averaged depth noise projected on the normal, h_thr = max(``height_threshold``,
   2 x the plane inliers' RMS). Colour (**shadow-proof**): a shadow darkens the table without
   changing its chromaticity, x = alpha t (t the table colour, alpha < 1). The colour distance is
   the distance from that shadow line, D = |x - clip(alpha*, 0, 1) t| with alpha* = x.t / |t|^2
   (0-255 RGB units), so a shadow gives D ~ 0 while a tint, another hue or a brighter surface
   does not; p_c = Phi((D - c_thr) / c_sigma) with c_thr = max(``color_threshold_min``, median + 5
   MAD) and c_sigma = max(2, MAD) of D over the plane's inliers unless given (robust statistics:
   the inliers include the table seen through clear objects). Optional, off by default
   (``color_smooth_px``, ``color_hole_margin_px``): a Gaussian smoothing of the colour image and
   leaving the inliers next to depth holes out of the colour statistics - measured on the real
   D435 captures they gained nothing, on the simulated bags they cost thin objects. Both maps are
   cleaned by a grey-level opening then closing. **Seen through** (``see_through_test``, default on,
   :func:`see_through_pixels`): objects on a table are height fields, so the column under every point
   seen above the table is solid; an evidence pixel whose return lies behind the columns imaged over its
   3 x 3 neighbourhood (by 3 sqrt(2) sigma_z + 5 mm) saw through a clear part - a stereo sensor returns
   the table behind it, or a blend - and its return is moved to where its ray enters that solid (the
   farthest its first surface can be). A top-down camera sees every column end-on: nothing is moved. On
   the real D435 captures the clear flower box's lower face, which returned the table 2-5 cm behind it,
   lands on the box. **The sensor's shadow** (``shadow_test``, default on, :func:`occlusion_shadow_pixels`):
   a structured-light sensor needs its projector to light a point, a stereo sensor its second imager to see
   it (``SensorModel.occluder_x_m``); table beside an object hidden from that viewpoint has no return. A
   no-return pixel whose colour is the table's, whose table point that viewpoint cannot see past the solid
   columns and that lies beside (not under) them, is table the sensor did not measure - not missing =
   object - where the visual hull cannot tell it from the object (the column over its table point images
   shorter than ``SHADOW_HULL_SPAN_PX``: a near top-down view; a tilted camera's prism test decides, step 5).
4. **Occupancy per pixel.** Inverse-variance combination of the masks (depth trusted more than
   colour: a transparent part seen only in colour does not enter the *mean* shape, Object A of
   the paper): o = (p_d / v_d + p_c / v_c) / (1 / v_d + 1 / v_c), v = p (1 - p) + floor.
   Pixels without a valid return are **missing** and count as object (o = 1), as in the paper (except the
   sensor's shadow above: unmeasured table, like a hole off the object's visual hull).
5. **Target isolation in the table plane.** Evidence = (o, p_d or p_c > 0.5, or missing), only
   above the plane (h > -band, below ``max_object_height_m``), over the table's extent (the convex
   hull of the plane's inliers) and inside the region of interest (``roi_px`` pixel box and/or
   ``roi_table`` box in the table frame). Each evidence pixel is projected **orthographically**
   onto the plane (its foot p - h n; a missing pixel next to a seen object is put where its ray
   enters that object's prism, :func:`_missing_height`, else where the ray meets the plane) and
   rasterised at about two pixel footprints; the raster is closed (3 x 3) and split into 8-connected
   components of the positive (depth or colour) evidence. **Objects in contact are split** there:
   at necks (:func:`split_touching`: h-maxima of the distance transform of the hole-filled
   components, both parts wider than their contact by 2 ``SPLIT_NECK_M``, flooded level by level)
   and where something taller stands on or next to a flat support such as a notebook or a plate
   (:func:`split_flat_support`: a smooth region of cell heights of at least ``FLAT_MIN_AREA_M2``
   and cells more than ``FLAT_JUMP_M`` above it); split parts are not joined again through holes.
   Hole regions join an object within
   ``MISSING_ATTACH_M`` of its seen parts (all of a hole region touching only that object, up to
   2 ``MISSING_BRIDGE_M`` across; a hole region up to ``MISSING_BRIDGE_M`` touching several objects
   joins them; one touching none is an object of its own), so drop-outs along a real table do not
   chain objects together; components under ``min_object_area_px`` pixels or ``min_object_area_m2``
   are specks. The number of objects seen is reported (``objects_seen``). ``target`` picks one:
   ``largest`` (table-plane area), ``nearest_center`` (its pixels' centroid nearest the image
   centre), ``pixel`` / ``table`` (the component containing ``target_point``: a pixel (u, v), or
   table-frame (x, y) in m, within ``target_tolerance_m``). The target is refused (ValueError,
   nothing to publish) when it reaches within ``border_px`` of the image (or pixel ROI) edge - it
   is cut by the border - or when it is wider than ``max_opening_m`` in every direction (convex
   hull) and no part of it is narrower (largest inscribed disc), i.e. no part fits the gripper.
   **Seen through the target** (:func:`seen_through`): the target's raster outline is dilated by
   ``transparent_close_m``, hole-filled and eroded back; table-level pixels in that enclosed interior
   (a clear object's outline around the table seen through it) join the target with colour/hole
   evidence only: object in the occupancy, p_c = 1 against table-level depth (uncertain cells, the
   paper's Object A treatment), never observed table. ``transparent_core_occupied`` (off: the
   paper keeps a part seen only in colour out of the mean shape) extends this to the colour-only
   pixels of the target's core. **A clear body seen through** (``chroma_z_min``, default 1.5; 0 = off):
   for a target with fewer than half of its pixels seen in depth (a clear object, seen through holes and
   specular edges), the table seen through clear plastic keeps the table's depth and, mostly, passes the shadow-line
   colour test, but its *chromaticity* (r, g, b) / (r + g + b) moves off the table's
   (:func:`chromaticity_distance`: robust sigmas over the plane's inliers, brightness-free, so shadows
   and highlights of the table's colour do not count). Table-level pixels more than ``chroma_z_min``
   sigmas off, connected in the image to the target's pixels, in regions holding a 7-pixel disc (a band
   of mixed pixels along an opaque edge does not), not another object's pixels nor over another
   object's raster cells, and not reaching the image border, join the target the same way (colour
   evidence only: uncertain cells, the prior governs) (:func:`chromatic_extension`). **A clear body is
   a prism** (``clear_body_prism``, default on): when the target, with the clear parts touching it in the
   image (hole regions, components seen mostly not in depth: a bottle falls apart into a specular ridge,
   holes at its ends and a seen-through interior, :func:`_touching_clear_parts`), has fewer than
   ``CLEAR_BODY_FRACTION`` (a quarter) of its pixels seen in depth, its silhouette (closed over gaps
   narrower than a 7-pixel disc, holes filled) is taken as the image of a prism standing on the table. The
   seen-through pixels' table points are the footprint swept H tan(tilt) away from the camera (a 6 cm
   bottle at 52 deg: 8 cm); the footprint is the prism's (:func:`prism_footprint`: the cells whose vertical
   segment up to H projects onto the silhouette), with H the height at which that footprint is as narrow as
   high or as deep as wide, whichever is lower (:func:`clear_body_height`: a body lying on the table, or a
   squat round one; an upright one higher than wide gets a larger footprint; ``clear_body_height_m`` > 0:
   a known height instead). The
   grid spans that footprint; cells outside it that the target reached only through its body or holes are
   the table seen through it: free, but trained with ``disagreement_variance_m2`` (free only if the height
   prior is right); observed cells inside it are object with colour/hole evidence, trained with the same
   variance (``train_clear_body``; off: unknown cells). A
   partly clear object (the paper's Object A: half of it seen in depth) keeps its clear part uncertain.
6. **Grid in the table plane.** The target's footprint bounding box in the table frame plus
   ``margin`` of its larger side on every side gives a square of side S, M x M cells
   (``grid_size``); the grid's pose is the table frame (``GridGeometry.rotation`` = R, ``z`` = d).
   Every pixel is projected orthographically as above and averaged into the cell under its
   foot, weighted by the table area its foot covers (a wall facing a tilted camera projects onto a
   line and gets ~0 weight, :func:`_table_area_weights`); the part of a cell hidden behind an object
   (beyond the far edge of its top, :func:`_hidden_fraction`) counts as table, so that a cell's
   occupancy is the fraction of it the object covers; cells between the feet of neighbouring pixels
   take the mean of their observed neighbours, unless hidden behind an object (:func:`_hidden_cells`);
   pixels of other objects count as table (occupancy 0: the grid holds the target only) and their
   missing pixels are ignored. A cell that no pixel reaches is sampled at its centre's
   image point if that pixel sees the table there (a grid finer than the pixels); if that pixel
   sees something above the table the cell is **occluded** (hidden behind an object from a
   tilted camera). Occluded cells and cells outside the image are ``observed = False``: assumed
   table (free), trained with SDF variance ``unobserved_variance_m2`` (the object is assumed to
   lie in view and to be a prism whose visible top covers its footprint; leaving them untrained
   would let the negative prior mean invent object there). A cell is missing when more than
   ``missing_cell_fraction`` of its pixels are the target's missing pixels (excluded from GPIS
   training, ``train_mask``).
7. **Object height** (``SensingResult.object_height``, :func:`object_height`): the 95th percentile
   of the heights of the target's pixels seen in depth above the table (m); parts without a depth
   return (specular, or transparent ones the sensor sees through) are not measured; 0 = unknown.

Noise map. The GP observes the *signed distance*, so the map is the variance (m^2) of each
cell's SDF value, the sum of these documented terms:

* depth:          mean over the cell of s_z^2 / n_eff (axial noise of the averaged depth, m^2). A
  surface seen with axial error s_z is localised laterally to about the same error, so it is
  used 1:1 as an SDF error (the paper's "noise map based on a noise model of the Primesense").
* disagreement:   ``disagreement_variance_m2`` x rho, rho = |mean p_d - mean p_c| over the
  cell's valid pixels, in [0, 1]: the two masks disagree about the cell; plus the same variance
  x the missing fraction of partly missing (still trained) cells. Shadows do not pass the colour
  test, so a shadow cell has rho ~ 0 and is never uncertain.
* propagation:    the SDF at a cell depends on the occupancy of the cells holding its nearest
  surface, not only on its own. For every connected component U_c of uncertain cells (missing,
  or rho > ``uncertainty_threshold``) the SDF is computed with U_c as object (f_obj) and as free
  (f_free); the cell's value is uncertain by Delta = f_obj - f_free, a Bernoulli choice with
  variance q (1 - q) Delta^2, q = 1/2 (``alternative_weight`` = 0.25); a component that is the
  only object evidence is skipped, and so are a clear body's prism cells and the table seen through it
  (their uncertainty is the prism's height, not whether the body is there: as an alternative, "free"
  would leave no object at all - on the clear bottle G it gave them sigma ~7 cm, 50 times the
  disagreement variance they are documented to carry, and the mean shape followed the table around
  them; they keep ``disagreement_variance_m2``). The term is multiplied by n_eff = min(#affected training
  cells, pi (l_e / res)^2) (``error_correlation_length_m`` l_e, an effective-sample-size
  correction) and **capped in extent**: it reaches only cells within ``propagation_radius_m`` of
  U_c (far cells' SDF is decided by certain surface nearer to them; without the cap a large
  missing region raised far cells to (90 mm)^2).

Unknown cells (``exclude_uncertain``, default on; issue 11's calibration study). The paper
builds the GPIS so that it is most uncertain where the measurements are missing or the RGB and depth
masks disagree (section III-B, Object A); it does not say how. An independent per-cell noise, however
large, does not achieve it: the GP pools ~pi (l / res)^2 neighbouring cells, so a transparent part
trained as observed table (depth sees the table through it) stayed confidently free - on the
shipped bags the true SDF lay 5-80 posterior sigmas from the mean there (Object A's dispenser arm,
D's specular wings, F's crystal body, G's bottle). So these cells are **not training points at all**
and count as **object in the SDF** of the other cells, exactly as the paper treats missing
measurements ("considered part of the object in the occupancy map but not used for the GPIS
construction"): the negative prior mean and the prior variance govern them. Unknown =

* missing cells (as before);
* extended regions where the masks disagree (rho > ``uncertainty_threshold``): 8-connected
  components of such cells holding a cell whose four neighbours disagree too
  (:func:`_extended_regions`). A band one or two cells wide is edge noise (the colour mask
  bleeding a pixel past a seen edge) and stays trained with its disagreement variance;
* cells made mostly (> ``missing_cell_fraction``) of no-return pixels the segmentation did not
  give the target (:func:`_foreign_missing_fraction`): a specular part split from the seen body
  would otherwise be dropped and its cells filled from their neighbours as observed table.
  Following the paper's assumption (missing measurements come from the object, the table is
  measured well) they are unknown, not free.

``train_mask`` = not unknown; ``uncertain`` flags missing, disagreeing and such no-return cells.
Gradient observations need both neighbours trained, so none is taken across an unknown cell. The
propagation term above uses the SDF with unknown cells as object (what the GP is trained on).
``exclude_uncertain=False`` restores the previous model (only missing cells untrained, disagreeing
cells trained and free in the SDF) for comparison. Seen edges get **no** extra noise: an independent
(1-2 cell)^2 at every edge cell raised the posterior sigma there by only ~25 % (the edge error of
a binarised EDT is correlated along the edge and the GP pools it away) while ML lengthened l and the
mean-shape IoU fell (H 0.80 -> 0.65 / 0.38, D 0.64 -> 0.41) - see README, Calibration.

Untrained cells carry at least ``disagreement_variance_m2`` so that the published map never shows
them as reliable; the GP does not use these values.

Grid (x, y) are table-frame metres (:class:`~gpis_grasp_ros.core.grid.GridGeometry`; for a
top-down camera the camera's x, y at the table depth).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.special import ndtr

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.noise_model import CARMINE, SensorModel, effective_frame_count
from gpis_grasp_ros.core.sdf import signed_distance
from gpis_grasp_ros.core.table_frame import TableFrame, fit_table_plane

TARGET_MODES = ('largest', 'nearest_center', 'pixel', 'table')
MISSING_HEIGHT_WINDOW_M = 0.02
MISSING_BRIDGE_M = 0.05  # a hole region this small joins the objects it touches (m)
MISSING_ATTACH_M = 0.01  # holes belong to an object within this distance of its seen parts (m)
OBJECT_HEIGHT_PERCENTILE = 95.0  # measured object height: this percentile of its depth-seen heights
FLAT_STEP_M = 0.004  # neighbouring cells of a flat surface differ by at most this height (m)
FLAT_JUMP_M = 0.01  # ... and something standing on/next to it differs from it by more (m)
FLAT_MIN_AREA_M2 = 0.002  # a flat support (notebook, plate, tray) covers at least this area (m^2)
SPLIT_NECK_M = 0.01  # touching objects split where both are wider than their contact by 2 x this (radius, m)
CHROMA_SMOOTH_PX = 1.5  # Gaussian sigma (px) of the colour image before its chromaticity is taken
CHROMA_DARK = 20.0  # darker pixels (mean of 0-255 RGB) have no reliable chromaticity
CHROMA_MIN_SIGMA = 0.006  # floor of the table's chromaticity spread (a noiseless table would flag every halo)
CHROMA_CLEAR_FRACTION = 0.5  # a target with fewer of its pixels seen in depth is clear: its body is grown
SEE_THROUGH_CHUNK = 1 << 19  # column samples per chunk in see_through_pixels (~40 MB of temporaries)
SHADOW_HULL_SPAN_PX = 3.0  # a column imaged this long or longer: the visual hull decides (_missing_height)
CLEAR_BODY_FRACTION = 0.25  # a target with fewer of its pixels seen in depth is a clear body (prism footprint)
PRISM_STEP_M = 0.003  # height step (m) of the visual-hull test of a clear body's prism
PRISM_RASTER_M = 0.002  # raster (m) on which a clear body's height is found
HIDDEN_SUBCELLS = 8  # points per cell side at which the hidden part of a cell is found
CHROMA_CORE_PX = 7  # a region seen through a clear body holds a disc this wide (px); an edge band does not


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

    def rays(self) -> np.ndarray:
        """(H, W, 3) camera-frame rays ((u - cx) / fx, (v - cy) / fy, 1) of every pixel."""
        u = (np.arange(self.width, dtype=np.float64) - self.cx) / self.fx
        v = (np.arange(self.height, dtype=np.float64) - self.cy) / self.fy
        uu, vv = np.meshgrid(u, v)
        return np.stack([uu, vv, np.ones_like(uu)], axis=-1)

    def project(self, points: np.ndarray) -> np.ndarray:
        """Camera-frame points (..., 3) (m) → pixel coordinates (..., 2) as (u, v)."""
        p = np.asarray(points, dtype=np.float64)
        z = p[..., 2]
        return np.stack([self.cx + self.fx * p[..., 0] / z, self.cy + self.fy * p[..., 1] / z], axis=-1)

    def pixel_index(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Camera-frame points (..., 3) (m) → the image pixel each projects onto: (u, v) int64 column and row
        (clipped into the image, so they can index an (H, W) map) and ``inside`` (in front of the camera and
        in the image)."""
        p = np.asarray(points, dtype=np.float64)
        with np.errstate(invalid='ignore', divide='ignore'):
            uv = np.round(self.project(p))
        u, v = uv[..., 0], uv[..., 1]
        inside = (p[..., 2] > 0) & np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u < self.width) & (v >= 0) \
            & (v < self.height)
        return (np.clip(np.nan_to_num(u), 0, self.width - 1).astype(np.int64),
                np.clip(np.nan_to_num(v), 0, self.height - 1).astype(np.int64), inside)


def _box(value: Sequence[float] | None, name: str) -> tuple[float, float, float, float] | None:
    if value is None:
        return None
    box = tuple(float(v) for v in value)
    if len(box) != 4 or not all(math.isfinite(v) for v in box) or box[2] <= box[0] or box[3] <= box[1]:
        raise ValueError(f'{name} must be (min_x, min_y, max_x, max_y) with max > min, got {value!r}')
    return box


@dataclass(frozen=True)
class SensingParams:
    """Settings of :func:`segment_frames` (lengths in metres, colours in 0-255 RGB units)."""

    grid_size: int = 25  # M, cells per side of the square grid
    margin: float = 0.2  # free margin on each side, fraction of the object's larger footprint side
    sensor: SensorModel = field(default_factory=lambda: CARMINE)  # depth-noise model (noise_model)
    table_plane: tuple[float, float, float, float] | None = None  # (a, b, c, d) camera frame; None = fit
    table_depth_m: float | None = None  # known fronto-parallel table depth (= table_plane (0, 0, -1, z))
    table_color: tuple[float, float, float] | None = None  # known table RGB; None = median of the plane inliers
    roi_px: tuple[float, float, float, float] | None = None  # (u_min, v_min, u_max, v_max) pixel box, inclusive
    roi_table: tuple[float, float, float, float] | None = None  # (x_min, y_min, x_max, y_max) table frame, m
    target: str = 'largest'  # 'largest', 'nearest_center', 'pixel' or 'table' (see target_point)
    target_point: tuple[float, float] | None = None  # (u, v) px for 'pixel', (x, y) m table frame for 'table'
    target_tolerance_m: float = 0.01  # a target point this close to a component selects it
    max_opening_m: float = 0.09  # refuse a target wider than this in every direction (0 = no check)
    max_tilt_deg: float = 75.0  # a fitted plane tilted more than this is edge-on: refused
    plane_band_sigmas: float = 3.0  # plane inlier band: this x sigma_z of the sensor ...
    plane_band_floor_m: float = 0.002  # ... but at least this (m)
    min_plane_fraction: float = 0.2  # the table must hold this fraction of the valid points
    border_px: int = 2  # a target reaching within this many pixels of the image edge is cut by the border
    height_threshold: float = 0.003  # depth mask: height above the table (m), at least 2 x plane RMS
    max_object_height_m: float = 0.4  # evidence higher above the table is not on the table (arms, people)
    color_threshold: float = 0.0  # colour mask: shadow-line distance from the table colour; <= 0 = adaptive
    color_threshold_min: float = 20.0  # adaptive threshold: max(this, median + color_mad_factor x MAD)
    color_mad_factor: float = 5.0
    color_sigma: float = 0.0  # width of the soft colour ramp; <= 0 = adaptive, max(2, MAD of the inliers)
    color_smooth_px: float = 0.0  # Gaussian sigma (px) of the colour image before the colour test (texture, JPEG)
    color_hole_margin_px: int = 0  # table pixels this close to a depth hole do not train the table colour
    transparent_close_m: float = 0.006  # closing radius (m) of the target's outline before its interior is filled
    transparent_core_occupied: bool = False  # colour-only pixels in the target's core count as seen-through object
    train_clear_body: bool = True  # a clear body's prism cells are trained as object (SDF variance
    #                                disagreement_variance_m2), not unknown
    see_through_test: bool = True  # a return behind the solid column under a point seen above the table saw
    #                               through a clear part: moved to where its ray enters that solid
    #                               (see_through_pixels)
    shadow_test: bool = True  # no-return pixels in the shadow of the sensor's second viewpoint (projector or
    #                          second imager, SensorModel.occluder_x_m) where the visual hull cannot tell them
    #                          from the object: table the sensor did not measure (occlusion_shadow_pixels)
    clear_body_prism: bool = True  # a clear target (mostly no depth on it): its footprint is the prism under its
    #                               silhouette, of the height at which it is as narrow as high or as deep as
    #                               wide, the lower (clear_body_height)
    clear_body_height_m: float = 0.0  # > 0: the clear body's known height (m), instead of those two priors
    chroma_z_min: float = 1.5  # > 0: grow the target over table-level pixels this many robust sigmas off the
    #                            table's chromaticity (a clear body seen through; chromatic_extension); 0 = off
    depth_floor_variance: float = 0.02  # trust of the depth mask in the inverse-variance weights
    color_floor_variance: float = 0.05  # trust of the RGB mask (higher = trusted less)
    morph_kernel_px: int = 3  # opening/closing kernel (ellipse) of the mask clean-up, 0 = off
    min_valid_returns: int = 1  # fewer valid returns than this = missing pixel
    min_object_area_px: int = 30  # smaller evidence components (pixels) are specks
    min_object_area_m2: float = 1e-4  # ... and smaller table-plane areas (m^2)
    missing_cell_fraction: float = 0.5  # a cell is missing above this fraction of missing pixels
    uncertainty_threshold: float = 0.5  # rho above which a cell's occupancy is uncertain
    unobserved_variance_m2: float = 1e-5  # SDF variance of cells not seen (outside the image, occluded)
    disagreement_variance_m2: float = 1e-4  # SDF variance (m^2) per unit disagreement rho
    alternative_weight: float = 0.25  # weight of (f_obj - f_free)^2 in the SDF noise
    error_correlation_length_m: float = 0.01  # extent over which propagated SDF errors are shared (m)
    propagation_radius_m: float = 0.03  # propagated SDF variance reaches this far from its cause (m)
    exclude_uncertain: bool = True  # uncertain cells: not trained, object in the SDF (False: trained, old model)

    def __post_init__(self) -> None:
        if self.grid_size < 3:
            raise ValueError(f'grid_size must be >= 3, got {self.grid_size}')
        if self.margin < 0:
            raise ValueError('margin must be >= 0')
        if self.border_px < 0:
            raise ValueError('border_px must be >= 0')
        if not self.height_threshold > 0:
            raise ValueError(f'height_threshold must be a positive number of metres, got {self.height_threshold}')
        if self.depth_floor_variance <= 0 or self.color_floor_variance <= 0:
            raise ValueError('mask floor variances must be positive')
        if not isinstance(self.sensor, SensorModel):
            raise ValueError(f'sensor must be a SensorModel, got {type(self.sensor).__name__}')
        if self.table_plane is not None:
            plane = tuple(float(v) for v in self.table_plane)
            if len(plane) != 4:
                raise ValueError(f'table_plane must be (a, b, c, d), got {self.table_plane!r}')
            TableFrame.from_plane(*plane)  # validates
            object.__setattr__(self, 'table_plane', plane)
        object.__setattr__(self, 'roi_px', _box(self.roi_px, 'roi_px'))
        object.__setattr__(self, 'roi_table', _box(self.roi_table, 'roi_table'))
        if self.target not in TARGET_MODES:
            raise ValueError(f"target must be one of {list(TARGET_MODES)}, got '{self.target}'")
        if self.target in ('pixel', 'table'):
            point = None if self.target_point is None else tuple(float(v) for v in self.target_point)
            if point is None or len(point) != 2 or not all(math.isfinite(v) for v in point):
                raise ValueError(f"target '{self.target}' needs target_point = two finite numbers, "
                                 f'got {self.target_point!r}')
            object.__setattr__(self, 'target_point', point)
        if not 0 < self.max_tilt_deg < 90:
            raise ValueError(f'max_tilt_deg must be in (0, 90), got {self.max_tilt_deg}')
        if self.max_opening_m < 0 or self.propagation_radius_m <= 0 or self.target_tolerance_m < 0:
            raise ValueError('max_opening_m and target_tolerance_m must be >= 0, propagation_radius_m > 0')
        if not 0.0 <= self.clear_body_height_m <= self.max_object_height_m:
            raise ValueError(f'clear_body_height_m must be in [0, max_object_height_m = {self.max_object_height_m}] '
                             f'(0 = from the priors), got {self.clear_body_height_m}')


@dataclass
class SensingResult:
    """Output of :func:`segment_frames`: grid maps (M x M) plus pixel maps (H x W) for debugging."""

    occupancy: np.ndarray  # (M, M) float in [0, 1], probability of object
    noise_variance: np.ndarray  # (M, M) m^2, observation-noise variance of each cell's SDF value
    missing: np.ndarray  # (M, M) bool, mostly no valid depth return (object in occupancy, not trained)
    geometry: GridGeometry  # in the table plane: rotation = table frame, z = plane offset d (m)
    table_depth: float  # m, the plane's distance from the camera (d; the table depth for a top-down camera)
    train_mask: np.ndarray  # (M, M) bool, cells used to train the GPIS (= not missing)
    observed: np.ndarray  # (M, M) bool, cells seen (the others - outside the image, occluded - are assumed table)
    occluded: np.ndarray  # (M, M) bool, in the image but hidden behind something above the table
    uncertain: np.ndarray  # (M, M) bool, missing or masks disagree (rho > uncertainty_threshold)
    disagreement: np.ndarray  # (M, M) float rho in [0, 1]
    table: TableFrame  # fitted (or given) table plane, camera frame
    table_color: np.ndarray  # (3,) RGB
    color_threshold: float  # colour distance threshold used (given or adaptive)
    height_threshold: float  # m, depth-evidence threshold used
    effective_frames: float  # n_eff, independent frames the average is worth
    objects_seen: int  # evidence components on the table (the target and the others)
    # pixel level
    mean_depth: np.ndarray  # (H, W) m, NaN where missing
    valid_count: np.ndarray  # (H, W) int, valid returns per pixel
    height: np.ndarray  # (H, W) m above the table along its normal, NaN where missing
    depth_mask: np.ndarray  # (H, W) bool
    rgb_mask: np.ndarray  # (H, W) bool, the colour test (seen-through pixels added to the target not included)
    missing_mask: np.ndarray  # (H, W) bool
    object_mask: np.ndarray  # (H, W) bool, the target's evidence pixels
    labels_px: np.ndarray  # (H, W) int, component of each evidence pixel (0 = none)
    occupancy_px: np.ndarray  # (H, W) float
    noise_px: np.ndarray  # (H, W) m^2, depth + disagreement terms, NaN where missing
    disagreement_px: np.ndarray  # (H, W) float rho
    bbox_px: tuple[int, int, int, int]  # (u_min, v_min, u_max, v_max) of the target, inclusive
    intrinsics: CameraIntrinsics
    object_height: float = 0.0  # m above the table, measured (:func:`object_height`); 0 = unknown
    seen_through_px: np.ndarray | None = None  # (H, W) bool, returns behind a seen object's solid, moved to where
    #                                             their rays enter it (:func:`see_through_pixels`)
    shadow_px: np.ndarray | None = None  # (H, W) bool, no-return pixels in the sensor's shadow, taken as
    #                                       unmeasured table (:func:`occlusion_shadow_pixels`)

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


# ----------------------------------------------------------------------------------------------
# table, colour and evidence

def _table_frame(points: np.ndarray, valid: np.ndarray, params: SensingParams) -> TableFrame:
    """Given or fitted table plane (module docstring, step 2)."""
    if params.table_plane is not None:
        frame = TableFrame.from_plane(*params.table_plane)
    elif params.table_depth_m is not None:
        if not (math.isfinite(params.table_depth_m) and params.table_depth_m > 0):
            raise ValueError(f'table_depth_m must be positive metres, got {params.table_depth_m}')
        frame = TableFrame.from_plane(0.0, 0.0, -1.0, float(params.table_depth_m))
    else:
        return fit_table_plane(points[valid], params.sensor, band_sigmas=params.plane_band_sigmas,
                               band_floor_m=params.plane_band_floor_m, min_inlier_fraction=params.min_plane_fraction,
                               max_tilt_deg=params.max_tilt_deg)
    if frame.tilt_deg > params.max_tilt_deg:
        raise ValueError(f'the given table plane is seen at {frame.tilt_deg:.0f} degrees (more than '
                         f'{params.max_tilt_deg:.0f}): edge-on')
    return frame


def shadow_line_distance(rgb: np.ndarray, table_rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance (0-255 units) of colours ``(..., 3)`` from the table's shadow line {alpha t, 0 <= alpha <= 1},
    and the brightness ratio alpha* = x.t / |t|^2 of each colour.

    A shadow scales the table colour t by alpha < 1 (same chromaticity) and is at distance ~0; a
    brighter colour is measured from t itself; a tint or another hue is off the line.
    """
    t = np.asarray(table_rgb, dtype=np.float64)
    ratio = (rgb @ t) / max(float(t @ t), 1e-9)
    alpha = np.clip(ratio, 0.0, 1.0)
    return np.linalg.norm(rgb - alpha[..., None] * t, axis=-1), ratio


@dataclass(frozen=True)
class ColourModel:
    """Table colour model learnt from the plane's inliers (robust statistics: median and 1.4826 MAD)."""

    table_rgb: np.ndarray  # (3,) median colour t of the training pixels (0-255)
    threshold: float  # shadow-line distance above which a colour is not the table's
    sigma: float  # width of the soft ramp of the test
    dark_ratio: float  # brightness ratio below which a colour on the shadow line is "darker than the table"

    def evidence(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """p_c (probability of "not the table") and the brightness ratio of colours ``rgb``."""
        dist, ratio = shadow_line_distance(rgb, self.table_rgb)
        return ndtr((dist - self.threshold) / self.sigma), ratio


def _colour_model(rgb: np.ndarray, train: np.ndarray, params: SensingParams) -> ColourModel:
    """Table colour model from the training pixels ``train`` of the colour image.

    t = median colour; threshold = max(``color_threshold_min``, median + ``color_mad_factor`` MAD) of
    the training pixels' shadow-line distances, ramp max(2, MAD); colours darker than the table's
    own texture (ratio below median - max(0.1, ``color_mad_factor`` MAD)) are "darker than the table".
    Robust statistics, because the plane's inliers include the table seen *through* clear objects."""
    samples = rgb[train]
    if samples.shape[0] > 50000:
        samples = samples[np.random.default_rng(0).choice(samples.shape[0], 50000, replace=False)]
    if params.table_color is not None:
        table_rgb = np.asarray(params.table_color, dtype=np.float64).reshape(3)
    else:
        table_rgb = np.median(samples, axis=0)
    dist, ratio = shadow_line_distance(samples, table_rgb)
    mad = 1.4826 * float(np.median(np.abs(dist - np.median(dist))))
    c_thr = (float(params.color_threshold) if params.color_threshold > 0
             else max(params.color_threshold_min, float(np.median(dist)) + params.color_mad_factor * mad))
    c_sigma = float(params.color_sigma) if params.color_sigma > 0 else max(2.0, mad)
    ratio_mad = 1.4826 * float(np.median(np.abs(ratio - np.median(ratio))))
    dark_ratio = float(np.median(ratio)) - max(0.1, params.color_mad_factor * ratio_mad)
    return ColourModel(table_rgb, c_thr, c_sigma, dark_ratio)


def _colour_evidence(rgb_mean: np.ndarray, inlier: np.ndarray, missing: np.ndarray,
                     params: SensingParams) -> tuple[ColourModel, np.ndarray, np.ndarray]:
    """Smoothed colour image -> table colour model and per-pixel colour evidence p_c and brightness ratio.

    The image is smoothed (Gaussian, ``color_smooth_px``: demosaicing/JPEG noise and the fine texture of
    a cloth or wood grain); the model is trained on the plane's inliers except those within
    ``color_hole_margin_px`` of a depth hole (a clear object's rim: the D435 sees the table through
    it, so its inliers near the holes carry the object's colour), unless that leaves too few."""
    img = rgb_mean.astype(np.float32)
    if params.color_smooth_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), params.color_smooth_px, borderType=cv2.BORDER_REPLICATE)
    img = img.astype(np.float64)
    train = inlier
    if params.color_hole_margin_px > 0 and missing.any():
        k = 2 * int(params.color_hole_margin_px) + 1
        near_hole = cv2.dilate(missing.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
        away = inlier & (near_hole == 0)
        if away.sum() >= max(20, inlier.sum() // 4):
            train = away
    model = _colour_model(img, train, params)
    p_c, ratio = model.evidence(img)
    return model, p_c, ratio


def _morph_clean(prob: np.ndarray, size: int) -> np.ndarray:
    """Grey-level opening then closing of a probability map (removes specks, fills pinholes)."""
    if size <= 1:
        return prob
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    img = prob.astype(np.float32)
    img = cv2.morphologyEx(img, cv2.MORPH_OPEN, kernel, borderType=cv2.BORDER_REPLICATE)
    img = cv2.morphologyEx(img, cv2.MORPH_CLOSE, kernel, borderType=cv2.BORDER_REPLICATE)
    return img.astype(np.float64)


# ----------------------------------------------------------------------------------------------
# components in the table plane and the target

@dataclass
class _Raster:
    """Table-plane raster of the evidence: cell (ix, iy) covers origin + [ix, ix+1) x [iy, iy+1) x res."""

    origin: np.ndarray  # (2,) m
    res: float
    labels: np.ndarray  # (ny, nx) int32 component labels after closing (0 = none)

    def cell(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        idx = np.floor((np.asarray(xy) - self.origin) / self.res)
        ny, nx = self.labels.shape
        ok = np.isfinite(idx).all(axis=-1) & (idx[..., 0] >= 0) & (idx[..., 0] < nx) & (idx[..., 1] >= 0) \
            & (idx[..., 1] < ny)
        idx = np.where(ok[..., None], idx, 0).astype(np.int64)
        return idx[..., 0], idx[..., 1], ok


def _missing_height(height: np.ndarray, above: np.ndarray, missing: np.ndarray, rays: np.ndarray, table: TableFrame,
                    intrinsics: CameraIntrinsics, footprint_m: float, window_m: float = MISSING_HEIGHT_WINDOW_M,
                    reach_m: float = MISSING_BRIDGE_M, samples: int = 24,
                    return_tested: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Height (m) above the table at which each pixel without a depth return is placed on its ray (0 = where
    the ray meets the table, also for every pixel with depth).

    What a no-return pixel sees (a specular part, or the table in a projector shadow) lies on its ray
    between the table and the top of the object next to it; seen by a camera tilted by theta, that ray
    segment projects orthographically onto a segment of length H tan(theta) on the table, its foot moving
    *away* from the camera as the height drops. Placing every hole where its ray meets the table would put
    the holes on an object's top up to H tan(theta) behind the object. So:

    1. **Local top H.** A hole region (8-connected in the image) touching pixels seen above the table
       (``above``) belongs next to that object: each of its pixels within ``reach_m`` (on the table) of
       the nearest seen-above pixel takes that pixel's *local top*, the highest height seen within
       ``window_m`` around it. Other holes (drop-outs on the bare table, holes away from any seen
       object) stay on the table.
    2. **Where the ray enters the object's prism.** The object is taken as a prism of height H whose
       image is the object's pixels (seen above the table, or holes): a table point x is under it when
       the vertical segment from x up to H projects onto object pixels (checked at every pixel it
       spans; a single-view visual hull). The pixel
       is placed at the highest point of its ray segment (H down to the table, ``samples`` heights)
       whose foot is under the prism - the first surface of the prism the ray meets: the top face for
       a hole in the top, the wall for a specular wall facing the camera (not in front of the object),
       and on the table (height 0) when the ray meets no such prism (a projector shadow or drop-out
       beside the object). The object's pixels are taken as they are, not dilated: with one pixel of slack
       (for the rounding of the projections) the points of a ray up to a pixel's footprint in front of a
       specular wall passed as under the prism, and so did a projector shadow next to the object's silhouette
       (seen by a tilted camera its pixels lie next to the wall's): the wall's holes were placed a footprint
       in front of the wall, the shadow's on the object. On the head bags (``test/core/bag_iou.py --holes``)
       the median placement error of the specular wall pixels fell from 2-5 mm to 0.5-2.2 mm and that of the
       projector shadows from 17-36 mm to 0-11 mm.

    Heights are along the table normal (m); ``footprint_m`` is a pixel's extent on the table (m).
    ``return_tested``: also return the pixels placed by the prism test (a tested pixel at height 0 is on
    the table beside the object: its ray meets no part of it)."""
    out = np.zeros(height.shape)
    tested = np.zeros(height.shape, dtype=bool)
    if not missing.any() or not above.any():
        return (out, tested) if return_tested else out
    k = max(3, 2 * int(round(0.5 * window_m / max(footprint_m, 1e-6))) + 1)
    h_above = np.where(above, np.nan_to_num(height), 0.0).astype(np.float32)
    top = cv2.dilate(h_above, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
    dist_px, nearest = nearest_pixel(above)
    n_reg, region = cv2.connectedComponents(missing.astype(np.uint8), connectivity=8)
    touching = np.zeros(n_reg, dtype=bool)
    touching[np.unique(region[missing & (dist_px <= 1.5)])] = True
    touching[0] = False
    vs, us = np.nonzero(missing & touching[region] & (dist_px * footprint_m <= reach_m))
    if vs.size == 0:
        return (out, tested) if return_tested else out
    near = nearest[vs, us]
    top_h = top[near[:, 0], near[:, 1]].astype(np.float64)
    ray = rays[vs, us]
    ray_n = ray @ table.n
    ok = (ray_n < -1e-9) & (top_h > 0)
    vs, us, top_h, ray, ray_n = vs[ok], us[ok], top_h[ok], ray[ok], ray_n[ok]
    tested[vs, us] = True
    if vs.size == 0:
        return (out, tested) if return_tested else out
    # the object's pixels, not dilated: a point projecting onto the pixel next to the silhouette is not on it
    obj = above | missing

    def on_object(points: np.ndarray) -> np.ndarray:
        u, v, inside = intrinsics.pixel_index(points)
        return inside & obj[v, u]

    # from the top down, the first sample whose foot has its whole vertical segment 0..H seen as object, checked
    # at every image pixel it spans (the object mask as it is, not dilated);
    # pixels are dropped from the search once placed
    lift = top_h[:, None] * table.n
    top_foot = ray * ((top_h - table.offset_m) / ray_n)[:, None] - lift
    span = np.linalg.norm(intrinsics.project(top_foot + lift) - intrinsics.project(top_foot), axis=-1)
    inner = np.linspace(0.0, 1.0, int(np.clip(np.ceil(np.nanmax(span, initial=1.0)) + 1, 2, 64)))[1:-1]
    placed = np.zeros(vs.size)
    todo = np.arange(vs.size)
    fractions = np.linspace(1.0, 0.0, samples)[:-1]  # the last sample is the table itself (height 0)
    for block in np.array_split(fractions, max(1, len(fractions) // 6)):
        h_k = top_h[todo, None] * block[None, :]  # (m, B)
        foot = ray[todo, None, :] * ((h_k - table.offset_m) / ray_n[todo, None])[..., None] - h_k[..., None] * table.n
        rows, cols = np.nonzero(on_object(foot) & on_object(foot + lift[todo, None, :]))
        for f in inner:
            if rows.size == 0:
                break
            keep = on_object(foot[rows, cols] + f * lift[todo[rows]])
            rows, cols = rows[keep], cols[keep]
        under = np.zeros(h_k.shape, dtype=bool)
        under[rows, cols] = True
        done = under.any(axis=1)
        placed[todo[done]] = h_k[done, np.argmax(under[done], axis=1)]
        todo = todo[~done]
        if todo.size == 0:
            break
    out[vs, us] = placed
    return (out, tested) if return_tested else out


def _column_samples(foot: np.ndarray, h: np.ndarray, n: np.ndarray, normal: np.ndarray,
                    include_point: bool) -> Iterator[np.ndarray]:
    """Points on the solid columns from ``foot`` (k, 3) up ``h`` (k,) m along ``normal``: ``n[i]`` evenly spaced
    samples of column i (from the foot up to the point itself with ``include_point``, else up to but not
    including it), yielded in chunks of about ``SEE_THROUGH_CHUNK`` samples (bounded memory in a cluttered
    frame) as (m, 3) arrays."""
    ends = np.cumsum(n)
    bounds = np.searchsorted(ends, np.arange(SEE_THROUGH_CHUNK, int(ends[-1]), SEE_THROUGH_CHUNK), side='right')
    for a, b in zip(np.r_[0, bounds], np.r_[bounds, foot.shape[0]], strict=True):
        if b <= a:
            continue
        column = np.repeat(np.arange(a, b), n[a:b])
        k = np.arange(column.size) + (ends[a] - n[a]) - (ends[column] - n[column])  # index within its column
        frac = k / (n[column] - 1) if include_point else k / n[column]
        yield foot[column] + (frac * h[column])[:, None] * normal


def see_through_pixels(points: np.ndarray, height: np.ndarray, solid: np.ndarray, depth: np.ndarray,
                       table: TableFrame, intrinsics: CameraIntrinsics, sensor: SensorModel,
                       slack_m: float = 0.005, max_samples: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Pixels whose return lies behind the solid under a point seen above the table, and where their rays
    enter that solid.

    Objects on a table are height fields: under a point seen at height h the column from its foot up to it
    is solid. The image of that column covers the pixels between the point's and its foot's; a pixel there
    whose return is farther from the camera (optical-axis depth) than the columns over its whole 3 x 3
    neighbourhood, by more than ``3 sqrt(2) sigma_z + slack_m``, saw *through* the object - a clear part and
    what lies behind it (the table, or a blend of both in a stereo sensor) - not its surface. Equivalently,
    along a ray's epipolar line the feet of a height field's visible points move away from the camera
    monotonically; a return whose foot lies behind the foot of a point seen farther up the image breaks
    that order. For a top-down camera a column projects onto its own pixel and nothing is flagged.

    Args:
        points: (H, W, 3) camera-frame points (m); height: (H, W) m along the table normal (NaN = none).
        solid: (H, W) bool, pixels seen above the table whose columns are solid.
        depth: (H, W) m optical-axis depth of each return (NaN = none).
        slack_m: tolerance (m) on top of the noise of the two depths compared.
        max_samples: at most this many samples per column (one per pixel of its image).

    Returns:
        ``(flagged, entry_depth)``: (H, W) bool, and (H, W) m, the depth at which each pixel's ray meets the
        nearest column (inf where it meets none) - the farthest its first surface can be."""
    entry = np.full(height.shape, np.inf)
    if not solid.any():
        return np.zeros(height.shape, dtype=bool), entry
    top = points[solid]
    h = np.nan_to_num(height[solid])
    foot = top - h[:, None] * table.n
    span = np.linalg.norm(intrinsics.project(top) - intrinsics.project(foot), axis=-1)
    n = np.clip(np.ceil(np.nan_to_num(span)).astype(np.int64) + 1, 1, max_samples)  # samples per column
    for samples in _column_samples(foot, h, n, table.n, include_point=False):  # the point itself excluded
        u, v, inside = intrinsics.pixel_index(samples)
        np.minimum.at(entry, (v[inside], u[inside]), samples[inside, 2])
    # behind the columns of the whole 3 x 3 neighbourhood: a column rounded onto the pixel beside the
    # object's silhouette does not cover it
    behind_all = cv2.dilate(entry.astype(np.float32), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT,
                            borderValue=np.inf).astype(np.float64)
    with np.errstate(invalid='ignore'):
        tol = 3.0 * math.sqrt(2.0) * sensor.sigma(np.nan_to_num(depth, nan=0.0)) + slack_m
        flagged = np.isfinite(depth) & np.isfinite(behind_all) & (depth - behind_all > tol)
    return flagged, entry


def column_zbuffer(top: np.ndarray, h: np.ndarray, table: TableFrame, intrinsics: CameraIntrinsics,
                   origin: np.ndarray, bounds: tuple[int, int, int, int], max_samples: int = 64) -> np.ndarray:
    """Depth buffer of the solid columns standing under the points ``top`` (n, 3) (camera frame, m; heights
    ``h`` (n,) m along the table normal), seen by a pinhole camera with this image's focal lengths, principal
    point and orientation but centred at ``origin`` (camera frame, m), over its pixels ``bounds`` = (u0, v0, u1,
    v1) (inclusive; they may lie beyond this image's bounds: a viewpoint 5-8 cm aside).

    Returns ``zbuf`` (v1 - v0 + 1, u1 - u0 + 1): ``zbuf[v - v0, u - u0]`` is the nearest depth (m, along the
    optical axis) at which the ray of that camera's pixel (u, v) meets a column, inf where it meets none. Each
    column is sampled at about one sample per pixel of its image (at most ``max_samples``), foot to point."""
    u0, v0, u1, v1 = (int(b) for b in bounds)
    zbuf = np.full((max(v1 - v0 + 1, 1), max(u1 - u0 + 1, 1)), np.inf)
    origin = np.asarray(origin, dtype=np.float64)
    foot = np.asarray(top, dtype=np.float64) - h[:, None] * table.n - origin
    top = np.asarray(top, dtype=np.float64) - origin
    with np.errstate(invalid='ignore', divide='ignore'):
        uv_top, uv_foot = intrinsics.project(top), intrinsics.project(foot)
    ok = (np.isfinite(uv_top).all(axis=-1) & np.isfinite(uv_foot).all(axis=-1) & (foot[:, 2] > 0)
          & (top[:, 2] > 0))
    top, foot, h, uv_top, uv_foot = top[ok], foot[ok], h[ok], uv_top[ok], uv_foot[ok]
    if top.shape[0] == 0:
        return zbuf
    lo = np.array([u0, v0])
    n = np.clip(np.ceil(np.linalg.norm(uv_top - uv_foot, axis=-1)).astype(np.int64) + 1, 2, max_samples)
    for samples in _column_samples(foot, h, n, table.n, include_point=True):
        uv = np.round(intrinsics.project(samples)).astype(np.int64) - lo
        keep = (uv[:, 0] >= 0) & (uv[:, 0] < zbuf.shape[1]) & (uv[:, 1] >= 0) & (uv[:, 1] < zbuf.shape[0])
        np.minimum.at(zbuf, (uv[keep, 1], uv[keep, 0]), samples[keep, 2])
    return zbuf


def occlusion_shadow_pixels(points: np.ndarray, height: np.ndarray, solid: np.ndarray, candidates: np.ndarray,
                            table: TableFrame, intrinsics: CameraIntrinsics, sensor: SensorModel,
                            footprint_m: float, slack_m: float = 0.005,
                            min_hull_span_px: float | None = SHADOW_HULL_SPAN_PX) -> np.ndarray:
    """No-return pixels that look at table the sensor's second viewpoint cannot see: its shadow.

    A structured-light sensor needs its projector to light a point, an active-stereo sensor its second imager
    to see it (:class:`~gpis_grasp_ros.core.noise_model.SensorModel`, ``occluder_x_m``: that viewpoint at
    (x, 0, 0) in the camera frame). Objects on a table are height fields, so under every point seen above the
    table the column down to its foot is solid. A candidate pixel (``candidates``: no return) is in the shadow
    when the table point on its ray

    * is hidden from the second viewpoint by those columns, by more than ``3 sqrt(2) sigma_z + slack_m``
      along that viewpoint's ray (a depth buffer of the columns seen from there, :func:`column_zbuffer`,
      eroded by one pixel so that the gaps between neighbouring columns do not let it through), and
    * does not lie under the object: outside the footprint of the columns (their feet rasterised at
      ``footprint_m``, closed by one cell and hole-filled) - the table point behind a hole in an object's
      top or a specular wall lies under the object, not beside it.

    With ``min_hull_span_px`` (default :data:`SHADOW_HULL_SPAN_PX`) only pixels where the visual hull cannot
    decide are taken: the column from the table point up to the local top of the nearest seen object (its
    highest height within ``MISSING_HEIGHT_WINDOW_M``) images shorter than that many pixels. Seen by a tilted
    camera that column images as a long segment and :func:`_missing_height` already tells a hole beside an
    object (its ray meets no part of the object's prism) from one on it; seen from straight above it images
    onto one or two pixels, a shadow band next to an object passes the prism test on its own pixels, and the
    object was grown by the band (a 3 cm box under a top-down Carmine: 18 % too much area).

    Returns (H, W) bool. Nothing when the sensor has no second viewpoint (``occluder_x_m`` = 0) or nothing is
    seen above the table."""
    out = np.zeros(candidates.shape, dtype=bool)
    off = float(sensor.occluder_x_m)
    if off == 0.0 or not candidates.any() or not solid.any():
        return out
    origin = np.array([off, 0.0, 0.0])
    hts = np.nan_to_num(height[solid])
    hit_pts, hit = table.ray_intersection(intrinsics.rays())
    cand = candidates & hit
    if not cand.any():
        return out
    vs, us = np.nonzero(cand)
    p = hit_pts[vs, us]
    if min_hull_span_px is not None:
        h_img = np.where(solid, np.nan_to_num(height), 0.0).astype(np.float32)
        k = max(3, 2 * int(round(0.5 * MISSING_HEIGHT_WINDOW_M / max(footprint_m, 1e-6))) + 1)
        local_top = cv2.dilate(h_img, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
        _, nearest = nearest_pixel(solid)
        top_h = local_top[nearest[vs, us, 0], nearest[vs, us, 1]].astype(np.float64)
        span = np.linalg.norm(intrinsics.project(p + top_h[:, None] * table.n) - intrinsics.project(p), axis=-1)
        keep = span < float(min_hull_span_px)
        vs, us, p = vs[keep], us[keep], p[keep]
        if vs.size == 0:
            return out
    # the second viewpoint's depth buffer of the columns, over the pixels where the candidates' table points fall
    q = p - origin
    uv_q = np.round(intrinsics.project(q)).astype(np.int64)
    u0, v0 = uv_q.min(axis=0) - 2
    u1, v1 = uv_q.max(axis=0) + 2
    zbuf = column_zbuffer(points[solid], hts, table, intrinsics, origin, (u0, v0, u1, v1))
    big = np.float32(1e9)
    zbuf = cv2.erode(np.where(np.isfinite(zbuf), zbuf, big).astype(np.float32), np.ones((3, 3), np.uint8),
                     borderType=cv2.BORDER_CONSTANT, borderValue=float(big)).astype(np.float64)
    uv = uv_q - np.array([u0, v0])
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < zbuf.shape[1]) & (uv[:, 1] >= 0) & (uv[:, 1] < zbuf.shape[0])
    u, v = np.clip(uv[:, 0], 0, zbuf.shape[1] - 1), np.clip(uv[:, 1], 0, zbuf.shape[0] - 1)
    tol = 3.0 * math.sqrt(2.0) * sensor.sigma(q[:, 2]) + slack_m
    hidden = inside & (zbuf[v, u] < q[:, 2] - tol)
    # the footprint of the columns in the table plane (hole-filled): a table point under the object is not beside it
    feet, _ = table.to_table(points[solid] - hts[:, None] * table.n)
    res = max(float(footprint_m), 1e-4)
    lo = feet.min(axis=0) - 3.0 * res
    idx = np.floor((feet - lo) / res).astype(np.int64)
    grid = np.zeros((int(idx[:, 1].max()) + 4, int(idx[:, 0].max()) + 4), np.uint8)
    grid[idx[:, 1], idx[:, 0]] = 1
    grid = _filled(cv2.morphologyEx(grid, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)) > 0)
    j = np.floor((table.to_table(p)[0] - lo) / res).astype(np.int64)
    on = (j[:, 0] >= 0) & (j[:, 0] < grid.shape[1]) & (j[:, 1] >= 0) & (j[:, 1] < grid.shape[0])
    under = np.zeros(j.shape[0], dtype=bool)
    under[on] = grid[j[on, 1], j[on, 0]]
    out[vs, us] = hidden & ~under
    return out


def object_height(height: np.ndarray, seen: np.ndarray, percentile: float = OBJECT_HEIGHT_PERCENTILE,
                  min_pixels: int = 10) -> float:
    """Height (m) of an object above the table: the ``percentile`` of the heights (m, along the table normal)
    of its pixels ``seen`` in depth above the table; 0 (unknown) with fewer than ``min_pixels`` of them.

    A high percentile rather than the maximum: the top face (or the crest of a lying cylinder) is the
    highest part seen, and 5 % of the pixels may be depth outliers (flying pixels at edges). Parts
    without a depth return (specular, or transparent ones the sensor sees through: their depth is the
    table's) are not measured, so an object seen only through holes and colour has an unknown height,
    and one whose top is entirely specular is measured by its highest seen part (its walls)."""
    h = np.asarray(height, dtype=np.float64)[np.asarray(seen, dtype=bool)]
    h = h[np.isfinite(h)]
    if h.size < max(1, min_pixels):
        return 0.0
    return max(0.0, float(np.percentile(h, percentile)))


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
    mask cells at or above the level, so each cell joins the blob it is deepest in."""
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
    return out.astype(np.int32)


def _filled(mask: np.ndarray) -> np.ndarray:
    """``mask`` (H x W) with every hole of its 8-connected regions filled (bool)."""
    out = np.zeros(mask.shape, np.uint8)
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, 1, thickness=cv2.FILLED)
    return out > 0


def split_touching(labels: np.ndarray, neck_cells: float) -> tuple[np.ndarray, np.ndarray]:
    """Split touching objects in a labelled raster at the necks of their union (distance-transform watershed).

    Two objects in contact form one evidence component shaped like two blobs joined by a neck (their
    contact). The components' holes are filled first (a clear object is seen as an outline around a
    see-through interior). The distance transform (DT, cells to the nearest non-evidence cell) of the
    filled components has a maximum in each blob; the markers are the maxima whose *dynamic* (peak DT
    minus the DT of the saddle joining them to a higher peak) is at least ``neck_cells``: the h-maxima
    of the DT, i.e. both blobs are wider than the neck by at least 2 ``neck_cells`` in diameter. A
    component with two or more markers is divided by a watershed of -DT from them (cells go to the
    blob they are deepest in); an elongated object with a narrow part (a bottle's neck, a marker's
    tip) has no maximum in the narrow part and stays whole.

    Returns the new labels (split parts get fresh labels after the existing ones) and, per new label,
    the label it came from (so that the parts are not joined again by later merging steps)."""
    n = int(labels.max()) + 1
    origin = np.arange(n)
    if n <= 1 or neck_cells <= 0:
        return labels, origin
    filled = _filled(labels > 0).astype(np.uint8)
    n_f, lab_f = cv2.connectedComponents(filled, connectivity=8)
    dist = cv2.distanceTransform(np.pad(filled, 1), cv2.DIST_L2, 5)[1:-1, 1:-1]
    hmax = _reconstruct(np.maximum(dist - neck_cells, 0.0), dist)
    eps = 1e-3
    maxima = (hmax - _reconstruct(np.maximum(hmax - eps, 0.0), hmax) > eps / 2) & (filled > 0)
    n_mark, markers = cv2.connectedComponents(maxima.astype(np.uint8), connectivity=8)
    if n_mark <= 2:
        return labels, origin
    owner = np.zeros(n_mark, np.int64)
    owner[markers[maxima]] = lab_f[maxima]
    per_comp = np.bincount(owner[1:], minlength=n_f)
    out = labels.astype(np.int32).copy()
    origin = list(origin)
    for comp_id in np.nonzero(per_comp >= 2)[0]:
        if comp_id == 0:
            continue
        comp = lab_f == comp_id
        flooded = _flood(np.where(comp & (markers > 0), markers, 0), dist, comp)
        cells = comp & (labels > 0)
        pairs = np.unique(np.stack([labels[cells], flooded[cells]], axis=1), axis=0)
        seen: set[int] = set()
        for lab, part in pairs:
            if int(lab) not in seen:  # the first part of each original label keeps the label
                seen.add(int(lab))
                continue
            out[cells & (labels == lab) & (flooded == part)] = len(origin)
            origin.append(int(lab))
    return out, np.asarray(origin)


def split_flat_support(labels: np.ndarray, cell_height: np.ndarray, res: float,
                       origin: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Split an object standing on or next to a flat one (a notebook, a plate, a tray) from it.

    ``cell_height`` (m, NaN = no depth-seen evidence in the cell) is the mean height of each raster
    cell's depth-seen pixels. Within a component, cells whose heights differ by at most
    ``FLAT_STEP_M`` from a 4-neighbour form *smooth* regions (the flat top of a notebook varies by
    ~1 mm from cell to cell; the feet of a box's walls and the rims of a clear object jump by
    centimetres). If the largest smooth region covers at least ``FLAT_MIN_AREA_M2`` and the rest of
    the component holds at least ``FLAT_MIN_AREA_M2`` / 4 of depth-seen cells more than ``FLAT_JUMP_M``
    *above* it (something taller standing on or next to it), the component is split:
    the flat region is one object, the rest is assigned to the flat region or to the other parts by a
    watershed of -DT (cells go to the part they are deepest in), each other part keeping its own label.
    A box's flat top is not a support: the feet of its walls lie *below* it. Limitation: one object
    made of a large flat base and a taller part (a tray with a handle) is split too.

    Returns the labels and the origin of every label (see :func:`split_touching`)."""
    n = int(labels.max()) + 1
    origin = np.arange(n) if origin is None else np.asarray(origin)
    out = labels.astype(np.int32).copy()
    origin = list(origin)
    seen = np.isfinite(cell_height) & (labels > 0)
    min_cells = FLAT_MIN_AREA_M2 / res ** 2
    h = np.nan_to_num(cell_height)
    # 4-neighbour smoothness edges between depth-seen cells of the same component
    ny, nx = labels.shape
    idx = np.arange(ny * nx).reshape(ny, nx)
    rows, cols = [], []
    for a, b in ((np.s_[:, :-1], np.s_[:, 1:]), (np.s_[:-1, :], np.s_[1:, :])):
        ok = seen[a] & seen[b] & (labels[a] == labels[b]) & (np.abs(h[a] - h[b]) <= FLAT_STEP_M)
        rows.append(idx[a][ok])
        cols.append(idx[b][ok])
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(r.size), (r, c)), shape=(ny * nx, ny * nx))
    _, smooth = connected_components(graph, directed=False)
    smooth = np.where(seen.ravel(), smooth + 1, 0).reshape(ny, nx)
    sizes = np.bincount(smooth.ravel())
    sizes[0] = 0
    big = np.nonzero(sizes >= min_cells)[0]  # smooth regions large enough to be a support, and their labels
    region_label = np.zeros(sizes.size, np.int64)
    region_label[smooth[seen]] = labels[seen]
    if big.size == 0:
        return out, np.asarray(origin)
    dist = cv2.distanceTransform(np.pad((labels > 0).astype(np.uint8), 1), cv2.DIST_L2, 5)[1:-1, 1:-1]
    for lab in np.unique(region_label[big]):
        comp = labels == lab
        regions = np.unique(smooth[comp & seen])
        if regions.size == 0:
            continue
        flat = int(regions[np.argmax(sizes[regions])])
        if sizes[flat] < min_cells:
            continue
        flat_cells = smooth == flat
        h_flat = float(np.median(h[flat_cells]))
        other = comp & seen & ~flat_cells & (h > h_flat + FLAT_JUMP_M)
        if other.sum() < min_cells / 4:
            continue
        n_o, lab_o = cv2.connectedComponents(other.astype(np.uint8), connectivity=8)
        markers = np.where(flat_cells, 1, np.where(lab_o > 0, lab_o + 1, 0)).astype(np.int32)
        flooded = _flood(markers, dist, comp)
        for part in range(2, n_o + 1):
            sel = comp & (flooded == part)
            if sel.any():
                out[sel] = len(origin)
                origin.append(int(origin[lab]) if lab < len(origin) else lab)
    return out, np.asarray(origin)


def _merge_across_small_holes(labels: np.ndarray, lab_miss: np.ndarray, n_miss: int, n_pos: int,
                              touching: np.ndarray, res: float, origin: np.ndarray | None = None) -> np.ndarray:
    """Objects touching the same small hole region (extent <= ``MISSING_BRIDGE_M``) are one object
    (e.g. a specular band across a marker); large hole regions (drop-outs along the table) join nothing.
    Parts of one component split at a neck (same ``origin``, :func:`split_touching`) are not joined again."""
    parent = np.arange(labels.max() + 1)
    source = np.arange(parent.size)
    if origin is not None:
        source[:min(origin.size, source.size)] = origin[:source.size]

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    grown = cv2.dilate((labels > 0).astype(np.uint8), np.ones((3, 3), np.uint8))
    for c in np.nonzero(touching)[0]:
        if c == 0:
            continue
        rows, cols = np.nonzero(lab_miss == c)
        if math.hypot(np.ptp(rows), np.ptp(cols)) * res > MISSING_BRIDGE_M:
            continue
        ring = cv2.dilate((lab_miss == c).astype(np.uint8), np.ones((3, 3), np.uint8)) & grown
        near = np.unique(labels[(ring > 0) & (labels > 0) & (labels <= n_pos)])
        for other in near[1:]:
            if source[int(other)] != source[int(near[0])]:
                parent[find(int(other))] = find(int(near[0]))
    roots = np.array([find(i) for i in range(parent.size)])
    return roots[labels].astype(np.int32)


def _table_components(foot_xy: np.ndarray, evidence: np.ndarray, missing: np.ndarray, inlier_xy: np.ndarray,
                      footprint_m: float, attach_m: float,
                      height: np.ndarray | None = None) -> tuple[_Raster, np.ndarray]:
    """Rasterise the evidence pixels' feet over the table's extent and label connected components.

    Components are built from the positive evidence (depth or colour). Holes (missing pixels) are
    grouped separately: a hole region touching an object joins it only within ``attach_m`` of its
    positive evidence (a hole is object where it is part of a seen object, e.g. a specular patch, not
    a path along the table's drop-outs to the next object), entirely if it touches only that object
    and is at most 2 ``MISSING_BRIDGE_M`` across; a small hole region (``MISSING_BRIDGE_M``) touching
    several objects joins them; a hole region touching no object is an object of its own (entirely
    specular / transparent).

    Returns the raster and the per-pixel labels (0 = not evidence or off the table)."""
    lo, hi = inlier_xy.min(axis=0), inlier_xy.max(axis=0)
    res = max(5e-4, 2.0 * footprint_m)
    while np.prod((hi - lo) / res) > 4e6:
        res *= 1.5
    nx, ny = (int(v) + 1 for v in np.ceil((hi - lo) / res))
    raster = _Raster(lo, res, np.zeros((ny, nx), np.int32))
    # the table's extent: convex hull of its inliers (in raster cell units)
    hull = cv2.convexHull(((inlier_xy - lo) / res).astype(np.float32))
    extent = np.zeros((ny, nx), np.uint8)
    cv2.fillConvexPoly(extent, np.round(hull).astype(np.int32), 1)
    extent = cv2.erode(extent, np.ones((5, 5), np.uint8))  # the rounded hull's rim (2 cells) is not surely table
    ix, iy, ok = raster.cell(foot_xy)
    use = evidence & ok & (extent[iy, ix] > 0)
    close = np.ones((3, 3), np.uint8)

    def mark(sel: np.ndarray) -> np.ndarray:
        m = np.zeros((ny, nx), np.uint8)
        m[iy[sel], ix[sel]] = 1
        return cv2.morphologyEx(m, cv2.MORPH_CLOSE, close)

    n_pos, lab_pos = cv2.connectedComponents(mark(use & ~missing), connectivity=8)
    lab_pos, origin = split_touching(lab_pos, SPLIT_NECK_M / res)  # objects in contact (module docstring)
    if height is not None:  # an object standing on / next to a flat one (notebook, plate)
        seen = use & ~missing & np.isfinite(height)
        h_sum = np.bincount(iy[seen] * nx + ix[seen], weights=height[seen], minlength=nx * ny)
        h_cnt = np.bincount(iy[seen] * nx + ix[seen], minlength=nx * ny)
        with np.errstate(invalid='ignore', divide='ignore'):
            cell_h = np.where(h_cnt > 0, h_sum / np.maximum(h_cnt, 1), np.nan).reshape(ny, nx)
        lab_pos, origin = split_flat_support(lab_pos, cell_h, res, origin)
    n_pos = int(lab_pos.max()) + 1
    n_miss, lab_miss = cv2.connectedComponents(mark(use & missing) & (lab_pos == 0).astype(np.uint8), connectivity=8)
    labels = lab_pos.astype(np.int32)
    if n_miss > 1:
        if n_pos > 1:
            nearest, dist = _nearest_label(lab_pos)
            touching = np.zeros(n_miss, dtype=bool)
            touching[np.unique(lab_miss[(dist <= 1.5) & (lab_miss > 0)])] = True
        else:
            nearest, dist, touching = np.zeros_like(labels), np.full(labels.shape, np.inf), np.zeros(n_miss, bool)
        attach = (lab_miss > 0) & touching[lab_miss] & (dist * res <= attach_m)
        labels[attach] = nearest[attach]
        for c in np.nonzero(touching)[0]:  # a hole region of one object only (a specular lever): all of it
            cells = lab_miss == c
            rows, cols = np.nonzero(cells)
            owners = np.unique(nearest[cells & (dist <= 1.5)])
            if owners.size == 1 and math.hypot(np.ptp(rows), np.ptp(cols)) * res <= 2 * MISSING_BRIDGE_M:
                labels[cells] = owners[0]
        alone = (lab_miss > 0) & ~touching[lab_miss]
        labels[alone] = n_pos + lab_miss[alone]
        labels = _merge_across_small_holes(labels, lab_miss, n_miss, n_pos, touching, res, origin)
    raster.labels = labels
    px_labels = np.where(use, raster.labels[iy, ix], 0)
    return raster, px_labels


def seen_through(raster: _Raster, target: int, foot_xy: np.ndarray, px_labels: np.ndarray, colour_only: np.ndarray,
                 table_level: np.ndarray, close_m: float) -> np.ndarray:
    """Pixels that see the table *through* the target: its enclosed interior (a transparent object's outline).

    A clear object lying on the table is seen as an outline - specular edges, depth holes at its ends,
    colour along its rims - around an interior where the sensor returns the table behind it (the paper's
    "invalid measurements", section VI). In the table raster the target's component is dilated with a
    disc of radius ``close_m`` (gaps in the outline up to ~2 ``close_m`` close), its holes are filled and it
    is eroded back with the same disc. The
    pixels returned are table-level pixels (``table_level``: valid depth, no depth evidence) not given to
    another object, whose foot lies (a) in a cell of the filled interior that is not in the component, or
    (b) in the component's core (its filled shape eroded by the closing disc: not the outline) with colour
    evidence only (``colour_only``; ``SensingParams.transparent_core_occupied``, off by default: the paper's
    Object A keeps a transparent part seen in colour only out of the mean shape). The caller makes them
    object in the occupancy map with colour/hole evidence only (p_c = 1 against the table-level depth: the
    masks disagree, the cells are uncertain), never observed-depth table. An opaque object's interior is
    seen in depth (no such pixels); a thin colour-only part (a transparent arm) has no core."""
    comp = (raster.labels == target).astype(np.uint8)
    r = max(1, int(round(close_m / raster.res)))
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    grown = cv2.dilate(np.pad(comp, r + 1), disc)  # gaps in a thin outline up to 2 r close
    filled = np.zeros_like(grown)
    contours, _ = cv2.findContours(grown, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(filled, contours, -1, 1, thickness=cv2.FILLED)
    filled = cv2.erode(filled, disc)[r + 1:-r - 1, r + 1:-r - 1] | comp  # back to the outline's extent
    interior = (filled > 0) & (comp == 0)
    core = cv2.erode(filled, disc) > 0
    ix, iy, ok = raster.cell(foot_xy)
    free = (px_labels == 0) | (px_labels == target)
    return ok & free & table_level & (interior[iy, ix] | (core[iy, ix] & colour_only))


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
    total = img.sum(axis=-1)
    chroma = img / np.maximum(total, 1e-3)[..., None]
    samples = chroma[train]
    if samples.shape[0] < 20:
        return np.zeros(total.shape), 0.0, 1.0
    dist = np.linalg.norm(chroma - np.median(samples, axis=0), axis=-1)
    med = float(np.median(dist[train]))
    scale = max(CHROMA_MIN_SIGMA, 1.4826 * float(np.median(np.abs(dist[train] - med))))
    # the chromaticity of a darker pixel is noisier (shot noise over less light): its spread is the table's
    # times sqrt(table brightness / pixel brightness), so a shadow is not flagged by its noise
    spread = scale * np.sqrt(np.maximum(1.0, float(np.median(total[train])) / np.maximum(total, 1e-3)))
    z = np.where(total / 3.0 >= dark, (dist - med) / spread, 0.0)
    return z.astype(np.float64), med, scale


def chromatic_extension(target_px: np.ndarray, candidate: np.ndarray, chroma_z: np.ndarray, z_min: float,
                        core_px: int = CHROMA_CORE_PX) -> np.ndarray:
    """Pixels of a clear target seen only as a change of the table's chromaticity, grown from the target.

    A transparent object lying on the table returns the table's depth through its body, and its colour
    test (:func:`shadow_line_distance`) passes only where it is specular; the body is seen as the table's
    colour desaturated by the plastic. ``chroma_z`` (:func:`chromaticity_distance`) > ``z_min`` marks such
    pixels among the ``candidate`` pixels (table-level, not another object's evidence), opened with a 3 x 3
    disc (isolated texture specks go); the result is the 8-connected regions of them that touch the
    target's pixels ``target_px`` and hold a disc of ``core_px`` pixels (a band of mixed pixels along an
    opaque object's seen edge does not). The region is grown in the image from the target, so chromatic
    pixels elsewhere (texture, other clear objects) never become evidence; other objects' evidence pixels
    are not candidates, so the growth stops at them. Limits: a clear object standing on a table of its
    own tint is not seen this way, and the region leaks along chromatic table pixels that touch the body
    (the base of another clear object seen through, behind it) - the threshold bounds how far."""
    grow = ((chroma_z > z_min) & candidate & ~target_px).astype(np.uint8)
    grow = cv2.morphologyEx(grow, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))) > 0
    if not grow.any():
        return np.zeros_like(grow)
    n, lab = cv2.connectedComponents(grow.astype(np.uint8), connectivity=8)
    touching = cv2.dilate(target_px.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    # a band along the target's seen edge (mixed pixels, a shading rim) has no core: only regions holding a
    # disc of ``core_px`` pixels are a body seen through
    core = cv2.erode(grow.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (core_px, core_px)),
                     borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
    keep = np.zeros(n, dtype=bool)
    keep[np.unique(lab[touching & grow])] = True
    has_core = np.zeros(n, dtype=bool)
    has_core[np.unique(lab[core])] = True
    keep &= has_core
    keep[0] = False
    # gaps enclosed by the body and the target (a label, a highlight) are body too
    return _filled(keep[lab] | target_px) & candidate & ~target_px


def _bounded_extension(target_px: np.ndarray, extension: np.ndarray, params: SensingParams) -> np.ndarray:
    """The chromatic extension, or nothing when it reaches the image (or pixel ROI) border: a region that
    runs out of the image is not the enclosed body of the target (the table's own colour changing)."""
    if not extension.any():
        return extension
    h, w = extension.shape
    b = params.border_px
    u_lo, v_lo, u_hi, v_hi = (0, 0, w - 1, h - 1) if params.roi_px is None else \
        (max(0, params.roi_px[0]), max(0, params.roi_px[1]), min(w - 1, params.roi_px[2]), min(h - 1, params.roi_px[3]))
    vs, us = np.nonzero(extension)
    if us.min() < u_lo + b or vs.min() < v_lo + b or us.max() > u_hi - b or vs.max() > v_hi - b:
        return np.zeros_like(extension)
    return extension


def minimum_width(xy: np.ndarray) -> float:
    """Smallest extent (m) of points ``(K, 2)`` over all directions (exact: the hull's edge directions)."""
    pts = np.asarray(xy, dtype=np.float64)
    if pts.shape[0] < 3:
        return 0.0
    hull = cv2.convexHull(pts.astype(np.float32)).reshape(-1, 2).astype(np.float64)
    if hull.shape[0] < 3:
        return 0.0
    edges = np.roll(hull, -1, axis=0) - hull
    length = np.linalg.norm(edges, axis=1)
    edges, starts = edges[length > 0], hull[length > 0]
    normals = np.stack([-edges[:, 1], edges[:, 0]], axis=1) / np.linalg.norm(edges, axis=1)[:, None]
    extent = np.abs((hull[None, :, :] - starts[:, None, :]) @ normals[..., None])[..., 0].max(axis=1)
    return float(extent.min())


def prism_footprint(cells_xy: np.ndarray, silhouette: np.ndarray, table: TableFrame, intrinsics: CameraIntrinsics,
                    height_m: float, step_m: float = PRISM_STEP_M) -> np.ndarray:
    """Table points (``cells_xy`` (..., 2), table frame, m) under a prism of height ``height_m`` whose image is
    ``silhouette`` (H x W bool): the single-view visual hull of a prism standing on the table.

    A point x is under it when the vertical segment from x up to ``height_m`` projects onto silhouette pixels
    at every ``step_m`` of height (the silhouette dilated by one pixel for the rounding). Seen by a camera
    tilted by theta, the silhouette's table points are the footprint swept H tan(theta) away from the camera;
    this undoes the sweep. ``height_m`` = 0 gives the silhouette's own table points."""
    sil = cv2.dilate(np.asarray(silhouette, dtype=np.uint8), np.ones((3, 3), np.uint8)) > 0
    base = table.to_camera(np.asarray(cells_xy, dtype=np.float64))  # camera frame, on the table
    under = np.ones(base.shape[:-1], dtype=bool)
    for h in np.linspace(0.0, max(height_m, 0.0), max(2, int(math.ceil(height_m / step_m)) + 1)):
        u, v, inside = intrinsics.pixel_index(base + h * table.n)  # h above the table, towards the camera
        under &= inside & sil[v, u]
    return under


def clear_body_height(silhouette: np.ndarray, table: TableFrame, intrinsics: CameraIntrinsics,
                      res_m: float = PRISM_RASTER_M, iterations: int = 12,
                      known_height_m: float = 0.0) -> tuple[float, np.ndarray]:
    """Height (m) of a clear body seen only as a silhouette (no depth on it), and the footprint under it.

    Without depth, a single view fixes the footprint only given H (the silhouette's table points are the
    footprint swept H tan(theta) away from the camera; :func:`prism_footprint` undoes the sweep). Two priors
    each fix H:

    * **lying** - a bottle on its side, a box on its face - is about as high as its footprint's smallest
      width: the prism height at which the footprint is as narrow as it is high;
    * **round** - an upright can, a knob, a glass - has a footprint as deep (along the camera's view, in the
      table plane) as it is wide (across it): the height at which the footprint's two extents are equal. A
      silhouette whose table points are already shallower than wide (a body lying across the view) has no
      such height.

    The lower of the two is taken: the one that leaves more of the footprint (a lower H sweeps less away).
    A squat round body (a 7 cm knob, 3.5 cm high) gets the round H, a lying bar the lying one whatever its
    direction (lying along the view its round H is far too high), and a body higher than wide (an upright
    bottle) the lying H, too small - its footprint then reaches too far away from the camera: more object,
    never a missing part. Both heights are found by bisection on a ``res_m`` raster. Returns H and the
    footprint's raster cell centres (K, 2) in the table frame (m); (0, the silhouette's table points) when
    it has fewer than 3 of them. ``known_height_m`` > 0 (the body's height known, e.g. from a catalogue of the
    objects): no prior, the footprint under a prism of that height.

    The priors assume vertical walls. A round body lying on the table (a bottle) leaves the silhouette of a
    box lower by a factor cos a + sin a (a: the rays' angle from the vertical across its axis; 1.4 at 45-52
    deg), so the lying prior puts it that much too low and its footprint H tan(a) / 2 too far from the
    camera. One view of a clear body does not tell the two apart."""
    hit, ok = table.ray_intersection(intrinsics.rays()[np.asarray(silhouette, dtype=bool)])
    if ok.sum() < 3:
        return 0.0, table.to_table(hit[ok])[0]
    xy = table.to_table(hit[ok])[0]
    lo, hi = xy.min(axis=0) - res_m, xy.max(axis=0) + res_m
    nx, ny = (int(math.ceil(c)) for c in (hi - lo) / res_m)
    gx, gy = np.meshgrid(lo[0] + (np.arange(nx) + 0.5) * res_m, lo[1] + (np.arange(ny) + 0.5) * res_m)
    cells = np.stack([gx, gy], axis=-1)
    view = xy.mean(axis=0) - table.to_table(np.zeros((1, 3)))[0][0]  # camera's foot -> body, in the table plane
    view = view / max(float(np.linalg.norm(view)), 1e-12)
    across = np.array([-view[1], view[0]])

    def footprint(h: float) -> np.ndarray:
        return cells[prism_footprint(cells, silhouette, table, intrinsics, h)]

    def narrow_minus_height(h: float) -> float:
        under = footprint(h)
        return (minimum_width(under) if under.shape[0] >= 3 else 0.0) - h

    def deep_minus_wide(h: float) -> float:
        under = footprint(h)
        return float(np.ptp(under @ view) - np.ptp(under @ across)) if under.shape[0] >= 3 else -1.0

    def bisect(f, high: float) -> float:  # the largest h in [0, high] with f(h) >= 0 (f decreasing)
        low = 0.0
        for _ in range(iterations):
            mid = 0.5 * (low + high)
            low, high = (mid, high) if f(mid) >= 0.0 else (low, mid)
        return low

    if known_height_m > 0:
        return float(known_height_m), footprint(float(known_height_m))
    top = narrow_minus_height(0.0)  # the silhouette's own smallest width bounds both heights
    height = bisect(narrow_minus_height, top)
    if deep_minus_wide(0.0) > 0.0:
        height = min(height, bisect(deep_minus_wide, top))
    return height, footprint(height)


def _touching_clear_parts(target_px: np.ndarray, missing: np.ndarray, depth_seen: np.ndarray, px_labels: np.ndarray,
                          target: int) -> np.ndarray:
    """Pixels of the other parts of a clear target: no-return regions and evidence components touching its
    pixels in the image (8-connected) that are themselves clear - fewer than ``CHROMA_CLEAR_FRACTION`` of
    their pixels seen in depth. A clear body falls apart into a specular ridge, holes at its ends and a
    seen-through interior; an object seen in depth next to it is not taken."""
    touch = cv2.dilate(target_px.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    out = np.zeros_like(target_px)
    for lab in np.unique(px_labels[touch & (px_labels > 0) & ~target_px]):
        if lab == target:
            continue
        part = px_labels == lab
        if np.mean(depth_seen[part]) < CHROMA_CLEAR_FRACTION:
            out |= part
    n, holes = cv2.connectedComponents((missing & (px_labels == 0)).astype(np.uint8), connectivity=8)
    ids = np.unique(holes[cv2.dilate((target_px | out).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0])
    return out | (np.isin(holes, ids[ids > 0]) & missing)


def _clear_body_cells(under: np.ndarray, depth_seen: np.ndarray, observed: np.ndarray, occupancy: np.ndarray,
                      missing: np.ndarray, miss_c: np.ndarray, disagreement: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A clear target's cells from its prism footprint ``under`` (:func:`prism_footprint`, M x M).

    Observed cells inside the footprint not mostly seen in depth (``depth_seen``) are the **body**: object
    with colour/hole evidence only (occupancy 1, disagreement 1). Cells outside it that the target reached
    only through its body or its holes are the table **behind** it, seen through the plastic: table
    (occupancy 0, not missing) but with disagreement 1 - they are free only if the prism's height, a prior,
    is right (a lower body would cover part of them). The caller trains both with the disagreement variance
    rather than leaving them unknown (unknown cells count as object). Returns new (occupancy, missing,
    miss_c, disagreement) and the body and behind masks."""
    behind = observed & ~under & ~depth_seen & ((occupancy > 0) | missing)
    body = observed & under & ~depth_seen & ~missing
    occupancy = np.where(behind, 0.0, np.where(body, np.maximum(occupancy, 1.0), occupancy))
    disagreement = np.where(behind | body, 1.0, disagreement)
    return occupancy, missing & ~behind, np.where(behind, 0.0, miss_c), disagreement, body, behind


def _select_target(px_labels: np.ndarray, raster: _Raster, foot_xy: np.ndarray, params: SensingParams,
                   intr: CameraIntrinsics) -> tuple[int, int]:
    """Label of the target component and the number of objects seen (module docstring, step 5)."""
    n_lab = int(raster.labels.max()) + 1
    px_count = np.bincount(px_labels.ravel(), minlength=n_lab)
    area_m2 = np.bincount(raster.labels.ravel(), minlength=n_lab) * raster.res ** 2
    kept = np.nonzero((px_count >= params.min_object_area_px) & (area_m2 >= params.min_object_area_m2))[0]
    kept = kept[kept > 0]
    if kept.size == 0:
        raise ValueError(f'no object found on the table: no region of at least {params.min_object_area_px} px and '
                         f'{params.min_object_area_m2 * 1e4:.1f} cm^2 stands out from the table in depth or colour '
                         'or lacks depth (empty table?)')
    if params.target == 'largest':
        return int(kept[np.argmax(area_m2[kept])]), int(kept.size)
    if params.target == 'nearest_center':
        vv, uu = np.nonzero(px_labels > 0)
        lab = px_labels[vv, uu]
        n = np.bincount(lab, minlength=n_lab).astype(np.float64)
        cu = np.bincount(lab, uu, minlength=n_lab) / np.maximum(n, 1)
        cv = np.bincount(lab, vv, minlength=n_lab) / np.maximum(n, 1)
        d = np.hypot(cu[kept] - (intr.width - 1) / 2, cv[kept] - (intr.height - 1) / 2)
        return int(kept[np.argmin(d)]), int(kept.size)
    if params.target == 'pixel':
        u, v = (int(round(c)) for c in params.target_point)
        if not (0 <= u < intr.width and 0 <= v < intr.height):
            raise ValueError(f'target pixel ({u}, {v}) is outside the {intr.width} x {intr.height} image')
        point = foot_xy[v, u]
        if not np.isfinite(point).all():
            raise ValueError(f'target pixel ({u}, {v}) does not look at the table (its ray misses the plane)')
        what = f'target pixel ({u}, {v})'
    else:
        point = np.asarray(params.target_point, dtype=np.float64)
        what = f'target point ({point[0]:.3f}, {point[1]:.3f}) m in the table frame'
    iy, ix = np.nonzero(np.isin(raster.labels, kept))
    centres = raster.origin + (np.stack([ix, iy], axis=1) + 0.5) * raster.res
    dist = np.linalg.norm(centres - point, axis=1)
    if dist.size == 0 or dist.min() > params.target_tolerance_m + raster.res:
        near = '' if dist.size == 0 else f' (nearest object {dist.min() * 1000:.0f} mm away)'
        raise ValueError(f'{what} is on no object{near}: {kept.size} object(s) seen on the table')
    return int(raster.labels[iy[np.argmin(dist)], ix[np.argmin(dist)]]), int(kept.size)


def _check_target(target_px: np.ndarray, target_xy: np.ndarray, target_raster: np.ndarray, raster_res: float,
                  params: SensingParams, intr: CameraIntrinsics) -> None:
    """Refuse a target cut by the image (or pixel ROI) border, or with no part narrow enough for the gripper.

    Too wide = the footprint's convex hull is wider than ``max_opening_m`` in every direction *and*
    its largest inscribed disc is wider too (a toy plane's wings are wide but its fuselage fits)."""
    vs, us = np.nonzero(target_px)
    b = params.border_px
    u_lo, v_lo, u_hi, v_hi = (0, 0, intr.width - 1, intr.height - 1) if params.roi_px is None else \
        (max(0, params.roi_px[0]), max(0, params.roi_px[1]), min(intr.width - 1, params.roi_px[2]),
         min(intr.height - 1, params.roi_px[3]))
    if us.min() < u_lo + b or vs.min() < v_lo + b or us.max() > u_hi - b or vs.max() > v_hi - b:
        raise ValueError(f'the target (pixels u {us.min()}..{us.max()}, v {vs.min()}..{vs.max()}) is cut by the image '
                         'border: its shape is not fully seen (move the camera or the object, or choose another '
                         'target)')
    if params.max_opening_m > 0:
        width = minimum_width(target_xy)
        if width > params.max_opening_m:
            padded = np.pad(target_raster.astype(np.uint8), 1)
            inscribed = 2.0 * float(cv2.distanceTransform(padded, cv2.DIST_L2, 5).max()) * raster_res
            if inscribed > params.max_opening_m:
                raise ValueError(f'the target is {width * 1000:.0f} mm wide in its narrowest direction and no part of '
                                 f'it is narrower than {inscribed * 1000:.0f} mm: more than the gripper opening '
                                 f'max_opening_m = {params.max_opening_m * 1000:.0f} mm')


# ----------------------------------------------------------------------------------------------
# grid accumulation and the noise map

def _nearer_difference(xy: np.ndarray, axis: int) -> np.ndarray:
    """Per pixel, the one-sided difference of the feet ``xy`` (H, W, 2) along image ``axis`` towards the neighbour
    whose foot is nearer (the other where one is missing; NaN without either)."""
    d = np.diff(xy, axis=axis)
    pad = [(0, 0)] * 3
    pad[axis] = (1, 0)
    back = np.pad(d, pad, constant_values=np.nan)
    pad[axis] = (0, 1)
    fwd = np.pad(d, pad, constant_values=np.nan)
    n_back = np.nan_to_num(back[..., 0] ** 2 + back[..., 1] ** 2, nan=np.inf)
    n_fwd = np.nan_to_num(fwd[..., 0] ** 2 + fwd[..., 1] ** 2, nan=np.inf)
    return np.where((n_back <= n_fwd)[..., None], back, fwd)


def _table_area_weights(foot_xy: np.ndarray, ray_xy: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Weight of each pixel in its cell: the table area its orthographic foot covers, relative to a table
    pixel's (|det| of the Jacobian of the feet over (u, v), clipped to [0, 4]).

    A wall facing the camera projects onto a line (weight ~0): it must not outweigh the top face and the
    table in the cells it borders, since the top face's feet already cover the object's footprint up to the
    wall's base and the table's feet cover the table in front of it. Two sources of a spurious wall weight are
    avoided: (1) depth noise - the feet are median-filtered (3 x 3) first, which keeps the feet of a wall on
    its base line and the step to the top face and the table sharp (a linear blur mixes them into the wall,
    and the |det| of noisy differences is biased upwards); (2) the steps - the Jacobian takes, along each
    image axis, the difference to the neighbour whose foot is nearer, i.e. the one on the same surface: a
    central difference across the top edge or the wall's base gives a wall pixel half the table area between
    the feet on both sides of the step (the gap between the wall's base and the first table foot would be
    counted as object). ``valid``: pixels whose foot is known (seen, or a no-return pixel placed on its ray:
    a specular wall placed on the wall covers no table either); the others take the nominal weight 1."""
    def area(xy: np.ndarray) -> np.ndarray:
        a, b = _nearer_difference(xy, 1), _nearer_difference(xy, 0)
        return np.abs(a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0])

    def plane_area(xy: np.ndarray) -> np.ndarray:  # the table's own feet: smooth, central differences
        xu, yu = np.gradient(xy[..., 0], axis=1), np.gradient(xy[..., 1], axis=1)
        xv, yv = np.gradient(xy[..., 0], axis=0), np.gradient(xy[..., 1], axis=0)
        return np.abs(xu * yv - yu * xv)

    if min(foot_xy.shape[:2]) < 3:
        return np.ones(foot_xy.shape[:2])
    feet = np.where(valid[..., None], foot_xy, ray_xy).astype(np.float32)
    feet = np.stack([cv2.medianBlur(np.ascontiguousarray(feet[..., i]), 3) for i in range(2)], axis=-1)
    with np.errstate(invalid='ignore', divide='ignore'):
        ratio = np.where(valid, area(feet.astype(np.float64)), np.nan) / plane_area(ray_xy)
    return np.clip(np.where(np.isfinite(ratio), ratio, 1.0), 0.0, 4.0)


def _hidden_cells(geometry: GridGeometry, intrinsics: CameraIntrinsics, foot_xy: np.ndarray, height: np.ndarray,
                  above: np.ndarray, tol_m: float) -> np.ndarray:
    """(M, M) bool: grid cells whose table patch a tilted camera cannot see (behind an object).

    The pixel looking at the cell centre sees a surface above the table (``above``) at height h; if
    something stands on the cell, the pixel looking at the point h above the cell centre sees it there
    (its orthographic foot within ``tol_m`` of the centre). If not, the surface seen belongs to an object
    in front of the cell and the cell is hidden: the feet of the neighbouring pixels (the object's far
    edge and the table beyond the occluded strip) must not be interpolated into it."""
    centres = geometry.cell_centers()
    u0, v0, in0 = intrinsics.pixel_index(geometry.to_sensor(centres, 0.0))
    covered = in0 & above[v0, u0]
    h_seen = np.where(covered, np.nan_to_num(height[v0, u0]), 0.0)
    u1, v1, in1 = intrinsics.pixel_index(geometry.to_sensor(centres, h_seen))
    dist = np.linalg.norm(foot_xy[v1, u1] - centres, axis=-1)
    under = in1 & np.isfinite(dist) & (dist <= tol_m)
    return covered & ~under


def _hidden_fraction(geometry: GridGeometry, intrinsics: CameraIntrinsics, foot_xy: np.ndarray, height: np.ndarray,
                     above: np.ndarray, tol_m: float, tan_max: float, cells: np.ndarray,
                     sub: int = HIDDEN_SUBCELLS, max_samples: int = 256,
                     window_m: float = MISSING_HEIGHT_WINDOW_M) -> np.ndarray:
    """(M, M) fraction of each cell's area hidden behind an object from the camera, on ``sub`` x ``sub``
    points per cell, for the ``cells`` asked (0 elsewhere).

    A table point x is under a surface the camera sees if, at some height h, the pixel looking at the point
    h above x sees a surface (``above``, at ``height``; no-return pixels placed above the table by
    :func:`_missing_height` count) whose orthographic foot is within ``tol_m`` (about a pixel's footprint) of
    x: the point is on that surface. h runs from 0 to the highest surface seen in steps whose feet move by at
    most ``tol_m`` (``tan_max``: the largest tangent of a ray's angle to the table normal). x is hidden when
    the pixel looking at it sees a surface above the table and no height puts x under a seen surface: the
    surface seen stands in front of x, not on it.

    Beyond the far edge of an object's top face (seen by a tilted camera) the table is occluded, so a cell
    crossed by that edge is seen only where the top covers it: its pixels are all object and their mean
    occupancy is 1, whatever part of the cell the top covers. Its occluded part is assumed table, as a
    wholly occluded cell is (the object is a prism whose visible top covers its footprint), so the cell's
    occupancy is the mean over its seen part times the fraction that is seen: the covered fraction. A
    top-down camera hides only a thin strip beside tall objects away from the optical axis."""
    m_y, m_x = geometry.shape
    fine = GridGeometry(geometry.origin_x, geometry.origin_y, geometry.resolution / sub, m_x * sub, m_y * sub,
                        geometry.z, geometry.frame_id, geometry.rotation)
    points = fine.cell_centers()

    def pixel(pts: np.ndarray, h: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return intrinsics.pixel_index(fine.to_sensor(pts, h))

    u, v, inside = pixel(points, 0.0)
    covered = inside & above[v, u] & np.repeat(np.repeat(cells, sub, axis=0), sub, axis=1)
    if not covered.any():
        return np.zeros((m_y, m_x))
    todo = points[covered]
    under = np.zeros(todo.shape[0], dtype=bool)
    top = float(np.max(height[above]))
    n_h = int(np.clip(math.ceil(top * max(tan_max, 1e-3) / max(tol_m, 1e-6)) + 1, 2, max_samples))
    for h in np.linspace(0.0, top, n_h):
        pts = todo[~under]
        if pts.shape[0] == 0:
            break
        u, v, inside = pixel(pts, float(h))
        with np.errstate(invalid='ignore'):
            near = np.linalg.norm(foot_xy[v, u] - pts, axis=-1) <= tol_m
        under[np.flatnonzero(~under)[inside & above[v, u] & near]] = True
    # a hidden point is table only if its occlusion shadow ends on the table: the ray over the local top of
    # what hides it (highest surface within window_m of the pixel looking at it) lands on the table beyond,
    # not on the object (a lower part of the object behind a taller one is object, not table)
    k = max(3, 2 * int(round(0.5 * window_m / max(tol_m, 1e-6))) + 1)
    local_top = cv2.dilate(np.where(above, height, 0.0).astype(np.float32),
                           cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
    rest = np.flatnonzero(~under)
    u, v, _ = pixel(todo[rest], 0.0)
    u, v, inside = pixel(todo[rest], local_top[v, u].astype(np.float64))
    under[rest[inside & above[v, u]]] = True
    hidden = covered.copy()
    hidden[covered] = ~under
    return hidden.reshape(m_y, sub, m_x, sub).mean(axis=(1, 3))


def _accumulate(cell: np.ndarray, maps: list[np.ndarray], n_cells: int) -> list[np.ndarray]:
    """Per-cell sums of pixel maps (``cell`` = flat cell index, -1 = not in the grid)."""
    ok = cell >= 0
    return [np.bincount(cell[ok], weights=m[ok], minlength=n_cells) for m in maps]


def _foreign_missing_fraction(row: np.ndarray, col: np.ndarray, in_grid: np.ndarray, informative: np.ndarray,
                              foreign: np.ndarray, m: int) -> np.ndarray:
    """Per cell: share of its pixels that are no-return pixels not given to the target (``foreign``).

    Such pixels (a specular wing the segmentation split from the seen body, D of the shipped bags) are
    otherwise dropped, and the cell is then filled from its neighbours as observed table - the GPIS
    would be confidently wrong exactly where nothing was measured. Unweighted pixel counts of the
    cell's informative pixels plus the foreign ones; 0 where no pixel falls in the cell.
    """
    idx = np.where(in_grid, np.nan_to_num(row) * m + np.nan_to_num(col), -1).astype(np.int64)
    n_foreign = np.bincount(idx[in_grid & foreign], minlength=m * m)
    n_seen = np.bincount(idx[informative], minlength=m * m)
    with np.errstate(invalid='ignore', divide='ignore'):
        frac = np.where(n_foreign > 0, n_foreign / np.maximum(n_foreign + n_seen, 1), 0.0)
    return frac.reshape(m, m)


def _extended_regions(mask: np.ndarray) -> np.ndarray:
    """The 8-connected components of ``mask`` that hold a cell whose four neighbours are all in ``mask``.

    Drops thin bands (one or two cells wide): where the colour mask bleeds a pixel or two past a seen
    object's edge the masks disagree along a ring, which is edge noise, not an unseen part.
    """
    if not mask.any():
        return np.zeros_like(mask)
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    core = cv2.erode(mask.astype(np.uint8), cross, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
    count, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    keep = np.zeros(count, dtype=bool)
    keep[np.unique(labels[core])] = True
    keep[0] = False
    return keep[labels]


def _propagation_variance(occ_bin: np.ndarray, uncertain: np.ndarray, train: np.ndarray, geometry: GridGeometry,
                          params: SensingParams) -> np.ndarray:
    """SDF variance (m^2) induced by uncertain cells on every cell's distance (module docstring)."""
    out = np.zeros(geometry.shape)
    if not uncertain.any():
        return out
    res = geometry.resolution
    n_local = math.pi * (params.error_correlation_length_m / res) ** 2
    count, labels = cv2.connectedComponents(uncertain.astype(np.uint8), connectivity=8)
    for c in range(1, count):
        comp = labels == c
        rest = occ_bin & ~comp
        if not rest.any():  # the component is the only object evidence: "free" would mean no object at all
            continue
        delta = signed_distance(occ_bin | comp, res) - signed_distance(rest, res)
        reach = cv2.distanceTransform((~comp).astype(np.uint8), cv2.DIST_L2, 5) * res
        delta = np.where(reach <= params.propagation_radius_m, delta, 0.0)
        affected = int(np.count_nonzero((np.abs(delta) > 1e-12) & train))
        n_eff = max(1.0, min(float(affected), n_local))
        out += params.alternative_weight * n_eff * delta ** 2
    return out


# ----------------------------------------------------------------------------------------------
# main entry point

def _validate_inputs(rgb_frames, depth_frames, intrinsics) -> tuple[np.ndarray, np.ndarray]:
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
    if depth_in.shape[1:] != (intrinsics.height, intrinsics.width):
        raise ValueError(f'images are {depth_in.shape[2]} x {depth_in.shape[1]} but the intrinsics are for '
                         f'{intrinsics.width} x {intrinsics.height}')
    return rgb, depth_in


def segment_frames(rgb_frames: np.ndarray | Sequence[np.ndarray], depth_frames: np.ndarray | Sequence[np.ndarray],
                   intrinsics: CameraIntrinsics, params: SensingParams = SensingParams(),
                   frame_id: str = '') -> SensingResult:
    """Segment the target object from N RGBD frames into an M x M occupancy grid and SDF noise map (III-B).

    Args:
        rgb_frames: ``(N, H, W, 3)`` uint8 RGB images (or one ``(H, W, 3)`` image).
        depth_frames: ``(N, H, W)`` float depth in metres, NaN (or <= 0) = no return.
        intrinsics: pinhole intrinsics of the (registered) images, pixels.
        params: thresholds, table, target and grid settings (see :class:`SensingParams`).
        frame_id: sensor frame stored in the returned geometry.

    Returns:
        :class:`SensingResult`; see the module docstring for every map. The grid lies in the
        table plane (``geometry.rotation`` = table frame).

    Raises:
        ValueError: wrong dtype or shape, no valid depth, no table plane (or seen edge-on), no object
            on the table, target point on no object, target cut by the image border or too wide.
    """
    rgb, depth_in = _validate_inputs(rgb_frames, depth_frames, intrinsics)
    n_frames, h, w = depth_in.shape

    # 1. averaging over valid returns; independent frames measured
    depth = depth_in.astype(np.float64)
    valid_f = np.isfinite(depth) & (depth > 0)
    count = valid_f.sum(axis=0)
    if count.max() == 0:
        raise ValueError('depth_frames contain no valid return (all NaN or <= 0)')
    missing_px = count < max(1, params.min_valid_returns)
    valid = ~missing_px
    with np.errstate(invalid='ignore', divide='ignore'):
        z_mean = np.where(valid, np.where(valid_f, depth, 0.0).sum(axis=0) / np.maximum(count, 1), np.nan)
    rgb_mean = rgb.sum(axis=0, dtype=np.uint32) / float(n_frames)  # exact; no float64 copy of the frames
    n_eff = effective_frame_count(np.where(valid_f, depth, np.nan), params.sensor) if n_frames > 1 else 1.0
    count_eff = count * (n_eff / n_frames)

    # 2. table frame from the whole valid cloud
    rays = intrinsics.rays()
    points = rays * np.where(valid, z_mean, np.nan)[..., None]
    table = _table_frame(points, valid, params)
    normal = table.n
    ray_n = np.abs(rays @ normal)  # height error per unit depth error along the ray

    def measured(z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Camera points, heights above the plane (NaN where no return), depths with the plane's offset where
        none, their averaged variance and the height noise s_h of depths ``z`` (m) - for the frames' returns,
        and again after the see-through test moved some."""
        pts = rays * np.where(valid, z, np.nan)[..., None]
        z_ok = np.where(valid, z, table.offset_m)
        var = params.sensor.variance(z_ok) / np.maximum(count_eff, 1.0)
        return (pts, np.where(valid, pts @ normal + table.offset_m, np.nan), z_ok, var,
                np.sqrt(var) * np.maximum(ray_n, 1e-3))

    points, height, z_safe, var_z, s_h = measured(z_mean)
    band = np.maximum(params.plane_band_floor_m, params.plane_band_sigmas * params.sensor.sigma(z_safe))
    inlier = valid & (np.abs(np.nan_to_num(height, nan=1.0)) <= band)
    if inlier.sum() < 20:
        raise ValueError(f'only {int(inlier.sum())} pixels lie on the table plane: cannot estimate the table '
                         '(check table_plane / table_depth_m, or the depth image)')
    rms = float(np.sqrt(np.mean(height[inlier] ** 2)))
    h_thr = max(params.height_threshold, 2.0 * rms)

    # 3. soft depth and colour evidence (the colour test ignores shadows)
    p_d = np.where(valid, ndtr((np.nan_to_num(height) - h_thr) / s_h), 0.0)
    colour, p_c, c_ratio = _colour_evidence(rgb_mean, inlier, missing_px, params)
    table_rgb, c_thr, dark_ratio = colour.table_rgb, colour.threshold, colour.dark_ratio
    p_d = _morph_clean(p_d, params.morph_kernel_px)
    p_c = _morph_clean(p_c, params.morph_kernel_px)
    # darker than the table on its shadow line: shadow or a dark object of the table's hue - colour
    # cannot tell, so it defers to depth (no evidence either way, no disagreement)
    p_c = np.where((c_ratio < dark_ratio) & (p_c < 0.5), p_d, p_c)

    # 3b. seen through: a return behind the solid under a point seen above the table (a height field) passed
    # through the object - a clear part's return of what lies behind it; its ray enters the object no later
    # than where it meets that solid, and is placed there
    through_px = np.zeros((h, w), dtype=bool)
    if params.see_through_test:
        flagged, entry = see_through_pixels(points, height, valid & (p_d > 0.5), z_mean, table, intrinsics,
                                            params.sensor)
        through_px = flagged & ((p_d > 0.5) | (p_c > 0.5))
        if through_px.any():
            z_mean = np.where(through_px, entry, z_mean)
            points, height, z_safe, var_z, s_h = measured(z_mean)
            p_d = np.where(through_px, ndtr((np.nan_to_num(height) - h_thr) / s_h), p_d)

    # 3c. the sensor's shadow: no return, table-coloured, on table its second viewpoint (projector or second imager)
    # cannot see beside an object, where the visual hull cannot tell it from the object: table the sensor did not
    # measure (not missing = object); treated like a hole off the object's visual hull below
    footprint = float(np.median(z_mean[inlier])) / min(intrinsics.fx, intrinsics.fy) / max(
        math.cos(math.radians(table.tilt_deg)), 0.3)  # a pixel's extent on the table (m)
    shadow_px = np.zeros((h, w), dtype=bool)
    if params.shadow_test:
        shadow_px = occlusion_shadow_pixels(points, height, valid & (p_d > 0.5), missing_px & (p_c <= 0.5), table,
                                            intrinsics, params.sensor, footprint)
        missing_px = missing_px & ~shadow_px

    # 4. inverse-variance combination, missing = object
    v_d = p_d * (1.0 - p_d) + params.depth_floor_variance
    v_c = p_c * (1.0 - p_c) + params.color_floor_variance
    occ = (p_d / v_d + p_c / v_c) / (1.0 / v_d + 1.0 / v_c)
    rho = np.where(missing_px, 0.0, np.abs(p_d - p_c))
    occ = np.where(missing_px, 1.0, occ)

    # 5. orthographic feet on the table; evidence above the plane, on the table, in the ROI; the target
    h_missing, tested = _missing_height(height, valid & (np.nan_to_num(height) > h_thr), missing_px, rays, table,
                                        intrinsics, footprint, return_tested=True)
    off_hull = tested & (h_missing <= 0)  # next to an object, but on the table: its ray meets no part of it
    off_hull |= shadow_px  # the sensor's shadow: table it did not measure (3c)
    hit_points, hit = table.ray_intersection(rays)
    ray_dot = rays @ normal
    ray_cos = np.maximum(np.abs(ray_dot) / np.linalg.norm(rays, axis=-1), 1e-3)  # cosine of a ray to the normal
    with np.errstate(invalid='ignore', divide='ignore'):
        t_missing = np.where(hit, (h_missing - table.offset_m) / np.where(hit, ray_dot, -1.0), np.nan)
    missing_points = rays * t_missing[..., None] - h_missing[..., None] * normal
    foot = np.where(valid[..., None], points - np.nan_to_num(height)[..., None] * normal, missing_points)
    foot_xy, _ = table.to_table(foot)
    foot_xy = np.where((valid | hit)[..., None], foot_xy, np.nan)
    evidence = (occ > 0.5) | (p_d > 0.5) | (p_c > 0.5) | missing_px
    if params.morph_kernel_px > 1:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (params.morph_kernel_px, params.morph_kernel_px))
        evidence = cv2.morphologyEx(evidence.astype(np.uint8), cv2.MORPH_OPEN, kernel).astype(bool)
    h_ok = np.nan_to_num(height, nan=0.0)
    evidence &= (h_ok > -band) & (h_ok < params.max_object_height_m) & np.isfinite(foot_xy).all(axis=-1)
    if params.roi_px is not None:
        u0, v0, u1, v1 = params.roi_px
        uu, vv = np.meshgrid(np.arange(w), np.arange(h))
        evidence &= (uu >= u0) & (uu <= u1) & (vv >= v0) & (vv <= v1)
    if params.roi_table is not None:
        x0, y0, x1, y1 = params.roi_table
        fx_, fy_ = foot_xy[..., 0], foot_xy[..., 1]
        evidence &= (fx_ >= x0) & (fx_ <= x1) & (fy_ >= y0) & (fy_ <= y1)
    # the table's extent is the hull of the inliers' feet, decided by the rim of the inlier region (the feet of
    # plane points are a projective image of the pixels: interior pixels are never hull vertices)
    rim = inlier & ~cv2.erode(inlier.astype(np.uint8), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT,
                              borderValue=0).astype(bool)
    inlier_xy = foot_xy[rim]
    raster, px_labels = _table_components(foot_xy, evidence, missing_px, inlier_xy, footprint, MISSING_ATTACH_M,
                                          np.where(p_d > 0.5, height, np.nan))
    target, objects_seen = _select_target(px_labels, raster, foot_xy, params, intrinsics)
    target_px = px_labels == target
    target_xy = foot_xy[target_px]
    _check_target(target_px, target_xy, raster.labels == target, raster.res, params, intrinsics)
    colour_core = (p_c > 0.5) & (p_d <= 0.5) & params.transparent_core_occupied
    through = seen_through(raster, target, foot_xy, px_labels, colour_core, valid & (p_d <= 0.5)
                           & (np.abs(np.nan_to_num(height)) <= h_thr), params.transparent_close_m)
    # seen through a transparent target: colour/hole evidence only - object in the occupancy, depth and colour
    # disagree (uncertain cells, like the paper's Object A), never observed-depth table
    depth_fraction = float(np.mean(p_d[target_px] > 0.5))
    if params.chroma_z_min > 0 and depth_fraction < CHROMA_CLEAR_FRACTION:  # a clear target's body
        chroma_z = chromaticity_distance(rgb_mean, inlier)[0]
        rx, ry, r_ok = raster.cell(foot_xy)  # not over another object's cells in the table plane either
        under = np.where(r_ok, raster.labels[ry, rx], 0)
        through |= _bounded_extension(target_px, chromatic_extension(
            target_px | through, valid & (p_d <= 0.5) & (np.abs(np.nan_to_num(height)) <= h_thr)
            & ((px_labels == 0) | (px_labels == target)) & ((under == 0) | (under == target)) & r_ok, chroma_z,
            params.chroma_z_min), params)
    rgb_test = p_c > 0.5  # the colour test itself (published as rgb_mask), before the seen-through pixels
    target_px, occ, p_c = target_px | through, np.where(through, 1.0, occ), np.where(through, 1.0, p_c)
    target_xy = foot_xy[target_px]
    body_height, clear_target = 0.0, False
    if params.clear_body_prism and depth_fraction < CHROMA_CLEAR_FRACTION:
        # a clear body: with its clear parts, less than CLEAR_BODY_FRACTION of it seen in depth (a partly clear
        # object - the paper's Object A - keeps its clear part uncertain)
        whole = target_px | _touching_clear_parts(target_px, missing_px, p_d > 0.5, px_labels, target)
        clear_target = bool(np.mean(p_d[whole] > 0.5) < CLEAR_BODY_FRACTION)
    if clear_target:
        # the body's silhouette: its parts closed over gaps narrower than a body's core disc, holes filled
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (CHROMA_CORE_PX, CHROMA_CORE_PX))
        target_px = _filled(cv2.morphologyEx(whole.astype(np.uint8), cv2.MORPH_CLOSE, disc)) & (valid | missing_px) \
            & np.isfinite(foot_xy).all(axis=-1)
        body_height, body_xy = clear_body_height(target_px, table, intrinsics,
                                                 known_height_m=params.clear_body_height_m)
        if body_xy.shape[0] >= 3:  # the grid spans the body's footprint, not the table seen through it
            target_xy = body_xy
    elif off_hull.any():
        # no-return pixels next to the target whose ray meets no part of its visual hull (_missing_height: a
        # projector shadow or drop-out on the table beside it) are table the sensor did not measure, not
        # the target: they neither vote object in the cells they fall in nor stretch the grid
        target_px = target_px & ~off_hull
        target_xy = foot_xy[target_px]

    # 6. square grid in the table plane around the target's footprint
    lo, hi = target_xy.min(axis=0), target_xy.max(axis=0)
    side = float(max(hi - lo)) * (1.0 + 2.0 * params.margin)
    side = max(side, 1e-3)
    m = params.grid_size
    centre = 0.5 * (lo + hi)
    geometry = table.grid(centre[0] - side / 2, centre[1] - side / 2, side / m, m, m, frame_id)
    res = geometry.resolution
    col = np.floor((foot_xy[..., 0] - geometry.origin_x) / res)
    row = np.floor((foot_xy[..., 1] - geometry.origin_y) / res)
    in_grid = np.isfinite(col) & np.isfinite(row) & (col >= 0) & (col < m) & (row >= 0) & (row < m)
    miss_t = missing_px & target_px
    informative = in_grid & (valid | miss_t)
    cell = np.where(informative, np.nan_to_num(row) * m + np.nan_to_num(col), -1).astype(np.int64)
    valid_px = valid.astype(np.float64)
    occ_t = np.where(target_px, occ, 0.0)  # other objects are not the target: table in its grid
    wt = _table_area_weights(foot_xy, table.to_table(hit_points)[0], np.isfinite(foot_xy).all(axis=-1))
    seen_in_depth = (target_px & valid & (p_d > 0.5)).astype(np.float64)
    sums = _accumulate(cell, [wt * v for v in (np.ones((h, w)), occ_t, p_d * valid_px, p_c * valid_px, valid_px,
                                               miss_t.astype(np.float64), np.where(valid, var_z, 0.0),
                                               seen_in_depth)], m * m)
    n_inf, s_occ, s_pd, s_pc, s_valid, s_miss, s_var, s_seen = (s.reshape(m, m) for s in sums)
    depth_seen_cell = s_seen > 0.5 * np.maximum(n_inf, 1e-12)  # mostly the target seen in depth (before any fill)

    # cells between the feet of neighbouring pixels (a grid finer than the pixels' footprint on the
    # table): the mean of their observed 8-neighbours, if at least 3, for as many cells as a footprint spans
    stats = [s_occ, s_pd, s_pc, s_valid, s_miss, s_var]
    kernel3 = np.ones((3, 3), np.float32)
    hidden = _hidden_cells(geometry, intrinsics, foot_xy, height, valid & (np.nan_to_num(height) > h_thr),
                           max(1.5 * res, 2.0 * footprint))  # behind an object: not interpolated
    # cells holding only the feet of holes on the table beside the target (off its visual hull) are not between
    # the feet of seen pixels: no measurement, not interpolated from the target's cells next to them
    unmeasured = np.bincount(np.where(in_grid & off_hull, np.nan_to_num(row) * m + np.nan_to_num(col), 0).astype(
        np.int64)[in_grid & off_hull], minlength=m * m).reshape(m, m) > 0
    for _ in range(int(math.ceil(footprint / res))):
        seen = (n_inf > 0).astype(np.float32)
        n_nb = cv2.filter2D(seen, -1, kernel3, borderType=cv2.BORDER_CONSTANT)
        fill = (n_inf == 0) & (n_nb >= 3) & ~hidden & ~unmeasured
        if not fill.any():
            break
        for arr in stats:
            mean = np.where(n_inf > 0, arr / np.maximum(n_inf, 1.0), 0.0).astype(np.float32)
            arr[fill] = (cv2.filter2D(mean, -1, kernel3, borderType=cv2.BORDER_CONSTANT)[fill] / n_nb[fill])
        n_inf[fill] = 1.0

    # cells no pixel reaches: their centre's image pixel (occluded, outside the image, or a target hole)
    empty = n_inf == 0
    occluded = np.zeros((m, m), dtype=bool)
    if empty.any():
        rr, cc = np.nonzero(empty)
        ui, vi, inside = intrinsics.pixel_index(geometry.to_sensor(geometry.cell_centers()[rr, cc]))
        sees_table = inside & valid[vi, ui] & (np.nan_to_num(height[vi, ui]) <= h_thr)
        # a target hole placed on its ray above the table (_missing_height) is not at this cell: hidden, not a hole
        sees_target_hole = inside & miss_t[vi, ui] & (h_missing[vi, ui] <= 0)
        occluded[rr, cc] = inside & ~sees_table & ~sees_target_hole
        take = sees_table | sees_target_hole
        r2, c2, v2, u2 = rr[take], cc[take], vi[take], ui[take]
        n_inf[r2, c2] = 1.0
        s_occ[r2, c2] = occ_t[v2, u2]
        s_pd[r2, c2], s_pc[r2, c2] = p_d[v2, u2] * valid_px[v2, u2], p_c[v2, u2] * valid_px[v2, u2]
        s_valid[r2, c2], s_miss[r2, c2] = valid_px[v2, u2], miss_t[v2, u2]
        s_var[r2, c2] = np.where(valid[v2, u2], var_z[v2, u2], 0.0)
    observed = n_inf > 0
    n_safe = np.maximum(n_inf, 1.0)
    # the part of a cell hidden behind an object is table, like a wholly occluded cell (_hidden_fraction)
    hidden_part = _hidden_fraction(geometry, intrinsics, foot_xy, np.where(valid, np.nan_to_num(height), h_missing),
                                   (valid & (np.nan_to_num(height) > h_thr)) | (h_missing > 0), footprint,
                                   float(np.nanmax(np.sqrt(np.maximum(1.0 - ray_cos ** 2, 0.0)) / ray_cos)),
                                   observed & (s_occ > 0))
    occupancy = np.clip(np.where(observed, s_occ / n_safe * (1.0 - hidden_part), 0.0), 0.0, 1.0)
    miss_c = s_miss / n_safe
    missing = observed & (miss_c > params.missing_cell_fraction)
    with np.errstate(invalid='ignore', divide='ignore'):
        rho_c = np.abs(s_pd - s_pc) / s_valid
        depth_var = np.where(s_valid > 0, s_var / s_valid, 0.0)
    disagreement = np.where(observed & (s_valid > 0), np.clip(np.nan_to_num(rho_c), 0.0, 1.0), 0.0)
    body = behind = np.zeros((m, m), dtype=bool)
    if clear_target:
        occupancy, missing, miss_c, disagreement, body, behind = _clear_body_cells(
            prism_footprint(geometry.cell_centers(), target_px, table, intrinsics, body_height), depth_seen_cell,
            observed, occupancy, missing, miss_c, disagreement)

    # SDF noise: depth + discretisation + disagreement + propagation (module docstring, Noise map). Unknown
    # cells - missing, extended regions where the masks disagree, or mostly no-return pixels the target did
    # not get - are not trained and count as object in the SDF, so the prior governs them (section III-B)
    disagree = disagreement > params.uncertainty_threshold
    uncertain = missing | disagree
    unknown = missing.copy()
    if params.exclude_uncertain:
        foreign = _foreign_missing_fraction(row, col, in_grid, informative, missing_px & ~target_px & ~off_hull,
                                            m) > params.missing_cell_fraction
        uncertain |= foreign
        trained_clear = behind | (body & params.train_clear_body)  # a clear body's prism, trained
        unknown |= foreign | (_extended_regions(disagree) & ~trained_clear)
    noise = (depth_var
             + params.disagreement_variance_m2 * disagreement
             + params.disagreement_variance_m2 * np.where(missing, 0.0, miss_c))
    occ_bin = occupancy >= 0.5
    if not occ_bin.any():
        raise ValueError('no object found: the target evidence is too weak for any grid cell to be occupied '
                         '(lower grid_size or the thresholds)')
    noise = np.where(observed, noise, params.unobserved_variance_m2)
    train_mask = ~unknown
    sdf_object = occ_bin | ~train_mask  # what the GPIS's SDF treats as object (pipeline.publishable_grids)
    noise = noise + _propagation_variance(sdf_object, uncertain & ~(body | behind), train_mask, geometry, params)
    noise = np.where(train_mask, noise, np.maximum(noise, params.disagreement_variance_m2))  # unused by the GP
    noise_px = np.where(missing_px, np.nan, var_z + params.disagreement_variance_m2 * rho)
    vs, us = np.nonzero(target_px)
    return SensingResult(
        occupancy=occupancy, noise_variance=noise, missing=missing, geometry=geometry, table_depth=table.offset_m,
        train_mask=train_mask, observed=observed, occluded=occluded, uncertain=uncertain, disagreement=disagreement,
        table=table, table_color=table_rgb, color_threshold=c_thr, height_threshold=h_thr, effective_frames=n_eff,
        objects_seen=objects_seen, mean_depth=z_mean, valid_count=count.astype(np.int64), height=height,
        depth_mask=p_d > 0.5, rgb_mask=rgb_test, missing_mask=missing_px, object_mask=target_px,
        labels_px=px_labels, occupancy_px=occ, noise_px=noise_px, disagreement_px=rho,
        bbox_px=(int(us.min()), int(vs.min()), int(us.max()), int(vs.max())), intrinsics=intrinsics,
        object_height=object_height(height, target_px & valid & (p_d > 0.5)), seen_through_px=through_px,
        shadow_px=shadow_px)
