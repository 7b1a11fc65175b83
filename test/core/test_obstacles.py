"""Other objects in the target's grid are obstacles: the jaws neither start in them nor close through them.

The world the jaws move in is ``min(target SDF, obstacle distance)`` (core.sdf_bank); a contact on an obstacle
makes the trial invalid (core.contacts); the planners keep out of obstacles; segmentation marks the other
objects' cells and the pipeline carries them into the posterior.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from gpis_grasp_ros.core.contacts import find_contacts
from gpis_grasp_ros.core.gripper import GripperParams
from gpis_grasp_ros.core.pipeline import (
    obstacle_distance,
    posterior_from_grids,
    publishable_grids,
    publishable_obstacles,
)
from gpis_grasp_ros.core.planners import PlannerParams, plan
from gpis_grasp_ros.core.quality import draw_shape_samples, probability_force_closure
from gpis_grasp_ros.core.sdf_bank import SdfBank, bilinear
from support.synthetic_shapes import disc_sdf, make_geometry, make_posterior, rectangle_sdf


def test_the_bank_is_the_minimum_of_shape_and_obstacles_by_both_constructions():
    rng = np.random.default_rng(3)
    g = make_geometry(20, 0.004)
    mean = disc_sdf(g, (0.04, 0.04), 0.015)
    dev = 0.002 * rng.standard_normal((6, g.height * g.width))
    obstacles = rectangle_sdf(g, (0.07, 0.04), (0.006, 0.02))
    direct = SdfBank(mean[None] + dev.reshape(6, *g.shape), g, obstacles=obstacles)
    assert np.array_equal(direct.sdfs, np.minimum(mean[None] + dev.reshape(6, *g.shape), obstacles[None]))
    fused = SdfBank.from_deviations(mean, dev, g, obstacles=obstacles)
    assert np.array_equal(fused.padded, direct.padded)
    plain = SdfBank.from_deviations(mean, dev, g)  # no obstacle: the sums' bits unchanged
    assert np.array_equal(plain.padded, SdfBank(mean[None] + dev.reshape(6, *g.shape), g).padded)
    with pytest.raises(ValueError, match='obstacle distance'):
        SdfBank(mean, g, obstacles=obstacles[:-1])


def _disc_and_box():
    """A 15 mm disc at the centre of a 0.1 m grid and a 15 x 40 mm box 5 mm to its right."""
    g = make_geometry(40, 0.0025)
    target = disc_sdf(g, (0.05, 0.05), 0.015)
    box = rectangle_sdf(g, (0.0775, 0.05), (0.0075, 0.02))
    return g, target, box


def test_a_jaw_closing_through_an_obstacle_is_invalid_and_one_clear_of_it_unchanged():
    g, target, box = _disc_and_box()
    gripper = GripperParams()
    world = SdfBank(target, g, obstacles=box)
    alone = SdfBank(target, g)
    # along x the right jaw meets the box first
    jaw1, jaw2 = np.array([0.005, 0.05]), np.array([0.095, 0.05])
    assert find_contacts(alone, jaw1, jaw2, gripper).valid
    through = find_contacts(world, jaw1, jaw2, gripper)
    assert through.on_obstacle and not through.valid
    assert abs(float(through.c2[0]) - 0.085) < 0.5 * g.resolution  # stopped at the box's far face
    # along y the jaw faces stay 17 mm from the box: the same contacts as without it
    jaw1, jaw2 = np.array([0.05, 0.005]), np.array([0.05, 0.095])
    clear, ref = find_contacts(world, jaw1, jaw2, gripper), find_contacts(alone, jaw1, jaw2, gripper)
    assert clear.valid and not clear.on_obstacle
    assert np.allclose(clear.c1, ref.c1, atol=1e-12) and np.allclose(clear.c2, ref.c2, atol=1e-12)
    # a jaw put down on the box starts inside the world
    inside = find_contacts(world, np.array([0.0, 0.05]), np.array([0.078, 0.05]), gripper)
    assert inside.start_inside and not inside.valid


def _boxed_in_bar(with_obstacles: bool):
    """A certain 110 x 24 mm bar (longer than the 90 mm opening: grasped across only), with (optionally) a box
    lying against each long side from its left end to 25 mm short of its right end."""
    g = make_geometry(60, 0.0025)
    c = 0.075
    mean = rectangle_sdf(g, (c, c), (0.055, 0.012))
    post = make_posterior(mean, g, 0.1 * g.resolution)
    if with_obstacles:
        occ = np.zeros(g.shape, np.int8)
        x, y = g.cell_centers()[..., 0], g.cell_centers()[..., 1]
        for dy in (-1.0, 1.0):
            occ[(x >= c - 0.055) & (x <= c + 0.03) & (np.abs(y - (c + dy * 0.022)) <= 0.01)] = 100
        post = replace(post, obstacles=obstacle_distance(occ, g))
    return post


@pytest.mark.parametrize('method', ['gp-gpis-opt', 'gp-p', 'gp-m'])
def test_planners_grasp_where_no_object_lies_against_the_target(method):
    """Free, a planner grasps the bar across anywhere along it; with boxes along most of its length the jaws
    land in the free end (x > the boxes' end + half a jaw), outside the boxes, at a high P_F for the planners
    that model the jaws' noise (GP-M plans on the mean alone: its jaws may graze a box); the free grasp among
    the boxes would have its jaws in them (P_F 0)."""
    gripper = PlannerParams().gripper
    free = plan(method, _boxed_in_bar(False), PlannerParams(), seed=0)
    assert free.success and abs(free.axis[1]) > 0.9
    post = _boxed_in_bar(True)
    grasp = plan(method, post, PlannerParams(), seed=0)
    assert grasp.success and abs(grasp.axis[1]) > 0.9, grasp
    assert grasp.center[0] > 0.075 + 0.03 + 0.5 * gripper.jaw_width
    assert grasp.p_f > (0.3 if method == 'gp-m' else 0.8)
    assert np.all(bilinear(post.obstacles, post.geometry, np.stack([grasp.jaw1, grasp.jaw2])) > 0.0)
    if free.center[0] < 0.075 + 0.03:
        samples = draw_shape_samples(post, 200, np.random.default_rng(1))
        est = probability_force_closure(free.jaw1[None], free.jaw2[None], samples, gripper, gripper.sigma_g)
        assert est.p[0] == 0.0


def test_segmentation_marks_a_neighbour_as_obstacle_and_the_posterior_keeps_it():
    """Two boxes 8 mm apart seen at 30 degrees: the target's grid holds the neighbour as obstacle cells (most of
    its footprint in the grid), none on the target; the posterior's obstacle distance is negative there."""
    from gpis_grasp_ros.core.sensing import SensingParams, segment_frames
    from support.tilted_scene import Box, TiltedScene

    target = Box(-0.025, 0.0, 0.02, 0.03, 0.03, rgb=(40.0, 90.0, 200.0))
    neighbour = Box(0.019, 0.0, 0.016, 0.03, 0.04, rgb=(200.0, 60.0, 40.0))
    scene = TiltedScene(30.0, boxes=[target, neighbour])
    rgb, depth, label = scene.frames(5, seed=2)
    vv, uu = np.nonzero(label == 1)
    result = segment_frames(rgb, depth, scene.intrinsics,
                            SensingParams(target='pixel', target_point=(float(np.median(uu)), float(np.median(vv)))))
    g = result.geometry
    xy = scene.table_xy(g.to_sensor(g.cell_centers()))

    def footprint(b: Box, shrink: float) -> np.ndarray:
        return (np.abs(xy[..., 0] - b.x) < b.half_x - shrink) & (np.abs(xy[..., 1] - b.y) < b.half_y - shrink)

    inner = footprint(neighbour, g.resolution)
    assert inner.sum() > 20
    assert result.obstacles[inner].mean() > 0.8
    assert not (result.obstacles & footprint(target, -g.resolution)).any()
    occ, noise, geometry = publishable_grids(result)
    post = posterior_from_grids(occ, noise, geometry, obstacles=publishable_obstacles(result))
    assert post.obstacles is not None and np.all(post.obstacles[inner] < 0)
    assert posterior_from_grids(occ, noise, geometry).obstacles is None
