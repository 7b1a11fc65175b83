"""Settings and output of the segmentation (:class:`SensingParams`, :class:`SensingResult`) and its constants."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.core.noise_model import CARMINE, SensorModel
from gpis_grasp_ros.core.sdf import signed_distance
from gpis_grasp_ros.core.sensing.camera import CameraIntrinsics
from gpis_grasp_ros.core.table_frame import TableFrame

TARGET_MODES = ('largest', 'nearest_center', 'pixel', 'table')
MISSING_HEIGHT_WINDOW_M = 0.02  # a hole takes the highest height seen within this window of its nearest seen pixel (m)
MISSING_BRIDGE_M = 0.05  # a hole region this small joins the objects it touches (m)
MISSING_ATTACH_M = 0.01  # holes belong to an object within this distance of its seen parts (m)
OBJECT_HEIGHT_PERCENTILE = 95.0  # measured object height: this percentile of its depth-seen heights
FLAT_STEP_M = 0.004  # neighbouring cells of a flat surface differ by at most this height (m)
FLAT_JUMP_M = 0.01  # ... and something standing on/next to it differs from it by more (m)
FLAT_MIN_AREA_M2 = 0.002  # a flat support (notebook, plate, tray) covers at least this area (m^2)
SOLID_FALSE_ALARM = 1e-3  # one-sided probability per pixel of table noise being taken as solid evidence
SPLIT_NECK_M = 0.01  # touching objects split where both are wider than their contact by 2 x this (radius, m)
CHROMA_SMOOTH_PX = 1.5  # Gaussian sigma (px) of the colour image before its chromaticity is taken
CHROMA_DARK = 20.0  # darker pixels (mean of 0-255 RGB) have no reliable chromaticity
CHROMA_MIN_SIGMA = 0.006  # floor of the table's chromaticity spread (a noiseless table would flag every halo)
CHROMA_CLEAR_FRACTION = 0.5  # a target with fewer of its pixels seen in depth is clear: its body is grown
SHADOW_HULL_SPAN_PX = 3.0  # a column imaged this long or longer: the visual hull decides (_missing_height)
CLEAR_BODY_FRACTION = 0.25  # a target with fewer of its pixels seen in depth is a clear body (prism footprint)
PRISM_STEP_M = 0.003  # height step (m) of the visual-hull test of a clear body's prism
PRISM_RASTER_M = 0.002  # raster (m) on which a clear body's height is found
HIDDEN_SUBCELLS = 8  # points per cell side at which the hidden part of a cell is found
CHROMA_CORE_PX = 7  # a region seen through a clear body holds a disc this wide (px); an edge band does not


# What the sensor did not measure stays uncertain (noise_map.prism_variance)
CLEAR_BODY_HEIGHT_FACTOR = math.sqrt(2.0)  # a clear body's prior height is right to within this factor: a round
#                                             body lying seen through is cos a + sin a <= sqrt 2 times higher


# The table that supports the target (table.target_support): its colour model is learnt within this radius
SUPPORT_RADIUS_M = 0.15  # of the target point in the table plane (m)
SUPPORT_MIN_PX = 500  # ... when at least this many plane inliers lie that close (else all of them)


def _box(value: Sequence[float] | None, name: str) -> tuple[float, float, float, float] | None:
    if value is None:
        return None
    box = tuple(float(v) for v in value)
    if len(box) != 4 or not all(math.isfinite(v) for v in box) or box[2] <= box[0] or box[3] <= box[1]:
        raise ValueError(f'{name} must be (min_x, min_y, max_x, max_y) with max > min, got {value!r}')
    return box


PAPER_GRID_SIZE = 25  # the paper's M (Table I, the 25 x 25 validation models): the simulated benchmark's grid


@dataclass(frozen=True)
class SensingParams:
    """Settings of :func:`segment_frames` (lengths in metres, colours in 0-255 RGB units)."""

    cell_size_m: float = 0.003  # planning-grid cell (m): the jaw noise sigma_g, a few depth pixels (grid_cells)
    min_grid_cells: int = 25  # M at least this (the paper's M): a small object gets finer cells
    max_grid_cells: int = 100  # M at most this: a large object gets coarser cells
    min_pixels_per_cell: float = 2.0  # a cell at least this many pixel footprints wide (sampling: 2 per cell)
    grid_size: int = 0  # 0 = the cell rule (cell_size_m, M within [min_grid_cells, max_grid_cells]); > 0: force M
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
    transparent_close_m: float = 0.006  # closing radius (m) of the target's outline before its interior is filled
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
    #                            table's chromaticity (a clear body seen through; chromatic_extension), and let
    #                            a target pixel there select the clear object (clear_object_at); 0 = off
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

    def __post_init__(self) -> None:
        if self.grid_size != 0 and self.grid_size < 3:
            raise ValueError(f'grid_size must be 0 (from cell_size_m) or >= 3, got {self.grid_size}')
        if not (math.isfinite(self.cell_size_m) and self.cell_size_m > 0):
            raise ValueError(f'cell_size_m must be a positive number of metres, got {self.cell_size_m}')
        if not (math.isfinite(self.min_pixels_per_cell) and self.min_pixels_per_cell >= 0):
            raise ValueError(f'min_pixels_per_cell must be >= 0 (0 = cell_size_m alone), got '
                             f'{self.min_pixels_per_cell}')
        if not 3 <= self.min_grid_cells <= self.max_grid_cells:
            raise ValueError(f'need 3 <= min_grid_cells <= max_grid_cells, got {self.min_grid_cells} and '
                             f'{self.max_grid_cells}')
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
    objects_seen: int  # evidence components on the table (the target and the others; in the window, if any)
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
    clear_body: np.ndarray | None = None  # (M, M) bool, a clear body's prism cells (object from colour/holes only)
    seen_behind: np.ndarray | None = None  # (M, M) bool, the table seen through a clear body
    obstacles: np.ndarray | None = None  # (M, M) bool, cells mostly another object: where no jaw can be
    window_px: tuple[int, int, int, int] | None = None  # (u_min, v_min, u_max, v_max) inclusive: the target's window
    #                                                      segmented (window.py; None = the whole image)

    @property
    def sdf(self) -> np.ndarray:
        """Signed distance (m) of the occupancy (>= 0.5 is object), :func:`~gpis_grasp_ros.core.sdf.signed_distance`."""
        return signed_distance(self.occupancy, self.geometry.resolution)


# Touching objects split at height steps (steps.split_height_steps): two neighbouring raster cells are on one
# continuous surface when their heights differ by at most steps.STEP_SIGMAS x the sensor model's noise of the difference
STEP_FALSE_ALARM = 1e-3  # (two-sided probability per edge that noise alone breaks one surface: 3.29 sigma)
STEP_SLOPE_DEG = 45.0  # ... plus the rise over one cell of a surface this steep; a steeper one is narrower in plan
#                        than it is high: its cells are slivers that join the part beside them
