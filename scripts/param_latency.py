"""planner_node's parameter latency under plan bursts and a model stream, against an idle node's.

    python scripts/param_latency.py --seconds 60 --domain 63 [--executor rclpy]

planner_node (``workers: 2``, ``max_queue: 128``, S = 10) and gripper_sim_node (idle: the floor set by the
machine's load) run as processes; a GPIS model of bag A is published 4 times a second, rounds of 5 new client
processes x 40 concurrent GP-M calls follow each other, and a pinger process asks both nodes for a parameter
every 50 ms. ``--executor rclpy`` runs planner_node with rclpy's plain MultiThreadedExecutor (every callback
group in one spinning thread) instead of the nodes' executor (the parameter services in a loop of their own),
for a before/after. Prints the pinger's table (ms) and the load average. Loopback only, own domain.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from gpis_grasp_interfaces.msg import GpisModel
from gpis_grasp_ros.data import messages
from gpis_grasp_ros.data.bags import load_bag, posterior_from_scene
from gpis_grasp_ros.ros import conversions
from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS
from gpis_grasp_ros.tools.soak import ROOT, Soak, start_node

PLAIN_RCLPY = '''import sys
from rclpy.executors import MultiThreadedExecutor
from gpis_grasp_ros.ros.nodes import common, planner_node
class Plain(MultiThreadedExecutor):
    def __init__(self, n, _node): super().__init__(num_threads=n)
    def start_defaults(self): pass
    def stop_defaults(self): pass
common.NodeExecutor = Plain
sys.exit(planner_node.main())
'''
PLANNER = ['-p', 'max_queue:=128', '-p', 'workers:=2', '-p', 'num_shape_samples:=10']


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--seconds', type=float, default=60.0)
    ap.add_argument('--domain', type=int, default=63)
    ap.add_argument('--executor', choices=('nodes', 'rclpy'), default='nodes')
    args = ap.parse_args()
    soak = Soak(args.domain, Path(tempfile.mkdtemp(prefix='param-latency-')))
    f = conversions.RclpyFactory()
    post, _ = posterior_from_scene(load_bag(next((ROOT / 'bags').glob('A_*.mcap'))))
    model = messages.posterior_to_gpis_model(post, messages.header(f, 1, 'cam'), f)
    stop = threading.Event()
    try:
        if args.executor == 'rclpy':
            log = soak.workdir / 'planner_node.log'
            soak.logs['planner_node'] = log
            soak.procs['planner_node'] = subprocess.Popen([sys.executable, '-c', PLAIN_RCLPY, '--ros-args', *PLANNER],
                                                          env=soak.env, stdout=log.open('w'), stderr=subprocess.STDOUT)
            while 'started;' not in log.read_text():
                time.sleep(0.2)
        else:
            start_node(soak, 'planner_node', PLANNER)
        start_node(soak, 'gripper_sim_node', [])
        pub = soak.node.create_publisher(GpisModel, 'gpis/model', LATCHED_QOS)
        pub.publish(model)
        time.sleep(3.0)
        pinger = subprocess.Popen([sys.executable, '-m', 'gpis_grasp_ros.tools.soak_load', 'pinger', '--duration',
                                   str(args.seconds), '--node', 'planner_node=max_queue', '--node',
                                   'gripper_sim_node=jaw_width'], env=soak.env, stdout=subprocess.PIPE, text=True)

        def models() -> None:
            y, rng, k = np.asarray(model.train_y), np.random.default_rng(0), 0
            while not stop.is_set():
                m = copy.copy(model)
                m.header = copy.deepcopy(model.header)
                m.header.stamp.sec = 2 + k
                m.train_y = (y + rng.normal(0.0, 1e-5, y.shape)).tolist()
                pub.publish(m)
                k += 1
                time.sleep(0.25)
        threading.Thread(target=models, daemon=True).start()
        start, seed = time.monotonic(), 1000
        while time.monotonic() - start < args.seconds - 5:
            procs = []
            for _ in range(5):
                seed += 40
                procs.append(subprocess.Popen([sys.executable, '-m', 'gpis_grasp_ros.tools.soak_load', 'client',
                                               '--count', '40', '--mode', 'burst', '--seed', str(seed)],
                                              env=soak.env, stdout=subprocess.PIPE, text=True))
            for p in procs:
                p.communicate(timeout=300)
        out, _ = pinger.communicate(timeout=120)
        table = json.loads(out.strip().splitlines()[-1])
        print(f'executor: {args.executor}; load average {os.getloadavg()[0]:.1f}')
        for name, row in table.items():
            print(f"  {name:<18} calls {row['calls']:4d}  p50 {row['p50_ms']:6.1f}  p99 {row['p99_ms']:6.1f}  "
                  f"max {row['max_ms']:6.1f} ms  unanswered {row['unanswered']}")
    finally:
        stop.set()
        soak.close()
    return 0


if __name__ == '__main__':
    sys.exit(main())
