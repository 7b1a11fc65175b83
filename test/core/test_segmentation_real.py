"""Segmentation pieces made for real captures: splitting touching objects, the seen-through
interior of a transparent target, the chromatic extension of a clear body, and the colour model's options
(a shadow still is no evidence).

Synthetic rasters with analytic shapes, and the analytic tilted renderer of ``tilted_scene``.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from gpis_grasp_ros.core.sensing import (
    SensingParams,
    chromatic_extension,
    chromaticity_distance,
    seen_through,
    segment_frames,
    split_flat_support,
    split_touching,
)
from gpis_grasp_ros.core.sensing.clear_body import _bounded_extension
from gpis_grasp_ros.core.sensing.evidence import _colour_model
from gpis_grasp_ros.core.sensing.objects import _Raster
from gpis_grasp_ros.core.sensing.params import FLAT_JUMP_M, FLAT_STEP_M
from support.tilted_scene import Box, Cylinder, TiltedScene

RES = 0.004  # m per raster cell, the scale of the real captures' rasters (2 pixel footprints)


def _disc(shape: tuple[int, int], centre: tuple[float, float], radius: float) -> np.ndarray:
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    return (xx - centre[0]) ** 2 + (yy - centre[1]) ** 2 <= radius ** 2


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


@pytest.mark.parametrize('overlap', [1.0, 2.0, 3.0])
def test_two_touching_discs_are_split_into_two_objects(overlap):
    """Two discs of radius 12 and 9 cells overlapping by ``overlap`` cells (contact half-width <= 5.3
    cells: the small disc is >= 3.7 cells deeper than the contact, more than the 2.5-cell neck of 1 cm at
    4 mm cells) form one component; the split gives two labels, each (nearly) one disc."""
    a = _disc((60, 80), (25.0, 30.0), 12.0)
    b = _disc((60, 80), (25.0 + 12.0 + 9.0 - overlap, 30.0), 9.0)
    _, labels = cv2.connectedComponents((a | b).astype(np.uint8), connectivity=8)
    assert labels.max() == 1
    out, origin = split_touching(labels, 0.01 / RES)
    parts = [out == lab for lab in np.unique(out[out > 0])]
    assert len(parts) == 2
    assert sorted(origin[np.unique(out[out > 0])]) == [1, 1]  # both parts remember the component they came from
    best_a = max(_iou(p, a & ~b) for p in parts)
    best_b = max(_iou(p, b & ~a) for p in parts)
    assert best_a > 0.9 and best_b > 0.85
    assert (out > 0).sum() == (a | b).sum()  # no cell lost


def test_discs_overlapping_more_than_the_neck_allows_stay_one_object():
    """Overlap 5 cells: contact half-width 6.7 cells, the small disc only 2.3 cells deeper (< 2.5): one object."""
    a = _disc((60, 80), (25.0, 30.0), 12.0)
    b = _disc((60, 80), (41.0, 30.0), 9.0)
    _, labels = cv2.connectedComponents((a | b).astype(np.uint8), connectivity=8)
    assert np.array_equal(split_touching(labels, 0.01 / RES)[0], labels)


def test_one_object_with_a_narrow_part_stays_whole():
    """A bottle lying down (body 40 x 16 cells, neck 8 x 6 cells), a disc, a ring and a thin bar: no split."""
    shape = (60, 100)
    bottle = np.zeros(shape, bool)
    bottle[22:38, 20:60] = True
    bottle[27:33, 60:68] = True
    ring = _disc(shape, (85.0, 15.0), 10.0) & ~_disc(shape, (85.0, 15.0), 6.0)
    disc = _disc(shape, (85.0, 45.0), 10.0)
    bar = np.zeros(shape, bool)
    bar[50:53, 5:60] = True
    n, labels = cv2.connectedComponents((bottle | ring | disc | bar).astype(np.uint8), connectivity=8)
    out, origin = split_touching(labels, 0.01 / RES)
    assert np.array_equal(out, labels) and len(origin) == n


def test_dumbbell_split_depends_on_how_much_wider_than_the_neck_the_parts_are():
    """Two discs (radius 10 cells) joined by a bar 2 h wide: split when the discs are wider than the neck by
    more than the neck parameter (radius), not when the parameter exceeds that difference."""
    shape = (40, 80)
    img = _disc(shape, (18.0, 20.0), 10.0) | _disc(shape, (60.0, 20.0), 10.0)
    img[17:24, 18:60] = True  # neck half-width ~3.5 cells: dynamic ~6.5 cells
    _, labels = cv2.connectedComponents(img.astype(np.uint8), connectivity=8)
    assert len(np.unique(split_touching(labels, 4.0)[0])) == 3  # background + two parts
    assert len(np.unique(split_touching(labels, 8.0)[0])) == 2  # kept whole


def test_object_standing_next_to_a_flat_support_is_split_from_it():
    """A notebook (flat, 12 mm, 1 mm noise) and a taller box (30-70 mm, rough) in contact: two objects.
    A box's flat top with its walls' feet *below* it, or a flat object alone, is not split."""
    rng = np.random.default_rng(0)
    shape = (50, 70)
    notebook = np.zeros(shape, bool)
    notebook[5:45, 5:40] = True  # 40 x 35 cells = 224 cm^2
    box = np.zeros(shape, bool)
    box[15:30, 40:52] = True  # touches the notebook's edge
    height = np.full(shape, np.nan)
    height[notebook] = 0.012 + 0.001 * rng.standard_normal(notebook.sum())
    height[box] = rng.uniform(0.03, 0.07, box.sum())
    _, labels = cv2.connectedComponents((notebook | box).astype(np.uint8), connectivity=8)
    out, origin = split_flat_support(labels, height, RES)
    labs = np.unique(out[out > 0])
    assert len(labs) == 2 and set(origin[labs]) == {1}
    owner_nb = np.bincount(out[notebook]).argmax()
    owner_box = np.bincount(out[box]).argmax()
    assert owner_nb != owner_box
    assert np.mean(out[notebook] == owner_nb) > 0.97 and np.mean(out[box] == owner_box) > 0.9

    # a 40 mm box seen at a tilt: flat top, the feet of its front wall (heights 0-40 mm) in front of it
    top = np.zeros(shape, bool)
    top[10:40, 10:50] = True
    walls = np.zeros(shape, bool)
    walls[40:43, 10:50] = True
    h2 = np.full(shape, np.nan)
    h2[top] = 0.04 + 0.001 * rng.standard_normal(top.sum())
    h2[walls] = rng.uniform(0.0, 0.04, walls.sum())
    _, lab2 = cv2.connectedComponents((top | walls).astype(np.uint8), connectivity=8)
    assert np.array_equal(split_flat_support(lab2, h2, RES)[0], lab2)
    # a flat object alone
    _, lab3 = cv2.connectedComponents(notebook.astype(np.uint8), connectivity=8)
    assert np.array_equal(split_flat_support(lab3, np.where(notebook, height, np.nan), RES)[0], lab3)


def _crest_span(radius: float, res: float) -> float:
    """Height span (m) of a lying cylinder's smooth crest: the cells whose neighbours' heights r + sqrt(r^2 - y^2)
    differ by at most FLAT_STEP_M at cell size ``res``, |y| <= r s / sqrt(1 + s^2) with s = FLAT_STEP_M / res."""
    return radius * (1.0 - 1.0 / np.sqrt(1.0 + (FLAT_STEP_M / res) ** 2))


def _lying_radius(res: float) -> float:
    """A lying cylinder's radius (m) whose smooth crest spans 1.25 FLAT_JUMP_M at cell size ``res``."""
    return 1.25 * FLAT_JUMP_M / _crest_span(1.0, res)


