"""``gpis-grasp benchmark`` command line."""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from gpis_grasp_ros.core.sensing.params import PAPER_GRID_SIZE
from gpis_grasp_ros.tools.benchmark.evaluation import (
    METHOD_BY_KEY,
    BenchmarkResult,
    BenchmarkSettings,
    default_bags,
    object_letter,
    run_benchmark,
)
from gpis_grasp_ros.tools.benchmark.figures import (
    convergence_figure,
    fig4_figure,
    object_figure,
    pf_bar_chart,
    reliability_figure,
    runtime_chart,
    save_figure,
)
from gpis_grasp_ros.tools.benchmark.report import (
    calibration_markdown,
    calibration_summary,
    goal_figures,
    table1_markdown,
    write_results_csv,
)
from gpis_grasp_ros.tools.benchmark.scaling import run_scaling, scaling_chart, scaling_markdown
from gpis_grasp_ros.tools.evaluation.reports import write_json


def _save(fig: Any, path: Path) -> Path:
    return save_figure(fig, path)


def write_outputs(result: BenchmarkResult, out: Path, figures: bool = True) -> list[Path]:
    """Write table1.md, results.csv, objects.csv, summary.json, the PNG figures and the calibration outputs."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = [write_results_csv(out / 'results.csv', result.rows),
             write_results_csv(out / 'objects.csv', [o.info for o in result.objects])]
    (out / 'table1.md').write_text(table1_markdown(result))
    paths.append(out / 'table1.md')
    summary: dict[str, Any] = {
        'settings': asdict(result.settings), 'workers': result.workers, 'wall_time_s': result.wall_time_s,
        'cpu_count': os.cpu_count(), 'platform': platform.platform(), 'python': platform.python_version(),
        'goal_figures': goal_figures(result)}
    cal = None
    if result.calibration_rows:
        cal = calibration_summary(result)
        summary['calibration'] = cal
        paths.append(write_results_csv(out / 'calibration.csv', result.calibration_rows))
        (out / 'calibration.md').write_text(calibration_markdown(result, cal))
        paths.append(out / 'calibration.md')
    write_json(out / 'summary.json', summary, end='', indent=2, default=_json_default)
    paths.append(out / 'summary.json')
    if figures:
        paths.append(_save(pf_bar_chart(result), out / 'pf_bars.png'))
        paths.append(_save(runtime_chart(result), out / 'runtime.png'))
        paths.append(_save(fig4_figure(result), out / 'fig4.png'))
        for o in result.objects:
            paths.append(_save(object_figure(o), out / 'objects' / f'{o.object}.png'))
        conv = convergence_figure(result)
        if conv is not None:
            paths.append(_save(conv, out / 'convergence.png'))
        if cal is not None:
            paths.append(_save(reliability_figure(result.calibration_rows, cal['overall'],
                                                  f'Calibration, all {len(result.objects)} objects'),
                               out / 'reliability.png'))
            for o in result.objects:
                if o.calibration:
                    paths.append(_save(reliability_figure(o.calibration, cal['objects'][o.letter],
                                                          f'Calibration, object {o.letter}'),
                                       out / 'calibration' / f'reliability_{o.letter}.png'))
    return paths


def _json_default(v: Any) -> Any:
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, (tuple, set, frozenset)):
        return list(v)
    raise TypeError(f'not JSON serialisable: {type(v).__name__}')


def write_fig5(out: Path, settings: BenchmarkSettings, workers: int, progress: bool, figures: bool) -> str:
    """Run the Fig. 5 study into ``out/fig5`` and return its Markdown."""
    from gpis_grasp_ros.tools.benchmark.fig5 import fig5_figure, fig5_markdown, run_fig5

    d = Path(out) / 'fig5'
    result, summary = run_fig5(d, settings, workers, progress)
    write_results_csv(d / 'results.csv', result.rows)
    text = fig5_markdown(result, summary)
    (d / 'fig5.md').write_text(text)
    write_json(d / 'summary.json', {'patterns': summary, 'wall_time_s': result.wall_time_s}, end='', indent=2,
               default=_json_default)
    if figures:
        save_figure(fig5_figure(result, summary), d / 'fig5.png')
    return text


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
    p.add_argument('--grid-size', type=int, default=PAPER_GRID_SIZE,
                   help=f'force M of the M x M GPIS grid, Table I run (default: {PAPER_GRID_SIZE}, the paper\'s; 0 = '
                        'from the object and the cell size, as segmentation_node)')
    p.add_argument('--blur-samples', type=int, default=1000,
                   help='joint samples of the GPIS-Blur figures (default: 1000)')
    p.add_argument('--methods', default=None,
                   help='comma-separated method keys to run (default: all: ' + ','.join(METHOD_BY_KEY) + ')')
    p.add_argument('--calibration', action='store_true',
                   help='add the calibration study (predicted P_F vs simulated executions; calibration.md, '
                        'reliability.png)')
    p.add_argument('--calibration-candidates', type=int, default=200,
                   help='calibration: GP-P candidates per object spread over P_F (default: 200)')
    p.add_argument('--calibration-trials', type=int, default=50,
                   help='calibration: simulated executions per grasp (default: 50)')
    p.add_argument('--fig5', action='store_true',
                   help="also run the paper's Fig. 5 study on object D (bags written to OUT/fig5/bags)")
    p.add_argument('--no-figures', action='store_true', help='skip the PNG figures')
    p.add_argument('--quiet', action='store_true', help='no progress bar')
    p.add_argument('--scaling', action='store_true', help='run the runtime-vs-M study instead of Table I')
    p.add_argument('--object', default='A', help='scaling: object letter or bag path (default: A)')
    p.add_argument('--sizes', default='25,40,55,70,100',
                   help='scaling: comma-separated grid sides M (default: 25,40,55,70,100)')
    p.add_argument('--repeats', type=int, default=3,
                   help='scaling: runs per timing, the shortest is kept (default: 3)')
    args = p.parse_args(argv)
    for name in ('seeds', 'grasp_samples', 'shape_samples', 'workers', 'blur_samples', 'repeats'):
        if getattr(args, name) < 1:
            p.error(f'--{name.replace("_", "-")} must be >= 1')
    if args.grid_size < 0 or 0 < args.grid_size < 3:
        p.error('--grid-size must be 0 (from the cell size) or >= 3')
    if args.trials < 0:
        p.error('--trials must be >= 0')
    if args.calibration_candidates < 0 or args.calibration_trials < 1:
        p.error('--calibration-candidates must be >= 0 and --calibration-trials >= 1')
    if args.methods is not None:
        keys = tuple(k.strip() for k in str(args.methods).split(',') if k.strip())
        unknown = [k for k in keys if k not in METHOD_BY_KEY]
        if unknown or not keys:
            p.error(f'unknown method(s) {unknown or args.methods!r}; valid: {", ".join(METHOD_BY_KEY)}')
        args.methods = keys
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
    extra: dict[str, Any] = {'methods': args.methods} if args.methods is not None else {}
    if args.calibration:
        extra.update(calibration_candidates=args.calibration_candidates, calibration_trials=args.calibration_trials)
    settings = BenchmarkSettings(seeds=args.seeds, grasp_samples=args.grasp_samples,
                                 shape_samples=args.shape_samples, trials=args.trials, grid_size=args.grid_size,
                                 blur_samples=args.blur_samples, **extra)
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
            save_figure(scaling_chart(rows), out / 'scaling.png')
        print(text)
        print(f'wrote {out}/scaling.md, scaling.csv' + ('' if args.no_figures else ', scaling.png'))
        return 0
    bags = args.bags if args.bags is not None else default_bags()
    missing = [b for b in bags if not Path(b).exists()]
    if not bags or missing:
        print(f'gpis-grasp benchmark: bag(s) not found: {missing or "bags/*.mcap"}', file=sys.stderr)
        return 2
    stems = [Path(b).stem for b in bags]
    if len(set(stems)) != len(stems):
        dup = sorted({s for s in stems if stems.count(s) > 1})
        print(f'gpis-grasp benchmark: bags with the same name {dup} (objects are keyed by name): run each set '
              'separately with its own --out', file=sys.stderr)
        return 2
    if args.calibration and any(k not in settings.methods for k in ('gp-p',)):
        print('gpis-grasp benchmark: --calibration needs gp-p among --methods', file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    result = run_benchmark(bags, settings, args.workers, progress=not args.quiet)
    paths = write_outputs(result, out, figures=not args.no_figures)
    print(table1_markdown(result))
    if result.calibration_rows:
        print((out / 'calibration.md').read_text())
    if args.fig5:
        print(write_fig5(out, settings, args.workers, not args.quiet, not args.no_figures))
        paths.append(out / 'fig5')
    print(f'total wall time {time.perf_counter() - t0:.1f} s; wrote ' + ', '.join(
        str(p.relative_to(out)) for p in paths if p.parent == out or p.name == 'fig5'))
    return 0


if __name__ == '__main__':
    sys.exit(main())
