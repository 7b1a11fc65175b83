"""Result files and tables of the evaluations: JSON-lines results with resume, CSV, Markdown tables.

Shared by ``gpis-grasp evaluate``, ``gpis-grasp tune`` and ``gpis-grasp benchmark``.
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gpis_grasp_ros.tools.evaluation.tasks import SURFACE_COLUMNS, TIMING_COLUMNS


def write_json(path: Path, data: Any, end: str = '\n', **kw: Any) -> Path:
    """``data`` as JSON text followed by ``end`` (``kw`` as for ``json.dumps``)."""
    path.write_text(json.dumps(data, **kw) + end, encoding='utf8')
    return path


# =========================================================================== result files
@dataclass
class RunFiles:
    """The files of one evaluation folder."""

    root: Path

    @property
    def results(self) -> Path:
        return self.root / 'results.jsonl'

    @property
    def failures(self) -> Path:
        return self.root / 'failures.jsonl'

    @property
    def run(self) -> Path:
        return self.root / 'run.json'


def read_results(path: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """Rows of a ``results.jsonl`` (or its folder); a trailing line cut by an interruption is ignored."""
    p = Path(path)
    p = p / 'results.jsonl' if p.is_dir() else p
    rows = []
    if not p.exists():
        return rows
    for line in p.read_text(encoding='utf8').splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return rows


def _repair_tail(path: Path) -> None:
    """Cut a partial last line (no newline: the run was interrupted while writing it)."""
    if not path.exists() or path.stat().st_size == 0:
        return
    data = path.read_bytes()
    if not data.endswith(b'\n'):
        path.write_bytes(data[:data.rfind(b'\n') + 1])


class ResultWriter:
    """Appends one JSON line per finished task and flushes it at once."""

    def __init__(self, path: Path) -> None:
        self.fh = open(path, 'a', encoding='utf8')

    def write(self, row: dict[str, Any]) -> None:
        self.fh.write(json.dumps(row, sort_keys=True) + '\n')
        self.fh.flush()

    def close(self) -> None:
        self.fh.close()


def prepare_out(out: Path, fingerprint: dict[str, Any], fresh: bool) -> RunFiles:
    """The files of ``out`` for a run with ``fingerprint``: cleared (``fresh``), checked for a resume."""
    files = RunFiles(out)
    if fresh and out.exists():
        for p in (files.results, files.failures, files.run, out / 'results.csv', out / 'summary.md'):
            p.unlink(missing_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    if files.run.exists():
        old = json.loads(files.run.read_text(encoding='utf8'))
        if old != fingerprint:
            raise ValueError(f'{out} holds results of another run (different settings or dataset: see {files.run}); '
                             'resume with the same settings, or start over with --fresh or another --out')
    else:
        files.run.write_text(json.dumps(fingerprint, sort_keys=True, indent=1) + '\n', encoding='utf8')
    _repair_tail(files.results)
    files.failures.unlink(missing_ok=True)  # failed tasks of an earlier run are tried again
    return files

def write_csv(path: Path, rows: Sequence[dict[str, Any]], float_format: str | None = None,
              lineterminator: str = '\n') -> Path:
    """Rows as CSV (union of the keys, first row's order first); floats as ``float_format`` (e.g. '.10g') if given."""
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, 'w', newline='', encoding='utf8') as fh:
        w = csv.DictWriter(fh, fieldnames=keys, lineterminator=lineterminator)
        w.writeheader()
        if float_format is None:
            w.writerows(rows)
        else:
            w.writerows({k: (format(v, float_format) if isinstance(v, float) else v) for k, v in r.items()}
                        for r in rows)
    return path


