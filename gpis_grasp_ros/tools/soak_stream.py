"""``gpis-grasp soak-stream``: a live camera at 30 Hz into the node chain, a plan every second (a benchmark).

A camera process publishes RGB-D frames continuously on realsense-ros topic names
(``/camera/camera/color/image_raw`` rgb8, ``/camera/camera/aligned_depth_to_color/image_raw`` 16UC1 mm,
``/camera/camera/color/camera_info``; sensor-data QoS, every frame stamped with the wall clock when it is
sent) at 640 x 480 or 1280 x 720: object A on the table seen whole-frame (no crop; ``frames`` distinct noisy
renderings sent in turn). segmentation_node (image input, best effort), gpis_node and planner_node run as
processes with their default settings; ``plan_grasp`` is called every second through
:class:`~gpis_grasp_ros.ros.client.GraspPlannerClient` (the action, asking again when a reply is lost). The
nodes work on the newest frames and drop what they cannot use (sensor-data queues of 5 frames, latched
depth-1 grids and models).

Measured: frame -> model latency (a GpisModel's stamp is the newest frame of its burst: the time from that
frame being sent to the model arriving here), plan request -> answer latency and the answered fraction,
estimates per second and frames used, and every node's RSS and threads over time (sampled every 5 s).
Bounded in time (``--duration``) and count; loopback only; its own ROS domain.

    gpis-grasp soak-stream --resolution 640x480 --duration 600 --domain 63 --json stream.json
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from gpis_grasp_ros.tools.soak_load import rss_mb, slope_per_1000, threads

#: realsense-ros (4.x) topic names of the colour image, the depth aligned to it and the colour intrinsics.
TOPICS = {'rgb': '/camera/camera/color/image_raw', 'depth': '/camera/camera/aligned_depth_to_color/image_raw',
          'info': '/camera/camera/color/camera_info'}
NODES = {
    'segmentation_node': ['-p', 'input_mode:=images', '-r', f"camera/rgb/image_raw:={TOPICS['rgb']}",
                          '-r', f"camera/depth/image_raw:={TOPICS['depth']}",
                          '-r', f"camera/rgb/camera_info:={TOPICS['info']}"],
    'gpis_node': [],
    'planner_node': [],
}
RSS_PERIOD = 5.0  # s between memory samples
WARM_UP = 60.0  # s before the RSS slope is counted
MAX_PLANS_WAITING = 30  # plan calls in flight at most (a plan every second)


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float('nan')


# --------------------------------------------------------------------------- the camera process
def run_camera(width: int, height: int, rate: float, duration: float, frames: int) -> dict[str, Any]:
    """Publish ``frames`` rendered frames in turn at ``rate`` Hz for ``duration`` s (a late tick is skipped,
    never sent in a burst); counts."""
    import rclpy
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import CameraInfo, Image

    from gpis_grasp_ros.data import messages
    from gpis_grasp_ros.ros import conversions
    from gpis_grasp_ros.tools.bench_e2e import whole_frame_scene

    rgb, depth, k = whole_frame_scene(width, height, frames=frames)
    f = conversions.RclpyFactory()
    hdr = messages.header(f, 0, 'camera_color_optical_frame')
    rgb_msgs = [messages.numpy_to_image(f, x, 'rgb8', hdr) for x in rgb]
    depth_msgs = [messages.numpy_to_image(f, x, '16UC1', hdr) for x in depth]
    info = messages.intrinsics_to_camera_info(f, k.fx, k.fy, k.cx, k.cy, k.width, k.height, hdr)
    rclpy.init()
    node = rclpy.create_node(f'soak_camera_{os.getpid()}')
    pubs = {name: node.create_publisher(Image if name != 'info' else CameraInfo, topic, qos_profile_sensor_data)
            for name, topic in TOPICS.items()}
    wait_end = time.monotonic() + 30.0
    while time.monotonic() < wait_end and pubs['depth'].get_subscription_count() == 0:
        time.sleep(0.1)
    sent = late = 0
    period = 1.0 / rate
    start = time.monotonic()
    tick = 0
    while time.monotonic() - start < duration:
        due = start + tick * period
        now = time.monotonic()
        if now < due:
            time.sleep(due - now)
        elif now - due > period:  # behind: skip to the current tick
            missed = int((now - due) / period)
            late += missed
            tick += missed
            continue
        stamp = messages.time_msg(f, time.time_ns())
        i = tick % len(rgb_msgs)
        for msg in (rgb_msgs[i], depth_msgs[i], info):
            msg.header.stamp = stamp
        pubs['info'].publish(info)
        pubs['rgb'].publish(rgb_msgs[i])
        pubs['depth'].publish(depth_msgs[i])
        sent += 1
        tick += 1
    elapsed = time.monotonic() - start
    return {'frames_sent': sent, 'ticks_skipped_late': late, 'rate_hz': sent / elapsed, 'seconds': elapsed}


# --------------------------------------------------------------------------- the driver
class Stream:
    """Subscribes the chain's outputs and calls plan_grasp every second, in the soak's own node."""

    def __init__(self, soak: Any) -> None:
        from std_msgs.msg import String

        from gpis_grasp_interfaces.msg import GpisModel
        from gpis_grasp_ros.data import messages
        from gpis_grasp_ros.ros.client import GraspPlannerClient
        from gpis_grasp_ros.ros.nodes.common import LATCHED_QOS
        self.soak = soak
        self.t0 = time.monotonic()
        self.models: list[tuple[float, float]] = []  # (time since start, frame -> model latency s)
        self.status: list[tuple[float, str]] = []
        self.plans: list[tuple[float, float, bool, str]] = []  # (sent since start, latency, success, status)
        self._lock = threading.Lock()
        self._stamp = messages.stamp_to_ns

        self.wall_start = time.time()
        self.foreign_models = 0

        def on_model(msg: Any) -> None:
            stamp = self._stamp(msg.header.stamp) * 1e-9
            with self._lock:
                if stamp < self.wall_start:  # not from this run's camera (another graph in the same domain)
                    self.foreign_models += 1
                    return
                self.models.append((time.monotonic() - self.t0, time.time() - stamp))
        soak.node.create_subscription(GpisModel, 'gpis/model', on_model, LATCHED_QOS)
        soak.node.create_subscription(String, 'segmentation/status',
                                      lambda m: self.status.append((time.monotonic() - self.t0, m.data)), LATCHED_QOS)
        self.client = GraspPlannerClient('soak_stream_client', context=soak.context)
        self.waiting = threading.Semaphore(MAX_PLANS_WAITING)
        self.plans_skipped = 0

    def plan_once(self, seed: int) -> None:
        if not self.waiting.acquire(blocking=False):
            self.plans_skipped += 1
            return

        def call() -> None:
            sent = time.monotonic()
            try:
                res = self.client.plan(seed=seed, timeout=60.0)
                with self._lock:
                    self.plans.append((sent - self.t0, time.monotonic() - sent, bool(res.success),
                                       res.status if res.success else res.message[:60]))
            finally:
                self.waiting.release()
        threading.Thread(target=call, daemon=True).start()

    def close(self) -> None:
        self.client.close()


def _per_minute(rows: list[tuple[float, float]], duration: float) -> list[str]:
    out = []
    for m in range(int(np.ceil(duration / 60.0))):
        v = [x for t, x in rows if m * 60 <= t < (m + 1) * 60]
        out.append(f'{len(v)}: p50 {_pct(v, 50):.2f} p95 {_pct(v, 95):.2f}' if v else '0')
    return out


def run(args: argparse.Namespace) -> dict[str, Any]:
    from gpis_grasp_ros.tools.soak import Soak, start_node
    width, height = (int(x) for x in args.resolution.lower().split('x'))
    workdir = Path(tempfile.mkdtemp(prefix='gpis-stream-'))
    soak = Soak(args.domain, workdir)
    figures: dict[str, Any] = {'resolution': f'{width}x{height}', 'duration_s': args.duration,
                               'load_before': os.getloadavg()}
    camera = stream = None
    try:
        for name, extra in NODES.items():
            start_node(soak, name, extra)
        stream = Stream(soak)
        camera = subprocess.Popen([sys.executable, '-m', 'gpis_grasp_ros.tools.soak_stream', 'camera',
                                   '--width', str(width), '--height', str(height), '--rate', str(args.rate),
                                   '--duration', str(args.duration), '--frames', str(args.frames)],
                                  env=soak.env, stdout=subprocess.PIPE, text=True)
        rss: dict[str, list[tuple[float, float]]] = {n: [] for n in NODES}
        loads = []
        start = time.monotonic()
        stream.t0 = start
        next_plan = next_rss = start
        seed = 0
        while camera.poll() is None and time.monotonic() - start < args.duration + 120:
            now = time.monotonic()
            if now >= next_plan and now - start < args.duration:
                seed += 1
                stream.plan_once(seed)
                next_plan += 1.0
            if now >= next_rss:
                for name in NODES:
                    rss[name].append((now - start, rss_mb(soak.procs[name].pid)))
                loads.append(os.getloadavg()[0])
                next_rss += RSS_PERIOD
            time.sleep(0.05)
        cam_out, _ = camera.communicate(timeout=60)
        time.sleep(5.0)  # the last plans and models
        figures['camera'] = json.loads(cam_out.strip().splitlines()[-1]) if cam_out.strip() else {}
        figures['load_avg_1min_during'] = {'p50': _pct(loads, 50), 'max': max(loads) if loads else float('nan')}
        latencies = [x for _, x in stream.models]
        used = [int(m.group(1)) for _, s in stream.status for m in [re.search(r'from (\d+) frames', s)] if m]
        failed = sum(s.startswith('failed') for _, s in stream.status)
        figures['frame_to_model'] = {
            'models': len(latencies), 'per_s': len(latencies) / args.duration,
            'p50_s': _pct(latencies, 50), 'p95_s': _pct(latencies, 95), 'p99_s': _pct(latencies, 99),
            'max_s': max(latencies) if latencies else float('nan'),
            'estimates_ok': len(used), 'estimates_failed': failed,
            'models_not_from_this_camera': stream.foreign_models,
            'bursts_superseded': soak.log_count(r'a newer burst replaces', ['segmentation_node']),
            'frames_used': int(sum(used)), 'frames_per_estimate': f'{min(used, default=0)}-{max(used, default=0)}',
            'per_minute': _per_minute(stream.models, args.duration),
        }
        plan_lat = [lat for _, lat, _, _ in stream.plans]
        sent = seed
        figures['plans'] = {
            'sent': sent, 'answered': len(stream.plans), 'answered_pct': 100.0 * len(stream.plans) / max(sent, 1),
            'planned_ok': sum(ok for _, _, ok, _ in stream.plans), 'not_sent_30_waiting': stream.plans_skipped,
            'p50_s': _pct(plan_lat, 50), 'p95_s': _pct(plan_lat, 95), 'p99_s': _pct(plan_lat, 99),
            'max_s': max(plan_lat) if plan_lat else float('nan'),
            'failures': sorted({s for _, _, ok, s in stream.plans if not ok})[:5],
            'per_minute': _per_minute([(t, lat) for t, lat, _, _ in stream.plans], args.duration),
        }
        figures['rss_mb'] = {}
        for name, rows in rss.items():
            ys = [y for _, y in rows]
            warm = [(t, y) for t, y in rows if t >= min(WARM_UP, args.duration / 2)]
            figures['rss_mb'][name] = {
                'first': ys[0] if ys else float('nan'), 'last': ys[-1] if ys else float('nan'),
                'max': max(ys) if ys else float('nan'), 'threads_at_end': threads(soak.procs[name].pid),
                'slope_after_warm_up_mb_per_min': slope_per_1000([t for t, _ in warm], [y for _, y in warm]) * 0.06,
                'per_minute': [round(y, 0) for t, y in rows if int(t) % 60 < RSS_PERIOD],
            }
        figures['health'] = {'node_deaths': sum(p.poll() is not None for p in soak.procs.values()),
                             'guard_exceptions': soak.log_count(r'unexpected \w+'),
                             'tracebacks': soak.log_count(r'Traceback')}
    finally:
        if camera is not None and camera.poll() is None:
            camera.kill()
        if stream is not None:
            stream.close()
        soak.close()
        if not args.keep_logs:
            for f in workdir.iterdir():
                f.unlink()
            workdir.rmdir()
    return figures


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='gpis-grasp soak-stream', description=__doc__.split('\n\n')[0])
    p.add_argument('--resolution', default='640x480', help='WIDTHxHEIGHT of the camera (default 640x480)')
    p.add_argument('--duration', type=float, default=600.0, help='seconds of streaming (default 600)')
    p.add_argument('--rate', type=float, default=30.0, help='camera frames per second (default 30)')
    p.add_argument('--frames', type=int, default=10, help='distinct rendered frames sent in turn (default 10)')
    p.add_argument('--domain', type=int, default=17, help='ROS_DOMAIN_ID of the graph (default 17)')
    p.add_argument('--json', default=None, help='also write the figures to this JSON file')
    p.add_argument('--keep-logs', action='store_true', help='keep the node logs')
    return p


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == 'camera':
        c = argparse.ArgumentParser(prog='soak_stream camera')
        c.add_argument('--width', type=int, required=True)
        c.add_argument('--height', type=int, required=True)
        c.add_argument('--rate', type=float, required=True)
        c.add_argument('--duration', type=float, required=True)
        c.add_argument('--frames', type=int, default=10)
        a = c.parse_args(argv[1:])
        print(json.dumps(run_camera(a.width, a.height, a.rate, a.duration, a.frames)), flush=True)
        os._exit(0)  # no teardown of the publishers (the context may abort)
    args = build_parser().parse_args(argv)
    figures = run(args)
    for section, values in figures.items():
        print(f'[{section}]')
        for k, v in (values.items() if isinstance(values, dict) else [('', values)]):
            print(f'  {k:<34} {v:.3f}' if isinstance(v, float) else f'  {k:<34} {v}')
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2, default=str))
    return 0


if __name__ == '__main__':
    sys.exit(main())
