"""End to end on real D435 captures (bags/real, made by ``gpis-grasp import-rgbd``; Apache-2.0 ClearGrasp data).

Head-camera-like views (44-52 degrees) of transparent objects among others. What these tests hold
(see README "Perception on a real, tilted camera" for the figures, including the targets missed):
the table plane and the grid pose, the isolation of the target from its neighbours (a box split
from the notebook it touches), the planner and gripper simulation on the imported ground truth, and
the node's behaviour (grids published in the table plane, or a latched reason when the target
cannot be isolated). The clear bottle meets the issue's occupancy IoU (0.5) and grasp target (>= 14 of 20
simulated executions in force closure on the true shape; README: 19.5 over planner seeds 0-9); the flower box
meets the occupancy target but not the grasp target (README: 10.3 over seeds 0-9), which its truth sampled at
the planning grid allows (planned on it: 17.9). The figures asserted are those achieved, with margin, averaged
over seeds where a single seed's grasp is too brittle to assert.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from rclpy.parameter import Parameter
from sensor_msgs.msg import PointCloud2

from gpis_grasp_ros.core.grid import quaternion_to_rotation
from gpis_grasp_ros.core.noise_model import SensorModel
from gpis_grasp_ros.core.sdf_bank import bilinear
from gpis_grasp_ros.core.sensing import SensingParams, segment_frames
from gpis_grasp_ros.data import messages
from gpis_grasp_ros.data.bags import load_bag
from gpis_grasp_ros.ros import conversions
from gpis_grasp_ros.ros.nodes.segmentation_node import SegmentationNode
from gpis_grasp_ros.tools.evaluation.real import evaluate_bag, evaluate_seeds
from gpis_grasp_ros.tools.import_rgbd import main
from support.rosutil import RosHarness, segmentation_graph, wait_for

REAL = Path(__file__).resolve().parents[2] / 'bags' / 'real'
BOTTLE = REAL / 'cleargrasp_000000080_bottle.mcap'
FLOWER = REAL / 'cleargrasp_000000123_flower_box.mcap'
TARGETS = {BOTTLE: (220.8, 160.8), FLOWER: (200.8, 122.8)}  # the README's target pixels in the bag images
D400 = SensorModel.named('realsense_d400')


def test_licence_ships_with_the_data():
    assert 'Apache License' in (REAL / 'LICENSE').read_text()
    assert sum(p.stat().st_size for p in REAL.glob('*.mcap')) < 5e6


@pytest.fixture(scope='module')
def bottle():
    scene = load_bag(BOTTLE, frames=10)
    params = SensingParams(sensor=D400, target='pixel', target_point=TARGETS[BOTTLE])
    return scene, segment_frames(scene.rgb_frames, scene.depth_frames, scene.intrinsics, params)


def test_real_table_plane_and_grid_pose(bottle):
    scene, result = bottle
    assert scene.depth_frames.shape[0] == 1  # one frame is one frame
    assert result.effective_frames == 1.0
    assert 45.0 < result.table.tilt_deg < 55.0  # the data set's 45-52 degree views
    assert result.table.inlier_fraction > 0.6
    g = result.geometry
    corners = g.to_sensor(np.array([[g.origin_x, g.origin_y], [g.origin_x + g.size_m[0], g.origin_y + g.size_m[1]]]))
    assert np.abs(result.table.height(corners)).max() < 1e-6
    # the ground truth (imported from the opaque twin of the scene) lies in the same plane
    tg = scene.true_geometry
    assert np.degrees(np.arccos(np.clip(tg.table_normal @ g.table_normal, -1, 1))) < 0.5


def test_real_target_is_isolated_from_its_neighbours(bottle):
    """Five objects on the cloth: the target's grid holds the lying bottle only - its occupied cells lie on
    the true bottle or within 1 cm of it (none on the upright bottles next to it, although the chromatic
    extension of its body touches the base of the one behind it): on the default 3.75 mm cells 415 cells, 84 %
    inside, 96 % within 1 cm, 99 % within 1.5 cm (on a 25-cell grid: 80 cells, 85 %, 99 %).
    The clear body is the prism under its silhouette: the
    table seen through it lands up to H tan 52 deg = 8 cm behind it and is table, not object."""
    scene, result = bottle
    assert result.objects_seen >= 3
    g, tg = result.geometry, scene.true_geometry
    true_sdf = bilinear(scene.true_sdf.astype(np.float64), tg, tg.from_sensor(g.to_sensor(g.cell_centers()))[0])
    occupied = result.occupancy >= 0.5
    assert occupied.sum() >= 70
    assert np.mean(true_sdf[occupied] < 0) > 0.75
    assert np.mean(true_sdf[occupied] < 0.01) > 0.93
    assert g.size_m[0] < 0.25  # a grid around one bottle, not around the scene


def test_real_bottle_plan_and_simulated_executions():
    evs = evaluate_seeds(BOTTLE, TARGETS[BOTTLE], range(3), trials=20)
    ev = evs[0]
    assert ev.trials == 20 and all(0 <= e.successes <= 20 for e in evs)
    assert 0.5 <= ev.occupancy_iou <= 1.0  # README: 0.58 (0.35 without the clear body's prism, previous truth)
    assert ev.mean_shape_iou > 0.3  # README: 0.53
    # README: 19, 20, 20 of 20 for seeds 0-2 (18, 20, 20 on the previous ground truth; 0, 0, 0 without the prism;
    # 18, 18, 18 while the body's cells carried the propagated variance of "no bottle at all"); P_F 0.97-1.00
    # (0.58-0.64 then) against 97.5 % over seeds 0-9
    assert np.mean([e.successes for e in evs]) >= 16
    # P_F 0.87-0.90 at 20 of 20 closures on seeds 0-9 since the prism's height is a prior with its own variance
    assert all(e.p_f > 0.8 for e in evs)
    assert all(e.jaw_clearance_m > 0.005 for e in evs)  # no jaw on another object seen on the table
    # planned on the truth sampled at the planning grid, the planner is sure of its grasp (README: 0.96-1.00)
    assert evaluate_bag(BOTTLE, TARGETS[BOTTLE], trials=20, seed=0, oracle=True).p_f > 0.9


def test_evaluate_command_runs_seeds_the_oracle_and_other_planners(capsys):
    u, v = TARGETS[BOTTLE]
    args = [str(BOTTLE), '--evaluate', '--target-pixel', str(u), str(v), '--trials', '5', '--seed', '3']
    assert main(args + ['--seeds', '2', '--oracle']) == 0
    out = capsys.readouterr().out.splitlines()
    seed_lines = [line for line in out if 'seed ' in line and 'seeds' not in line]
    assert [line.split(': ')[0].endswith(f'(planned on the ground truth) seed {s}')
            for line, s in zip(seed_lines, (3, 4), strict=True)] == [True, True]
    assert out[-1].startswith('seeds 3-4: successes [') and 'of 5; P_F' in out[-1]
    assert main(args + ['--seeds', '0']) == 2
    assert 'seeds must be >= 1' in capsys.readouterr().err
    assert main(args + ['--method', 'gp-m']) == 0
    out = capsys.readouterr().out
    assert '; gp-m ' in out and '/5 in force closure (collision ' in out and ') on the true shape' in out

    def occupancy_iou(text: str) -> float:
        return float(text.split('target occupancy IoU ')[1].split(',')[0])

    # --clear-body-height reaches the segmentation: the bottle's prism at its true 6.1 cm instead of the priors'
    # 5.4 cm is narrower and the figures change. On the previous ground truth its occupancy IoU fell from 0.60 to
    # 0.58 (asserted: lower by 0.01); on the current one (data/ground_truth.py, itself ~2 % smaller) both round to
    # 0.58 (0.583 against 0.581) and the mean-shape IoU is 0.54 against 0.53, so the line as a whole is compared
    assert main(args + ['--clear-body-height', '0.061']) == 0
    given = capsys.readouterr().out
    assert main(args) == 0
    default = capsys.readouterr().out
    assert given.split(': ', 1)[1] != default.split(': ', 1)[1]
    assert abs(occupancy_iou(given) - occupancy_iou(default)) < 0.05
    assert main(args + ['--clear-body-height', '-0.01']) == 2
    assert 'clear_body_height_m' in capsys.readouterr().err

    # --lambda reaches the planner: on the flower box seed 0 the grasp at the default λ (P_F 0.84) and without the
    # penalty (λ = 0: P_F 0.76, other contacts) differ
    u, v = TARGETS[FLOWER]
    flower = [str(FLOWER), '--evaluate', '--target-pixel', str(u), str(v), '--seed', '0']

    def p_f(text: str) -> float:
        return float(text.split('(P_F ')[1].split(')')[0])

    assert main(flower) == 0
    default_line = capsys.readouterr().out
    default = p_f(default_line)
    assert main(flower + ['--lambda', '0']) == 0
    unpenalised = capsys.readouterr().out
    assert unpenalised != default_line and abs(p_f(unpenalised) - default) > 0.01
    assert main(flower + ['--lambda', '-1']) == 2
    assert 'uncertainty penalty' in capsys.readouterr().err


def test_real_flower_box_is_split_from_the_notebook_it_touches():
    """The clear box stands against the notebook, whose evidence reaches the image border: the flat
    notebook (12-16 mm) and the taller box are split in the table raster, so the box is a target of
    its own (README: occupancy IoU 0.55, grasp target missed) while the notebook itself is still refused
    as cut by the border. Its lower face, through which the D435 returns the table 2-5 cm behind it, is
    moved onto the box (see_through_test)."""
    scene = load_bag(FLOWER, frames=1)
    params = SensingParams(sensor=D400, target='pixel', target_point=TARGETS[FLOWER])
    result = segment_frames(scene.rgb_frames, scene.depth_frames, scene.intrinsics, params)
    u0, v0, u1, v1 = result.bbox_px
    assert u1 - u0 < 100 and v1 - v0 < 100  # the box (~70 px), not the notebook (~160 px wide, at the border)
    assert result.objects_seen >= 3 and result.geometry.size_m[0] < 0.2
    g, tg = result.geometry, scene.true_geometry
    true_sdf = bilinear(scene.true_sdf.astype(np.float64), tg, tg.from_sensor(g.to_sensor(g.cell_centers()))[0])
    occupied = result.occupancy >= 0.5
    assert np.mean(true_sdf[occupied] < 0.03) > 0.6  # the occupied cells lie on or just behind the true box
    notebook = dataclasses.replace(params, target_point=(80.0, 180.0))
    with pytest.raises(ValueError, match='border'):
        segment_frames(scene.rgb_frames, scene.depth_frames, scene.intrinsics, notebook)
    moved = result.seen_through_px & result.object_mask
    assert moved.sum() > 150  # README: 269 pixels
    off = segment_frames(scene.rgb_frames, scene.depth_frames, scene.intrinsics,
                         dataclasses.replace(params, see_through_test=False))
    assert np.nanmedian(result.height[moved]) > np.nanmedian(off.height[moved]) + 0.02  # lifted onto the box
    evs = evaluate_seeds(FLOWER, TARGETS[FLOWER], range(10), trials=20)
    assert evs[0].occupancy_iou > 0.5 and all(e.jaw_clearance_m > 0.005 for e in evs)  # no jaw on another object
    # seeds 0-9: 8, 5, 6, 6, 10, 5, 10, 3, 8, 4 of 20 at P_F 0.84-0.90. The notebook's cells where it touches the
    # box are uncertain table (the line between them is a split, not a measurement), so eq. 6 no longer puts a
    # jaw on the box's part the split gave the notebook (before: 0.2 of 20 at P_F 0.59-0.72); the grasp across the
    # box's depth fails where its clear near face returned the table, and P_F does not know it (over-confident by
    # ~0.45: docs/real-benchmark.md). GP-P, seeds 0-9, closes 12, 3, 5, 8, 16, 11, 10, 6, 9, 9 at P_F 0.87-0.91 (its
    # choice turns on its own shape samples: ten seeds, not three). Asserted: the grasps close about as often as the
    # Monte-Carlo planner's, and neither says more than 0.95
    assert np.mean([e.successes for e in evs]) >= 5 and all(e.p_f < 0.95 for e in evs)
    gp_p = evaluate_seeds(FLOWER, TARGETS[FLOWER], range(10), trials=20, method='gp-p')
    assert np.mean([e.successes for e in gp_p]) >= 8 and all(0.8 < e.p_f < 0.95 for e in gp_p)
    # planned on its truth sampled at the planning grid, the grasp target is within reach (README: 19, 20, 20;
    # 19, 20, 20 on the previous ground truth too; 12, 7, 5 on the ground truth built from the halved mask, whose
    # stair-step normals made executions slip)
    oracle = evaluate_seeds(FLOWER, TARGETS[FLOWER], range(3), trials=20, oracle=True)
    assert np.mean([e.successes for e in oracle]) >= 16


def _cloud(path: Path, stamp_ns: int) -> PointCloud2:
    f = conversions.RclpyFactory()
    scene = load_bag(path, frames=1)
    xyz = scene.intrinsics.rays() * scene.depth_frames[0][..., None]
    return messages.xyz_rgb_to_pointcloud2(f, xyz.astype(np.float32), scene.rgb_frames[0],
                                           messages.header(f, stamp_ns, scene.frame_id))


def _run_node(path: Path, target: tuple[float, float] | None = None) -> tuple[list, list, SegmentationNode]:
    """segmentation_node on one bag's cloud with its (or the given) target pixel; returns the grids and statuses."""
    ros = RosHarness()
    try:
        node, grids, status, pub = segmentation_graph(ros, [
            Parameter('sensor_model', value='realsense_d400'), Parameter('target', value='pixel'),
            Parameter('target_point', value=list(target or TARGETS[path]))])
        pub.publish(_cloud(path, 1))
        assert wait_for(lambda: bool(status), 60.0)
        wait_for(lambda: bool(grids), 1.0)
        # the node is still alive and serving after either outcome
        assert node.count_subscribers('segmentation/status') >= 1 and node.context.ok()
        return grids, status, node
    finally:
        ros.close()


def test_segmentation_node_publishes_grids_in_the_tilted_table_plane():
    grids, status, _ = _run_node(BOTTLE)
    assert status[-1].data.startswith('ok:') and grids
    q = grids[-1].info.origin.orientation
    r = quaternion_to_rotation(np.array([q.x, q.y, q.z, q.w]))
    tilt = np.degrees(np.arccos(np.clip(r[2, 2], -1, 1)))
    assert 45.0 < tilt < 55.0  # the grid lies in the tilted table plane, not fronto-parallel


def test_segmentation_node_latches_the_reason_when_the_target_cannot_be_isolated():
    """The notebook reaches the image border: with the target pixel on it nothing is published and the
    reason is latched on segmentation/status; the node keeps running."""
    grids, status, _ = _run_node(FLOWER, (80.0, 180.0))
    assert not grids
    assert status[-1].data.startswith('failed:') and 'border' in status[-1].data
