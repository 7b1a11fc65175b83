"""Final P_F benchmark: where the S = 1000 Monte-Carlo estimate of one grasp spends its time, and whether the
float32 shape samples give the float64 ones' force-closure counts.

    python -m gpis_grasp_ros.bench pf [--repeats N] [--bags A_tape_dispenser head/A_tape_dispenser] [--grid-size M]
    python -m gpis_grasp_ros.bench pf --equivalence [--seeds 3]

Timing: CPU ms (``time.process_time``, one BLAS thread) of the parts of ``draw_shape_samples`` +
``probability_force_closure`` on the GP-GPIS-OPT grasp (seed 0) of each bag (on the nodes' default grid, the
3 mm cell rule, or with ``--grid-size M`` an M x M grid, e.g. the paper's 25), for float32 (the default) and
float64 samples, min / median of ``--repeats`` after a warm-up: the joint samples
(:meth:`GpisPosterior.sample_deviations`), the lookup grids (:meth:`SdfBank.from_deviations`), the Monte-Carlo
contacts and force closure, and the whole estimate. ``--equivalence``: on every shipped bag (top-down and
head), 24 grasps near the mean shape's centre of mass at random angles, S = 1000, seeds 0..``--seeds``-1:
trials whose force-closure outcome count differs between float32 and float64 samples, and the largest sample
difference (m).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from gpis_grasp_ros.core.planners import PlannerParams, plan
from gpis_grasp_ros.core.planners.context import PlanningContext
from gpis_grasp_ros.core.quality import draw_shape_samples, force_closure_successes, probability_force_closure
from gpis_grasp_ros.core.sdf_bank import SdfBank
from gpis_grasp_ros.core.sensing import SensingParams
from gpis_grasp_ros.data.bags import load_bag, posterior_from_scene

BAG_DIR = Path(__file__).resolve().parents[2] / 'bags'


def _ms(times: list[float]) -> str:
    return f'{min(times) * 1e3:.1f} / {float(np.median(times)) * 1e3:.1f}'


def time_parts(posterior, repeats: int, precision: type, n: int = 1000) -> dict[str, list[float]]:
    """CPU s of the final P_F's parts on ``posterior``'s GP-GPIS-OPT grasp (seed 0), ``repeats`` runs after one."""
    params = PlannerParams(n_shape_samples=n)
    grasp = plan('gp-gpis-opt', posterior, params, seed=0)
    ctx = PlanningContext(posterior, params)
    jaw1, jaw2 = grasp.jaw1[None], grasp.jaw2[None]
    out: dict[str, list[float]] = {'samples': [], 'grids': [], 'monte carlo': [], 'whole': []}
    for i in range(repeats + 1):
        rng = np.random.default_rng(i)
        c0 = time.process_time()
        dev = posterior.sample_deviations(n, rng, precision)
        c1 = time.process_time()
        bank = SdfBank.from_deviations(posterior.mean, dev, posterior.geometry)
        c2 = time.process_time()
        samples = draw_shape_samples(posterior, n, np.random.default_rng(100 + i), ctx.rho, precision)
        c3 = time.process_time()
        probability_force_closure(jaw1, jaw2, samples, ctx.gripper, ctx.sigma_g)
        c4 = time.process_time()
        del bank, samples
        c5 = time.process_time()
        whole = draw_shape_samples(posterior, n, np.random.default_rng(200 + i), ctx.rho, precision)
        probability_force_closure(jaw1, jaw2, whole, ctx.gripper, ctx.sigma_g)
        c6 = time.process_time()
        if i:
            for key, dt in zip(out, (c1 - c0, c2 - c1, c4 - c3, c6 - c5), strict=True):
                out[key].append(dt)
    return out


def equivalence(paths: list[Path], seeds: int, n: int = 1000, grasps: int = 24) -> None:
    """Print, per bag, the trials whose force-closure outcome differs between float32 and float64 samples."""
    params = PlannerParams()
    print('| bag | rank | max sample difference (m) | grasps with a different count | trials that differ |')
    print('|---|---:|---:|---:|---:|')
    total = differ = 0
    for path in paths:
        post = posterior_from_scene(load_bag(path))[0]
        ctx = PlanningContext(post, params)
        rng = np.random.default_rng(11)
        theta = rng.uniform(0, np.pi, grasps)
        u = np.stack([np.cos(theta), np.sin(theta)], axis=1)
        centre = post.center_of_mass() + rng.normal(0.0, 0.004, (grasps, 2))
        half = 0.5 * params.gripper.max_opening
        jaw1, jaw2 = centre - half * u, centre + half * u
        worst, n_grasps, n_trials = 0.0, 0, 0
        for seed in range(seeds):
            a, b = (draw_shape_samples(post, n, np.random.default_rng(seed), ctx.rho, precision)
                    for precision in (np.float64, np.float32))
            worst = max(worst, float(np.abs(a.bank.sdfs - b.bank.sdfs).max()))
            d = np.abs(force_closure_successes(jaw1, jaw2, a, params.gripper, ctx.sigma_g)
                       - force_closure_successes(jaw1, jaw2, b, params.gripper, ctx.sigma_g))
            n_grasps += int(np.count_nonzero(d))
            n_trials += int(d.sum())
        total += seeds * grasps * n
        differ += n_trials
        name = path.relative_to(BAG_DIR).with_suffix('')
        print(f'| {name} | {post.cov_factor.shape[1]} | {worst:.1e} | {n_grasps} of {seeds * grasps} | {n_trials} |',
              flush=True)
    print(f'\n{differ} of {total} trials differ')


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m gpis_grasp_ros.bench pf', description=__doc__.split('\n')[0])
    ap.add_argument('--repeats', type=int, default=15, help='timed runs (min and median reported)')
    ap.add_argument('--bags', nargs='+', default=['A_tape_dispenser', 'head/A_tape_dispenser'],
                    help='bags under bags/ (without .mcap)')
    ap.add_argument('--equivalence', action='store_true', help='float32 vs float64 counts on every shipped bag')
    ap.add_argument('--seeds', type=int, default=3, help='seeds of the equivalence table')
    ap.add_argument('--grid-size', type=int, default=0,
                    help='M of the M x M planning grid for the timing table (default 0: the nodes\' cell rule)')
    args = ap.parse_args(argv)
    with threadpool_limits(1):
        if args.equivalence:
            equivalence(sorted(BAG_DIR.glob('*.mcap')) + sorted(BAG_DIR.glob('head/*.mcap')), args.seeds)
            return 0
        grid = 'the nodes\' cell-rule grid' if args.grid_size <= 0 else f'M = {args.grid_size}'
        print(f'final P_F, S = 1000, {grid}, CPU ms min / median of {args.repeats}, one BLAS thread')
        print('\n| bag | S | basis | part | float32 | float64 |')
        print('|---|---:|---|---|---:|---:|')
        for bag in args.bags:
            post = posterior_from_scene(load_bag(BAG_DIR / f'{bag}.mcap'),
                                        SensingParams(grid_size=max(int(args.grid_size), 0)))[0]
            res = {p: time_parts(post, args.repeats, p) for p in (np.float32, np.float64)}
            for part in res[np.float32]:
                print(f'| {bag} | 1000 | rank {post.cov_factor.shape[1]} | {part} | {_ms(res[np.float32][part])} | '
                      f'{_ms(res[np.float64][part])} |', flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
