"""Dataset evaluation (tools/evaluate.py, tools/evaluation/): the same rows from the serial, process and Dask executors,
retry-once-then-report, incremental results and resume after an interruption."""

from __future__ import annotations

import json
import os

import numpy as np
import psutil
import pytest

from gpis_grasp_ros.sim import dataset as ds
from gpis_grasp_ros.tools import evaluate
from gpis_grasp_ros.tools.evaluation import reports, runner
from gpis_grasp_ros.tools.evaluation import tasks as task_lib

TINY = task_lib.EvalSettings(grid_size=12, frames=2, grasp_samples=30, shape_samples=30, n_initial_grasps=2, trials=8)
METHODS = ('gp-m', 'gp-gpis-opt')


@pytest.fixture(scope='module')
def dataset(tmp_path_factory):
    return ds.make_dataset(tmp_path_factory.mktemp('dataset'), 6, seed=5)


@pytest.fixture(scope='module')
def tasks(dataset):
    return task_lib.make_tasks(dataset.entries, METHODS, [0], settings=TINY)


@pytest.fixture(scope='module')
def serial(tasks, tmp_path_factory):
    return runner.run_evaluation(tasks, tmp_path_factory.mktemp('serial'), 'serial', progress=False)


@pytest.fixture(scope='module')
def dask_client():
    """A private LocalCluster on 127.0.0.1 without dashboard, closed at the end of the module."""
    with runner.dask_client('local', workers=2) as client:
        yield client


def _listening(pids):
    found = []
    for pid in pids:
        try:
            conns = psutil.Process(pid).net_connections(kind='inet')
        except psutil.NoSuchProcess:
            continue
        found += [(pid, c.laddr) for c in conns if c.status == psutil.CONN_LISTEN]
    return found


def test_serial_rows(serial, tasks):
    assert not serial.failures and serial.ran == len(tasks) == 12 and serial.resumed == 0
    rows = serial.rows
    assert [r['task_id'] for r in rows] == [t.task_id for t in tasks]
    statuses = {r['status'] for r in rows}
    assert statuses <= {'ok', 'no_gpis', 'no_grasp'} and 'ok' in statuses
    for r in rows:
        if r['status'] == 'ok':
            assert r['success'] and 0 <= r['p_f'] <= 1 and r['sim_trials'] == TINY.trials
            assert r['sim_success_rate'] == r['sim_successes'] / TINY.trials
            assert 0 < r['width_m'] <= 0.09 + 1e-9
        elif r['status'] == 'no_gpis':
            assert r['message'] and not r['success'] and r['sim_trials'] == 0
    # the GPIS near the true surface: per object (both methods carry the same values), NaN without a GPIS
    for r in rows:
        vals = [r[k] for k in task_lib.SURFACE_COLUMNS]
        if r['status'] == 'no_gpis':
            assert all(np.isnan(v) for v in vals)
        else:
            z_rms, bias, sd = vals
            # a GPIS of the same shape: its mean within a few cells of the truth, sigma positive (the frames of the
            # planning grid and the truth agree; a mix-up would put the surface tens of cells off)
            assert z_rms > 0 and sd > 0 and abs(bias) < 3.0
    surface = {}
    for r in rows:
        surface.setdefault(r['object'], set()).add(repr([r[k] for k in task_lib.SURFACE_COLUMNS]))
    assert all(len(v) == 1 for v in surface.values())
    # common random numbers: both methods of an object share the planner seed
    by_obj = {}
    for r in rows:
        by_obj.setdefault(r['object'], set()).add(r['planner_seed'])
    assert all(len(s) == 1 for s in by_obj.values())
    assert (serial.out / 'results.csv').read_text().count('\n') == len(rows) + 1


