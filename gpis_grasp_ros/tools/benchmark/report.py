"""Aggregation of the evaluation rows and the Markdown/CSV reports (Table I, goal figures)."""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gpis_grasp_ros.core.planners import PlannerParams
from gpis_grasp_ros.core.sensing import SensingParams
from gpis_grasp_ros.tools.benchmark.calibration import DIAGNOSTICS, PREDICTORS, summarise
from gpis_grasp_ros.tools.benchmark.evaluation import METHOD_BY_KEY, PAPER_COLUMNS, PAPER_TABLE1, BenchmarkResult
from gpis_grasp_ros.tools.evaluation.reports import write_csv

# ------------------------------------------------------------------------------------------
# Aggregation and tables
# ------------------------------------------------------------------------------------------


@dataclass
class Cell:
    """Aggregate over seeds of one object × method."""

    p_f: float
    p_f_min: float
    p_f_max: float
    p_f_se: float  # mean Monte-Carlo standard error of one seed's estimate
    q_f_mean: float
    q_n: float  # mean over seeds, degenerate grasps counted as 0
    q_n_fc: int  # seeds whose grasp is in force closure on the true shape (Q_N > 0)
    sim_successes: int
    sim_trials: int
    time_worst: float
    time_median: float
    n_seeds: int
    failures: int  # seeds without a grasp


