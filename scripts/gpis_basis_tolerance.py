"""What the GPIS basis' rank tolerance and cap cost and change: fixed-hyperparameter fits of ``bench e2e``'s grids.

    python scripts/gpis_basis_tolerance.py [--bags A_tape_dispenser.mcap head/A_tape_dispenser.mcap] [--repeats 5]
                                           [--tolerances 1e-15 1e-12 1e-10 1e-8] [--grid-size 25] [--max-rank 2000]

Each bag (under ``bags/``, 10 frames) is segmented as ``bench e2e`` does, its C and l found by the cold search, then
fitted with C and l fixed at every tolerance (``GpisParams.rank_tolerance``; ``--max-rank`` caps the modes, 0 = no
cap). Printed per fit: modes, CPU ms of the conditioning (``time.process_time``, one BLAS thread, mean of
``--repeats`` calls after one untimed call), and the largest change of the mean (m), of the variance (relative to
its largest value) and of the log marginal likelihood (nats) against the first tolerance's fit.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from gpis_grasp_ros.core.gpis.regression import GpisParams
from gpis_grasp_ros.core.pipeline import posterior_from_grids, publishable_grids
from gpis_grasp_ros.core.sensing import SensingParams, segment_frames
from gpis_grasp_ros.data.bags import load_bag

BAGS = Path(__file__).resolve().parents[1] / 'bags'


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--bags', nargs='+', default=['A_tape_dispenser.mcap', 'head/A_tape_dispenser.mcap'])
    ap.add_argument('--tolerances', nargs='+', type=float, default=[1e-15, 1e-12, 1e-10, 1e-8])
    ap.add_argument('--repeats', type=int, default=5)
    ap.add_argument('--grid-size', type=int, default=25, help='M of the grid (0 = the cell rule)')
    ap.add_argument('--max-rank', type=int, default=0, help='cap on the modes (0 = none)')
    args = ap.parse_args(argv)
    print('| bag | tolerance | modes | conditioning (CPU ms) | max |d mean| (m) | max |d var| / max var | d log lik |')
    print('|---|---:|---:|---:|---:|---:|---:|')
    for name in args.bags:
        scene = load_bag(BAGS / name, frames=10)
        result = segment_frames(scene.rgb_frames, scene.depth_frames, scene.intrinsics,
                                SensingParams(grid_size=args.grid_size), frame_id=scene.frame_id)
        grids = publishable_grids(result)
        with threadpool_limits(1):
            cold = posterior_from_grids(*grids)
            ref = None
            for tol in args.tolerances:
                params = GpisParams(optimize_hyperparameters=False, signal_variance=cold.params.signal_variance,
                                    length_scale=cold.params.length_scale, rank_tolerance=tol,
                                    max_rank=args.max_rank or 10 ** 7)
                post = posterior_from_grids(*grids, params)
                t0 = time.process_time()
                for _ in range(args.repeats):
                    post = posterior_from_grids(*grids, params)
                ms = (time.process_time() - t0) / args.repeats * 1e3
                ref = ref or post
                print(f'| {name} | {tol:g} | {post.rank} | {ms:.1f} | {np.abs(post.mean - ref.mean).max():.2g} | '
                      f'{np.abs(post.variance - ref.variance).max() / ref.variance.max():.2g} | '
                      f'{post.log_marginal_likelihood - ref.log_marginal_likelihood:.2g} |', flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
