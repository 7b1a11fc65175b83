"""Figures of the benchmark (PNG, matplotlib with the Agg backend).

P_F bars, worst-case runtime, the paper's Fig. 4 panels (grasps over GPIS-Blur), per-object grasp
panels, SCP convergence per restart (objective vs iteration, the paper's supplementary plots) and
the calibration reliability diagram. Figures are built with the object-oriented API
(:class:`matplotlib.figure.Figure`, no pyplot state), so they are safe in worker processes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use('Agg')

import numpy as np  # noqa: E402
from matplotlib.axes import Axes  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from gpis_grasp_ros.core.grid import GridGeometry  # noqa: E402
from gpis_grasp_ros.tools.benchmark.calibration import DIAGNOSTICS, N_BINS, PREDICTORS, reliability  # noqa: E402
from gpis_grasp_ros.tools.benchmark.evaluation import (  # noqa: E402
    METHOD_BY_KEY,
    PAPER_TABLE1,
    BenchmarkResult,
    ObjectResult,
)
from gpis_grasp_ros.tools.benchmark.report import _ratio, aggregate  # noqa: E402

DPI = 100


def save_figure(fig: Figure, path: str | Path, dpi: int = DPI) -> Path:
    """Write ``fig`` as PNG (creating the folder) and return the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, format='png')
    return path


def _methods_present(result: BenchmarkResult, keys: Sequence[str]) -> list[str]:
    have = set(result.settings.methods)
    return [k for k in keys if k in have]


# ------------------------------------------------------------------------------------------
# Bar charts
# ------------------------------------------------------------------------------------------


def grouped_bars(ax: Axes, groups: Sequence[str], keys: Sequence[str], values: np.ndarray,
                 lo: np.ndarray | None = None, hi: np.ndarray | None = None, markers: np.ndarray | None = None,
                 marker_label: str = '', log: bool = False) -> None:
    """Grouped bars ``values (G, S)`` coloured by method, optional min–max whiskers and black ticks."""
    n_s = len(keys)
    width = 0.8 / max(n_s, 1)
    x = np.arange(len(groups), dtype=np.float64)
    for si, key in enumerate(keys):
        spec = METHOD_BY_KEY[key]
        xs = x - 0.4 + (si + 0.5) * width
        v = values[:, si]
        ax.bar(xs, np.where(np.isfinite(v), v, 0.0), width * 0.92, color=spec.color, label=spec.label,
               log=log, zorder=2)
        if lo is not None and hi is not None:
            ok = np.isfinite(lo[:, si]) & np.isfinite(hi[:, si]) & (hi[:, si] > lo[:, si])
            ax.vlines(xs[ok], lo[ok, si], hi[ok, si], color='0.25', linewidth=1, zorder=3)
        if markers is not None:
            ok = np.isfinite(markers[:, si])
            ax.hlines(markers[ok, si], xs[ok] - width * 0.46, xs[ok] + width * 0.46, color='black', linewidth=2,
                      zorder=4, label=marker_label if si == 0 and marker_label else None)
    ax.set_xticks(x, list(groups))
    ax.grid(axis='y', color='0.9', zorder=0)


def pf_bar_chart(result: BenchmarkResult) -> Figure:
    """P_F per object and method (mean over seeds, whiskers min–max), the paper's value as a black tick."""
    keys = _methods_present(result, ('gp-m', 'gp-d', 'gp-u', 'gp-p', 'gp-g', 'gp-g-reranked'))
    cells = aggregate(result.rows)
    objs = result.objects
    vals = np.array([[cells[(o.object, k)].p_f for k in keys] for o in objs])
    lo = np.array([[cells[(o.object, k)].p_f_min for k in keys] for o in objs])
    hi = np.array([[cells[(o.object, k)].p_f_max for k in keys] for o in objs])
    paper = np.array([[PAPER_TABLE1.get(o.letter, {}).get(k, np.nan) for k in keys] for o in objs])
    s = result.settings
    fig = Figure(figsize=(10, 4.3))
    ax = fig.add_subplot()
    grouped_bars(ax, [o.letter for o in objs], keys, vals, lo, hi, paper, 'paper')
    ax.set_ylim(0, 1.05)
    ax.set_ylabel('probability of force closure $P_F$')
    ax.set_title(f'$P_F$ per object and method (mean of {s.seeds} seed(s), S = {s.shape_samples}; '
                 'whiskers: min–max over seeds)', fontsize=10)
    ax.legend(ncol=len(keys) + 1, fontsize=8, loc='upper center', bbox_to_anchor=(0.5, -0.08), frameon=False)
    fig.tight_layout()
    return fig


