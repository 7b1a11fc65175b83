"""``gpis-grasp evaluate-real MANIFEST``: the planners on real captures with ground truth, as a table.

Examples::

    gpis-grasp evaluate-real manifests/bags_real.yaml --seeds 3 --oracle
    gpis-grasp evaluate-real my_captures.yaml --root /data/captures --methods gp-gpis-opt --out results/real \\
        --workers 2

Every capture of the manifest (:mod:`~gpis_grasp_ros.tools.evaluate_real.manifest`) is imported in memory
(as ``import-rgbd`` would write it; ``--keep-bags DIR`` writes the bags too), whole-frame and cropped, segmented
as segmentation_node does (``target:=pixel``), and each method plans with each seed; the grasp is executed
``--trials`` times on the truth (``import-rgbd --evaluate``'s evaluation). Prints a table per unit and a summary
line; ``--out DIR`` also writes results.jsonl, results.json, table.md and reliability.png.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
from pathlib import Path

from gpis_grasp_ros.core.sensing.params import SensingParams
from gpis_grasp_ros.tools.evaluate_real import report
from gpis_grasp_ros.tools.evaluate_real.manifest import load_manifest
from gpis_grasp_ros.tools.evaluate_real.tasks import import_unit, make_tasks, run_real_task
from gpis_grasp_ros.tools.evaluation.runner import EXECUTORS, run_evaluation
from gpis_grasp_ros.tools.evaluation.tasks import DEFAULT_METHODS


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog='gpis-grasp evaluate-real', description=__doc__.split('\n\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('manifest', help='YAML manifest of the captures (raw files or imported bags)')
    p.add_argument('--root', help="directory the manifest's capture paths are relative to (default: its root: "
                   "key, relative to the manifest file; else the manifest's directory)")
    p.add_argument('--methods', default=','.join(DEFAULT_METHODS),
                   help=f"comma-separated planners (default {','.join(DEFAULT_METHODS)})")
    p.add_argument('--only', action='append', metavar='TEXT',
                   help="only the units whose id (capture|variant, e.g. 'gqcnn_single_0|whole') contains TEXT; "
                   'repeat for several (default: every unit)')
    p.add_argument('--seeds', type=int, default=10, help='planner seeds 0 .. N-1 per method (default 10)')
    p.add_argument('--oracle', action='store_true',
                   help='also plan GP-GPIS-OPT on the truth sampled at the planning grid (default: off)')
    p.add_argument('--trials', type=int, default=20,
                   help='simulated executions of each grasp on the ground truth (default 20)')
    p.add_argument('--grid-size', type=int, default=SensingParams.grid_size,
                   help=f'force M of the M x M planning grid, cells (default {SensingParams.grid_size}, as '
                        'segmentation_node: from the target and the cell size)')
    p.add_argument('--out', help='write results.jsonl, results.json, table.md and reliability.png here (a rerun '
                   'with the same settings resumes; default: print only)')
    p.add_argument('--fresh', action='store_true', help='with --out: discard earlier results there')
    p.add_argument('--keep-bags', metavar='DIR', help='also write each raw capture variant as a bag into DIR '
                   '(default: none written)')
    p.add_argument('--executor', choices=EXECUTORS, default=None,
                   help='serial, process or dask (default: process with --workers > 1, else serial)')
    p.add_argument('--workers', type=int, default=1, help='worker processes (default 1)')
    p.add_argument('--scheduler', default='local', help="dask: 'local' or a scheduler address (default local)")
    return p.parse_args(argv)


def keep_bags(entries: list[dict], out: Path) -> None:
    """Write the bag of every raw unit (``NAME_VARIANT.mcap``); an import refused is reported and skipped."""
    from gpis_grasp_ros.data import rgbd_import as ri

    out.mkdir(parents=True, exist_ok=True)
    for e in entries:
        if e['bag']:
            continue
        try:
            imported = import_unit(e)
        except ValueError as exc:
            print(f"evaluate-real: no bag for {e['id']}: {exc}", file=sys.stderr)
            continue
        path = ri.write_capture_bag(imported.capture, out / f"{e['capture']}_{e['variant']}.mcap", imported.truth,
                                    {'target_pixel': [round(c, 2) for c in imported.target_px]}, overwrite=True)
        print(f"evaluate-real: wrote {path} (target pixel in the bag {imported.target_px[0]:.2f} "
              f'{imported.target_px[1]:.2f})', file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    from gpis_grasp_ros.core.planners import METHODS

    args = parse_args(argv)
    try:
        methods = [m.strip() for m in args.methods.split(',') if m.strip()]
        unknown = [m for m in methods if m not in METHODS]
        if unknown:
            raise ValueError(f"unknown planner(s) {', '.join(unknown)}; valid names: {', '.join(METHODS)}")
        if not methods:
            raise ValueError('--methods needs at least one planner')
        for name, value, low in (('--seeds', args.seeds, 1), ('--trials', args.trials, 1),
                                 ('--workers', args.workers, 1)):
            if value < low:
                raise ValueError(f'{name} must be >= {low}, got {value}')
        if args.grid_size < 0 or 0 < args.grid_size < 3:
            raise ValueError(f'--grid-size must be 0 (from the cell size) or >= 3, got {args.grid_size}')
        units = load_manifest(args.manifest, args.root)
        if args.only:
            chosen = [u for u in units if any(text in u.id for text in args.only)]
            if not chosen:
                raise ValueError(f"--only {' '.join(args.only)} matches no unit; the manifest's units: "
                                 f"{', '.join(u.id for u in units)}")
            units = chosen
    except (ValueError, FileNotFoundError) as exc:
        print(f'evaluate-real: error: {exc}', file=sys.stderr)
        return 2
    entries = [u.entry() for u in units]
    if args.keep_bags:
        keep_bags(entries, Path(args.keep_bags))
    tasks = make_tasks(entries, methods, range(args.seeds), args.oracle, args.trials, args.grid_size)
    executor = args.executor or ('process' if args.workers > 1 else 'serial')
    digest = hashlib.sha256(json.dumps(entries, sort_keys=True).encode()).hexdigest()
    with tempfile.TemporaryDirectory(prefix='evaluate-real-') as tmp:
        out = Path(args.out) if args.out else Path(tmp)
        try:
            run = run_evaluation(tasks, out, executor, args.workers, args.scheduler, fresh=args.fresh or not args.out,
                                 progress=False, max_attempts=1, dataset_digest=digest, task_fn=run_real_task)
        except ValueError as exc:
            print(f'evaluate-real: error: {exc}', file=sys.stderr)
            return 2
        rows = run.rows
    agg = report.aggregate(rows, methods, args.oracle)
    summ = report.summary(agg, methods, args.oracle)
    text = report.table(agg, methods, args.oracle)
    line = report.summary_line(summ, args.trials)
    summ['per_capture'] = report.capture_checks(agg, methods, args.oracle)
    line += '\n' + report.capture_line(summ['per_capture'])
    print(text)
    print()
    print(line)
    print(f'{len(rows)} grasps in {run.wall_time_s:.0f} s ({executor}, {run.workers} worker(s))'
          + (f'; {len(run.failures)} task(s) FAILED (see failures.jsonl)' if run.failures else ''))
    if args.out:
        out = Path(args.out)
        rel = report.reliability(rows)
        settings = {'manifest': str(args.manifest), 'methods': methods, 'seeds': args.seeds, 'oracle': args.oracle,
                    'trials': args.trials, 'grid_size': args.grid_size, 'executor': executor,
                    'workers': run.workers}
        (out / 'table.md').write_text(f'{text}\n\n{line}\n', encoding='utf8')
        (out / 'results.json').write_text(json.dumps({'settings': settings, 'units': agg, 'summary': summ,
                                                      'reliability': rel, 'rows': rows}, indent=1) + '\n',
                                          encoding='utf8')
        report.plot_reliability(rel, out / 'reliability.png')
        print(f'wrote {out}/results.json, table.md, reliability.png')
    return 1 if run.failures else 0