def test_lying_cylinder_with_a_taller_end_cap_is_no_flat_support():
    """Top-down cell heights of a lying cylinder (radius 1.25 x the radius whose smooth crest spans FLAT_JUMP_M,
    25 cm long) and a head 8 mm wider in radius (4 cm long, its crest 16 mm higher), 1 mm noise: the body's smooth
    crest covers more than FLAT_MIN_AREA_M2 but is not flat, so the cylinder stays one object. A box standing on
    a flat slab (its top 5 cm above the slab's 12 mm) is still split from it."""
    rng = np.random.default_rng(0)
    r = _lying_radius(RES)
    r_head = r + 0.008
    ny, nx = int(np.ceil(2 * r_head / RES)) + 4, 80
    yy, xx = np.mgrid[:ny, :nx]
    y = (yy + 0.5) * RES - ny * RES / 2
    body = (xx >= 5) & (xx < 67) & (np.abs(y) < r)
    head = (xx >= 67) & (xx < 77) & (np.abs(y) < r_head)
    height = np.full((ny, nx), np.nan)
    height[body] = r + np.sqrt(r ** 2 - y[body] ** 2)
    height[head] = r_head + np.sqrt(r_head ** 2 - y[head] ** 2)
    height += 0.001 * rng.standard_normal(height.shape)
    _, labels = cv2.connectedComponents((body | head).astype(np.uint8), connectivity=8)
    assert _crest_span(r, RES) > FLAT_JUMP_M and 2 * (r_head - r) > FLAT_JUMP_M
    assert np.array_equal(split_flat_support(labels, height, RES)[0], labels)

    slab = np.zeros((60, 60), bool)
    slab[5:55, 5:55] = True  # 20 x 20 cm
    box = np.zeros_like(slab)
    box[22:38, 25:37] = True  # 6.4 x 4.8 cm, standing on the slab
    h2 = np.where(slab, 0.012, np.nan) + 0.001 * rng.standard_normal(slab.shape)
    h2[box] = 0.062 + 0.001 * rng.standard_normal(box.sum())
    _, lab2 = cv2.connectedComponents(slab.astype(np.uint8), connectivity=8)
    out, _ = split_flat_support(lab2, h2, RES)
    owner_box = np.bincount(out[box]).argmax()
    assert len(np.unique(out[slab])) == 2 and np.mean(out[box] == owner_box) > 0.9
    assert np.mean(out[slab & ~box] != owner_box) > 0.97