def runtime_chart(result: BenchmarkResult) -> Figure:
    """Worst-case planning time (log scale) of GP-P (brute force and adaptive) and GP-G per object."""
    keys = _methods_present(result, ('gp-p', 'gp-p-adaptive', 'gp-g', 'gp-g-reranked'))
    cells = aggregate(result.rows)
    objs = result.objects
    vals = np.array([[cells[(o.object, k)].time_worst for k in keys] for o in objs])
    fig = Figure(figsize=(10, 4.3))
    ax = fig.add_subplot()
    grouped_bars(ax, [o.letter for o in objs], keys, vals, log=True)
    ax.set_ylabel('planning time (s)')
    ax.set_title('Worst-case planning time over seeds (log scale; label: GP-P / GP-G)', fontsize=10)
    if 'gp-p' in keys and 'gp-g' in keys:
        top = np.nanmax(vals) if np.isfinite(vals).any() else 1.0
        for i, o in enumerate(objs):
            ratio = cells[(o.object, 'gp-p')].time_worst / max(cells[(o.object, 'gp-g')].time_worst, 1e-9)
            ax.text(i, top * 1.6, _ratio(ratio), ha='center', fontsize=8, color='0.3')
        ax.set_ylim(top=top * 4)
    ax.legend(ncol=len(keys), fontsize=8, loc='upper center', bbox_to_anchor=(0.5, -0.08), frameon=False)
    fig.tight_layout()
    return fig


# ------------------------------------------------------------------------------------------
# Grasp panels over GPIS-Blur
# ------------------------------------------------------------------------------------------


def draw_grasp_panel(ax: Axes, blur: np.ndarray, geometry: GridGeometry, outline: Sequence[np.ndarray],
                     grasp: tuple[np.ndarray, np.ndarray] | None, color: str, title: str, subtitle: str,
                     jaw_width: float) -> None:
    """One Fig. 4 panel: GPIS-Blur (grid frame, metres, y down), true outline (green), the grasp.

    The grasp is drawn as its closing line and a jaw bar ``jaw_width`` long at each jaw.
    """
    g = geometry
    x0, y0 = g.origin_x, g.origin_y
    x1, y1 = x0 + g.width * g.resolution, y0 + g.height * g.resolution
    ax.imshow(np.asarray(blur), cmap='gray', vmin=0, vmax=255, extent=(x0, x1, y1, y0), interpolation='bilinear')
    for poly in outline:
        p = np.vstack([poly, poly[:1]])
        ax.plot(p[:, 0], p[:, 1], color='#00b000', linewidth=1.0)
    if grasp is not None:
        a, b = np.asarray(grasp[0], dtype=np.float64), np.asarray(grasp[1], dtype=np.float64)
        d = b - a
        n = np.array([-d[1], d[0]]) / max(float(np.hypot(*d)), 1e-12) * 0.5 * jaw_width
        ax.plot([a[0], b[0]], [a[1], b[1]], color=color, linewidth=1.2, linestyle='--')
        for p in (a, b):
            ax.plot([p[0] - n[0], p[0] + n[0]], [p[1] - n[1], p[1] + n[1]], color=color, linewidth=3.5,
                    solid_capstyle='butt')
    ax.set_xlim(x0, x1)
    ax.set_ylim(y1, y0)
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(f'{title}\n{subtitle}', fontsize=8, loc='left')


def _subtitle(row: dict[str, Any] | None) -> str:
    if row is None or not row['success']:
        return 'no grasp'
    qn = f'{row["q_n"]:.2f}' if math.isfinite(row['q_n']) else row['q_n_status']
    return f'$P_F$={row["p_f"]:.2f}  $Q_N$={qn}  sim {row["sim_successes"]}/{row["sim_trials"]}'


def _panel_for(ax: Axes, o: ObjectResult, key: str, title_prefix: str = '') -> None:
    spec = METHOD_BY_KEY[key]
    row0 = next((r for r in o.rows if r['method'] == key and r['seed'] == 0), None)
    draw_grasp_panel(ax, o.blur, o.geometry, o.outline, o.grasps.get(key), spec.color,
                     f'{title_prefix}{spec.label}', _subtitle(row0), o.jaw_width)


def object_figure(o: ObjectResult, keys: Sequence[str] | None = None) -> Figure:
    """Every method's seed-0 grasp on the object's GPIS-Blur (3 panels per row)."""
    keys = list(keys) if keys is not None else sorted({r['method'] for r in o.rows},
                                                      key=lambda k: list(METHOD_BY_KEY).index(k))
    cols = 3
    rows = max(1, math.ceil(len(keys) / cols))
    fig = Figure(figsize=(3.0 * cols, 3.25 * rows))
    for i, key in enumerate(keys):
        _panel_for(fig.add_subplot(rows, cols, i + 1), o, key, f'{o.letter}: ')
    fig.suptitle(f'{o.object}: GPIS-Blur (dark = object), true outline green, seed-0 grasps', fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    return fig


def fig4_figure(result: BenchmarkResult) -> Figure:
    """The paper's Fig. 4: objects A–D (or the first four) × GP-M, GP-P, GP-G."""
    objs = [o for o in result.objects if o.letter in 'ABCD'] or result.objects[:4]
    objs = objs[:4]
    keys = _methods_present(result, ('gp-m', 'gp-p', 'gp-g'))
    fig = Figure(figsize=(2.9 * len(keys), 3.1 * len(objs)))
    for r, o in enumerate(objs):
        for c, key in enumerate(keys):
            _panel_for(fig.add_subplot(len(objs), len(keys), r * len(keys) + c + 1), o, key, f'{o.letter}: ')
    fig.suptitle('Fig. 4: GP-M / GP-P / GP-G on GPIS-Blur (green: true outline)', fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.94))
    return fig


