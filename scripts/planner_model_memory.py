"""What planner_node keeps per GPIS model: RSS and Python allocations over many models, in one process.

The soak streams models through DDS and measures RSS only; this takes the transport away. A PlannerNode in
its own rclpy context takes ``--models`` models of one shipped bag (``--bag``, on ``--grid-size`` cells), each
with a new stamp, through its subscription callback as the executor would call it. After ``--warmup`` models
a ``tracemalloc`` snapshot is taken; at the end the RSS over the models after the warm-up is fitted with a line
and the largest growths of Python allocations since the snapshot are printed with their tracebacks. Memory the
node keeps per model shows there as a growth with the number of models; the model held at the end (allocated
after the snapshot, while the one held at the snapshot was allocated before tracing began) is the only expected
difference.

    python scripts/planner_model_memory.py --models 2000 --warmup 200
"""

from __future__ import annotations

import argparse
import gc
import time
import tracemalloc
from pathlib import Path

import numpy as np
import psutil

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--models', type=int, default=2000, help='models taken (default 2000)')
    p.add_argument('--warmup', type=int, default=200, help='models before the snapshot (default 200)')
    p.add_argument('--bag', default='H_marker.mcap', help='shipped bag in bags/ (default H_marker.mcap)')
    p.add_argument('--grid-size', type=int, default=25, help='M of the model (default 25; 0 = the cell rule)')
    p.add_argument('--top', type=int, default=5, help='allocation growths printed (default 5)')
    args = p.parse_args(argv)
    if not 0 < args.warmup < args.models:
        p.error('need 0 < --warmup < --models')

    import rclpy
    from rclpy.context import Context

    from gpis_grasp_ros.core.sensing import SensingParams
    from gpis_grasp_ros.data import messages
    from gpis_grasp_ros.data.bags import load_bag, posterior_from_scene
    from gpis_grasp_ros.ros import conversions
    from gpis_grasp_ros.ros.nodes.planner_node import PlannerNode

    factory = conversions.RclpyFactory()
    post, _ = posterior_from_scene(load_bag(ROOT / 'bags' / args.bag), SensingParams(grid_size=args.grid_size))
    msg = messages.posterior_to_gpis_model(post, messages.header(factory, 1, 'cam'), factory)
    context = Context()
    rclpy.init(context=context)
    proc = psutil.Process()
    rss, snap0, planner = [], None, None
    try:
        planner = PlannerNode(context=context)
        planner.get_logger().set_level(40)  # errors only: one info line per model otherwise
        t0 = time.monotonic()
        for k in range(args.models):
            msg.header.stamp.sec = k + 1
            planner._on_model(msg)
            if k == args.warmup:
                gc.collect()
                tracemalloc.start(25)
                snap0 = tracemalloc.take_snapshot()
            if k >= args.warmup:
                rss.append(proc.memory_info().rss / 1e6)
            if k % 250 == 0:
                print(f'{k:>6} models  RSS {proc.memory_info().rss / 1e6:7.1f} MB  {time.monotonic() - t0:6.0f} s',
                      flush=True)
        gc.collect()
        snap1 = tracemalloc.take_snapshot()
    finally:
        if planner is not None:
            planner.destroy_node()
        rclpy.shutdown(context=context)
    n = np.arange(len(rss))
    slope = float(np.polyfit(n, rss, 1)[0]) * 1000.0
    print(f'{args.bag} at M = {post.geometry.width}: {args.models} models; after the first {args.warmup}: RSS '
          f'{rss[0]:.1f} -> {rss[-1]:.1f} MB (min {min(rss):.1f}, max {max(rss):.1f}), slope {slope:+.2f} MB '
          f'per 1000 models')
    diffs = snap1.compare_to(snap0, 'traceback')
    grown = sum(d.size_diff for d in diffs if d.size_diff > 0) / 1e6
    print(f'Python allocations grown since the snapshot: {grown:.2f} MB in total; the largest:')
    for d in diffs[:args.top]:
        frames = [f'{f.filename.split("/gpis_grasp_ros/")[-1]}:{f.lineno}' for f in d.traceback[-4:]]
        print(f'  {d.size_diff / 1e3:+10.1f} kB in {d.count_diff:+d} blocks  ' + ' <- '.join(reversed(frames)))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