@pytest.mark.parametrize('tilt', [0.0, 30.0, 45.0, 60.0])
def test_lying_cylinder_with_a_taller_end_cap_stays_one_object(tilt):
    """Rendered at tilts 0-60 degrees (10 Carmine frames at 0.8 m): a lying cylinder whose smooth crest spans
    1.25 FLAT_JUMP_M at the raster's cells (two pixel footprints) and a head 8 mm wider in radius is one object."""
    res = 2.0 * 0.8 / 570.0 / np.cos(np.radians(tilt))
    r = _lying_radius(res)
    body = Cylinder(-0.10, 0.06, 0.0, r)
    head = Cylinder(0.06, 0.10, 0.0, r + 0.008, rgb=(90.0, 90.0, 90.0))
    scene = TiltedScene(tilt, cylinders=[body, head])
    rgb, depth, label = scene.frames(10, seed=int(tilt))
    result = segment_frames(rgb, depth, scene.intrinsics, SensingParams(max_opening_m=0.0))
    assert result.objects_seen == 1
    assert result.object_mask[label > 0].mean() > 0.95 and result.object_mask[label == 2].mean() > 0.95


def _raster_pixels(mask: np.ndarray) -> tuple[_Raster, np.ndarray]:
    """A raster whose cells are the labels of ``mask`` and one 'pixel' per cell (its foot = the cell centre)."""
    labels = mask.astype(np.int32)
    raster = _Raster(np.zeros(2), RES, labels)
    yy, xx = np.mgrid[:mask.shape[0], :mask.shape[1]]
    foot = (np.stack([xx, yy], axis=-1) + 0.5) * RES
    return raster, foot