def aggregate(rows: Iterable[dict[str, Any]]) -> dict[tuple[str, str], Cell]:
    """(object, method) → :class:`Cell` over the seeds in ``rows``."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault((row['object'], row['method']), []).append(row)
    out = {}
    for key, rs in groups.items():
        p = np.array([r['p_f'] for r in rs], dtype=np.float64)
        qn = np.array([r['q_n'] for r in rs], dtype=np.float64)
        qf = np.array([r['q_f_mean'] for r in rs], dtype=np.float64)
        # Times of plans that produced a grasp (a failed plan's time says nothing about the method).
        t = np.array([r['planning_time_s'] for r in rs if r['success']] or [np.nan], dtype=np.float64)
        out[key] = Cell(p_f=float(p.mean()), p_f_min=float(p.min()), p_f_max=float(p.max()),
                        p_f_se=float(np.mean([r['p_f_std_error'] for r in rs])),
                        q_f_mean=float(np.nanmean(qf)) if np.isfinite(qf).any() else float('nan'),
                        q_n=float(np.mean(np.nan_to_num(qn, nan=0.0))), q_n_fc=int(np.count_nonzero(qn > 0)),
                        sim_successes=int(sum(r['sim_successes'] for r in rs)),
                        sim_trials=int(sum(r['sim_trials'] for r in rs)),
                        time_worst=float(np.max(t)), time_median=float(np.median(t)), n_seeds=len(rs),
                        failures=sum(1 for r in rs if not r['success']))
    return out


def goal_figures(result: BenchmarkResult) -> dict[str, Any]:
    """The issue's goal figures, measured (reported, not asserted).

    Time ratios GP-P / GP-G are formed per object from the same statistic of both methods
    (worst case over seeds, the paper's statistic, or median over seeds) and summarised over the
    objects by their mean and their median.
    """
    cells = aggregate(result.rows)
    objs = [o.object for o in result.objects]
    by = {o.object: o for o in result.objects}
    n = len(objs)
    have = set(result.settings.methods)
    out: dict[str, Any] = {'n_objects': n}
    if {'gp-g', 'gp-p'} <= have:
        within = [o for o in objs if cells[(o, 'gp-g')].p_f >= cells[(o, 'gp-p')].p_f - 0.05]
        out['gp_g_within_0.05_of_gp_p'] = [by[o].letter for o in within]
        timed = [o for o in objs if all(math.isfinite(cells[(o, k)].time_worst) for k in ('gp-p', 'gp-g'))]
        worst = {by[o].letter: cells[(o, 'gp-p')].time_worst / max(cells[(o, 'gp-g')].time_worst, 1e-9)
                 for o in timed}
        med = {by[o].letter: cells[(o, 'gp-p')].time_median / max(cells[(o, 'gp-g')].time_median, 1e-9)
               for o in timed}
        out.update({
            'time_ratio_gp_p_over_gp_g_worst': worst,
            'time_ratio_mean': float(np.mean(list(worst.values()))),
            'time_ratio_median': float(np.median(list(worst.values()))),
            'time_ratio_median_per_object': med,
            'time_ratio_median_mean': float(np.mean(list(med.values()))),
            'time_ratio_median_median': float(np.median(list(med.values()))),
            'time_ratio_of_mean_times': float(np.mean([cells[(o, 'gp-p')].time_worst for o in timed])
                                              / max(np.mean([cells[(o, 'gp-g')].time_worst for o in timed]), 1e-9))
            if timed else float('nan'),
        })
    if {'gp-g', 'gp-m'} <= have:
        out['gp_g_above_gp_m'] = [by[o].letter for o in objs if cells[(o, 'gp-g')].p_f > cells[(o, 'gp-m')].p_f]
    for key in ('gp-d', 'gp-u', 'gp-g', 'gp-d-single', 'gp-u-single'):
        rs = [r for r in result.rows if r['method'] == key]
        total = sum(int(r.get('restarts', 0)) for r in rs)
        if total:
            out[f'restarts_converged_{key}'] = sum(int(r.get('restarts_converged', 0)) for r in rs) / total
    a = [o for o in objs if by[o].letter == 'A']
    if a:
        for key in ('gp-m', 'gp-p', 'gp-g', 'gp-g-reranked'):
            if key in have:
                c = cells[(a[0], key)]
                out[f'A_sim_success_{key}'] = c.sim_successes / max(c.sim_trials, 1)
    return out


def _f2(x: float) -> str:
    return '—' if not math.isfinite(x) else f'{x:.2f}'


def _ratio(x: float) -> str:
    return f'{x:.1f}x' if x < 10 else f'{x:.0f}x'


def _ratio_or_dash(a: float, b: float) -> str:
    return f'{a / max(b, 1e-9):.1f}x' if math.isfinite(a) and math.isfinite(b) else '—'


def _rate(successes: int, trials: int) -> str:
    return f'{successes}/{trials} ({successes / max(trials, 1):.2f})'


def _time(x: float) -> str:
    if not math.isfinite(x):
        return '—'
    return f'{x:.3f}' if x < 1 else f'{x:.2f}' if x < 100 else f'{x:.0f}'


def _table(header: Sequence[str], rows: Sequence[Sequence[str]], align: str | None = None) -> list[str]:
    align = align or 'l' + 'r' * (len(header) - 1)
    sep = ['---:' if a == 'r' else '---' for a in align]
    lines = ['| ' + ' | '.join(header) + ' |', '| ' + ' | '.join(sep) + ' |']
    lines += ['| ' + ' | '.join(r) + ' |' for r in rows]
    return lines


def grid_text(settings: Any) -> str:
    """The planning grid of a run in words: the forced M x M, or the cell-size rule."""
    if settings.grid_size > 0:
        return f'{settings.grid_size} x {settings.grid_size} cells'
    d = SensingParams()
    return (f'{1000 * d.cell_size_m:g} mm cells (M = {d.min_grid_cells} to {d.max_grid_cells} cells per side, from '
            'the object)')


def table1_markdown(result: BenchmarkResult) -> str:
    """The contents of ``table1.md`` (see the module docstring)."""
    s = result.settings
    cells = aggregate(result.rows)
    objs = result.objects
    lines = [
        '# Table I — probability of force closure and runtime (ours vs. the paper)', '',
        f'{len(objs)} objects (simulated Carmine bags), GPIS on {grid_text(s)} built as the '
        f'nodes build it; N_g = {s.n_initial_grasps}, λ = {s.uncertainty_penalty:g} per m², K = {s.grasp_samples} '
        f'grasp samples, S = {s.shape_samples} shape samples, σ_g = {1000 * PlannerParams().gripper.sigma_g:g} mm, '
        f'{s.seeds} seed(s). GP-P is brute force '
        '(every candidate scored on all S samples), as in the paper.', '',
        f'P_F: mean over seeds of the Monte-Carlo estimate on S = {s.shape_samples} evaluation shape samples '
        f'(std error of one estimate ≤ {0.5 / math.sqrt(max(s.shape_samples, 1)):.3f}); the paper\'s value in '
        'parentheses. Runtime: worst case over seeds of the planning time (s) on this machine, one core per '
        'object; the paper\'s worst-case runtime (Matlab, 2.7 GHz laptop) and time ratio in parentheses.', '',
        f'Timing protocol (every method alike): each plan is timed once per seed ({s.seeds} seeds) by the '
        'planner\'s own clock (call to choice of the grasp, without the final P_F evaluation), in one process '
        'per object with one BLAS thread; tables give the worst case over seeds (the paper\'s statistic) and the '
        'median over seeds.', '',
    ]
    have = set(s.methods)
    cols = [k for k in PAPER_COLUMNS if k in have]
    timed = {'gp-p', 'gp-g'} <= have
    header = ['Object'] + [METHOD_BY_KEY[k].label for k in cols]
    if timed:
        header += ['GP-P time (s)', 'GP-G time (s)', 'GP-P / GP-G (worst)', 'GP-P / GP-G (median)']
    rows = []
    for o in objs:
        paper = PAPER_TABLE1.get(o.letter, {})
        r = [o.letter]
        for k in cols:
            c = cells[(o.object, k)]
            ref = f' ({paper[k]:.2f})' if k in paper else ''
            r.append(f'{_f2(c.p_f)}{ref}' + (f' [{c.failures} failed]' if c.failures else ''))
        if timed:
            tp, tg = cells[(o.object, 'gp-p')].time_worst, cells[(o.object, 'gp-g')].time_worst
            r.append(_time(tp) + (f' ({paper["time_gp-p"]:g})' if paper else ''))
            r.append(_time(tg) + (f' ({paper["time_gp-g"]:g})' if paper else ''))
            ratio_ref = f' ({paper["time_gp-p"] / paper["time_gp-g"]:.1f}x)' if paper else ''
            r.append(_ratio_or_dash(tp, tg) + ratio_ref)
            r.append(_ratio_or_dash(cells[(o.object, 'gp-p')].time_median, cells[(o.object, 'gp-g')].time_median))
        rows.append(r)
    lines += _table(header, rows)
    g = goal_figures(result)
    n = g['n_objects']
    lines += ['']
    if 'gp_g_within_0.05_of_gp_p' in g:
        lines += [f'GP-G P_F ≥ GP-P − 0.05 on {len(g["gp_g_within_0.05_of_gp_p"])} of {n} objects '
                  f'({", ".join(g["gp_g_within_0.05_of_gp_p"]) or "none"}). Per-object time ratio GP-P / GP-G of the '
                  f'worst-case times: mean {g["time_ratio_mean"]:.1f}x, median {g["time_ratio_median"]:.1f}x over '
                  f'objects (ratio of the mean worst-case times {g["time_ratio_of_mean_times"]:.1f}x); of the median '
                  f'times: mean {g["time_ratio_median_mean"]:.1f}x, median {g["time_ratio_median_median"]:.1f}x. '
                  'Paper: 5.7x ("averaged over all shapes").']
    if 'gp_g_above_gp_m' in g:
        above = g['gp_g_above_gp_m']
        lines += [f'GP-G P_F > GP-M on {len(above)} of {n} ({", ".join(above) or "none"}).']
    refused = [f'{o.letter} ({o.info["segmentation_refusal"]})' for o in objs if o.info.get('segmentation_refusal')]
    if refused:
        lines += ['', 'Segmentation with the node defaults refused: ' + '; '.join(refused)
                  + '. The benchmark evaluated these objects with that check off.']
    lines += ['']
    conv = [f'{METHOD_BY_KEY[k].label} {100 * g[f"restarts_converged_{k}"]:.0f} %'
            for k in ('gp-d', 'gp-u', 'gp-g', 'gp-d-single', 'gp-u-single') if f'restarts_converged_{k}' in g]
    if conv:
        lines += ['SCP restarts that met the convergence test (all objects and seeds): ' + ', '.join(conv) + '.', '']

    extra = [m for m in result.settings.method_specs]
    lines += ['## All methods: P_F', '',
              'Mean over seeds, min–max over seeds in brackets. Extras beyond the paper: GP-P adaptive (successive '
              'halving), GP-G re-ranked (the N_g local optima re-scored by Monte-Carlo P_F) and GP-D / GP-U from one '
              'start.', '']
    header = ['Object'] + [m.label for m in extra]
    rows = [[o.letter] + [f'{_f2(c.p_f)} [{_f2(c.p_f_min)}–{_f2(c.p_f_max)}]'
                          for c in (cells[(o.object, m.key)] for m in extra)] for o in objs]
    lines += _table(header, rows)

    lines += ['', '## Objects: GPIS and centre of mass', '',
              'COM spread over 1000 joint shape samples (RMS and 95th percentile of the distance to the mean '
              'shape\'s COM, in cells; the paper\'s condition 1 asks for < 1 cell), IoU of the mean shape with the '
              'true shape, the GP length scale (cells) and, with the calibration study, the RMS z-score of the true '
              'SDF under the GPIS (1 = calibrated, > 1 over-confident; all cells / within 2 cells of the true '
              'surface).', '']
    header = ['Object', 'COM spread RMS / p95 (cells)', 'mean-shape IoU', 'length scale (cells)', 'GP z RMS']
    rows = []
    for o in objs:
        i = o.info
        z = (f'{i["gp_z_rms"]:.2f} / {i["gp_z_rms_near_surface"]:.2f}' if 'gp_z_rms' in i else '—')
        rows.append([o.letter, f'{i["com_spread_rms_cells"]:.2f} / {i["com_spread_p95_cells"]:.2f}',
                     _f2(i['mean_shape_iou']), f'{i["length_scale_m"] / i["resolution_m"]:.2f}', z])
    lines += _table(header, rows)

    lines += ['', '## Q_N — Ferrari–Canny quality of the planned grasp on the true shape', '',
              'Mean over seeds of Q_N (unperturbed grasp, true SDF, true centre of mass; a grasp that misses the '
              'true object or starts inside it counts as 0); in brackets the number of seeds whose grasp is in '
              'force closure on the true shape (Q_N > 0).', '']
    header = ['Object'] + [m.label for m in extra]
    rows = [[o.letter] + [f'{_f2(cells[(o.object, m.key)].q_n)} [{cells[(o.object, m.key)].q_n_fc}/'
                          f'{cells[(o.object, m.key)].n_seeds}]' for m in extra] for o in objs]
    lines += _table(header, rows)

    lines += ['', '## Simulated gripper on the true shape', '',
              f'Force-closure successes / executions ({s.trials} per seed, the planners\' gripper: σ_g = '
              f'{1000 * PlannerParams().gripper.sigma_g:g} mm; true centre of mass; other objects are obstacles), '
              'summed over seeds.', '']
    rows = [[o.letter] + [_rate(cells[(o.object, m.key)].sim_successes, cells[(o.object, m.key)].sim_trials)
                          for m in extra] for o in objs]
    lines += _table(header, rows)

    lines += ['', '## Q_F on the GPIS mean shape', '', 'Mean over seeds (— : degenerate on the mean).', '']
    rows = [[o.letter] + [_f2(cells[(o.object, m.key)].q_f_mean) for m in extra] for o in objs]
    lines += _table(header, rows)

    lines += ['', '## Planning time (s): median / worst case over seeds', '']
    rows = [[o.letter] + [f'{_time(c.time_median)} / {_time(c.time_worst)}'
                          for c in (cells[(o.object, m.key)] for m in extra)] for o in objs]
    lines += _table(header, rows)
    lines += ['', f'Wall time of the run: {result.wall_time_s:.1f} s with {result.workers} worker process(es) '
              f'on {os.cpu_count()} CPU core(s).', '']
    return '\n'.join(lines)


def calibration_summary(result: BenchmarkResult) -> dict[str, Any]:
    """ECE / Brier / bias / null ECE per predictor: overall, per object, and planned grasps only."""
    rows = result.calibration_rows
    out: dict[str, Any] = {'overall': summarise(rows, np.random.default_rng(1)),
                           'planned': summarise([r for r in rows if r['kind'] == 'planned'],
                                                np.random.default_rng(2)),
                           'objects': {}}
    for o in result.objects:
        out['objects'][o.letter] = summarise(o.calibration, np.random.default_rng(3))
    return out


def calibration_markdown(result: BenchmarkResult, summary: dict[str, Any] | None = None) -> str:
    """Contents of ``calibration.md``: ECE (10 bins) and Brier per predictor, overall and per object."""
    s = result.settings
    summary = calibration_summary(result) if summary is None else summary
    rows = result.calibration_rows
    n_planned = sum(1 for r in rows if r['kind'] == 'planned')
    keys = [k for k, _ in PREDICTORS] + list(DIAGNOSTICS)
    labels = {'p_tilde_hard': "P̃_F (GP-M's Q_F)", 'p_tilde_smooth': 'P̃_F (GP-G, smoothed)', 'p_f': 'P_F',
              'p_true_grid': 'P_F, true shape on the grid', 'p_f_inflated': 'P_F, σ inflated by z RMS'}
    lines = ['# Calibration: predicted probability of force closure vs simulated executions', '',
             f'{len(rows)} grasps on {len(result.objects)} objects: {n_planned} planned in the Table I run and up '
             f'to {s.calibration_candidates} GP-P candidates per object spread over P_F; each executed '
             f'{s.calibration_trials} times by the simulated gripper on the true shape (σ_g = '
             f'{1000 * PlannerParams().gripper.sigma_g:g} mm). '
             f'P̃_F of GP-M from {s.calibration_perturbations} jaw perturbations on the mean shape; P̃_F of GP-G as '
             'the optimiser computes it; P_F on S = '
             f'{s.shape_samples} shape samples independent of the candidate choice. ECE with 10 equal-width bins; '
             'Brier score per execution; bias = mean(prediction − success rate) (> 0: over-confident); null ECE = '
             'mean ECE of a perfectly calibrated predictor with the same predictions and executions (the floor set '
             'by the finite number of executions). The last two predictors are diagnostics: P_F with the true shape '
             'resampled on the planning grid (no GP), and P_F with the GPIS deviations scaled by the RMS z-score '
             'of the true SDF near the surface (per object, "σ ×" column).', '']
    header = ['predictor', 'ECE', 'null ECE (mean / p95)', 'Brier', 'bias', 'ECE planned only']
    body = []
    for k in keys:
        m = summary['overall'].get(k)
        if m is None:
            continue
        mp = summary['planned'].get(k, {})
        body.append([labels[k], f'{m["ece"]:.3f}', f'{m["null_ece_mean"]:.3f} / {m["null_ece_p95"]:.3f}',
                     f'{m["brier"]:.3f}', f'{m["bias"]:+.3f}', f'{mp.get("ece", float("nan")):.3f}'])
    lines += ['## All objects', ''] + _table(header, body, 'lrrrrr')
    lines += ['', '## Per object: ECE / Brier', '']
    header = ['Object'] + [labels[k] for k in keys] + ['GP z RMS all / near surface', '95 % coverage', 'σ ×',
                                                      'μ − sdf / σ near surface (cells)']
    body = []
    for o in result.objects:
        m = summary['objects'].get(o.letter, {})
        r = [o.letter] + [f'{m[k]["ece"]:.3f} / {m[k]["brier"]:.3f}' if k in m else '—' for k in keys]
        i = o.info
        r.append(f'{i["gp_z_rms"]:.2f} / {i["gp_z_rms_near_surface"]:.2f}' if 'gp_z_rms' in i else '—')
        r.append(f'{i["gp_coverage95"]:.2f}' if 'gp_coverage95' in i else '—')
        r.append(f'{i["sigma_inflation"]:.1f}' if 'sigma_inflation' in i else '—')
        r.append(f'{i["gp_bias_near_surface_cells"]:+.2f} / {i["gp_sd_near_surface_cells"]:.2f}'
                 if 'gp_bias_near_surface_cells' in i else '—')
        body.append(r)
    lines += _table(header, body)
    lines += ['']
    return '\n'.join(lines)


def write_results_csv(path: Path, rows: Sequence[dict[str, Any]]) -> Path:
    """One row per object × method × seed (columns in the order of the first row, floats to 10 digits)."""
    return write_csv(path, rows, float_format='.10g', lineterminator='\r\n')


# END
