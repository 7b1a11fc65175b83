"""``gpis-grasp benchmark``: structure, invariants and serial/parallel identity on small settings.

The benchmark runs once serially and once with two spawned workers on objects A and B with
50 grasp x 50 shape samples, one seed, 5 simulated executions and a small calibration study
(module-scoped fixtures); the scaling fit is checked on synthetic power laws.
"""

from __future__ import annotations

import csv
import json
import math
import queue
import threading
from pathlib import Path

import numpy as np
import pytest

from gpis_grasp_ros.tools.benchmark import cli, report, scaling
from gpis_grasp_ros.tools.benchmark import evaluation as ev
from gpis_grasp_ros.tools.evaluation.runner import drain
from gpis_grasp_ros.tools.evaluation.truth import TrueShape
from gpis_grasp_ros.tools.seeds import derive_seed

ROOT = Path(__file__).resolve().parents[2]
BAGS = [ROOT / 'bags' / 'A_tape_dispenser.mcap', ROOT / 'bags' / 'B_nail.mcap']
SMALL = ev.BenchmarkSettings(seeds=1, grasp_samples=50, shape_samples=50, trials=5, blur_samples=200,
                             com_samples=200, calibration_candidates=8, calibration_trials=10,
                             calibration_perturbations=64)


def _without_times(rows: list[dict], drop: tuple[str, ...] = ev.TIME_COLUMNS) -> list[dict]:
    """Rows without the timing columns, NaN replaced by a marker (NaN != NaN would fail ==)."""
    def norm(v: object) -> object:
        return 'nan' if isinstance(v, float) and math.isnan(v) else v
    return [{k: norm(v) for k, v in r.items() if k not in drop} for r in rows]


@pytest.fixture(scope='module')
def serial() -> ev.BenchmarkResult:
    return ev.run_benchmark(BAGS, SMALL, workers=1, progress=False)


@pytest.fixture(scope='module')
def parallel() -> ev.BenchmarkResult:
    return ev.run_benchmark(BAGS, SMALL, workers=2, progress=False)


@pytest.fixture(scope='module')
def written(serial: ev.BenchmarkResult, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp('benchmark')
    cli.write_outputs(serial, out)
    return out


def test_every_method_plans_a_grasp_with_valid_numbers(serial: ev.BenchmarkResult) -> None:
    rows = serial.rows
    assert len(rows) == len(BAGS) * len(ev.METHODS) * SMALL.seeds
    assert {(r['object'], r['method']) for r in rows} == {(b.stem, m.key) for b in BAGS for m in ev.METHODS}
    for r in rows:
        assert r['success'], r
        assert np.all(np.isfinite([r['jaw1_x'], r['jaw1_y'], r['jaw2_x'], r['jaw2_y']]))
        assert 0.0 <= r['p_f'] <= 1.0
        assert 0.0 <= r['p_f_std_error'] <= 0.5 / math.sqrt(SMALL.shape_samples) + 1e-12
        assert 0 <= r['sim_successes'] <= r['sim_trials'] == SMALL.trials
        assert r['q_n_status'] in ('ok', 'no_contact', 'start_inside', 'opening_exceeded')
        assert math.isfinite(r['q_n']) == (r['q_n_status'] == 'ok')
        assert r['planning_time_s'] > 0
    for o in serial.objects:
        assert o.info['com_spread_rms_cells'] >= 0 and o.info['com_spread_p95_cells'] >= 0
        assert 0 <= o.info['mean_shape_iou'] <= 1
        assert o.blur.shape == o.geometry.shape and o.outline


def test_gp_p_is_not_worse_than_gp_m(serial: ev.BenchmarkResult) -> None:
    """GP-M and GP-P choose among the same candidates (common random numbers) and GP-P keeps the best
    Monte-Carlo P_F, so on the independent evaluation samples it cannot lose by more than the noise."""
    cells = report.aggregate(serial.rows)
    for o in serial.objects:
        p, m = cells[(o.object, 'gp-p')], cells[(o.object, 'gp-m')]
        if p.failures or m.failures:
            continue
        assert p.p_f >= m.p_f - 3 * math.hypot(p.p_f_se, m.p_f_se) - 0.05, o.object


def test_parallel_run_equals_serial_run(serial: ev.BenchmarkResult, parallel: ev.BenchmarkResult) -> None:
    assert parallel.workers == 2 and serial.workers == 1
    assert _without_times(parallel.rows) == _without_times(serial.rows)
    for a, b in zip(serial.objects, parallel.objects, strict=True):
        assert np.array_equal(a.blur, b.blur)
        assert _without_times([a.info], ev.OBJECT_TIME_COLUMNS) == _without_times([b.info], ev.OBJECT_TIME_COLUMNS)


def test_output_files(written: Path) -> None:
    for name in ('table1.md', 'results.csv', 'objects.csv', 'summary.json', 'pf_bars.png', 'runtime.png',
                 'fig4.png', 'calibration.csv', 'calibration.md', 'reliability.png'):
        assert (written / name).stat().st_size > 0, name
    for name in ('pf_bars.png', 'fig4.png', 'reliability.png'):
        assert (written / name).read_bytes()[:8] == b'\x89PNG\r\n\x1a\n', name
    for bag in BAGS:
        assert (written / 'objects' / f'{bag.stem}.png').stat().st_size > 0
        assert (written / 'calibration' / f'reliability_{bag.stem[0]}.png').stat().st_size > 0
    with open(written / 'results.csv') as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(BAGS) * len(ev.METHODS) * SMALL.seeds
    # The first table of table1.md (Table I layout) has one row per object.
    lines = (written / 'table1.md').read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith('| Object |'))
    body = []
    for line in lines[start + 2:]:
        if not line.startswith('|'):
            break
        body.append(line)
    assert [line.split('|')[1].strip() for line in body] == ['A', 'B']
    assert '(0.72)' in body[0]  # the paper's GP-M value of object A next to ours
    summary = json.loads((written / 'summary.json').read_text())
    g = summary['goal_figures']
    ratios = list(g['time_ratio_gp_p_over_gp_g_worst'].values())
    assert g['time_ratio_mean'] == pytest.approx(np.mean(ratios))
    assert g['time_ratio_median'] == pytest.approx(np.median(ratios))
    assert set(summary['calibration']['overall']) >= {'p_tilde_hard', 'p_tilde_smooth', 'p_f', 'p_true_grid'}