def test_a_ring_of_evidence_gets_its_interior_filled():
    """A clear object's outline (a ring 2 cells thick with a 3-cell gap) around a see-through interior:
    the interior's table-level pixels are returned; the table outside is not."""
    shape = (60, 60)
    outer, inner = _disc(shape, (30.0, 30.0), 20.0), _disc(shape, (30.0, 30.0), 18.0)
    ring = outer & ~inner
    ring[28:31, 47:52] = False  # a 3-cell gap in the outline (closed: 2 x 0.006 m / 4 mm = 3 cells)
    raster, foot = _raster_pixels(ring)
    px_labels = ring.astype(np.int64)
    table_level = ~ring
    through = seen_through(raster, 1, foot, px_labels, table_level, 0.006)
    interior = inner & ~ring
    assert through[interior].mean() > 0.97
    assert not through[~outer].any() and not through[ring].any()
    # a pixel of another object inside the ring is not taken
    px_labels[30, 30] = 2
    assert not seen_through(raster, 1, foot, px_labels, table_level, 0.006)[30, 30]


def test_open_outline_and_solid_component():
    """A C-shape whose opening (10 cells) is far wider than the closing disc is not closed: nothing inside is
    returned. A solid component has no interior: nothing is returned."""
    shape = (60, 60)
    outer, inner = _disc(shape, (30.0, 30.0), 20.0), _disc(shape, (30.0, 30.0), 17.0)
    c_shape = outer & ~inner
    c_shape[25:36, 40:] = False
    raster, foot = _raster_pixels(c_shape)
    through = seen_through(raster, 1, foot, c_shape.astype(np.int64), ~c_shape, 0.006)
    assert through.sum() < 0.05 * (inner.sum())
    solid = outer
    raster, foot = _raster_pixels(solid)
    none = seen_through(raster, 1, foot, solid.astype(np.int64), solid, 0.006)
    assert not none.any()


def test_colour_model_rejects_a_shadow_and_flags_a_clear_object():
    """Textured table (brightness +-8 %, RGB noise), a shadow at 40 % brightness, a less saturated
    (clear-object) patch: robust statistics give a threshold that passes the texture and the shadow
    as table and flags the desaturated patch."""
    rng = np.random.default_rng(1)
    t = np.array([52.0, 144.0, 176.0])  # the blue cloth of capture 000000080
    tex = rng.uniform(0.92, 1.08, (80, 80))[..., None] * t + 3.0 * rng.standard_normal((80, 80, 3))
    model = _colour_model(tex, np.ones((80, 80), bool), SensingParams())
    assert np.allclose(model.table_rgb, t, atol=6.0)
    p_tex, _ = model.evidence(tex)
    assert np.mean(p_tex > 0.5) < 0.01
    p_shadow, ratio = model.evidence(0.4 * tex)
    assert np.mean(p_shadow > 0.5) < 0.01 and np.all(ratio < model.dark_ratio)
    clear = 0.5 * tex + 0.5 * np.array([170.0, 175.0, 180.0])  # table seen through clear plastic: desaturated
    p_clear, _ = model.evidence(clear)
    assert np.mean(p_clear > 0.5) > 0.95


def test_shadow_rejected_by_the_colour_model():
    """The shadow-line colour model keeps a strong shadow out of the colour evidence and out of the uncertain
    cells."""
    box = Box(0.0, 0.0, 0.025, 0.02, 0.04)
    scene = TiltedScene(40.0, boxes=[box], shadows=[(0.025, -0.02, 0.055, 0.02, 0.35)])
    rgb, depth, _ = scene.frames(3, seed=2)
    params = SensingParams()
    result = segment_frames(rgb, depth, scene.intrinsics, params)
    pts = scene.intrinsics.rays() * np.nanmean(depth, axis=0)[..., None]
    xy = scene.table_xy(pts)
    _, _, lab = scene.frames(1)
    shadow_px = (lab == 0) & (xy[..., 0] > 0.03) & (xy[..., 0] < 0.05) & (np.abs(xy[..., 1]) < 0.015)
    assert shadow_px.sum() > 150 and not result.rgb_mask[shadow_px].any()
    g = result.geometry
    cxy = scene.table_xy(g.to_sensor(g.cell_centers()))
    shadow_cells = (cxy[..., 0] > 0.03) & (cxy[..., 0] < 0.05) & (np.abs(cxy[..., 1]) < 0.015)
    assert shadow_cells.sum() >= 5 and not result.uncertain[shadow_cells].any()


