#!/usr/bin/env python3
"""Plan a grasp with GraspPlannerClient, express it in the robot's base frame and execute it in simulation.

Run the pipeline first, e.g. replaying a shipped bag with the simulated gripper:

    ros2 launch gpis_grasp_ros gpis_grasp.launch.py bag:=bags/A_tape_dispenser.mcap gripper_sim:=true
    python3 examples/plan_and_execute.py --method gp-gpis-opt --seed 1 --trials 20

The camera → base transform is an example value (camera 0.8 m above the base, looking straight down);
take yours from TF (tf2_ros.Buffer.lookup_transform(base, camera, time)) on a robot.
"""

from __future__ import annotations

import argparse
import math
import sys

import rclpy
from geometry_msgs.msg import TransformStamped

from gpis_grasp_ros.ros.client import GraspPlannerClient


def example_camera_to_base(camera_frame: str, base_frame: str) -> TransformStamped:
    """Camera optical frame 0.8 m above ``base_frame``, z (optical axis) pointing down: a 180 degree turn about x."""
    t = TransformStamped()
    t.header.frame_id = base_frame
    t.child_frame_id = camera_frame
    t.transform.translation.z = 0.8
    t.transform.rotation.x, t.transform.rotation.w = math.sin(math.pi / 2), math.cos(math.pi / 2)
    return t


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--method', default='gp-gpis-opt', help='planner (default gp-gpis-opt)')
    p.add_argument('--seed', type=int, default=1, help='planner seed (default 1; 0 = nondeterministic)')
    p.add_argument('--trials', type=int, default=20, help='simulated executions (default 20; 0 = do not execute)')
    p.add_argument('--timeout', type=float, default=120.0, help='s to wait for the model and the plan (default 120)')
    p.add_argument('--base-frame', default='base_link', help='frame to express the grasp in (default base_link)')
    p.add_argument('--namespace', default='', help='namespace of the gpis_grasp_ros nodes (default none)')
    args = p.parse_args(argv)

    rclpy.init()
    client = GraspPlannerClient(namespace=args.namespace)
    try:
        if not client.wait_until_ready(timeout=args.timeout):
            print('planner_node or a GPIS model on gpis/model did not show up', file=sys.stderr)
            return 1

        def progress(fb) -> None:
            print(f'  restart {fb.restarts_done}/{fb.restarts_total}, best P_F {fb.best_probability_force_closure:.2f}')

        grasp = client.plan(method=args.method, seed=args.seed, timeout=args.timeout, feedback_callback=progress)
        if not grasp.success:
            print(f'no grasp: {grasp.message} ({grasp.status})', file=sys.stderr)
            return 1
        print(f'{grasp.method}: P_F {grasp.probability_force_closure:.2f}, '
              f'opening {grasp.jaw_separation * 1000:.1f} mm, '
              f'{grasp.planning_time:.2f} s')
        framed = client.to_frame(grasp, example_camera_to_base(grasp.jaw1.header.frame_id, args.base_frame))
        for name in ('jaw1', 'jaw2', 'grasp_pose'):
            pos = getattr(framed, name).pose.position
            print(f'  {name} in {framed.frame_id}: ({pos.x:.4f}, {pos.y:.4f}, {pos.z:.4f}) m')
        if args.trials > 0:
            outcome = client.execute(grasp, trials=args.trials, seed=args.seed)
            print(f'execution: {outcome.message}' if outcome.success else f'not executed: {outcome.message}')
        return 0
    finally:
        client.close()
        rclpy.try_shutdown()


if __name__ == '__main__':
    sys.exit(main())
