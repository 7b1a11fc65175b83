"""``gpis-grasp demo``: the perceive–plan–grasp loop in one process, no launch files.

A MultiThreadedExecutor hosts the four nodes (segmentation, GPIS, planner, simulated gripper)
and the bag player; a client waits for the GPIS, calls ``plan_grasp`` with GP-M and with
GP-GPIS-OPT, executes each grasp on the simulated gripper, prints a table and writes
``<out>/<object>/``: GPIS-Blur, mean/variance figure, one overlay per method, ``summary.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path

import numpy as np

DEFAULT_BAG = Path(__file__).resolve().parents[2] / 'bags' / 'A_tape_dispenser.mcap'
METHODS = ('gp-m', 'gp-gpis-opt')


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog='gpis-grasp demo', description=__doc__.splitlines()[0])
    p.add_argument('--bag', type=Path, default=DEFAULT_BAG, help='bag to replay (default: object A)')
    p.add_argument('--out', type=Path, default=Path('out'), help='output directory (default: out/)')
    p.add_argument('--trials', type=int, default=10, help='simulated grasp executions per method (default 10)')
    p.add_argument('--seed', type=int, default=1, help='planner / gripper seed (default 1)')
    p.add_argument('--grid-size', type=int, default=25, help='M of the M x M GPIS grid (default 25)')
    p.add_argument('--timeout', type=float, default=120.0, help='overall time limit in seconds (default 120)')
    return p.parse_args(argv)


def log(text: str) -> None:
    print(f'[demo] {text}', flush=True)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if not args.bag.exists():
        print(f'gpis-grasp demo: bag not found: {args.bag}', file=sys.stderr)
        return 2
    import rclpy
    from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
    from rclpy.parameter import Parameter

    from gpis_grasp_interfaces.msg import GpisModel
    from gpis_grasp_interfaces.srv import ExecuteGrasp, GraspPlan
    from gpis_grasp_ros.data import messages
    from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS
    from gpis_grasp_ros.ros.nodes.gpis_node import GpisNode
    from gpis_grasp_ros.ros.nodes.gripper_sim_node import GripperSimNode
    from gpis_grasp_ros.ros.nodes.planner_node import PlannerNode
    from gpis_grasp_ros.ros.nodes.segmentation_node import SegmentationNode
    from gpis_grasp_ros.ros.player import BagPlayer
    from gpis_grasp_ros.viz import images as viz

    obj = args.bag.stem if args.bag.suffix else args.bag.name
    out_dir = args.out / obj
    out_dir.mkdir(parents=True, exist_ok=True)
    rclpy.init()
    executor = MultiThreadedExecutor(num_threads=4)
    nodes = []
    try:
        seg = SegmentationNode(parameter_overrides=[Parameter('grid_size', value=args.grid_size)])
        planner = PlannerNode()
        nodes = [seg, GpisNode(), planner, GripperSimNode()]
        client = rclpy.create_node('demo_client')
        nodes.append(client)
        for n in nodes:
            executor.add_node(n)
        got_model = threading.Event()
        models: list = []

        def on_model(msg):
            models.append(msg)
            got_model.set()

        client.create_subscription(GpisModel, 'gpis/model', on_model, LATCHED_QOS)
        spinner = threading.Thread(target=executor.spin, daemon=True)
        spinner.start()

        log(f'replaying {args.bag} ...')
        t0 = time.perf_counter()
        player = BagPlayer(client, args.bag, rate=1.0, loop=True)
        player.play_once(blocking=False)
        if not got_model.wait(args.timeout):
            log(f'no GPIS within {args.timeout:.0f} s; giving up')
            return 1
        player.stop()
        while not planner.has_model() and time.perf_counter() - t0 < args.timeout:
            time.sleep(0.02)
        log(f'GPIS ready after {time.perf_counter() - t0:.1f} s')
        posterior = messages.gpis_model_to_posterior(models[-1])

        plan_cli = client.create_client(GraspPlan, 'plan_grasp')
        exec_cli = client.create_client(ExecuteGrasp, 'execute_grasp')
        for c in (plan_cli, exec_cli):
            if not c.wait_for_service(timeout_sec=10.0):
                log(f'service {c.srv_name} not available')
                return 1
        rows, results = [], []
        for method in METHODS:
            log(f'planning with {method} ...')
            req = GraspPlan.Request(method=method, seed=args.seed)
            plan = plan_cli.call(req, timeout_sec=args.timeout)
            if plan is None or not plan.success:
                log(f'{method}: no grasp ({plan.message if plan else "timeout"})')
                rows.append({'method': method, 'success': False, 'message': plan.message if plan else 'timeout'})
                continue
            log(f'executing {method} grasp {args.trials}x on the simulated gripper ...')
            ex = exec_cli.call(ExecuteGrasp.Request(jaw1=plan.jaw1, jaw2=plan.jaw2, trials=args.trials,
                                                    seed=args.seed), timeout_sec=args.timeout)
            # jaw poses are 3D points in the camera frame; the pictures are drawn in the grid (table) frame
            jaw1 = [plan.jaw1.pose.position.x, plan.jaw1.pose.position.y, plan.jaw1.pose.position.z]
            jaw2 = [plan.jaw2.pose.position.x, plan.jaw2.pose.position.y, plan.jaw2.pose.position.z]
            rows.append({
                'method': method, 'success': True, 'p_f': plan.probability_force_closure,
                'p_f_std_error': plan.probability_force_closure_std_error,
                'q_mean': plan.ferrari_canny_on_mean, 'objective': plan.objective,
                'planning_time_s': plan.planning_time, 'width_m': plan.width, 'jaw1_m': jaw1, 'jaw2_m': jaw2,
                'frame_id': plan.jaw1.header.frame_id,
                'sim_successes': int(ex.successes) if ex else 0, 'sim_trials': int(ex.trials) if ex else 0,
                'sim_success_rate': float(ex.success_rate) if ex else float('nan'),
            })
            results.append((method, posterior.geometry.from_sensor(np.array(jaw1))[0],
                            posterior.geometry.from_sensor(np.array(jaw2))[0], plan.probability_force_closure))

        # ------------------------------------------------------------ pictures + summary
        from gpis_grasp_ros.core.blur import gpis_blur
        blur = gpis_blur(posterior, n_samples=1000, rng=np.random.default_rng(0))
        viz.save_gpis_figure(out_dir / 'gpis.png', posterior, blur)
        viz.write_png(out_dir / 'gpis_blur.png', viz.upscale(blur, 16))
        for method, j1, j2, p_f in results:
            img = viz.grasp_overlay(blur, posterior.geometry, [(j1, j2, f'{method} P_F={p_f:.2f}')], scale=16)
            viz.write_png(out_dir / f'grasp_{method}.png', img)
        summary = {'bag': str(args.bag), 'object': obj, 'grid_size': args.grid_size,
                   'gpis': {'signal_variance_m2': posterior.params.signal_variance,
                            'length_scale_m': posterior.params.length_scale,
                            'prior_mean_m': posterior.params.prior_mean,
                            'resolution_m': posterior.geometry.resolution},
                   'methods': rows}
        (out_dir / 'summary.json').write_text(json.dumps(summary, indent=2))
        print()
        print(f'{"method":<14}{"P_F":>7}{"Q_F(mean)":>11}{"sim success":>13}{"time (s)":>10}')
        for r in rows:
            if r['success']:
                print(f'{r["method"]:<14}{r["p_f"]:>7.2f}{r["q_mean"]:>11.3f}'
                      f'{r["sim_successes"]:>8d}/{r["sim_trials"]:<4d}{r["planning_time_s"]:>10.2f}')
            else:
                print(f'{r["method"]:<14}  no grasp: {r["message"]}')
        print(f'\nwrote {out_dir}/: gpis.png, gpis_blur.png, ' +
              ', '.join(f'grasp_{m}.png' for m, *_ in results) + ', summary.json')
        return 0 if all(r['success'] for r in rows) else 1
    except (KeyboardInterrupt, ExternalShutdownException):
        return 130
    finally:
        executor.shutdown()
        for n in nodes:
            n.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    sys.exit(main())