def test_box_next_to_a_notebook_is_isolated_end_to_end():
    """Tilted camera (45 degrees): a 5 cm box standing against the edge of a 12 mm notebook. The notebook
    reaches the image border; the box, picked by a pixel, is its own object and its grid excludes the notebook."""
    notebook = Box(-0.3, 0.0, 0.3, 0.07, 0.012, rgb=(40.0, 120.0, 160.0))
    box = Box(0.025, 0.0, 0.025, 0.02, 0.05, rgb=(200.0, 190.0, 60.0))
    scene = TiltedScene(45.0, boxes=[notebook, box])
    rgb, depth, label = scene.frames(3, seed=4)
    uv = scene.intrinsics.project(scene.to_camera(np.array([0.025, 0.0]), 0.05)[None])[0]
    assert label[int(round(uv[1])), int(round(uv[0]))] == 2
    assert (label == 1)[:, :3].any() or (label == 1)[:, -3:].any() or (label == 1)[-3:, :].any()
    params = SensingParams(target='pixel', target_point=(float(uv[0]), float(uv[1])))
    result = segment_frames(rgb, depth, scene.intrinsics, params)
    assert result.objects_seen >= 2
    assert np.mean(label[result.object_mask] == 2) > 0.9  # the target's pixels are the box's
    g = result.geometry
    cxy = scene.table_xy(g.to_sensor(g.cell_centers()))
    occupied = result.occupancy >= 0.5
    in_box = (np.abs(cxy[..., 0] - 0.025) <= 0.025 + 0.004) & (np.abs(cxy[..., 1]) <= 0.02 + 0.004)
    assert occupied.sum() >= 10 and np.mean(in_box[occupied]) > 0.9
    assert g.size_m[0] < 0.12  # a grid around the 5 x 4 cm box, not the notebook


@pytest.mark.parametrize('tilt', [20.0, 45.0])
def test_an_object_in_contact_is_uncertain_table_in_the_targets_grid(tilt):
    """The box against the notebook, and a second box beyond 10 mm of table with table seen between them.
    Where the notebook touches the target the line between them is a split, not a measurement: the
    notebook's cells in the target's grid are uncertain but trained (table by hypothesis, not unknown), with
    at least half the disagreement variance; the separate box and the open table are measured table."""
    notebook = Box(-0.3, 0.0, 0.3, 0.07, 0.012, rgb=(40.0, 120.0, 160.0))
    box = Box(0.025, 0.0, 0.025, 0.02, 0.05, rgb=(200.0, 190.0, 60.0))
    apart = Box(0.025, 0.04, 0.02, 0.01, 0.03, rgb=(60.0, 160.0, 70.0))  # 10 mm of table from the target
    scene = TiltedScene(tilt, boxes=[notebook, box, apart])
    rgb, depth, label = scene.frames(3, seed=4)
    uv = scene.intrinsics.project(scene.to_camera(np.array([0.025, 0.0]), 0.05)[None])[0]
    params = SensingParams(target='pixel', target_point=(float(uv[0]), float(uv[1])))
    result = segment_frames(rgb, depth, scene.intrinsics, params)
    assert np.mean(label[result.object_mask] == 2) > 0.9
    g = result.geometry
    cxy = scene.table_xy(g.to_sensor(g.cell_centers()))
    x, y = cxy[..., 0], cxy[..., 1]
    on_notebook = (x < -0.008) & (np.abs(y) < 0.06) & result.observed
    on_apart = (np.abs(x - 0.025) < 0.012) & (y > 0.032) & result.observed
    open_table = (x > 0.053) & (np.abs(y) < 0.015) & result.observed  # the side away from the notebook
    assert on_notebook.sum() >= 20 and on_apart.sum() >= 3 and open_table.sum() >= 10
    assert np.mean(result.uncertain[on_notebook]) > 0.9 and result.train_mask[on_notebook].all()
    assert np.all(result.occupancy[on_notebook] < 0.5)
    assert np.median(result.noise_variance[on_notebook]) >= 0.5 * params.disagreement_variance_m2
    for measured in (on_apart, open_table):
        assert not result.uncertain[measured].any()
        assert np.median(result.noise_variance[measured]) < 0.1 * params.disagreement_variance_m2