def test_process_and_dask_executors_give_identical_rows(serial, tasks, dask_client, tmp_path):
    # process pool: the first three objects (spawned workers import the package and fit their own GPIS)
    process = runner.run_evaluation(tasks[:6], tmp_path / 'process', 'process', workers=2, progress=False)
    assert not process.failures
    assert reports.comparable(process.rows) == reports.comparable(serial.rows[:6])
    # Dask: every socket of the private cluster (scheduler in this process, nannies and workers in
    # children) listens on the loopback interface only
    me = psutil.Process()
    listening = _listening([me.pid] + [c.pid for c in me.children(recursive=True)])
    assert listening and all(addr.ip == '127.0.0.1' for _, addr in listening), listening
    assert dask_client.scheduler_info()['address'].startswith('tcp://127.0.0.1:')
    dask = runner.run_evaluation(tasks, tmp_path / 'dask', 'dask', client=dask_client, progress=False)
    assert not dask.failures
    assert reports.comparable(dask.rows) == reports.comparable(serial.rows)
    single = runner.run_evaluation(tasks[:4], tmp_path / 'dask-task', 'dask', client=dask_client, progress=False,
                               affinity='task')
    assert reports.comparable(single.rows) == reports.comparable(serial.rows[:4])
    workers = {r['worker'] for r in dask.rows}
    assert len(workers) >= 1 and all(w.split(':')[1] != str(os.getpid()) for w in workers)


def test_failed_tasks_are_retried_once_then_reported(serial, tasks, dask_client, tmp_path):
    transient = tasks[0].__class__(**{**tasks[0].__dict__, 'fail_first_attempts': 1})
    permanent = tasks[1].__class__(**{**tasks[1].__dict__, 'fail_first_attempts': 2})
    subset = [transient, permanent, tasks[2]]
    for executor, kw in (('serial', {}), ('dask', {'client': dask_client})):
        run = runner.run_evaluation(subset, tmp_path / executor, executor, progress=False, **kw)
        assert [r['task_id'] for r in run.rows] == [transient.task_id, tasks[2].task_id]
        retried = run.rows[0]
        assert retried['attempts'] == 2
        expected = {k: v for k, v in reports.comparable([serial.rows[0]])[0].items() if k != 'attempts'}
        assert {k: v for k, v in reports.comparable([retried])[0].items() if k != 'attempts'} == expected
        assert [f['task_id'] for f in run.failures] == [permanent.task_id]
        assert run.failures[0]['attempts'] == 2 and 'InjectedFailure' in run.failures[0]['error']
        written = [json.loads(x) for x in (tmp_path / executor / 'failures.jsonl').read_text().splitlines()]
        assert [f['task_id'] for f in written] == [permanent.task_id] and 'Traceback' in written[0]['traceback']


class _Interrupt:
    """Task function that is 'killed' (KeyboardInterrupt) when starting task number ``at``."""

    def __init__(self, at: int) -> None:
        self.at, self.calls = at, 0

    def __call__(self, task, attempt):
        self.calls += 1
        if self.calls == self.at:
            raise KeyboardInterrupt
        return task_lib.execute(task, attempt)


def test_interrupted_run_resumes_from_what_was_written(serial, tasks, tmp_path):
    # the last four objects (8 tasks, one of them without a GPIS) are enough for an interruption after
    # four rows and the resume; models still in this process's LRU cache are not fitted again
    part = tasks[4:]
    out = tmp_path / 'run'
    with pytest.raises(KeyboardInterrupt):
        runner.run_evaluation(part, out, 'serial', progress=False, task_fn=_Interrupt(at=5))
    assert len(reports.read_results(out)) == 4
    # a row cut in the middle by the interruption is discarded
    with open(out / 'results.jsonl', 'a', encoding='utf8') as fh:
        fh.write('{"task_id": "gen_00004|gp-m|lam')
    counting = _Interrupt(at=-1)
    run = runner.run_evaluation(part, out, 'serial', progress=False, task_fn=counting)
    assert run.resumed == 4 and run.ran == len(part) - 4 == counting.calls
    assert reports.comparable(run.rows) == reports.comparable(serial.rows[4:])
    lines = (out / 'results.jsonl').read_text().splitlines()
    assert len(lines) == len(part) and all(json.loads(x) for x in lines)
    # nothing left to do
    again = runner.run_evaluation(part, out, 'serial', progress=False)
    assert again.ran == 0 and again.resumed == len(part)
    # other settings in the same folder are refused; --fresh starts over
    other = task_lib.make_tasks([t.entry for t in part[::2]], ['gp-m'], [0],
                                settings=task_lib.EvalSettings(grid_size=10))
    with pytest.raises(ValueError, match='another run'):
        runner.run_evaluation(other, out, 'serial', progress=False)


