"""``gpis-grasp soak``: reliability figures of the ROS nodes run as separate processes.

Starts segmentation_node (cloud input, and a second one with image input), gpis_node,
planner_node and gripper_sim_node as separate processes (``python -m``, loopback-only discovery,
their own ROS domain), then, in this order:

1. **replay**: every shipped bag, one-shot, ``passes`` times, each pass a new ``gpis-grasp play
   --reliable`` process started after the nodes: frames used per estimate (from
   ``segmentation/status``) and the time from the end of the player process to the GPIS model;
2. **plan before**: one GP-GPIS-OPT plan with a fixed seed on the last bag's model;
3. **fuzz**: ``malformed`` malformed messages spread over all node inputs (clouds, images,
   camera info, occupancy and noise grids, GPIS models, ground truth SDF and centre of mass),
   each violating a size or value limit in its own way, then the same plan again: it must be
   identical; node deaths, guard exceptions ("unexpected" in the logs), rejected-message warnings;
4. **bad requests**: ``bad_requests`` degenerate plan_grasp / execute_grasp requests: every one
   must be answered success=false with a reason;
5. **load**: ``concurrent`` GP-GPIS-OPT requests at once from ``clients`` client nodes: answered
   %, p50/p95/max latency, throughput;
6. **timeout**: ``planning_timeout`` set at run time to its minimum (0.1 s): slow requests must be
   answered as timeouts, latency vs timeout, and the queue wait of the next request;
7. **matrix** and **models** (:mod:`gpis_grasp_ros.tools.soak_load`): the concurrency matrix (1-10 new
   client processes x workers 1, 2, 4 x max_queue 32, 128, 1024, bursts and closed loops: every request
   answered) and a stream of GPIS models into planner_node (RSS slope after warm-up);
8. **shutdown**: SIGINT to every node while a plan is running: exit codes, seconds to exit,
   error lines in the logs, and the in-flight caller's answer.

During the whole run every node is asked for a parameter every 50 ms (latency p50/p99/max per node,
while estimates, fits and plans run). ``--phases`` picks phases (the model from the first bag is used
when ``replay`` is left out).

Bounded in count and time; loopback only. Prints a table of the figures (and ``--json`` writes them).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from gpis_grasp_ros.tools.soak_load import rss_mb

ROOT = Path(__file__).resolve().parents[2]
NODES = {
    'segmentation_node': ['-p', 'input_reliability:=reliable'],
    # image input, fed only by the fuzzer (under /images so the bag replay does not reach it)
    'segmentation_images': ['-r', '__node:=segmentation_images', '-p', 'input_mode:=images',
                            '-r', 'camera/rgb/image_raw:=/images/camera/rgb/image_raw',
                            '-r', 'camera/depth/image_raw:=/images/camera/depth/image_raw',
                            '-r', 'camera/rgb/camera_info:=/images/camera/rgb/camera_info',
                            '-r', 'object/occupancy:=/images/object/occupancy',
                            '-r', 'object/noise_map:=/images/object/noise_map',
                            '-r', 'segmentation/status:=/images/segmentation/status'],
    'gpis_node': [],
    'planner_node': ['-p', 'max_queue:=128', '-p', 'workers:=2'],
    'gripper_sim_node': [],
}
MODULES = {'segmentation_images': 'segmentation_node'}
#: The parameter the pinger asks each node for.
PINGED = {'segmentation_node': 'frames_to_average', 'gpis_node': 'blur_samples', 'planner_node': 'max_queue',
          'gripper_sim_node': 'jaw_width'}
PHASES = ('replay', 'fuzz', 'bad_requests', 'load', 'matrix', 'models', 'timeout', 'shutdown')


def start_node(soak: Soak, name: str, extra: list[str], suffix: str = '') -> None:
    """Start node ``name`` as a process (its log in the soak folder; an earlier log of it is kept)."""
    module = f'gpis_grasp_ros.ros.nodes.{MODULES.get(name, name)}'
    if name in soak.logs:
        soak.logs[f'{name}{suffix or len(soak.logs)}#old'] = soak.logs[name]
    log = soak.workdir / f'{name}{suffix}.log'
    soak.logs[name] = log
    cmd = [sys.executable, '-X', 'faulthandler', '-m', module, '--ros-args', *extra]
    soak.procs[name] = subprocess.Popen(cmd, env=soak.env, stdout=log.open('w'), stderr=subprocess.STDOUT, cwd=ROOT)
    deadline = time.monotonic() + 60
    while 'started;' not in log.read_text():
        if soak.procs[name].poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f'{name} did not start; see {log}')
        time.sleep(0.2)


def _percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float('nan')


class Soak:
    """The node processes, a client node in this process, and the figures."""

    def __init__(self, domain: int, workdir: Path) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import MultiThreadedExecutor

        self.domain = domain
        self.workdir = workdir
        self.env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
                        PYTHONUNBUFFERED='1', RCUTILS_COLORIZED_OUTPUT='0')
        os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
        self.procs: dict[str, subprocess.Popen] = {}
        self.logs: dict[str, Path] = {}
        self.figures: dict[str, Any] = {}
        #: (node, stopped, started again) wall-clock times of every node the soak restarted
        self.restarts: list[tuple[str, float, float]] = []
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node('soak', context=self.context)
        self.executor = MultiThreadedExecutor(num_threads=8, context=self.context)
        self.executor.add_node(self.node)
        self._spin = threading.Thread(target=self.executor.spin, daemon=True)
        self._spin.start()

    # ------------------------------------------------------------------ processes
    def start_nodes(self) -> None:
        for name, extra in NODES.items():
            start_node(self, name, extra)
        self.deaths: list[str] = []

    def log_count(self, pattern: str, names: list[str] | None = None) -> int:
        return sum(len(re.findall(pattern, self.logs[n].read_text())) for n in (names or list(self.logs)))

    def close(self) -> None:
        import rclpy
        for p in self.procs.values():
            if p.poll() is None:
                p.kill()
        self.executor.shutdown(timeout_sec=2.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)

    # ------------------------------------------------------------------ helpers
    def call(self, client: Any, request: Any, timeout: float = 120.0) -> tuple[Any, float]:
        """Call a service, wait for the answer; (response or None, latency s)."""
        done = threading.Event()
        start = time.monotonic()
        future = client.call_async(request)
        future.add_done_callback(lambda _f: done.set())
        if not done.wait(timeout):
            return None, time.monotonic() - start
        return future.result(), time.monotonic() - start

    def plan_client(self, node: Any = None):
        from gpis_grasp_interfaces.srv import GraspPlan
        from gpis_grasp_ros.ros.nodes.common import SERVICE_QOS
        cli = (node or self.node).create_client(GraspPlan, 'plan_grasp', qos_profile=SERVICE_QOS)
        if not cli.wait_for_service(timeout_sec=20.0):
            raise RuntimeError('plan_grasp not available')
        return cli

    def set_param(self, node_name: str, name: str, value: Any) -> bool:
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter
        cli = self.node.create_client(SetParameters, f'/{node_name}/set_parameters')
        if not cli.wait_for_service(timeout_sec=10.0):
            return False
        res, _ = self.call(cli, SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()]))
        self.node.destroy_client(cli)
        return bool(res and res.results[0].successful)

    # ------------------------------------------------------------------ 1. replay
    def replay(self, bags: list[Path], passes: int) -> None:
        from std_msgs.msg import String

        from gpis_grasp_interfaces.msg import GpisModel
        from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS
        status: list[tuple[float, str]] = []
        models: list[tuple[float, Any]] = []
        self.node.create_subscription(String, 'segmentation/status',
                                      lambda m: status.append((time.monotonic(), m.data)), LATCHED_QOS)
        self.node.create_subscription(GpisModel, 'gpis/model', lambda m: models.append((time.monotonic(), m)),
                                      LATCHED_QOS)
        time.sleep(1.0)
        rows, frames_used, gpis_delays, failures, reasons = [], [], [], 0, []
        for bag in bags:
            for _ in range(passes):
                n_status, n_models = len(status), len(models)
                player = subprocess.run([sys.executable, '-m', 'gpis_grasp_ros.tools.cli', 'play', str(bag),
                                         '--reliable', '--require', '/camera/depth/points'],
                                        env=self.env, cwd=ROOT, capture_output=True, text=True,
                                        timeout=120)
                end = time.monotonic()
                deadline = end + 30
                while time.monotonic() < deadline and (len(status) == n_status or len(models) == n_models):
                    time.sleep(0.02)
                new = [s for _, s in status[n_status:]]
                used = [int(m.group(1)) for s in new for m in [re.search(r'from (\d+) frames', s)] if m]
                if player.returncode != 0 or len(models) == n_models or not used:
                    failures += 1
                    tail = (player.stderr.strip().splitlines() or [''])[-1][:200]
                    reasons.append(f'{bag.name}: player exit {player.returncode}, status {new[-1:] or "none"}, '
                                   f'model {"yes" if len(models) > n_models else "no"}; {tail}')
                    continue
                frames_used.append(used[0])
                gpis_delays.append(models[n_models][0] - end)
            rows.append(bag.name)
        self.figures['replay'] = {
            'bags': len(bags), 'passes_per_bag': passes, 'passes_ok': len(frames_used), 'failures': failures,
            'frames_used_min': min(frames_used) if frames_used else 0,
            'frames_used_max': max(frames_used) if frames_used else 0,
            'gpis_after_player_exit_s_max': max(gpis_delays) if gpis_delays else float('nan'),
            'gpis_after_player_exit_s_p50': _percentile(gpis_delays, 50),
            'failure_reasons': reasons,
        }
        self.last_model = models[-1][1] if models else None

    # ------------------------------------------------------------------ 2-3. fuzz
    def plan_once(self, seed: int = 11) -> Any:
        from gpis_grasp_interfaces.srv import GraspPlan
        res, _ = self.call(self.plan_client(), GraspPlan.Request(method='gp-gpis-opt', seed=seed))
        return res

    def fuzz(self, count: int, seed: int = 0) -> None:
        from geometry_msgs.msg import PointStamped
        from nav_msgs.msg import OccupancyGrid
        from sensor_msgs.msg import CameraInfo, Image, PointCloud2

        from gpis_grasp_interfaces.msg import FloatGrid, GpisModel
        from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS, RELIABLE_SENSOR_QOS
        rng = np.random.default_rng(seed)
        pubs = {
            'cloud': self.node.create_publisher(PointCloud2, 'camera/depth/points', RELIABLE_SENSOR_QOS),
            'rgb': self.node.create_publisher(Image, '/images/camera/rgb/image_raw', RELIABLE_SENSOR_QOS),
            'depth': self.node.create_publisher(Image, '/images/camera/depth/image_raw', RELIABLE_SENSOR_QOS),
            'info': self.node.create_publisher(CameraInfo, '/images/camera/rgb/camera_info', RELIABLE_SENSOR_QOS),
            'occupancy': self.node.create_publisher(OccupancyGrid, 'object/occupancy', LATCHED_QOS),
            'noise': self.node.create_publisher(FloatGrid, 'object/noise_map', LATCHED_QOS),
            'model': self.node.create_publisher(GpisModel, 'gpis/model', LATCHED_QOS),
            'sdf': self.node.create_publisher(FloatGrid, 'ground_truth/sdf', LATCHED_QOS),
            'com': self.node.create_publisher(PointStamped, 'ground_truth/center_of_mass', LATCHED_QOS),
        }
        from gpis_grasp_ros.tools.soak_fuzz import malformed_makers
        makers = malformed_makers(self.last_model)
        time.sleep(1.0)
        sent = dict.fromkeys(pubs, 0)
        rejected_before = self.log_count(r'\bignoring\b')
        names = list(makers)
        for k in range(count):
            topic = names[k % len(names)]
            pubs[topic].publish(makers[topic](rng))
            sent[topic] += 1
            if k % len(names) == len(names) - 1:
                time.sleep(0.003)
        time.sleep(3.0)
        deaths = [n for n, p in self.procs.items() if p.poll() is not None]
        self.figures['fuzz'] = {
            'malformed_sent': count, 'per_input': sent,
            'rejected_logged': self.log_count(r'\bignoring\b') - rejected_before,
            'node_deaths': len(deaths), 'guard_exceptions': self.log_count(r'unexpected \w+'),
            'memory_errors': self.log_count('MemoryError'),
            'peak_rss_mb': {n: round(rss_mb(p.pid, 'VmHWM'), 1) for n, p in self.procs.items()},
        }
        for pub in pubs.values():
            self.node.destroy_publisher(pub)

    # ------------------------------------------------------------------ 4. bad requests
    def bad_requests(self, count: int) -> None:
        from geometry_msgs.msg import PoseStamped

        from gpis_grasp_interfaces.srv import ExecuteGrasp, GraspPlan
        from gpis_grasp_ros.ros.nodes.common import SERVICE_QOS
        plan_cli = self.plan_client()
        exec_cli = self.node.create_client(ExecuteGrasp, 'execute_grasp', qos_profile=SERVICE_QOS)
        exec_cli.wait_for_service(timeout_sec=20.0)
        frame = self.last_model.header.frame_id if self.last_model is not None else ''
        com = self.last_model.center_of_mass

        def pose(x: float, y: float, qw: float = 1.0, frame_id: str = frame) -> PoseStamped:
            p = PoseStamped()
            p.header.frame_id = frame_id
            p.pose.position.x, p.pose.position.y, p.pose.position.z = float(x), float(y), float(com.z)
            p.pose.orientation.w = float(qw)
            return p

        nan = math.nan
        x0, y0 = com.x, com.y
        plans = [
            GraspPlan.Request(method='gp-nonsense'), GraspPlan.Request(uncertainty_penalty=nan),
            GraspPlan.Request(uncertainty_penalty=math.inf), GraspPlan.Request(uncertainty_penalty=1e12),
            GraspPlan.Request(method='gp-gpis-opt', num_initial_grasps=10 ** 6),
            GraspPlan.Request(method='gp-m', num_initial_grasps=10 ** 7), GraspPlan.Request(method='gp-gpis-opt!'),
        ]
        executes = [
            ExecuteGrasp.Request(jaw1=pose(x0, y0), jaw2=pose(x0, y0)),
            ExecuteGrasp.Request(jaw1=pose(nan, y0), jaw2=pose(x0 + 0.03, y0)),
            ExecuteGrasp.Request(jaw1=pose(x0, nan), jaw2=pose(x0 + 0.03, y0)),
            ExecuteGrasp.Request(jaw1=pose(x0 - 0.03, y0, qw=nan), jaw2=pose(x0 + 0.03, y0)),
            ExecuteGrasp.Request(jaw1=pose(x0 - 0.03, y0), jaw2=pose(1e6, y0)),
            ExecuteGrasp.Request(jaw1=pose(x0 - 0.03, y0), jaw2=pose(x0 + 0.03, y0), trials=10 ** 6),
            ExecuteGrasp.Request(jaw1=pose(x0 - 0.03, y0, frame_id='elsewhere'), jaw2=pose(x0 + 0.03, y0)),
            ExecuteGrasp.Request(jaw1=pose(x0 - 0.03, y0, qw=2.0), jaw2=pose(x0 + 0.03, y0)),
        ]
        answered = successes = with_reason = 0
        for k in range(count):
            if k % 2 == 0:
                res, _ = self.call(plan_cli, plans[(k // 2) % len(plans)], timeout=30)
            else:
                res, _ = self.call(exec_cli, executes[(k // 2) % len(executes)], timeout=30)
            if res is not None:
                answered += 1
                successes += int(res.success)
                with_reason += int(not res.success and bool(res.message.strip()))
        self.figures['bad_requests'] = {'sent': count, 'answered': answered, 'success_true': successes,
                                        'false_with_reason': with_reason}

    # ------------------------------------------------------------------ 5. load
    def load(self, concurrent: int, clients: int, n_initial: int) -> None:
        import rclpy

        from gpis_grasp_interfaces.srv import GraspPlan
        nodes = [rclpy.create_node(f'soak_client_{i}', context=self.context) for i in range(clients)]
        for n in nodes:
            self.executor.add_node(n)
        clis = [self.plan_client(n) for n in nodes]
        latencies: list[float] = []
        messages: list[str] = []
        lock = threading.Lock()
        done = threading.Semaphore(0)
        start = time.monotonic()
        for k in range(concurrent):
            sent = time.monotonic()
            fut = clis[k % clients].call_async(GraspPlan.Request(method='gp-gpis-opt', num_initial_grasps=n_initial,
                                                                 seed=k + 1))

            def finished(f: Any, sent: float = sent) -> None:
                with lock:
                    latencies.append(time.monotonic() - sent)
                    res = f.result()
                    messages.append('ok' if res.success else res.message)
                done.release()
            fut.add_done_callback(finished)
        deadline = time.monotonic() + 600
        for _ in range(concurrent):
            if not done.acquire(timeout=max(0.0, deadline - time.monotonic())):
                break
        elapsed = time.monotonic() - start
        self.figures['load'] = {
            'requests': concurrent, 'clients': clients, 'num_initial_grasps': n_initial,
            'answered': len(latencies), 'answered_pct': 100.0 * len(latencies) / concurrent,
            'planned_ok': messages.count('ok'),
            'queue_full': sum('queue full' in m for m in messages),
            'latency_p50_s': _percentile(latencies, 50), 'latency_p95_s': _percentile(latencies, 95),
            'latency_max_s': max(latencies) if latencies else float('nan'),
            'throughput_per_s': len(latencies) / elapsed if elapsed > 0 else float('nan'),
        }

    # ------------------------------------------------------------------ 6. timeout
    def timeouts(self, slow: int = 5) -> None:
        """planning_timeout at its minimum, set at run time; slow requests of two sizes.

        Per size: answers that are timeouts, answer latency minus the timeout, and the queue wait
        of a request sent right after each timeout (latency minus its own planning time): how soon
        the worker, stopped at the planner's next checkpoint, takes new work.
        """
        from gpis_grasp_interfaces.srv import GraspPlan
        cli = self.plan_client()
        ok_set = self.set_param('planner_node', 'planning_timeout', 0.1)
        out: dict[str, Any] = {'set_at_run_time': ok_set, 'planning_timeout_s': 0.1}
        for n_initial in (20, 200, 500, 1000):
            timed_out, overshoot, waits = 0, [], []
            for k in range(slow):
                res, latency = self.call(cli, GraspPlan.Request(method='gp-gpis-opt', num_initial_grasps=n_initial,
                                                                seed=k + 1))
                if res is not None and not res.success and 'planning_timeout' in res.message:
                    timed_out += 1
                    overshoot.append(latency - 0.1)
                nxt, lat2 = self.call(cli, GraspPlan.Request(method='gp-m', num_initial_grasps=10, seed=1))
                if nxt is not None:
                    waits.append(lat2 - (nxt.planning_time if math.isfinite(nxt.planning_time) else 0.0))
            out[f'N_g={n_initial}: answered_as_timeout'] = f'{timed_out}/{slow}'
            out[f'N_g={n_initial}: answer_after_timeout_s_max'] = max(overshoot) if overshoot else float('nan')
            out[f'N_g={n_initial}: next_request_queue_wait_s_max'] = max(waits) if waits else float('nan')
        self.set_param('planner_node', 'planning_timeout', 60.0)
        self.figures['timeout'] = out

    # ------------------------------------------------------------------ 7. shutdown
    def shutdown(self) -> None:
        from gpis_grasp_interfaces.srv import GraspPlan
        cli = self.plan_client()
        answer: dict[str, Any] = {}

        def call() -> None:
            res, _ = self.call(cli, GraspPlan.Request(method='gp-gpis-opt', num_initial_grasps=1000, seed=3), 30)
            answer['res'] = res
        caller = threading.Thread(target=call)
        caller.start()
        time.sleep(1.0)  # the plan is running
        errors_before = {n: self.log_count(r'\[ERROR\]', [n]) for n in self.procs}
        t0 = time.monotonic()
        for p in self.procs.values():
            p.send_signal(signal.SIGINT)
        exit_s, codes = {}, {}
        for name, p in self.procs.items():
            try:
                codes[name] = p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                codes[name] = None
                p.send_signal(signal.SIGABRT)  # faulthandler writes every thread's stack to the log
            exit_s[name] = round(time.monotonic() - t0, 2)
        caller.join(timeout=10)
        res = answer.get('res')
        self.figures['shutdown'] = {
            'exit_codes': codes, 'exit_after_s': exit_s,
            'error_lines': {n: self.log_count(r'\[ERROR\]', [n]) - errors_before[n] for n in self.procs},
            'in_flight_answer': None if res is None else res.message,
        }


def _same_plan(a: Any, b: Any) -> bool:
    if a is None or b is None or not (a.success and b.success):
        return False
    key = ('x', 'y', 'z')
    return all(getattr(a.jaw1.pose.position, k) == getattr(b.jaw1.pose.position, k) for k in key) and \
        all(getattr(a.jaw2.pose.position, k) == getattr(b.jaw2.pose.position, k) for k in key) and \
        a.probability_force_closure == b.probability_force_closure


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='gpis-grasp soak', description=__doc__.split('\n\n')[0])
    p.add_argument('--domain', type=int, default=17, help='ROS_DOMAIN_ID of the soak graph (default 17)')
    p.add_argument('--bags', nargs='*', default=None, help='bags to replay (default: every bags/*.mcap)')
    p.add_argument('--passes', type=int, default=10, help='one-shot replays per bag (default 10)')
    p.add_argument('--malformed', type=int, default=10000, help='malformed messages (default 10000)')
    p.add_argument('--bad-requests', type=int, default=500, help='degenerate requests (default 500)')
    p.add_argument('--concurrent', type=int, default=100, help='concurrent plan_grasp requests (default 100)')
    p.add_argument('--clients', type=int, default=5, help='client nodes sending them (default 5)')
    p.add_argument('--num-initial-grasps', type=int, default=5, help='N_g of the load requests (default 5)')
    p.add_argument('--phases', default=','.join(PHASES), help=f"comma-separated phases to run (default: all: "
                   f"{','.join(PHASES)})")
    p.add_argument('--matrix-client', choices=('plain', 'ask-again'), default='plain',
                   help="matrix clients: plain rclpy calls (default: every answer must arrive as sent) or "
                        "GraspPlannerClient's asking again")
    p.add_argument('--models', type=int, default=10000, help='GPIS models streamed into planner_node (default 10000)')
    p.add_argument('--model-rate', type=float, default=100.0,
                   help='models published per second (default 100; planner_node takes the newest when busy)')
    p.add_argument('--json', default=None, help='also write the figures to this JSON file')
    p.add_argument('--keep-logs', action='store_true', help='keep the node logs (their folder is printed)')
    return p


def _print(figures: dict[str, Any]) -> None:
    for section, values in figures.items():
        print(f'[{section}]')
        for k, v in values.items():
            if isinstance(v, float):
                v = f'{v:.3f}'
            print(f'  {k:<32} {v}')


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from gpis_grasp_ros.tools import soak_load
    bags = [Path(b) for b in args.bags] if args.bags else sorted((ROOT / 'bags').glob('*.mcap'))
    phases = [p.strip() for p in args.phases.split(',') if p.strip()]
    unknown = sorted(set(phases) - set(PHASES))
    if unknown:
        print(f"soak: unknown phase(s) {', '.join(unknown)}; known: {', '.join(PHASES)}", file=sys.stderr)
        return 2
    workdir = Path(tempfile.mkdtemp(prefix='gpis-soak-'))
    soak = Soak(args.domain, workdir)
    t0 = time.monotonic()
    try:
        soak.start_nodes()
        pinger = soak_load.ParameterPinger(soak, PINGED)
        pinger.start()
        soak.replay(bags if 'replay' in phases else bags[:1], args.passes if 'replay' in phases else 1)
        if soak.last_model is None:
            print('soak: no GPIS model after the replay; see ' + str(workdir), file=sys.stderr)
            return 1
        if 'fuzz' in phases:
            before = soak.plan_once()
            soak.fuzz(args.malformed)
            after = soak.plan_once()
            soak.figures['fuzz']['plan_identical_before_after'] = _same_plan(before, after)
        if 'bad_requests' in phases:
            soak.bad_requests(args.bad_requests)
        if 'load' in phases:
            soak.load(args.concurrent, args.clients, args.num_initial_grasps)
        if 'matrix' in phases:
            soak_load.matrix(soak, soak.last_model, retry=args.matrix_client == 'ask-again')
        if 'models' in phases:
            soak_load.model_stream(soak, soak.last_model, args.models, rate_hz=args.model_rate,
                                   sample_every=max(1, min(100, args.models // 40)))
        if 'timeout' in phases:
            soak.timeouts()
        soak.figures['parameter_latency'] = pinger.stop(soak.restarts)
        soak.figures['health'] = {
            'node_deaths_before_shutdown': sum(p.poll() is not None for p in soak.procs.values()),
            'guard_exceptions': soak.log_count(r'unexpected \w+'),
            'tracebacks': soak.log_count(r'Traceback'),
        }
        if 'shutdown' in phases:
            soak.shutdown()
    finally:
        soak.close()
    soak.figures['total_s'] = {'wall_clock_s': time.monotonic() - t0}
    _print(soak.figures)
    if args.json:
        Path(args.json).write_text(json.dumps(soak.figures, indent=2, default=str))
    print(f'node logs: {workdir}' if args.keep_logs else '', end='\n' if args.keep_logs else '')
    if not args.keep_logs:
        for f in workdir.iterdir():
            f.unlink()
        workdir.rmdir()
    return 0


if __name__ == '__main__':
    sys.exit(main())