# ------------------------------------------------------------------------------------------
# SCP convergence (objective vs iteration per restart)
# ------------------------------------------------------------------------------------------


def convergence_figure(result: BenchmarkResult) -> Figure | None:
    """Eq. 6 objective vs SCP iteration for every GP-G restart (seed 0) of every object; None if not recorded.

    Solid: restart reported as converged; dotted: stopped at the iteration cap or another reason.
    The restart the planner chose is not marked (it is the best feasible final value).
    """
    objs = [o for o in result.objects if any(e['history'] is not None for e in o.convergence)]
    if not objs:
        return None
    cols = min(4, len(objs))
    rows = math.ceil(len(objs) / cols)
    fig = Figure(figsize=(max(3.3 * cols, 7.0), 2.7 * rows + 0.5))
    for i, o in enumerate(objs):
        ax = fig.add_subplot(rows, cols, i + 1)
        n_conv = 0
        for e in o.convergence:
            h = e['history']
            if h is None:
                continue
            n_conv += int(e['converged'])
            ax.plot(np.arange(h.size), h, linewidth=0.9, linestyle='-' if e['converged'] else ':',
                    color='#1e961e' if e['feasible'] else '#c03030', alpha=0.8)
        ax.set_title(f'{o.letter}: {n_conv}/{len(o.convergence)} restarts converged', fontsize=9)
        ax.set_xlabel('SCP iteration', fontsize=8)
        ax.set_ylabel('objective (eq. 6)', fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(color='0.9')
    fig.suptitle('GP-G (seed 0): objective vs SCP iteration per restart\n'
                 'green: feasible, red: infeasible; solid: converged, dotted: not converged', fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.9))
    return fig


# ------------------------------------------------------------------------------------------
# Calibration
# ------------------------------------------------------------------------------------------


def reliability_figure(rows: Sequence[dict[str, Any]], summary: dict[str, dict[str, float]],
                       title: str = 'Reliability of the predicted probability of force closure') -> Figure:
    """Reliability diagram per predictor: observed success rate vs mean prediction per bin, with counts.

    Every grasp is a dot (prediction, simulated success rate); squares are the bin means (10 equal-
    width bins); the grey bars at the bottom show how many grasps fall in each bin.
    """
    keys = [k for k, _ in PREDICTORS] + [k for k in DIAGNOSTICS if rows and k in rows[0]]
    labels = dict(PREDICTORS) | DIAGNOSTICS
    fig = Figure(figsize=(3.4 * len(keys), 4.5))
    s = np.array([r['sim_successes'] for r in rows], dtype=np.float64)
    n = np.array([r['sim_trials'] for r in rows], dtype=np.float64)
    for i, key in enumerate(keys):
        ax = fig.add_subplot(1, len(keys), i + 1)
        p = np.array([r[key] for r in rows], dtype=np.float64)
        ax.plot([0, 1], [0, 1], color='0.5', linewidth=1, linestyle='--')
        if p.size:
            ax.scatter(p, s / n, s=5, color='#1e6eaa', alpha=0.25, linewidths=0)
            rel = reliability(p, s, n)
            ok = rel.count > 0
            centres = 0.5 * (rel.edges[:-1] + rel.edges[1:])
            ax.bar(centres, rel.count / max(rel.count.max(), 1) * 0.25, width=1.0 / N_BINS * 0.9, color='0.8',
                   zorder=0)
            ax.plot(rel.mean_pred[ok], rel.observed[ok], marker='s', color='#dc2828', linewidth=1.5)
        m = summary.get(key, {})
        ax.set_title(f'{labels[key]}\nECE {m.get("ece", float("nan")):.3f}  Brier {m.get("brier", float("nan")):.3f}'
                     f'  (null ECE {m.get("null_ece_mean", float("nan")):.3f})', fontsize=8)
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        ax.set_aspect('equal')
        ax.set_xlabel('predicted probability', fontsize=8)
        if i == 0:
            ax.set_ylabel('simulated success rate on the true shape', fontsize=8)
        ax.tick_params(labelsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.94))
    return fig