def test_evaluate_command(dataset, tmp_path, capsys):
    args = ['--dataset', str(dataset.root), '--out', str(tmp_path), '--objects', '2', '--methods', 'gp-m',
            '--grid-size', '12', '--frames', '2', '--grasp-samples', '30', '--shape-samples', '30',
            '--initial-grasps', '2', '--trials', '8', '--no-progress']
    assert evaluate.main(args) == 0
    out = capsys.readouterr().out
    assert '2 of 2 tasks done' in out and '| material_class |' in out
    assert (tmp_path / 'summary.md').exists() and (tmp_path / 'run.json').exists()
    assert evaluate.main(args + ['--executor', 'dask', '--scheduler', 'udp://nowhere']) == 2
    assert evaluate.main(['--dataset', str(tmp_path / 'none'), '--out', str(tmp_path)]) == 2


def test_summary_and_projection_tables():
    rows = [{'material_class': 'dark', 'size_class': 'small', 'method': 'gp-m', 'status': 'ok', 'success': True,
             'p_f': 0.8, 'sim_success_rate': 0.5, 'planning_time_s': 0.1},
            {'material_class': 'dark', 'size_class': 'small', 'method': 'gp-m', 'status': 'no_grasp', 'success': False,
             'p_f': float('nan'), 'sim_success_rate': float('nan'), 'planning_time_s': 0.3},
            {'material_class': 'dark', 'size_class': 'small', 'method': 'gp-m', 'status': 'no_gpis', 'success': False,
             'p_f': float('nan'), 'sim_success_rate': float('nan'), 'planning_time_s': float('nan')}]
    table = reports.summary_table(rows)
    # no grasp counts as P_F 0 and success 0; the no-GPIS task is counted apart
    assert '| dark |  | gp-m | 3 | 1 | 0.400 | 0.250 | 0.200 |' in table
    assert reports.surface_table(rows) == ''  # no object has the surface columns
    surf = [{'object': o, 'method': m, 'material_class': mat, 'size_class': size, 'camera': cam,
             'mean_shape_iou': iou, 'gp_z_rms_near_surface': z, 'gp_bias_near_surface_cells': b,
             'gp_sd_near_surface_cells': sd}
            for o, mat, size, cam, iou, z, b, sd in (('a', 'dark', 'small', 'head', 0.5, 2.0, -0.4, 0.1),
                                                    ('b', 'dark', 'large', 'head', 0.7, 4.0, -0.2, 0.3),
                                                    ('c', 'opaque', 'large', 'top-down', 0.9, 1.0, 0.0, 0.2))
            for m in ('gp-m', 'gp-gpis-opt')]
    surf.append({**surf[0], 'object': 'd', 'gp_z_rms_near_surface': float('nan')})  # no GPIS: left out
    table = reports.surface_table(surf)
    # one value per object (not per task), medians over the objects of the group
    assert '| all |  |  | 3 | 0.70 | -0.20 | 0.20 | 2.0 |' in table
    assert '| dark |  |  | 2 | 0.60 | -0.30 | 0.20 | 3.0 |' in table
    assert '|  | large |  | 2 | 0.80 | -0.10 | 0.25 | 2.5 |' in table
    assert '|  |  | top-down | 1 | 0.90 | +0.00 | 0.20 | 1.0 |' in table
    proj = reports.projection_markdown(task_s=2.0, overhead_s=0.5, tasks=100, cores_per_machine=2, machines=(1, 5))
    # 1 machine: ceil(100 / 2) x 2.5 s = 125 s; 5 machines: ceil(100 / 10) x 2.5 s = 25 s
    assert '| 1 | 2 | 2.1 | 0.80 |' in proj and '| 5 | 10 | 0.4 | 4.00 |' in proj
    assert np.isfinite(reports._mean([1.0, float('nan')]))
