"""``gpis-grasp evaluate``: dataset-scale evaluation as independent tasks on three executors.

    gpis-grasp evaluate --dataset DIR --out DIR [--methods gp-gpis-opt,gp-m,gp-p] [--lambda 2] [--alpha 0.5]
                        [--seeds 1] [--executor serial|process|dask] [--workers N] [--scheduler local|tcp://HOST:PORT]
    gpis-grasp evaluate --dataset DIR --out DIR --throughput 1,2 [--executors serial,process,dask]

**Tasks.** The evaluation is a list of independent :class:`Task` s, one per object × method ×
parameter setting (λ = ``uncertainty_penalty``, α = ``antipodal_alpha`` of
:class:`~gpis_grasp_ros.core.planners.PlannerParams`) × seed
(:mod:`gpis_grasp_ros.tools.evaluation.tasks`). :func:`~gpis_grasp_ros.tools.evaluation.tasks.run_task`
is a pure function of its task: it renders the object's scene in memory
(:func:`~gpis_grasp_ros.sim.dataset.render_entry`; a user's bag is read instead), segments it and fits
the GPIS exactly as the nodes do
(:func:`~gpis_grasp_ros.tools.evaluation.tasks.fit_scene`), plans with
:func:`~gpis_grasp_ros.core.planners.plan` and executes the grasp ``trials`` times on the TRUE
shape with :func:`~gpis_grasp_ros.sim.execution.execute_grasp_trials` (σ_g = 0.5 planning cell,
true centre of mass). A task carries its manifest entry, so a remote worker needs the package but no
files (except for user-bag entries). The GPIS of an object is cached per worker process
(``object_model``, LRU), so consecutive tasks of one object fit it once per worker.

**Seeds (common random numbers).** The planner seed is a function of (seed, object) only, the
execution noise of (seed, object) only: every method and parameter setting of one seed faces the
same candidates, evaluation samples and positioning errors. Nothing depends on the process, the
executor or the order of execution, and every task runs with one BLAS thread (threadpoolctl), so the
results are identical whatever the executor and worker count, apart from ``TIMING_COLUMNS``.

**Executors.** ``serial`` (this process), ``process`` (a spawned ``ProcessPoolExecutor``) and
``dask`` (:mod:`dask.distributed`): ``--scheduler local`` starts a private
``LocalCluster(host='127.0.0.1', dashboard_address=None, processes=True, threads_per_worker=1)``
whose sockets all listen on 127.0.0.1; ``--scheduler tcp://HOST:PORT`` joins an existing cluster
(``dask scheduler`` on one machine, ``dask worker tcp://HOST:PORT --nthreads 1`` on the others; the
workers need this package installed). Progress is a tqdm bar for every executor. The parallel
executors schedule the pending tasks of one object as one unit (``--affinity object``, default): the
GPIS fit (1-4 s at M = 25, more than most plans) then happens once per object instead of once per
object and worker; ``--affinity task`` schedules single tasks (finer load balance, repeated fits).

**Failures, incremental results, resume.** Every finished task appends one JSON line to
``results.jsonl`` as soon as the parent receives it (flushed; with object units, when the object's
unit returns). A task that raises is retried once; if it fails again the error
and traceback go to ``failures.jsonl`` and the run ends with exit code 1 and a list of the failed
tasks — never silently dropped. Domain outcomes are not failures but statuses of a result row:
``ok``, ``no_gpis`` (segmentation/GPIS rejected the scene, e.g. nothing segmented), ``no_grasp``
(the planner found no grasp; message kept), ``no_ground_truth`` (a bag without ground truth).
Running the same command again resumes: tasks already in ``results.jsonl`` are skipped (a line cut
by an interruption is discarded), failed tasks are tried again; ``run.json`` records the settings
and the dataset digest, and a resume with other settings is refused (use ``--fresh``).

Outputs: ``results.jsonl``, ``results.csv`` (task order), ``failures.jsonl``, ``run.json`` and
``summary.md`` (per material class × size class × method: P_F, simulated success, planning time; then per
class the GPIS near the true surface, one value per object: mean-shape IoU, the mean's bias, σ and the z RMS -
how far the posterior is from calibrated where the grasps touch).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

from gpis_grasp_ros.tools.evaluation.reports import summary_table, surface_table, throughput_report, write_json
from gpis_grasp_ros.tools.evaluation.runner import EXECUTORS, run_evaluation
from gpis_grasp_ros.tools.evaluation.tasks import DEFAULT_METHODS, EvalSettings, make_tasks
from gpis_grasp_ros.tools.evaluation.throughput import throughput


# =========================================================================== CLI
def floats(text: str) -> list[float]:
    try:
        return [float(x) for x in text.split(',') if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got '{text}'") from None


def ints(text: str) -> list[int]:
    try:
        return [int(x) for x in text.split(',') if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got '{text}'") from None


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """Options shared by ``evaluate`` and ``tune``: dataset, output, executor, sample counts."""
    parser.add_argument('--dataset', required=True, help='dataset folder (gpis-grasp make-dataset) or manifest.json')
    parser.add_argument('--out', required=True, help='output folder (results.jsonl, results.csv, ...)')
    parser.add_argument('--objects', type=int, default=0, help='use only the first N objects (default: all)')
    parser.add_argument('--seeds', type=int, default=1, help='seeds 0 .. N-1 (default: %(default)s)')
    parser.add_argument('--executor', choices=EXECUTORS, default='serial')
    parser.add_argument('--workers', type=int, default=os.cpu_count() or 1,
                        help='worker processes for process / local Dask (default: %(default)s)')
    parser.add_argument('--scheduler', default='local',
                        help="Dask: 'local' (private LocalCluster on 127.0.0.1) or a scheduler address tcp://HOST:PORT")
    parser.add_argument('--affinity', choices=('object', 'task'), default='object',
                        help="parallel executors: schedule an object's tasks together or single tasks")
    parser.add_argument('--fresh', action='store_true', help='discard earlier results in --out instead of resuming')
    parser.add_argument('--no-progress', action='store_true', help='no progress bar')
    d = EvalSettings()
    parser.add_argument('--grid-size', type=int, default=d.grid_size,
                        help=f'force M of the M x M GPIS grid (default {d.grid_size}; 0 = from the object and the '
                             'cell size)')
    parser.add_argument('--frames', type=int, default=d.frames)
    parser.add_argument('--grasp-samples', type=int, default=d.grasp_samples)
    parser.add_argument('--shape-samples', type=int, default=d.shape_samples)
    parser.add_argument('--initial-grasps', type=int, default=d.n_initial_grasps)
    parser.add_argument('--trials', type=int, default=d.trials, help='simulated executions per grasp')


def settings_from_args(args: argparse.Namespace) -> EvalSettings:
    return EvalSettings(grid_size=args.grid_size, frames=args.frames, grasp_samples=args.grasp_samples,
                        shape_samples=args.shape_samples, n_initial_grasps=args.initial_grasps, trials=args.trials)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog='gpis-grasp evaluate', description=__doc__.split('\n\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_run_arguments(p)
    p.add_argument('--methods', default=','.join(DEFAULT_METHODS), help='planners (default: %(default)s)')
    p.add_argument('--lambda', dest='lambdas', type=floats, default=None, help='λ values (default: planner default)')
    p.add_argument('--alpha', dest='alphas', type=floats, default=None, help='α values (default: planner default)')
    p.add_argument('--throughput', type=ints, default=None, metavar='W1,W2',
                   help='measure tasks/s for these worker counts instead of a normal run')
    p.add_argument('--executors', default='serial,process,dask', help='executors of --throughput')
    return p.parse_args(argv)


def load_entries(dataset: str, limit: int = 0) -> tuple[list[dict[str, Any]], str]:
    from gpis_grasp_ros.sim.dataset import load_dataset, manifest_digest

    ds = load_dataset(dataset)
    entries = ds.entries[:limit] if limit and limit > 0 else ds.entries
    return entries, manifest_digest(ds)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        entries, digest = load_entries(args.dataset, args.objects)
        settings = settings_from_args(args)
        methods = [m.strip() for m in args.methods.split(',') if m.strip()]
        tasks = make_tasks(entries, methods, range(max(1, args.seeds)), args.lambdas or [None], args.alphas or [None],
                           settings)
    except ValueError as err:
        print(f'gpis-grasp evaluate: {err}', file=sys.stderr)
        return 2
    out = Path(args.out)
    if args.throughput:
        execs = [e.strip() for e in args.executors.split(',') if e.strip()]
        configs = [('serial', 1)] if 'serial' in execs else []
        configs += [(e, w) for e in execs if e != 'serial' for w in args.throughput]
        stats = throughput(tasks, out, configs, progress=not args.no_progress, affinity=args.affinity)
        text = throughput_report(stats, len(tasks), len(entries))
        (out / 'throughput.md').write_text(text + '\n', encoding='utf8')
        write_json(out / 'throughput.json', stats, indent=1)
        print(text)
        return 0
    try:
        run = run_evaluation(tasks, out, args.executor, args.workers, args.scheduler, fresh=args.fresh,
                             progress=not args.no_progress, dataset_digest=digest, affinity=args.affinity)
    except ValueError as err:
        print(f'gpis-grasp evaluate: {err}', file=sys.stderr)
        return 2
    table = summary_table(run.rows)
    surface = surface_table(run.rows)
    if surface:
        table += '\n\nThe GPIS near the true surface (one value per object; median over the objects):\n\n' + surface
    (out / 'summary.md').write_text(table + '\n', encoding='utf8')
    print(table)
    where = f'Dask at {args.scheduler}' if args.executor == 'dask' and args.scheduler != 'local' else \
        f'{run.executor} x {run.workers}'
    print(f'\n{len(run.rows)} of {len(tasks)} tasks done ({run.resumed} resumed) in {run.wall_time_s:.1f} s '
          f'with {where}; results in {out}')
    if run.failures:
        print(f'gpis-grasp evaluate: {len(run.failures)} task(s) failed after retry (details in '
              f'{out / "failures.jsonl"}):', file=sys.stderr)
        for f in run.failures:
            print(f"  {f['task_id']}: {f['error']}", file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