def test_convergence_histories(serial: ev.BenchmarkResult, written: Path) -> None:
    """GP-G's restarts (seed 0) are recorded; with objective histories the convergence plot is written."""
    for o in serial.objects:
        if not next(r for r in o.rows if r['method'] == 'gp-g' and r['seed'] == 0)['success']:
            continue
        assert len(o.convergence) == SMALL.n_initial_grasps
        for e in o.convergence:
            if e['history'] is not None:
                assert e['history'].ndim == 1 and np.all(np.isfinite(e['history']))
    has = any(e['history'] is not None for o in serial.objects for e in o.convergence)
    assert (written / 'convergence.png').exists() == has


def test_calibration_rows(serial: ev.BenchmarkResult) -> None:
    """Every planned grasp and the requested candidates get three predictions and simulated outcomes."""
    for o in serial.objects:
        planned = [r for r in o.calibration if r['kind'] == 'planned']
        cands = [r for r in o.calibration if r['kind'] == 'candidate']
        assert len(planned) == sum(1 for r in o.rows if r['success'])
        assert len(cands) == SMALL.calibration_candidates
        for r in o.calibration:
            for key in ('p_f', 'p_tilde_hard', 'p_tilde_smooth', 'p_true_grid', 'p_f_inflated'):
                assert 0.0 <= r[key] <= 1.0, (key, r)
            assert r['sim_trials'] == SMALL.calibration_trials and 0 <= r['sim_successes'] <= r['sim_trials']
        assert {'gp_z_rms', 'gp_coverage95', 'sigma_inflation'} <= set(o.info)
    # Candidates spread over the screening P_F: on A (grasps on the unseen dispenser fail, grasps
    # across the tape roll hold) the choice reaches both ends.
    screen = [r['screen_p_f'] for r in serial.objects[0].calibration if r['kind'] == 'candidate']
    assert min(screen) <= 0.2 and max(screen) >= 0.8


def test_progress_messages_are_all_drained() -> None:
    """Late progress messages of the workers are waited for until the bar is complete."""
    q: queue.Queue = queue.Queue()
    seen: list[tuple[str, str]] = []
    for i in range(5):
        q.put(('obj', f'm{i}'))
    drain(q, seen.append)
    assert len(seen) == 5
    threading.Timer(0.3, lambda: q.put(('obj', 'late'))).start()
    drain(q, seen.append, wait_s=3.0, complete=lambda: len(seen) >= 6)
    assert seen[-1] == ('obj', 'late')


def test_derived_seeds_are_stable_and_distinct() -> None:
    assert derive_seed('planner', 0, 'A_tape_dispenser') == derive_seed('planner', 0, 'A_tape_dispenser')
    seeds = {derive_seed('planner', s, o) for s in range(3) for o in ('A', 'B', 'C')}
    assert len(seeds) == 9


@pytest.mark.parametrize('k', [1.0, 2.0, 3.7])
def test_power_law_fit_recovers_the_exponent(k: float) -> None:
    sizes = np.array([25, 40, 55, 70, 100], dtype=float)
    rng = np.random.default_rng(0)
    c, k_fit = scaling.fit_power_law(sizes, 3e-4 * sizes ** k)
    assert k_fit == pytest.approx(k, abs=1e-9) and c == pytest.approx(3e-4, rel=1e-9)
    _, k_noisy = scaling.fit_power_law(sizes, 3e-4 * sizes ** k * np.exp(rng.normal(0, 0.02, sizes.size)))
    assert k_noisy == pytest.approx(k, abs=0.1)
    with pytest.raises(ValueError):
        scaling.fit_power_law([25, 25], [1.0, 2.0])