def _cloth(shape: tuple[int, int], seed: int) -> np.ndarray:
    """The blue cloth of capture 000000080: brightness texture +-8 %, RGB noise of 3 units."""
    rng = np.random.default_rng(seed)
    t = np.array([52.0, 144.0, 176.0])
    return rng.uniform(0.92, 1.08, shape)[..., None] * t + 3.0 * rng.standard_normal(shape + (3,))


def test_chromaticity_distance_ignores_shadows_and_flags_a_body_seen_through():
    """On the cloth: a 40 % shadow and a 30 % highlight of the cloth's colour stay at the table's level
    (brightness is not chromaticity); the cloth seen through clear plastic (half mixed with grey) is far
    above; pixels too dark for a chromaticity get z = 0."""
    tex = _cloth((120, 120), 3)
    img = tex.copy()
    img[10:50, 10:50] *= 0.4  # shadow
    img[10:50, 70:110] = np.minimum(img[10:50, 70:110] * 1.3, 255.0)  # highlight of the same colour
    img[70:110, 10:50] = 0.5 * img[70:110, 10:50] + 0.5 * np.array([170.0, 175.0, 180.0])  # seen through plastic
    img[70:110, 70:110] = 5.0  # black
    train = np.zeros((120, 120), bool)
    train[:, 55:65] = True
    train[55:65, :] = True
    z, med, scale = chromaticity_distance(np.clip(img, 0, 255), train)
    inner = (slice(14, 46), slice(14, 46)), (slice(14, 46), slice(74, 106)), (slice(74, 106), slice(14, 46))
    for sl in inner[:2]:  # the shadow's chromaticity is noisier (same RGB noise, less light), not shifted
        assert np.median(z[sl]) < 1.0 and np.percentile(z[sl], 95) < 3.0
    assert z[inner[2]].min() > 10.0
    assert np.all(z[74:106, 74:106] == 0.0) and scale > 0
    # a reddish tint of 15 units is also seen (another hue), whatever its brightness
    tinted = tex * 0.6 + np.array([15.0, 0.0, 0.0])
    z2 = chromaticity_distance(np.vstack([tex, tinted]), np.vstack([train, np.zeros_like(train)]))[0]
    assert np.median(z2[120:]) > 3.0


def test_chromatic_extension_grows_only_thick_regions_touching_the_target():
    """Target = a specular stripe; a thick chromatic body next to it (20 x 70 px, with an enclosed gap) is returned
    whole; a chromatic patch elsewhere (not touching the target), a 2-pixel band of mixed pixels along the
    stripe's other side and pixels that are not candidates (another object) are not."""
    shape = (100, 120)
    target = np.zeros(shape, bool)
    target[40:43, 20:90] = True
    z = np.zeros(shape)
    body = np.zeros(shape, bool)
    body[43:63, 20:90] = True  # the body below the stripe
    z[body] = 5.0
    z[30:38, 20:90] = 5.0  # beyond a gap: does not touch the target
    z[38:40, 20:90] = 0.0
    z[80:95, 100:115] = 5.0  # elsewhere
    z[38:40, 20:90] = 5.0  # 2-px band above the stripe ...
    z[30:38, 20:90] = 0.0  # ... with nothing behind it
    z[50:54, 50:60] = 0.0  # a gap enclosed by the body (a label, a highlight): filled
    candidate = np.ones(shape, bool)
    ext = chromatic_extension(target, candidate, z, 1.5)
    assert ext[body].mean() > 0.99 and ext[50:54, 50:60].all()  # (the 3 x 3 opening rounds two corners)
    assert not ext[38:40].any() and not ext[80:95, 100:115].any() and not ext[target].any()
    assert not chromatic_extension(target, candidate, z, 6.0).any()  # under the threshold: nothing
    # another object's pixels (not candidates) cut the body off the target: the growth stops at them
    blocked = candidate.copy()
    blocked[43:47, :] = False
    assert not chromatic_extension(target, blocked, z, 1.5).any()