def comparable(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Rows without :data:`TIMING_COLUMNS`, sorted by task id (for executor-identity checks)."""
    return sorted(({k: v for k, v in r.items() if k not in TIMING_COLUMNS} for r in rows), key=lambda r: r['task_id'])



# =========================================================================== summaries
def _mean(values: Sequence[float]) -> float:
    v = [x for x in values if x is not None and math.isfinite(x)]
    return float(np.mean(v)) if v else float('nan')


def summary_table(rows: Sequence[dict[str, Any]], by: Sequence[str] = ('material_class', 'size_class')) -> str:
    """Markdown: per group and method, tasks, mean P_F, simulated success, median planning time.

    Tasks without a grasp count as P_F 0 and success 0 (the robot would not grasp); ``no_gpis``
    tasks are counted separately."""
    methods = sorted({r['method'] for r in rows})
    lines = [f"| {' | '.join(by)} | method | tasks | no GPIS | mean P_F | sim success | median planning (s) |",
             '|' + '---|' * (len(by) + 6)]
    for dim in by:
        groups = sorted({r[dim] for r in rows})
        for g in groups:
            for m in methods:
                sel = [r for r in rows if r[dim] == g and r['method'] == m]
                if not sel:
                    continue
                usable = [r for r in sel if r['status'] != 'no_gpis']
                pf = _mean([r['p_f'] if r['success'] else 0.0 for r in usable])
                succ = _mean([r['sim_success_rate'] if r['success'] else 0.0 for r in usable
                              if r['status'] != 'no_ground_truth'])
                times = [r['planning_time_s'] for r in usable if math.isfinite(r['planning_time_s'])]
                cells = [g if d == dim else '' for d in by]
                lines.append(f"| {' | '.join(cells)} | {m} | {len(sel)} | {len(sel) - len(usable)} | {pf:.3f} | "
                             f"{succ:.3f} | {np.median(times) if times else float('nan'):.3f} |")
    return '\n'.join(lines)


def surface_table(rows: Sequence[dict[str, Any]],
                  by: Sequence[str] = ('material_class', 'size_class', 'camera')) -> str:
    """Markdown: per group, the GPIS near the true surface, one value per object (median over the objects with a
    GPIS and a ground truth): mean-shape IoU, bias mu - sdf_true (cells; < 0: the mean shape bulges out), sigma
    (cells) and the z RMS of (sdf_true - mu) / sigma (1 for a calibrated posterior). '' when no row has them."""
    per_object: dict[str, dict[str, Any]] = {}
    for r in rows:
        if all(math.isfinite(float(r.get(k, float('nan')))) for k in SURFACE_COLUMNS):
            per_object.setdefault(r['object'], r)
    if not per_object:
        return ''
    objs = list(per_object.values())
    lines = [f"| {' | '.join(by)} | objects | mean-shape IoU | bias near surface (cells) | σ near surface (cells) "
             '| z RMS near surface |', '|' + '---|' * (len(by) + 5)]
    for dim in ('all', *by):
        for g in (['all'] if dim == 'all' else sorted({o[dim] for o in objs})):
            sel = objs if dim == 'all' else [o for o in objs if o[dim] == g]
            med = [float(np.median([float(o[k]) for o in sel])) for k in ('mean_shape_iou', *SURFACE_COLUMNS)]
            cells = [('all' if dim == 'all' and i == 0 else (g if d == dim else '')) for i, d in enumerate(by)]
            lines.append(f"| {' | '.join(cells)} | {len(sel)} | {med[0]:.2f} | {med[2]:+.2f} | {med[3]:.2f} | "
                         f'{med[1]:.1f} |')
    return '\n'.join(lines)


def throughput_markdown(stats: Sequence[dict[str, Any]]) -> str:
    lines = ['| executor | workers | tasks | wall (s) | tasks/s | speed-up vs serial | task CPU (s) | '
             'idle per task (s) | start-up (s) | Dask no-op round trip (ms) | max RSS per worker (MB) | '
             'rows identical | machine load (1 min) |', '|---' * 13 + '|']
    for s in stats:
        rt = s['dask_round_trip_s']
        lines.append(f"| {s['executor']} | {s['workers']} | {s['tasks']} | {s['wall_s']:.1f} | "
                     f"{s['tasks_per_s']:.3f} | {s['speedup_vs_serial']:.2f} | {s['cpu_s']:.1f} | "
                     f"{s['idle_per_task_s']:.3f} | {s['startup_s']:.1f} | "
                     f"{'' if math.isnan(rt) else f'{rt * 1e3:.1f}'} | {s['max_rss_mb_per_worker']:.0f} | "
                     f"{'yes' if s['identical_to_first'] else 'NO'} | {s['load_avg_1min']:.1f} |")
    return '\n'.join(lines)


def projection_markdown(task_s: float, overhead_s: float, tasks: int, cores_per_machine: int = 2,
                        machines: Sequence[int] = (1, 2, 4, 8, 16, 32)) -> str:
    """Projected wall time of ``tasks`` tasks on N machines from a per-task time and overhead.

    Assumptions: identical machines with ``cores_per_machine`` worker slots each, each slot a
    dedicated core; tasks independent, so wall = ceil(tasks / slots) × (task + overhead) (no
    straggler tail beyond one task, GPIS fits amortised as in the measurement)."""
    lines = ['| machines | worker slots | projected wall (min) | tasks/s |', '|---|---|---|---|']
    for n in machines:
        slots = n * cores_per_machine
        wall = math.ceil(tasks / slots) * (task_s + overhead_s)
        lines.append(f'| {n} | {slots} | {wall / 60:.1f} | {tasks / wall:.2f} |')
    return '\n'.join(lines)


def throughput_report(stats: Sequence[dict[str, Any]], n_tasks: int, n_objects: int, target_objects: int = 200) -> str:
    """Throughput table, per-task CPU time, Dask overhead and the projection for ``target_objects`` objects.

    The projection takes the serial run's mean task CPU time (what a dedicated core needs) plus the
    Dask no-op round trip as the per-task overhead."""
    serial = [s for s in stats if s['executor'] == 'serial']
    dask_rows = [s for s in stats if s['executor'] == 'dask']
    ref = max(dask_rows or stats, key=lambda s: s['workers'])
    task_s = (serial[0] if serial else ref)['cpu_s'] / n_tasks
    overhead = ref['dask_round_trip_s'] if dask_rows else max(0.0, ref['idle_per_task_s'])
    per_object = n_tasks / max(1, n_objects)
    total = int(round(target_objects * per_object))
    lines = [throughput_markdown(stats), '']
    lines += [f"CPU-time speed-up ({s['executor']}, {s['workers']} workers): {s['cpu_speedup']:.2f}"
              for s in stats if 'cpu_speedup' in s]
    lines += ['', f'Mean task CPU time {task_s:.3f} s (serial); per-task overhead {overhead * 1e3:.1f} ms '
              f"({ref['executor']}, {ref['workers']} workers). Projection for {target_objects} objects x "
              f'{per_object:g} tasks per object = {total} tasks:', '',
              projection_markdown(task_s, overhead, total)]
    return '\n'.join(lines)
