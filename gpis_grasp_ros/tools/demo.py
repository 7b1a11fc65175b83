"""``gpis-grasp demo``: the perceive–plan–grasp loop in one process, no launch files.

A MultiThreadedExecutor hosts the four nodes (segmentation, GPIS, planner, simulated gripper)
and the bag player; a client waits for the GPIS, calls ``plan_grasp`` with GP-M and with
GP-GPIS-OPT, executes each grasp on the simulated gripper, prints a table and writes
``<out>/<object>/``: GPIS-Blur, mean/variance figure, one overlay per method, ``summary.json``.

Any bag in the shipped layout replays: the segmentation settings come from the bag (:func:`replay_settings`):
``frames_to_average`` from its frame count, the sensor model and the target pixel from the metadata the
simulator and ``gpis-grasp import-rgbd`` store in it; ``--sensor`` and ``--target-pixel`` override them.
Bags without ground truth are planned on, not executed.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gpis_grasp_ros.core.noise_model import SENSOR_MODELS
from gpis_grasp_ros.core.sensing.params import SensingParams
from gpis_grasp_ros.data import bagio
from gpis_grasp_ros.data.topics import TOPICS

DEFAULT_BAG = Path(__file__).resolve().parents[2] / 'bags' / 'A_tape_dispenser.mcap'
METHODS = ('gp-m', 'gp-gpis-opt')
#: segmentation_node's defaults the bag's frame count replaces: frames per estimate, fewest frames of a burst
FRAMES_TO_AVERAGE, MIN_FRAMES = 10, 3
#: segmentation_node's sensor_model default, used for bags that do not name theirs
DEFAULT_SENSOR = 'carmine'


@dataclass
class ReplaySettings:
    """segmentation_node parameters for replaying one bag, and where each came from (``notes``)."""

    frames: int  # camera frames in the bag
    frames_to_average: int
    min_frames: int
    sensor_model: str
    target: str = 'largest'
    target_point: tuple[float, float] = (0.0, 0.0)
    ground_truth: bool = False
    notes: list[str] = field(default_factory=list)

    def overrides(self) -> dict[str, object]:
        return {'frames_to_average': self.frames_to_average, 'min_frames': self.min_frames,
                'sensor_model': self.sensor_model, 'target': self.target,
                'target_point': [float(v) for v in self.target_point]}


def bag_metadata(bag: Path) -> tuple[dict, bool]:
    """The JSON the simulator / ``import-rgbd`` stored in the bag's custom metadata, merged, and whether there
    was any (a bag recorded elsewhere has none)."""
    merged: dict = {}
    found = False
    for key, value in sorted(bagio.bag_custom_data(bag).items()):
        if not key.startswith('gpis_grasp_ros'):
            continue
        found = True
        try:
            data = json.loads(value)
        except ValueError:
            continue
        if isinstance(data, dict):
            merged.update(data)
    return merged, found


def replay_settings(bag: Path, sensor: str | None = None,
                    target_pixel: tuple[float, float] | None = None) -> ReplaySettings:
    """segmentation_node settings for ``bag``: the frame count from its cloud topic, the sensor model and
    target pixel from its metadata unless given. ValueError when the bag is not in the shipped layout."""
    topics = bagio.bag_topics(bag)
    cloud = TOPICS['points']
    if cloud not in topics or not topics[cloud]['count']:
        raise ValueError(f'{bag} has no {cloud} messages: not a bag in the shipped layout '
                         '(gpis-grasp import-rgbd turns a colour + depth capture into one)')
    frames = int(topics[cloud]['count'])
    meta, has_meta = bag_metadata(bag)
    notes = []
    if sensor is None:
        sensor = meta.get('sensor') or (DEFAULT_SENSOR if has_meta else None)
        if sensor is None:
            sensor = DEFAULT_SENSOR
            notes.append(f'{bag.name} does not say which camera took it: sensor_model {DEFAULT_SENSOR}; pass '
                         '--sensor realsense_d400 for a RealSense capture')
    target, point = 'largest', (0.0, 0.0)
    if target_pixel is None and meta.get('target_pixel'):
        target_pixel = tuple(float(v) for v in meta['target_pixel'])
    if target_pixel is not None:
        target, point = 'pixel', (float(target_pixel[0]), float(target_pixel[1]))
    elif 'rgb' in meta or not has_meta:  # a capture (imported or recorded) with no target named
        notes.append(f'{bag.name} names no target: modelling the largest object; pass --target-pixel U V '
                     '(pixels of the bag image) to choose one')
    return ReplaySettings(frames=frames, frames_to_average=min(frames, FRAMES_TO_AVERAGE),
                          min_frames=min(frames, MIN_FRAMES), sensor_model=sensor, target=target,
                          target_point=point, ground_truth=TOPICS['sdf'] in topics, notes=notes)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog='gpis-grasp demo', description=__doc__.splitlines()[0])
    p.add_argument('--bag', type=Path, default=DEFAULT_BAG, help='bag to replay (default: object A)')
    p.add_argument('--out', type=Path, default=Path('out'), help='output directory (default: out/)')
    p.add_argument('--trials', type=int, default=10, help='simulated grasp executions per method (default 10)')
    p.add_argument('--seed', type=int, default=1, help='planner / gripper seed (default 1)')
    p.add_argument('--grid-size', type=int, default=SensingParams.grid_size,
                   help=f'force M of the M x M GPIS grid (default {SensingParams.grid_size}: from the object and '
                        'the cell size)')
    p.add_argument('--timeout', type=float, default=120.0, help='overall time limit in seconds (default 120)')
    p.add_argument('--sensor', choices=[m for m in SENSOR_MODELS if m != 'custom'],
                   help="segmentation_node's sensor_model (default: the one stored in the bag, else "
                        f'{DEFAULT_SENSOR})')
    p.add_argument('--target-pixel', type=float, nargs=2, metavar=('U', 'V'),
                   help="model the object at this pixel of the bag image (segmentation_node's target:=pixel "
                        'target_point:=[U, V]; default: the pixel stored in the bag, else the largest object)')
    return p.parse_args(argv)


def log(text: str) -> None:
    print(f'[demo] {text}', flush=True)


def _wait_for_model(got_model: threading.Event, player, status: list[str], timeout: float) -> bool:
    """Wait for the GPIS model; stop early when the bag has been played and segmentation reported failure."""
    end = time.perf_counter() + timeout
    while not got_model.wait(0.05):
        if time.perf_counter() > end:
            return False
        if player.done.is_set() and status and status[-1].startswith('failed'):
            return got_model.wait(1.0)
    return True


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if not args.bag.exists():
        print(f'gpis-grasp demo: bag not found: {args.bag}', file=sys.stderr)
        return 2
    try:
        settings = replay_settings(args.bag, args.sensor, tuple(args.target_pixel) if args.target_pixel else None)
    except ValueError as exc:
        print(f'gpis-grasp demo: {exc}', file=sys.stderr)
        return 2
    import rclpy
    from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
    from rclpy.parameter import Parameter
    from std_msgs.msg import String

    from gpis_grasp_interfaces.msg import GpisModel
    from gpis_grasp_interfaces.srv import ExecuteGrasp, GraspPlan
    from gpis_grasp_ros.data import messages
    from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS, SERVICE_QOS
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
    nodes, player, spinner = [], None, None
    try:
        # reliable input: a one-frame bag must not lose its frame
        seg_params = {'grid_size': args.grid_size, 'input_reliability': 'reliable', **settings.overrides()}
        seg = SegmentationNode(parameter_overrides=[Parameter(k, value=v) for k, v in seg_params.items()])
        nodes = [seg, GpisNode(), PlannerNode(), GripperSimNode()]
        client = rclpy.create_node('demo_client')
        nodes.append(client)
        for n in nodes:
            executor.add_node(n)
        got_model = threading.Event()
        models: list = []
        status: list[str] = []

        def on_model(msg):
            models.append(msg)
            got_model.set()

        client.create_subscription(GpisModel, 'gpis/model', on_model, LATCHED_QOS)
        client.create_subscription(String, 'segmentation/status', lambda msg: status.append(msg.data), LATCHED_QOS)
        spinner = threading.Thread(target=executor.spin, daemon=True)
        spinner.start()

        target = (f'pixel ({settings.target_point[0]:g}, {settings.target_point[1]:g})'
                  if settings.target == 'pixel' else settings.target)
        log(f'replaying {args.bag} ({settings.frames} frame(s); frames_to_average {settings.frames_to_average}, '
            f'sensor_model {settings.sensor_model}, target {target}) ...')
        for note in settings.notes:
            log(note)
        t0 = time.perf_counter()
        player = BagPlayer(client, args.bag, rate=1.0, reliable=True)
        player.play_once(blocking=False)
        if not _wait_for_model(got_model, player, status, args.timeout):
            log(f'no GPIS within {time.perf_counter() - t0:.0f} s; giving up'
                + (f' (segmentation/status: {status[-1]})' if status else ''))
            if settings.target != 'pixel' or args.sensor is None:
                log('the segmentation settings can be given with --sensor and --target-pixel U V')
            return 1
        player.stop()
        log(f'GPIS ready after {time.perf_counter() - t0:.1f} s')
        posterior = messages.gpis_model_to_posterior(models[-1])

        plan_cli = client.create_client(GraspPlan, 'plan_grasp', qos_profile=SERVICE_QOS)  # docs/reliability.md
        exec_cli = client.create_client(ExecuteGrasp, 'execute_grasp', qos_profile=SERVICE_QOS)
        for c in (plan_cli, exec_cli):
            if not c.wait_for_service(timeout_sec=10.0):
                log(f'service {c.srv_name} not available')
                return 1
        if not settings.ground_truth:
            log(f'{args.bag.name} has no ground truth: the grasps are planned, not executed')
        rows, results = [], []
        for method in METHODS:
            log(f'planning with {method} ...')
            req = GraspPlan.Request(method=method, seed=args.seed)
            plan = plan_cli.call(req, timeout_sec=args.timeout)
            if plan is None or not plan.success:
                log(f'{method}: no grasp ({plan.message if plan else "timeout"})')
                rows.append({'method': method, 'success': False, 'message': plan.message if plan else 'timeout'})
                continue
            ex = None
            if settings.ground_truth:
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
                   'segmentation': settings.overrides(),
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
                sim = f'{r["sim_successes"]:>8d}/{r["sim_trials"]:<4d}' if settings.ground_truth else f'{"-":>9}    '
                print(f'{r["method"]:<14}{r["p_f"]:>7.2f}{r["q_mean"]:>11.3f}{sim}{r["planning_time_s"]:>10.2f}')
            else:
                print(f'{r["method"]:<14}  no grasp: {r["message"]}')
        print(f'\nwrote {out_dir}/: gpis.png, gpis_blur.png, ' +
              ', '.join(f'grasp_{m}.png' for m, *_ in results) + ', summary.json')
        return 0 if all(r['success'] for r in rows) else 1
    except (KeyboardInterrupt, ExternalShutdownException):
        return 130
    finally:
        # in order: the player's thread, the executor (and its spinning thread), then the player's publishers and
        # the nodes - nothing the executor may be waiting on is destroyed while it spins
        if player is not None:
            player.stop()
        executor.shutdown()
        if spinner is not None:
            spinner.join(timeout=5.0)
        if player is not None:
            player.destroy()
        for n in reversed(nodes):
            n.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    sys.exit(main())