def test_a_clear_slab_seen_through_is_recovered_and_an_opaque_box_is_not_grown():
    """Tilted camera (45 degrees), default table: an opaque box is segmented the same with the
    chromatic extension on and off (its shadow and edges are not a body seen through); a clear slab whose
    depth is the table's, seen as a desaturated patch with a specular stripe (depth holes) along its middle,
    is recovered from the stripe to the whole patch (plus the halo of the image smoothing, <= 4 px, and a few
    texture-noise pixels)."""
    box = Box(0.0, 0.0, 0.025, 0.02, 0.04, rgb=(200.0, 190.0, 60.0))
    scene = TiltedScene(45.0, boxes=[box], shadows=[(0.025, -0.02, 0.055, 0.02, 0.4)])
    rgb, depth, _ = scene.frames(1, seed=5)
    on = segment_frames(rgb, depth, scene.intrinsics, SensingParams())
    off = segment_frames(rgb, depth, scene.intrinsics, SensingParams(chroma_z_min=0.0))
    assert np.array_equal(on.object_mask, off.object_mask) and np.array_equal(on.occupancy, off.occupancy)
    # the clear slab: table depth everywhere but a stripe of holes; colour desaturated over 50 x 24 mm
    empty = TiltedScene(45.0, boxes=[])
    rgb, depth, _ = empty.frames(1, seed=6)
    rgb, depth = rgb[0].astype(np.float64), depth[0].copy()
    xy = empty.table_xy(empty.intrinsics.rays() * depth[..., None])
    slab = (np.abs(xy[..., 0]) < 0.04) & (np.abs(xy[..., 1]) < 0.02)
    stripe = slab & (np.abs(xy[..., 1]) < 0.004)
    rgb[slab] = 0.5 * rgb[slab] + 0.5 * np.array([170.0, 175.0, 180.0])
    depth[stripe] = np.nan
    v, u = (int(c.mean()) for c in np.nonzero(stripe))
    params = SensingParams(target='pixel', target_point=(u, v), transparent_close_m=0.001, color_threshold_min=200.0)
    res_off = segment_frames(rgb.astype(np.uint8), depth, empty.intrinsics,
                             dataclasses.replace(params, chroma_z_min=0.0))
    res_on = segment_frames(rgb.astype(np.uint8), depth, empty.intrinsics, params)
    assert _iou(res_off.object_mask, slab) < 0.4  # the stripe: 8 of the 24 mm
    halo = cv2.dilate(slab.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0  # the image smoothing's 4-px halo
    assert res_on.object_mask[slab].mean() > 0.95 and (res_on.object_mask & ~halo).sum() < 0.01 * slab.sum()
    assert _iou(res_on.object_mask, slab) > 0.6 > _iou(res_off.object_mask, slab)


def test_an_extension_running_out_of_the_image_is_dropped():
    """A chromatic region that reaches the image (or pixel ROI) border is the table's colour changing, not the
    enclosed body of the target: nothing is added; one inside the image is kept whole."""
    target = np.zeros((60, 80), bool)
    target[28:31, 20:40] = True
    inside = np.zeros_like(target)
    inside[31:45, 20:40] = True
    out = inside.copy()
    out[31:60, 20:40] = True  # down to the last row
    params = SensingParams()
    assert np.array_equal(_bounded_extension(target, inside, params), inside)
    assert not _bounded_extension(target, out, params).any()
    roi = dataclasses.replace(params, roi_px=(0, 0, 79, 42))  # the ROI's lower edge cuts the inside region
    assert not _bounded_extension(target, inside, roi).any()


def _clear_slab_frame(half_width: float, tint_box: Box | None = None) -> tuple[np.ndarray, np.ndarray, TiltedScene,
                                                                              np.ndarray, np.ndarray]:
    """A clear slab (80 mm x 2 ``half_width``) lying on the table at 45 degrees: the table's depth everywhere but a
    stripe of holes along its middle, its colour desaturated; with ``tint_box``, an opaque box with a patch of the
    same tint on the table beside it. Returns rgb, depth, scene, the slab's and the table's (x, y) per pixel."""
    scene = TiltedScene(45.0, boxes=[] if tint_box is None else [tint_box])
    rgb, depth, _ = scene.frames(1, seed=6)
    rgb, depth = rgb[0].astype(np.float64), depth[0].copy()
    xy = scene.table_xy(scene.intrinsics.rays() * depth[..., None])
    slab = (np.abs(xy[..., 0]) < 0.04) & (np.abs(xy[..., 1] - 0.03) < half_width)
    stripe = slab & (np.abs(xy[..., 1] - 0.03) < 0.004)
    tinted = slab.copy()
    if tint_box is not None:  # a tinted patch on the table touching the box's -x side
        tinted |= ((xy[..., 0] > tint_box.x - tint_box.half_x - 0.03) & (xy[..., 0] < tint_box.x - tint_box.half_x)
                   & (np.abs(xy[..., 1] - tint_box.y) < 0.015))
    rgb[tinted] = 0.5 * rgb[tinted] + 0.5 * np.array([170.0, 175.0, 180.0])
    depth[stripe] = np.nan
    return rgb.astype(np.uint8), depth, scene, slab, xy


def _pixel_at(xy: np.ndarray, x: float, y: float) -> tuple[float, float]:
    v, u = np.unravel_index(np.argmin(np.hypot(xy[..., 0] - x, xy[..., 1] - y)), xy.shape[:2])
    return float(u), float(v)


def test_a_target_pixel_on_a_clear_body_seen_through_selects_it():
    """A click on the body of a clear slab, 20 mm from the only part with depth evidence (its specular stripe, more
    than target_tolerance_m away), selects the slab and gives the same object as a click on the stripe; a click on
    the bare table as far away is refused as before, and so is a click on a tinted patch that touches only an
    opaque box (the link is to clear objects, whose body the segmentation grows over such pixels)."""
    rgb, depth, scene, slab, xy = _clear_slab_frame(0.026)
    params = SensingParams(target='pixel', target_point=(0.0, 0.0), transparent_close_m=0.001,
                           color_threshold_min=200.0)
    on_stripe = segment_frames(rgb, depth, scene.intrinsics,
                               dataclasses.replace(params, target_point=_pixel_at(xy, 0.0, 0.03)))
    on_body = segment_frames(rgb, depth, scene.intrinsics,
                             dataclasses.replace(params, target_point=_pixel_at(xy, 0.02, 0.05)))
    assert on_body.object_mask[slab].mean() > 0.95
    assert np.array_equal(on_body.object_mask, on_stripe.object_mask)
    with pytest.raises(ValueError, match='on no object'):
        segment_frames(rgb, depth, scene.intrinsics,
                       dataclasses.replace(params, target_point=_pixel_at(xy, 0.02, -0.01)))
    box = Box(0.0, -0.04, 0.015, 0.015, 0.03, rgb=(200.0, 190.0, 60.0))
    rgb, depth, scene, slab, xy = _clear_slab_frame(0.026, tint_box=box)
    segment_frames(rgb, depth, scene.intrinsics, dataclasses.replace(params, target_point=_pixel_at(xy, 0.0, 0.03)))
    with pytest.raises(ValueError, match='on no object'):
        segment_frames(rgb, depth, scene.intrinsics,
                       dataclasses.replace(params, target_point=_pixel_at(xy, box.x - box.half_x - 0.025, box.y)))
