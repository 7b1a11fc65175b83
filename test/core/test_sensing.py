"""RGBD segmentation, noise map and grid resampling (gpis_grasp_ros.core.sensing, section III-B)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.ndimage import binary_dilation

from gpis_grasp_ros.core.gpis import GpisParams
from gpis_grasp_ros.core.noise_model import axial_sigma, axial_variance, quantise
from gpis_grasp_ros.core.pipeline import posterior_from_grids
from gpis_grasp_ros.core.sensing import (
    CameraIntrinsics,
    SensingParams,
    frames_from_clouds,
    segment_frames,
)
from gpis_grasp_ros.core.sensing.rasterise import grid_cells

TABLE_Z = 0.7
TABLE_RGB = np.array([120.0, 120.0, 120.0])


def make_scene(n_frames: int = 10, seed: int = 0, tint=(0, 30, 40), size: int = 240, specular: bool = True):
    """Carmine-like frames of a 6 x 4 x 3 cm red box on a grey table 0.7 m below the camera.

    * transparent part: 2 x 4 cm right of the box, depth = table, colour = table + ``tint``
    * specular part: 1.8 x 1.8 cm inside the box, no depth return in any frame (NaN)
    Depth noise: Nguyen et al. axial model + disparity quantisation (the simulator's model).
    """
    rng = np.random.default_rng(seed)
    intr = CameraIntrinsics(570.0, 570.0, (size - 1) / 2, (size - 1) / 2, size, size)
    u, v = np.meshgrid(np.arange(size), np.arange(size))
    x = (u - intr.cx) * TABLE_Z / intr.fx
    y = (v - intr.cy) * TABLE_Z / intr.fy
    regions = {
        'box': (np.abs(x + 0.01) < 0.03) & (np.abs(y) < 0.02),
        'trans': (x >= 0.02) & (x < 0.04) & (np.abs(y) < 0.02),
        'spec': (np.abs(x + 0.02) < 0.009) & (np.abs(y) < 0.009),
    }
    z_true = np.where(regions['box'], TABLE_Z - 0.03, TABLE_Z)
    colour = np.broadcast_to(TABLE_RGB, (size, size, 3)).copy()
    colour[regions['box']] = (200, 60, 50)
    colour[regions['trans']] = TABLE_RGB + np.asarray(tint)
    if specular:
        colour[regions['spec']] = (230, 230, 230)
    depth, rgb = [], []
    for _ in range(n_frames):
        z = quantise(z_true + rng.standard_normal(z_true.shape) * axial_sigma(z_true))
        if specular:
            z[regions['spec']] = np.nan
        depth.append(z)
        rgb.append(np.clip(colour + rng.normal(0.0, 3.0, colour.shape), 0, 255).astype(np.uint8))
    return np.array(rgb), np.array(depth), intr, regions, (x, y)


def cell_fraction(result, region_xy_fn) -> np.ndarray:
    """Fraction of each grid cell's area inside a metric region (5 x 5 sub-samples per cell).

    The region functions below are grown by PAD (2 pixels at 0.7 m) so that a fraction of 0
    means "clear of the region" and 1 - fraction of the shrunken complement means "inside"
    despite pixel-edge effects.
    """
    g = result.geometry
    offs = (np.arange(5) + 0.5) / 5
    xs = g.origin_x + (np.arange(g.width)[:, None] + offs[None, :]).ravel() * g.resolution
    ys = g.origin_y + (np.arange(g.height)[:, None] + offs[None, :]).ravel() * g.resolution
    xx, yy = np.meshgrid(xs, ys)
    return region_xy_fn(xx, yy).reshape(g.height, 5, g.width, 5).mean(axis=(1, 3))


PAD = 2 * TABLE_Z / 570.0


def _regions(pad: float) -> dict:
    return {
        'box': lambda x, y: (np.abs(x + 0.01) < 0.03 + pad) & (np.abs(y) < 0.02 + pad),
        'trans': lambda x, y: (x >= 0.02 - pad) & (x < 0.04 + pad) & (np.abs(y) < 0.02 + pad),
        'spec': lambda x, y: (np.abs(x + 0.02) < 0.009 + pad) & (np.abs(y) < 0.009 + pad),
    }


REGION_FNS = _regions(0.0)
INNER_FNS = _regions(-PAD)  # a cell with fraction 1 of the inner region is inside for sure
OUTER_FNS = _regions(PAD)  # a cell with fraction 0 of the outer region is outside for sure


@pytest.fixture(scope='module')
def scene():
    rgb, depth, intr, regions, xy = make_scene()
    result = segment_frames(rgb, depth, intr, frame_id='camera_optical')
    fractions = {name: cell_fraction(result, fn) for name, fn in REGION_FNS.items()}
    fractions.update({name + '_in': cell_fraction(result, fn) for name, fn in INNER_FNS.items()})
    fractions.update({name + '_out': cell_fraction(result, fn) for name, fn in OUTER_FNS.items()})
    return result, regions, fractions


def test_geometry_is_a_square_metric_grid_around_box_and_transparent_part(scene):
    result, _, _ = scene
    g = result.geometry
    m = grid_cells(g.size_m[0], SensingParams())  # M from the default rule (a forced M or the cell size)
    assert g.shape == (m, m) and m >= 25 and g.frame_id == 'camera_optical'
    assert g.z == pytest.approx(TABLE_Z, abs=1e-3) and result.table_depth == g.z
    # object bounding box x in [-0.04, 0.04], y in [-0.02, 0.02]; 20 % margin on each side
    assert g.size_m[0] == pytest.approx(0.08 * 1.4, rel=0.05)
    assert g.origin_x < -0.04 - 0.01 and g.origin_x + g.size_m[0] > 0.04 + 0.01
    assert g.origin_y < -0.02 and g.origin_y + g.size_m[1] > 0.02
    assert np.allclose(result.table_color, TABLE_RGB, atol=2)
    assert result.observed.all()


def test_pixel_masks(scene):
    result, regions, _ = scene
    assert np.array_equal(result.missing_mask, regions['spec'])
    solid = regions['box'] & ~regions['spec']
    depth = result.depth_mask
    assert (depth & solid).sum() / (depth | solid).sum() > 0.97  # IoU of the depth mask with the box
    assert not depth[regions['trans']].any()  # the table is seen through the transparent part
    assert result.rgb_mask[regions['trans']].mean() > 0.95 and result.rgb_mask[solid].mean() > 0.97
    assert result.object_mask[regions['box'] | regions['trans']].mean() > 0.97
    # pixel noise: depth variance / returns on the box, inflated on the transparent part
    box_noise = np.nanmedian(result.noise_px[solid])
    assert box_noise == pytest.approx(axial_variance(TABLE_Z - 0.03) / 10, rel=0.5)
    assert np.nanmedian(result.noise_px[regions['trans']]) > 100 * box_noise
    assert np.all(np.isnan(result.noise_px[regions['spec']]))


def test_grid_occupancy_missing_and_noise_regions(scene):
    result, _, fr = scene
    box_only = (fr['box_in'] == 1) & (fr['spec_out'] == 0)
    spec = fr['spec_in'] == 1
    trans = fr['trans_in'] == 1
    table = (fr['box_out'] == 0) & (fr['trans_out'] == 0)
    assert box_only.sum() > 40 and spec.sum() >= 6 and trans.sum() >= 10
    # missing exactly where most of the cell has no depth return
    assert np.array_equal(result.missing[(fr['spec'] > 0.6) | (fr['spec'] < 0.4)],
                          fr['spec'][(fr['spec'] > 0.6) | (fr['spec'] < 0.4)] > 0.6)
    assert not result.train_mask[result.missing].any()
    # seen in depth (box, table): trained; the transparent part (an extended region seen in colour only) is
    # unknown, not trained (the GPIS prior governs it)
    assert result.train_mask[box_only | table].all() and not result.train_mask[trans].any()
    # occupancy: box and specular part (missing = object) occupied, table free
    assert np.all(result.occupancy[box_only] > 0.95) and np.all(result.occupancy[spec] == 1.0)
    assert np.all(result.occupancy[table] < 0.05)
    # the transparent part: depth sees the table and is trusted more than colour -> free in the mean
    # shape, but flagged uncertain with a high SDF noise
    assert np.all(result.occupancy[trans] < 0.5)
    assert result.uncertain[trans].all() and result.disagreement[trans].min() > 0.8
    # noise map: low on table cells whose nearest surface is certain (the box's long sides),
    # >= 100 x higher on the transparent part. Box cells next to the specular patch are not
    # certain either: their SDF depends on whether the patch is object or a hole (propagation).
    certain_table = table & (cell_fraction(result, lambda x, y: (np.abs(y) > 0.03) & (x > -0.01) & (x < 0.01)) == 1)
    assert certain_table.sum() >= 4
    low = result.noise_variance[certain_table].max()
    assert low < 1e-6  # m^2: (1 mm)^2
    assert result.noise_variance[trans].min() > 100 * low
    ring = binary_dilation(result.missing, np.ones((3, 3), bool)) & ~result.missing
    assert result.noise_variance[ring].min() > 100 * low
    assert np.all(np.isfinite(result.noise_variance)) and np.all(result.noise_variance > 0)


def test_noise_map_is_low_everywhere_without_transparent_or_specular_parts():
    rgb, depth, intr, regions, _ = make_scene(n_frames=10, tint=(0, 0, 0), specular=False)
    result = segment_frames(rgb, depth, intr)
    assert not result.missing.any() and not result.uncertain.any()
    assert result.noise_variance.max() < 1e-6
    # depth term only: axial variance (with quantisation) of a 10-frame average, table to box top
    expected = axial_variance(TABLE_Z - 0.03) / 10
    assert np.median(result.noise_variance) == pytest.approx(expected, rel=0.6)


def test_gpis_from_sensing_is_uncertain_at_the_transparent_part(scene):
    result, _, fr = scene
    occupancy = np.where(result.train_mask, np.where(result.occupancy >= 0.5, 100, 0), -1)
    noise = np.where(result.train_mask, result.noise_variance, np.nan)
    post = posterior_from_grids(occupancy, noise, result.geometry,
                                GpisParams(optimize_hyperparameters=False, signal_variance=5e-4, length_scale=0.02))
    trans = fr['trans_in'] == 1
    box = (fr['box_in'] == 1) & (fr['spec_out'] == 0)
    assert post.variance[trans].mean() > 30 * post.variance[box].mean()
    assert np.all(post.mean[box] < 0)


def test_subtle_tint_below_threshold_still_raises_noise():
    rgb, depth, intr, regions, _ = make_scene(tint=(0, 12, 12))  # colour distance 17 < adaptive threshold 20
    result = segment_frames(rgb, depth, intr)
    assert not result.rgb_mask[regions['trans']].any()
    trans = cell_fraction(result, INNER_FNS['trans']) == 1
    table = cell_fraction(result, lambda x, y: np.abs(y) > 0.03) == 1
    assert result.noise_variance[trans].min() > 10 * result.noise_variance[table].max()


def test_given_table_depth_colour_and_grid_size():
    rgb, depth, intr, _, _ = make_scene(n_frames=3)
    params = SensingParams(grid_size=40, table_depth_m=TABLE_Z, table_color=(120, 120, 120), margin=0.3)
    result = segment_frames(rgb, depth, intr, params)
    assert result.geometry.shape == (40, 40)
    assert result.table_depth == TABLE_Z
    assert result.geometry.size_m[0] == pytest.approx(0.08 * 1.6, rel=0.05)


def test_tilted_table_plane_is_fitted():
    rgb, depth, intr, regions, _ = make_scene(n_frames=4)
    u = np.arange(intr.width)[None, None, :]
    tilted = depth + 1e-4 * (u - intr.cx)  # 0.1 mm per pixel across the image
    result = segment_frames(rgb, tilted, intr)
    solid = regions['box'] & ~regions['spec']
    assert np.nanmedian(result.height[solid]) == pytest.approx(0.03, abs=2e-3)
    assert np.abs(np.nanmedian(result.height[~regions['box'] & ~regions['trans']])) < 1e-3


def test_frames_from_clouds_recovers_intrinsics_and_depth():
    rgb, depth, intr, _, _ = make_scene(n_frames=2)
    v, u = np.mgrid[0:intr.height, 0:intr.width]
    xyz = np.stack([(u - intr.cx) * depth / intr.fx, (v - intr.cy) * depth / intr.fy, depth], axis=-1)
    rgb2, depth2, intr2 = frames_from_clouds(xyz, rgb)
    assert np.array_equal(rgb2, rgb)
    assert np.array_equal(np.isnan(depth2), np.isnan(depth))
    assert np.allclose(depth2[~np.isnan(depth2)], depth[~np.isnan(depth)])
    for name in ('fx', 'fy', 'cx', 'cy'):
        assert getattr(intr2, name) == pytest.approx(getattr(intr, name), rel=1e-9)
    assert (intr2.width, intr2.height) == (intr.width, intr.height)
    a = segment_frames(rgb2, depth2, intr2)
    b = segment_frames(rgb, depth, intr)
    assert np.allclose(a.occupancy, b.occupancy, atol=1e-6)


@pytest.mark.parametrize('case, match', [
    ('float_rgb', 'uint8'),
    ('uint16_depth', 'floating point'),
    ('frame_count', 'differ'),
    ('image_size', 'differ'),
    ('intrinsics', 'intrinsics'),
    ('all_nan', 'no valid return'),
    ('no_object', 'no object found'),
    ('no_table', 'no table plane found'),
    ('edge_on', 'edge-on'),
    ('bad_shape', 'expected shape'),
    ('ragged', 'different shapes'),
])
def test_bad_input_raises_clear_value_error(case, match):
    rgb, depth, intr, _, _ = make_scene(n_frames=2)
    args = [rgb, depth, intr]
    if case == 'float_rgb':
        args[0] = rgb.astype(np.float32)
    elif case == 'uint16_depth':
        args[1] = np.nan_to_num(depth * 1000).astype(np.uint16)
    elif case == 'frame_count':
        args[1] = depth[:1]
    elif case == 'image_size':
        args[1] = depth[:, :-1]
    elif case == 'intrinsics':
        args[2] = CameraIntrinsics(570, 570, 100, 100, 320, 240)
    elif case == 'all_nan':
        args[1] = np.full_like(depth, np.nan)
    elif case == 'no_object':
        args[0] = np.full_like(rgb, 120)
        args[1] = np.full_like(depth, TABLE_Z)
    elif case == 'no_table':  # a cloud without any plane: depths scattered over 0.5 ... 1.5 m
        args[1] = np.random.default_rng(1).uniform(0.5, 1.5, depth.shape)
    elif case == 'edge_on':  # a plane seen at 85 degrees from the optical axis (a wall, or a table edge-on)
        tilt = np.radians(85.0)
        normal = np.array([0.0, -np.sin(tilt), -np.cos(tilt)])
        v, u = np.mgrid[0:intr.height, 0:intr.width]
        rays = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones(u.shape)], axis=-1)
        with np.errstate(divide='ignore'):
            z = -0.3 / (rays @ normal)
        z = np.where((z > 0) & (z < 3.0), z, np.nan)
        args[1] = np.repeat(z[None], depth.shape[0], axis=0)
    elif case == 'bad_shape':
        args[0] = rgb[..., :2]
    elif case == 'ragged':
        args[1] = [depth[0], depth[1, :-1]]
    with pytest.raises(ValueError, match=match):
        segment_frames(*args)


def test_invalid_parameters():
    with pytest.raises(ValueError):
        SensingParams(grid_size=2)
    with pytest.raises(ValueError):
        CameraIntrinsics(0.0, 570.0, 1.0, 1.0, 10, 10)
    with pytest.raises(ValueError, match='fewer than 3'):
        frames_from_clouds(np.full((1, 4, 4, 3), np.nan), np.zeros((1, 4, 4, 3), np.uint8))


# ---------------------------------------------------------------------------------------- real captures
def test_shadow_is_not_transparency():
    """Opaque box and its strong shadow on the table (darker, same chromaticity): no colour evidence and
    no uncertain cell in the shadow, while a tinted (transparent-like) patch still is uncertain."""
    from support.tilted_scene import Box, TiltedScene

    box = Box(0.0, 0.0, 0.025, 0.02, 0.04)
    scene = TiltedScene(40.0, boxes=[box], shadows=[(0.025, -0.02, 0.055, 0.02, 0.35)])
    rgb, depth, label = scene.frames(5, seed=2)
    result = segment_frames(rgb, depth, scene.intrinsics)
    _, _, lab = scene.frames(1)
    pts = scene.intrinsics.rays() * np.nanmean(depth, axis=0)[..., None]
    xy = scene.table_xy(pts)
    shadow_px = (lab == 0) & (xy[..., 0] > 0.03) & (xy[..., 0] < 0.05) & (np.abs(xy[..., 1]) < 0.015)
    assert shadow_px.sum() > 150
    assert not result.rgb_mask[shadow_px].any()
    g = result.geometry
    cxy = scene.table_xy(g.to_sensor(g.cell_centers()))
    shadow_cells = (cxy[..., 0] > 0.03) & (cxy[..., 0] < 0.05) & (np.abs(cxy[..., 1]) < 0.015)
    assert shadow_cells.sum() >= 10
    assert not result.uncertain[shadow_cells].any() and result.occupancy[shadow_cells].max() < 0.5
    assert result.noise_variance[shadow_cells].max() < 1e-5
    # the old Euclidean colour distance from the table colour would have flagged the shadow
    old_distance = np.linalg.norm(rgb.astype(float).mean(axis=0) - result.table_color, axis=-1)
    assert np.median(old_distance[shadow_px]) > 100


def test_identical_repeated_frames_count_as_one():
    rgb, depth, intr, regions, _ = make_scene(n_frames=10, tint=(0, 0, 0), specular=False)
    independent = segment_frames(rgb, depth, intr)
    repeated = segment_frames(np.repeat(rgb[:1], 10, axis=0), np.repeat(depth[:1], 10, axis=0), intr)
    assert independent.effective_frames == pytest.approx(10, rel=0.25)
    assert repeated.effective_frames == 1.0
    solid = regions['box']
    ratio = np.nanmedian(repeated.noise_px[solid]) / np.nanmedian(independent.noise_px[solid])
    assert ratio == pytest.approx(independent.effective_frames, rel=0.3)  # a repeat is not 10 measurements


def test_sensor_models():
    from gpis_grasp_ros.core.noise_model import SensorModel, effective_frame_count

    d400 = SensorModel.named('realsense_d400')
    assert d400.sigma(1.0) == pytest.approx(0.08 / (424.0 * 0.050), rel=1e-9)  # Intel RMS formula, 3.8 mm
    assert d400.sigma(0.5) == pytest.approx(d400.sigma(1.0) / 4)  # grows with z^2
    assert SensorModel.named('carmine').sigma(0.7) == pytest.approx(axial_sigma(0.7))
    custom = SensorModel('custom', 0.001, 0.0, 0.0, 0.002, 0.0, 0.0005)
    assert custom.sigma(2.0) == pytest.approx(0.009) and custom.quantisation(2.0) == 0.0005
    with pytest.raises(ValueError):
        SensorModel('custom', -1.0)
    # the second viewpoint whose shadow has no return: Carmine's projector, the D435's right imager
    assert (SensorModel.named('carmine').occluder_x_m, d400.occluder_x_m) == (0.075, 0.050)
    for bad in (float('nan'), float('inf'), 1.5):
        with pytest.raises(ValueError, match='occluder'):
            SensorModel('custom', 0.001, occluder_x_m=bad)
    with pytest.raises(ValueError, match='unknown sensor'):
        SensorModel.named('kinect_v9')
    rng = np.random.default_rng(0)
    frames = 0.8 + d400.sigma(0.8) * rng.standard_normal((6, 40, 40))
    assert effective_frame_count(frames, d400) == pytest.approx(6, rel=0.15)
    two_distinct = np.concatenate([np.repeat(frames[:1], 3, axis=0), np.repeat(frames[1:2], 3, axis=0)])
    assert effective_frame_count(two_distinct, d400) == pytest.approx(2, rel=0.25)


def test_propagated_variance_is_capped_in_extent():
    rgb, depth, intr, _, _ = make_scene()
    near = segment_frames(rgb, depth, intr, SensingParams(propagation_radius_m=0.01))
    far = segment_frames(rgb, depth, intr, SensingParams(propagation_radius_m=1.0))
    g = near.geometry
    dist = cv2.distanceTransform((~near.uncertain).astype(np.uint8), cv2.DIST_L2, 5) * g.resolution
    beyond = dist > 0.01 + g.resolution
    assert beyond.sum() > 50
    assert near.noise_variance[beyond].max() < 1e-5
    assert far.noise_variance[beyond].max() > 10 * near.noise_variance[beyond].max()
