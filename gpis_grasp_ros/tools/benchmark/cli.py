"""``gpis-grasp benchmark`` command line."""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import asdict
from pathlib import Path

from gpis_grasp_ros.tools.benchmark.evaluation import (
    BenchmarkResult,
    BenchmarkSettings,
    default_bags,
    object_letter,
    run_benchmark,
)
from gpis_grasp_ros.tools.benchmark.figures import _write_png, fig4_figure, object_figure, pf_bar_chart, runtime_chart
from gpis_grasp_ros.tools.benchmark.report import aggregate, goal_figures, table1_markdown, write_results_csv
from gpis_grasp_ros.tools.benchmark.scaling import run_scaling, scaling_chart, scaling_markdown


def write_outputs(result: BenchmarkResult, out: Path, figures: bool = True) -> list[Path]:
    """Write table1.md, results.csv, objects.csv, summary.json and (optionally) the PNG figures."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = [write_results_csv(out / 'results.csv', result.rows),
             write_results_csv(out / 'objects.csv', [o.info for o in result.objects])]
    (out / 'table1.md').write_text(table1_markdown(result))
    paths.append(out / 'table1.md')
    summary = {'settings': asdict(result.settings), 'workers': result.workers, 'wall_time_s': result.wall_time_s,
               'cpu_count': os.cpu_count(), 'platform': platform.platform(), 'python': platform.python_version(),
               'goal_figures': goal_figures(result)}
    (out / 'summary.json').write_text(json.dumps(summary, indent=2))
    paths.append(out / 'summary.json')
    if figures:
        paths.append(_write_png(out / 'pf_bars.png', pf_bar_chart(result)))
        paths.append(_write_png(out / 'runtime.png', runtime_chart(result)))
        paths.append(_write_png(out / 'fig4.png', fig4_figure(result)))
        for o in result.objects:
            paths.append(_write_png(out / 'objects' / f'{o.object}.png', object_figure(o, aggregate(o.rows))))
    return paths




# ------------------------------------------------------------------------------------------
# Command line
# ------------------------------------------------------------------------------------------


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog='gpis-grasp benchmark', description=__doc__.splitlines()[0])
    p.add_argument('--bags', nargs='+', type=Path, default=None, help='bags to run (default: bags/*.mcap)')
    p.add_argument('--out', type=Path, default=Path('out/benchmark'), help='output directory (default: out/benchmark)')
    p.add_argument('--workers', type=int, default=os.cpu_count() or 1,
                   help='worker processes, 1 = serial in this process (default: os.cpu_count())')
    p.add_argument('--seeds', type=int, default=3, help='seeds 0 .. N-1 per object and method (default: 3)')
    p.add_argument('--grasp-samples', type=int, default=1000,
                   help='K heuristic grasp candidates of GP-M / GP-P (default: 1000)')
    p.add_argument('--shape-samples', type=int, default=1000,
                   help='S shape samples of every Monte-Carlo P_F (default: 1000)')
    p.add_argument('--trials', type=int, default=20, help='simulated executions per grasp and seed (default: 20)')
    p.add_argument('--grid-size', type=int, default=25, help='M of the M x M GPIS grid, Table I run (default: 25)')
    p.add_argument('--blur-samples', type=int, default=1000,
                   help='joint samples of the GPIS-Blur figures (default: 1000)')
    p.add_argument('--no-figures', action='store_true', help='skip the PNG figures')
    p.add_argument('--quiet', action='store_true', help='no progress bar')
    p.add_argument('--scaling', action='store_true', help='run the runtime-vs-M study instead of Table I')
    p.add_argument('--object', default='A', help='scaling: object letter or bag path (default: A)')
    p.add_argument('--sizes', default='25,40,55,70,100',
                   help='scaling: comma-separated grid sides M (default: 25,40,55,70,100)')
    p.add_argument('--repeats', type=int, default=3,
                   help='scaling: runs per timing, the shortest is kept (default: 3)')
    args = p.parse_args(argv)
    for name in ('seeds', 'grasp_samples', 'shape_samples', 'workers', 'grid_size', 'blur_samples', 'repeats'):
        if getattr(args, name) < 1:
            p.error(f'--{name.replace("_", "-")} must be >= 1')
    if args.trials < 0:
        p.error('--trials must be >= 0')
    return args


def _resolve_object(spec: str) -> Path:
    path = Path(spec)
    if path.suffix == '.mcap' and path.exists():
        return path
    for bag in default_bags():
        if object_letter(bag.stem).upper() == spec.upper() or bag.stem == spec:
            return bag
    raise FileNotFoundError(f'no bag for object {spec!r} in bags/')


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    settings = BenchmarkSettings(seeds=args.seeds, grasp_samples=args.grasp_samples,
                                 shape_samples=args.shape_samples, trials=args.trials, grid_size=args.grid_size,
                                 blur_samples=args.blur_samples)
    out: Path = args.out
    if args.scaling:
        try:
            bag = _resolve_object(args.object)
            sizes = [int(v) for v in str(args.sizes).split(',') if v.strip()]
        except (FileNotFoundError, ValueError) as exc:
            print(f'gpis-grasp benchmark: {exc}', file=sys.stderr)
            return 2
        t0 = time.perf_counter()
        rows = run_scaling(bag, sizes, settings, args.repeats, progress=not args.quiet)
        wall = time.perf_counter() - t0
        out.mkdir(parents=True, exist_ok=True)
        write_results_csv(out / 'scaling.csv', rows)
        text = scaling_markdown(rows, settings, args.repeats, wall)
        (out / 'scaling.md').write_text(text)
        if not args.no_figures:
            _write_png(out / 'scaling.png', scaling_chart(rows))
        print(text)
        print(f'wrote {out}/scaling.md, scaling.csv' + ('' if args.no_figures else ', scaling.png'))
        return 0
    bags = args.bags if args.bags is not None else default_bags()
    missing = [b for b in bags if not Path(b).exists()]
    if not bags or missing:
        print(f'gpis-grasp benchmark: bag(s) not found: {missing or "bags/*.mcap"}', file=sys.stderr)
        return 2
    result = run_benchmark(bags, settings, args.workers, progress=not args.quiet)
    write_outputs(result, out, figures=not args.no_figures)
    print(table1_markdown(result))
    print(f'wrote {out}/: table1.md, results.csv, objects.csv, summary.json'
          + ('' if args.no_figures else ', pf_bars.png, runtime.png, fig4.png, objects/*.png'))
    return 0


if __name__ == '__main__':
    sys.exit(main())
