"""A head-camera bag (tilted Carmine, shadows, distractors; truth in the table frame) end to end through
the nodes: segmentation → GPIS → planner → simulated gripper on the tilted ground truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_nodes_pipeline import Loop

from gpis_grasp_ros.core.sdf_bank import bilinear
from gpis_grasp_ros.data import bagio, messages

HEAD_BAG = Path(__file__).resolve().parents[2] / 'bags' / 'head' / 'E_mechanical_switch.mcap'


def _xyz(msg) -> np.ndarray:
    p = msg.pose.position if hasattr(msg, 'pose') else msg.point
    return np.array([p.x, p.y, p.z])


def test_head_bag_end_to_end():
    truth_sdf, truth = messages.float_grid_to_numpy(
        next(m for _, _, _, m in bagio.read_messages(HEAD_BAG, ['/ground_truth/sdf'])), 'm')
    loop = Loop(HEAD_BAG)
    try:
        plan = loop.plan()
        assert plan.success, plan.message
        plan_geom = messages.gpis_model_to_posterior(loop.models[-1]).geometry
        # the fitted table frame is the true one (the camera is tilted 52 degrees)
        angle = np.degrees(np.arccos(np.clip(plan_geom.table_normal @ truth.table_normal, -1.0, 1.0)))
        assert angle < 1.0
        assert np.degrees(np.arccos(-truth.table_normal[2])) == pytest.approx(52.0, abs=1e-6)
        # the switch's measured height (2 cm prism, specular lever without depth) sets the automatic grasp height
        height = loop.models[-1].object_height
        assert height == pytest.approx(0.020, abs=0.004)
        assert plan.grasp_height == pytest.approx(max(height / 2, 0.01), abs=1e-12)
        # jaws, centre and contacts at grasp_height above the fitted plane; the jaws at different depths
        for msg in (plan.jaw1, plan.jaw2, plan.grasp_pose, plan.contact1, plan.contact2):
            assert plan_geom.from_sensor(_xyz(msg))[1] == pytest.approx(plan.grasp_height, abs=1e-9)
        assert plan.width == pytest.approx(np.linalg.norm(_xyz(plan.contact2) - _xyz(plan.contact1)), abs=1e-12)
        # the contacts on the mean shape lie near the TRUE boundary (mapped through the camera frame)
        res = plan_geom.resolution
        for c in (plan.contact1, plan.contact2):
            xy, _ = truth.from_sensor(_xyz(c))
            assert abs(float(bilinear(truth_sdf.astype(np.float64), truth, xy[None])[0])) <= 2 * res
        ex = loop.execute(plan, trials=20)
        assert ex.success, ex.message
        assert ex.success_rate >= 0.5, ex.message
    finally:
        loop.close()
