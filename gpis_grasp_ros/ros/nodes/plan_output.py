"""What planner_node sends back for a finished request: the GraspPlan response (or PlanGrasp result: same
fields) and the grasp drawn for RViz (``grasp/markers``) and on the GPIS-Blur image (``grasp/image``).

Called from the planning thread that finished the job (so the contact search's scratch memory exists
for the planning threads only, not for every executor thread).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from sensor_msgs.msg import Image
from visualization_msgs.msg import MarkerArray

from gpis_grasp_ros.core import contacts
from gpis_grasp_ros.core.gripper import GripperParams
from gpis_grasp_ros.core.sdf_bank import SdfBank
from gpis_grasp_ros.data import messages
from gpis_grasp_ros.ros import conversions
from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS, SHUTTING_DOWN
from gpis_grasp_ros.viz import images as viz


def object_height(config: Any, model: Any) -> float:
    """Object height (m) for the automatic grasp height: the ``object_height`` parameter when > 0, else the
    height segmentation measured (``GpisModel.object_height``, 0 = unknown)."""
    return config.object_height if config.object_height > 0 else messages.gpis_model_object_height(model)


def _grasp_height(job: Any) -> float:
    c = job.config
    return conversions.grasp_height_for(c.grasp_height, object_height(c, job.model), c.jaw_height)


def fill_answer(response: Any, job: Any, logger: Any, visuals: GraspVisuals) -> Any:
    """Fill ``response`` from a finished planner_node job (success, the grasp, or why not); a successful
    grasp is also drawn (``visuals``)."""
    response.success = False
    response.method = job.method
    if job.started is not None:
        response.planning_time = time.monotonic() - job.started
    if job.stopped == 'timeout':
        response.message = (f'planning with {job.method} exceeded planning_timeout='
                            f'{job.config.planning_timeout:.1f} s and was stopped; try fewer initial grasps / '
                            'samples or a larger timeout')
    elif job.stopped == SHUTTING_DOWN:
        response.message = f'planner_node is {SHUTTING_DOWN}; request not completed'
    elif job.stopped == 'cancelled':
        response.message = 'cancelled by the client'
    elif job.stopped:
        response.message = f'stopped: {job.stopped}'
    elif job.error is not None:
        response.message = f'{job.method} failed: {type(job.error).__name__}: {job.error}'
        logger.error(response.message)
    elif job.result is not None:
        result = job.result
        conversions.fill_grasp_plan_response(
            response, result, job.model.header, geometry=job.posterior.geometry, grasp_height=_grasp_height(job),
            contacts_xy=conversions.mean_shape_contacts(job.posterior, result, job.config.gripper.jaw_width))
        finite = np.isfinite(np.concatenate([np.ravel(result.jaw1), np.ravel(result.jaw2)])).all()
        if response.success and not finite:
            response.success = False
            response.message = f'{job.method} returned non-finite jaw positions; not a valid grasp'
        if response.success:
            visuals.publish(result, job)
        logger.info(f'{job.method}: {response.message} (P_F={float(result.p_f):.2f}, '
                    f'{float(result.planning_time):.2f} s)')
    else:
        response.message = 'planning did not finish'
    return response


class GraspVisuals:
    """The latched ``grasp/markers`` (MarkerArray) and ``grasp/image`` (the grasp on the GPIS-Blur image)."""

    def __init__(self, node: Any) -> None:
        self.marker_pub = node.create_publisher(MarkerArray, 'grasp/markers', LATCHED_QOS)
        self.image_pub = node.create_publisher(Image, 'grasp/image', LATCHED_QOS)

    def publish(self, result: Any, job: Any) -> None:
        posterior, header = job.posterior, job.model.header
        c = job.config
        jaw_width = c.gripper.jaw_width
        bank = SdfBank(posterior.mean[None], posterior.geometry, posterior.gradient[None],
                       obstacles=posterior.obstacles)
        con = contacts.find_contacts(bank, result.jaw1, result.jaw2, GripperParams(jaw_width=jaw_width),
                                     check_opening=False)
        touches = np.stack([np.reshape(con.c1, (-1, 2))[0], np.reshape(con.c2, (-1, 2))[0]])
        if not bool(np.ravel(con.valid)[0]):
            touches = None
        self.marker_pub.publish(conversions.grasp_markers(
            result, header, posterior.geometry, jaw_width, jaw_height=c.jaw_height, contacts_xy=touches,
            grasp_height=_grasp_height(job)))
        overlay = viz.grasp_overlay(job.blur, posterior.geometry, [result], scale=c.image_scale, jaw_width_m=jaw_width)
        factory = conversions.RclpyFactory()
        self.image_pub.publish(messages.numpy_to_image(factory, overlay, 'rgb8', messages.header(
            factory, messages.stamp_to_ns(header.stamp), header.frame_id)))
