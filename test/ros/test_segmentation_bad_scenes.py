"""segmentation_node on bad scenes: no plane, plane edge-on, empty table, target point on no
object → a latched reason on segmentation/status, nothing published, and the node keeps working."""

from __future__ import annotations

import numpy as np
from rclpy.parameter import Parameter
from sensor_msgs.msg import PointCloud2

from gpis_grasp_ros.data import messages  # noqa: E402
from gpis_grasp_ros.ros import conversions  # noqa: E402
from support.rosutil import RosHarness, segmentation_graph, wait_for  # noqa: E402
from support.tilted_scene import Box, TiltedScene  # noqa: E402

F = conversions.RclpyFactory()


def _cloud(depth: np.ndarray, rgb: np.ndarray, scene: TiltedScene, stamp: int) -> PointCloud2:
    xyz = (scene.intrinsics.rays() * depth[..., None]).astype(np.float32)
    return messages.xyz_rgb_to_pointcloud2(F, xyz, rgb, messages.header(F, stamp, 'cam'))


def _scenes() -> list[tuple[str, PointCloud2]]:
    small = dict(width=160, height=120, focal_px=150.0)
    out = []
    rng = np.random.default_rng(0)
    empty = TiltedScene(40.0, **small)
    rgb, depth, _ = empty.frames(1)
    out.append(('no table plane', _cloud(rng.uniform(0.5, 1.5, depth[0].shape), rgb[0], empty, 1)))
    edge = TiltedScene(85.0, distance_m=0.3, **small)
    rgb_e, depth_e, _ = edge.frames(1)
    depth_e = np.where((depth_e[0] > 0) & (depth_e[0] < 3.0), depth_e[0], np.nan)
    out.append(('edge-on', _cloud(depth_e, rgb_e[0], edge, 2)))
    out.append(('no object found on the table', _cloud(depth[0], rgb[0], empty, 3)))
    box = TiltedScene(40.0, boxes=[Box(0.0, 0.0, 0.03, 0.02, 0.04)], **small)
    rgb_b, depth_b, _ = box.frames(1)
    out.append(('on no object', _cloud(depth_b[0], rgb_b[0], box, 4)))
    return out, _cloud(depth_b[0], rgb_b[0], box, 5)


def _run(overrides: list[Parameter], clouds: list[PointCloud2]) -> tuple[list, list]:
    """One segmentation_node fed ``clouds`` one at a time (waiting for each outcome)."""
    ros = RosHarness()
    try:
        _, grids, status, pub = segmentation_graph(ros, overrides)
        for k, cloud in enumerate(clouds):
            pub.publish(cloud)
            assert wait_for(lambda k=k: len(status) > k, 30.0), f'no status for cloud {k}'
        return grids, [m.data for m in status]
    finally:
        ros.close()


def test_bad_scenes_latch_a_reason_and_the_node_keeps_working():
    bad, good = _scenes()
    grids, status = _run([], [cloud for reason, cloud in bad[:3]] + [good])
    for (reason, _), text in zip(bad[:3], status[:3], strict=True):
        assert text.startswith('failed:') and reason in text, (reason, text)
    assert len(grids) == 1 and status[3].startswith('ok:')  # only the good scene was published


def test_target_point_on_no_object_is_refused_by_the_node():
    bad, good = _scenes()
    grids, status = _run([Parameter('target', value='table'), Parameter('target_point', value=[0.0, 0.0])],
                         [bad[3][1]])
    assert not grids and status[0].startswith('failed:') and 'on no object' in status[0]