@pytest.mark.parametrize('argv', [['--methods', 'gp-x'], ['--methods', ','], ['--calibration-trials', '0'],
                                  ['--calibration-candidates', '-1'], ['--seeds', '0']])
def test_cli_refuses_bad_arguments(argv: list[str]) -> None:
    with pytest.raises(SystemExit):
        cli.parse_args(argv)


def test_cli_refuses_bags_with_the_same_name(tmp_path: Path) -> None:
    other = tmp_path / 'A_tape_dispenser.mcap'
    other.write_bytes(BAGS[0].read_bytes())
    assert cli.main(['--bags', str(BAGS[0]), str(other), '--out', str(tmp_path / 'out'), '--quiet']) == 2
    assert cli.main(['--bags', str(BAGS[0]), '--methods', 'gp-m,gp-g', '--calibration', '--out',
                     str(tmp_path / 'out'), '--quiet']) == 2  # the calibration study needs GP-P


def _rot(tilt_deg: float, yaw_deg: float) -> tuple[float, ...]:
    t, y = np.radians(tilt_deg), np.radians(yaw_deg)
    rx = np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
    rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    return tuple((rx @ rz).ravel())


def test_true_shape_maps_planning_grid_points_through_the_sensor_frame() -> None:
    """Head camera: the truth grid and the planning grid share the table plane but not the in-plane axes."""
    from gpis_grasp_ros.core.grid import GridGeometry
    from gpis_grasp_ros.core.gripper import GripperParams

    true_g = GridGeometry(-0.03, -0.06, 0.001, 120, 120, z=0.8, rotation=_rot(50, 5))
    xy = true_g.cell_centers()
    disc = np.hypot(xy[..., 0] - 0.03, xy[..., 1]) - 0.02  # disc of radius 2 cm at (3 cm, 0) of the true grid
    centre = TrueShape(disc, true_g, GridGeometry(0, 0, 0.005, 25, 25, z=0.8, rotation=_rot(50, 95))).to_plan(
        np.array([0.03, 0.0]))
    plan_g = GridGeometry(centre[0] - 0.0625, centre[1] - 0.0625, 0.005, 25, 25, z=0.8, rotation=_rot(50, 95))
    truth = TrueShape(disc, true_g, plan_g)
    pts = np.random.default_rng(0).uniform(-0.05, 0.05, (20, 2))
    assert np.allclose(truth.to_true(truth.to_plan(pts)), pts, atol=1e-12)
    assert np.allclose(truth.com, [0.03, 0.0], atol=2e-4)
    # A grasp across the disc centre, expressed in planning-grid coordinates.
    j1, j2 = truth.to_plan(np.array([-0.01, 0.0])), truth.to_plan(np.array([0.07, 0.0]))
    gripper = GripperParams(position_noise=0.002)
    q, status = truth.nominal_quality(j1, j2, gripper)
    assert status == 'ok' and q > 0
    assert truth.execute(j1, j2, gripper, 20, np.random.default_rng(1)) == 20
    # The same numbers read as if both grids were one frame would miss the disc entirely.
    same_frame = TrueShape(disc, true_g)
    assert same_frame.nominal_quality(j1, j2, gripper)[1] != 'ok'
    assert truth.iou_on(plan_g, truth.values_at(plan_g.cell_centers())) == pytest.approx(1.0)
    assert truth.iou_on(plan_g, np.hypot(*(plan_g.cell_centers() - centre).T) - 0.02) > 0.9
    # on the true 1 mm grid: the same disc's SDF interpolated from 5 mm cells; a disc 1 mm too large (area ratio
    # (20/21)^2 = 0.907); a planning grid covering only the disc's half (the other half counts as missed)
    d = plan_g.cell_centers() - centre
    exact = np.hypot(d[..., 0], d[..., 1]) - 0.02
    assert truth.iou_fine(plan_g, exact) > 0.98
    # (bilinear interpolation of the convex distance function overestimates it: the disc comes out ~0.3 mm smaller)
    assert truth.iou_fine(plan_g, exact - 0.001) == pytest.approx((20 / 21) ** 2, abs=0.02)
    half = GridGeometry(centre[0] - 0.0625, centre[1], 0.005, 25, 13, z=0.8, rotation=_rot(50, 95))
    d = half.cell_centers() - centre
    half_mean = np.hypot(d[..., 0], d[..., 1]) - 0.02
    assert truth.iou_on(half, half_mean) == pytest.approx(1.0)  # the cell-centre IoU sees no miss
    # covered: the disc beyond the half grid's first row of cell centres, 2.5 mm past the centre line
    a, r = 0.0025, 0.02
    segment = r ** 2 * np.arccos(a / r) - a * np.sqrt(r ** 2 - a ** 2)
    assert truth.iou_fine(half, half_mean) == pytest.approx(segment / (np.pi * r ** 2), abs=0.02)
    outline = np.concatenate(truth.outline())
    assert np.allclose(np.hypot(*(truth.to_true(outline) - [0.03, 0.0]).T), 0.02, atol=0.0015)
