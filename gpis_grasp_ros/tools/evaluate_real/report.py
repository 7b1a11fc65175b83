"""Tables, summary and reliability diagram of ``gpis-grasp evaluate-real`` from its result rows.

Per unit (capture × variant): the perceived IoUs, per method the closures (mean over seeds of the successes
of ``trials`` simulated executions), the mean P_F and the mean |P_F − closure rate| over the seeds' grasps, how the
other executions failed (mean over seeds: a jaw in collision with the target or another object, a jaw missing the
target, contacts that slip: :class:`~gpis_grasp_ros.sim.execution.ExecutionOutcome`), the
oracle's closures and P_F, the nearest other object to a jaw centre (smallest over the perceived grasps): seen
by the perception, and of the truth (its obstacle distance at the jaw; 'none seen' without another true object),
objects seen, the refusal reason and the summed task time. A seed without a grasp closes 0 and has no P_F.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gpis_grasp_ros.tools.evaluate_real.tasks import FAILURES, ORACLE


def _mean(values: Sequence[float]) -> float:
    v = [float(x) for x in values if x is not None and math.isfinite(float(x))]
    return float(np.mean(v)) if v else math.nan


def _method_figures(sel: Sequence[dict[str, Any]]) -> dict[str, float]:
    rates = [(r['p_f'], r['successes'] / r['trials']) for r in sel if math.isfinite(r['p_f']) and r['trials']]
    return {'closures': _mean([r['successes'] for r in sel]), 'p_f': _mean([p for p, _ in rates]),
            'gap': _mean([abs(p - c) for p, c in rates]), 'grasps': len(rates), 'seeds': len(sel),
            **{k: _mean([r.get(k, math.nan) for r in sel]) for k in FAILURES}}


def _smallest_mm(rows: Sequence[dict[str, Any]], key: str) -> float:
    """Smallest finite or infinite ``key`` (m) over ``rows``, in mm (NaN when no row has one)."""
    values = [r.get(key) for r in rows]
    values = [v for v in values if v is not None and not math.isnan(v)]
    return 1000.0 * min(values) if values else math.nan


def aggregate(rows: Sequence[dict[str, Any]], methods: Sequence[str], oracle: bool) -> list[dict[str, Any]]:
    """One summary dict per unit, in the rows' order."""
    units: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        units.setdefault(r['object'], []).append(r)
    out = []
    for uid, sel in units.items():
        first = sel[0]
        u: dict[str, Any] = {'unit': uid, 'capture': first['capture'], 'variant': first['variant'],
                             'refusal': first['refusal'], 'trials': first['trials'],
                             'time_s': float(sum(r['task_time_s'] for r in sel))}
        if first['status'] == 'refused':
            u.update({'occupancy_iou': math.nan, 'mean_shape_iou': math.nan, 'objects_seen': None,
                      'jaw_clearance_mm': math.nan, 'true_clearance_mm': math.nan, 'methods': {}, 'oracle': None})
            out.append(u)
            continue
        perceived = [r for r in sel if not r['oracle']]
        u.update({'occupancy_iou': first['occupancy_iou'], 'mean_shape_iou': first['mean_shape_iou'],
                  'objects_seen': first['objects_seen'], 'tilt_deg': first['tilt_deg'],
                  'jaw_clearance_mm': _smallest_mm(perceived, 'jaw_clearance_m'),
                  'true_clearance_mm': _smallest_mm(perceived, 'true_clearance_m'),
                  'methods': {m: _method_figures([r for r in perceived if r['method'] == m]) for m in methods},
                  'oracle': _method_figures([r for r in sel if r['oracle']]) if oracle else None})
        out.append(u)
    return out


def _f(x: float | None, fmt: str = '.2f') -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return '–'
    if isinstance(x, float) and math.isinf(x):
        return 'none seen'
    return format(x, fmt)


def _failures(f: dict[str, Any]) -> str:
    """Mean failed executions by cause, e.g. ``2.4 / 0.0 / 1.2`` (a commanded opening wider than the gripper's, which
    the planners never give, is in the JSON's ``too_wide`` only)."""
    return ' / '.join(_f(f[k], '.1f') for k in ('collision', 'missed', 'slipped'))


def table(units: Sequence[dict[str, Any]], methods: Sequence[str], oracle: bool) -> str:
    """Markdown table, one row per unit."""
    trials = units[0]['trials'] if units else 0
    head = ['capture', 'variant', 'occ. IoU', 'mean-shape IoU']
    for m in methods:
        head += [f'{m} closures /{trials}', f'{m} P_F', f'{m} \\|P_F − rate\\|', f'{m} collision / missed / slipped']
    if oracle:
        head += [f'oracle closures /{trials}', 'oracle P_F']
    head += ['jaw clearance (mm)', 'true clearance (mm)', 'objects seen', 'refused', 'time (s)']
    lines = ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    for u in units:
        cells = [u['capture'], u['variant'], _f(u['occupancy_iou']), _f(u['mean_shape_iou'])]
        for m in methods:
            f = u['methods'].get(m)
            cells += ['–'] * 4 if f is None else [_f(f['closures'], '.1f'), _f(f['p_f']), _f(f['gap']), _failures(f)]
        if oracle:
            o = u['oracle']
            cells += ['–', '–'] if o is None else [_f(o['closures'], '.1f'), _f(o['p_f'])]
        refusal = u['refusal'].replace('|', '/')
        cells += [_f(u['jaw_clearance_mm'], '.0f'), _f(u['true_clearance_mm'], '.1f'), _f(u['objects_seen'], 'd'),
                  refusal or '', _f(u['time_s'], '.0f')]
        lines.append('| ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


def summary(units: Sequence[dict[str, Any]], methods: Sequence[str], oracle: bool) -> dict[str, Any]:
    """Means over the units that were not refused (captures and variants alike)."""
    ok = [u for u in units if not u['refusal']]
    s: dict[str, Any] = {'units': len(units), 'refused': len(units) - len(ok),
                         'occupancy_iou': _mean([u['occupancy_iou'] for u in ok]),
                         'mean_shape_iou': _mean([u['mean_shape_iou'] for u in ok]),
                         'methods': {m: {k: _mean([u['methods'][m][k] for u in ok]) for k in ('closures', 'p_f', 'gap')}
                                     for m in methods}}
    if oracle:
        s['oracle'] = {k: _mean([u['oracle'][k] for u in ok]) for k in ('closures', 'p_f', 'gap')}
    return s


def summary_line(s: dict[str, Any], trials: int) -> str:
    parts = [f"{s['units']} units ({s['refused']} refused): occupancy IoU {_f(s['occupancy_iou'])}, "
             f"mean-shape IoU {_f(s['mean_shape_iou'])}"]
    for m, f in s['methods'].items():
        parts.append(f"{m} {_f(f['closures'], '.1f')}/{trials} (P_F {_f(f['p_f'])}, |P_F − rate| {_f(f['gap'])})")
    if 'oracle' in s:
        o = s['oracle']
        parts.append(f"oracle {_f(o['closures'], '.1f')}/{trials} (P_F {_f(o['p_f'])})")
    return 'mean over ' + '; '.join(parts)


#: Per-capture checks of the real-objects targets, as fractions of the executions: whole frame and crop of a capture
#: within 3 of 20 closures of each other, and the oracle closing at least 17 of 20 on every variant
VARIANT_SPREAD, ORACLE_FLOOR = 3 / 20, 17 / 20


def capture_checks(units: Sequence[dict[str, Any]], methods: Sequence[str], oracle: bool) -> dict[str, Any]:
    """Per capture (its variants together; a refused variant closes 0): whether the first method's closures of the
    variants lie within ``VARIANT_SPREAD`` of the executions of each other (captures with two or more variants),
    whether its mean over the variants reaches GP-M's (when both were run), and whether the oracle closes at least
    ``ORACLE_FLOOR`` of them on every variant (with ``--oracle``). Counts of the captures that pass each."""
    by_capture: dict[str, list[dict[str, Any]]] = {}
    for u in units:
        by_capture.setdefault(u['capture'], []).append(u)
    first = methods[0] if methods else None

    def closures(u: dict[str, Any], m: str | None) -> float:
        f = u['oracle'] if m is None else u['methods'].get(m) if u['methods'] else None
        return 0.0 if f is None or not math.isfinite(f['closures']) else float(f['closures'])

    out: dict[str, Any] = {'captures': len(by_capture), 'method': first}
    if first is not None:
        multi = [v for v in by_capture.values() if len(v) >= 2]
        spread = [max(closures(u, first) for u in v) - min(closures(u, first) for u in v) for v in multi]
        out['with_variants'] = len(multi)
        out['variants_within'] = sum(d <= VARIANT_SPREAD * v[0]['trials'] + 1e-9
                                     for d, v in zip(spread, multi, strict=True))
        if first != 'gp-m' and 'gp-m' in methods:
            out['at_least_gp_m'] = sum(_mean([closures(u, first) for u in v]) >= _mean([closures(u, 'gp-m') for u in v])
                                       for v in by_capture.values())
    if oracle:
        out['oracle_floor'] = sum(all(closures(u, None) >= ORACLE_FLOOR * u['trials'] - 1e-9 for u in v)
                                  for v in by_capture.values())
    return out


def capture_line(c: dict[str, Any]) -> str:
    """The per-capture counts of :func:`capture_checks` as one line."""
    parts = []
    if 'variants_within' in c:
        parts.append(f"{c['method']} within {VARIANT_SPREAD * 20:.0f}/20 across variants on {c['variants_within']} "
                     f"of {c['with_variants']}")
    if 'at_least_gp_m' in c:
        parts.append(f"{c['method']} >= gp-m on {c['at_least_gp_m']} of {c['captures']}")
    if 'oracle_floor' in c:
        parts.append(f"oracle >= {ORACLE_FLOOR * 20:.0f}/20 on every variant of {c['oracle_floor']} of {c['captures']}")
    return f"per capture ({c['captures']}): " + ('; '.join(parts) if parts else 'nothing to compare')


def reliability(rows: Sequence[dict[str, Any]], bins: int = 10) -> dict[str, list[dict[str, Any]]]:
    """Per series (perceived grasps of every method; oracle grasps): P_F bins with count, mean P_F, closure rate."""
    out: dict[str, list[dict[str, Any]]] = {}
    for name, sel in (('perceived', [r for r in rows if not r['oracle']]), (ORACLE, [r for r in rows if r['oracle']])):
        pts = [(r['p_f'], r['successes'] / r['trials']) for r in sel if math.isfinite(r['p_f']) and r['trials']]
        if not pts:
            continue
        p = np.array(pts)
        idx = np.minimum((p[:, 0] * bins).astype(int), bins - 1)
        out[name] = [{'lo': k / bins, 'hi': (k + 1) / bins, 'count': int((idx == k).sum()),
                      'p_f': float(p[idx == k, 0].mean()), 'closure_rate': float(p[idx == k, 1].mean())}
                     for k in range(bins) if (idx == k).any()]
    return out


def plot_reliability(rel: dict[str, list[dict[str, Any]]], path: Path, title: str = '') -> Path:
    """Reliability diagram (binned P_F vs closure rate, counts beside the points) as a PNG."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 5.0), dpi=120)
    ax.plot([0, 1], [0, 1], color='0.6', lw=1, ls='--', label='calibrated')
    for (name, bins), style in zip(rel.items(), ('o-', 's:'), strict=False):
        x, y = [b['p_f'] for b in bins], [b['closure_rate'] for b in bins]
        ax.plot(x, y, style, label=f"{name} ({sum(b['count'] for b in bins)} grasps)")
        for b in bins:
            ax.annotate(str(b['count']), (b['p_f'], b['closure_rate']), textcoords='offset points', xytext=(4, 4),
                        fontsize=8)
    ax.set(xlim=(0, 1.02), ylim=(-0.02, 1.02), xlabel='P_F of the planned grasp (binned by 0.1)',
           ylabel='closure rate on the true shape', title=title or 'Real captures: P_F vs closures')
    ax.legend(loc='upper left', fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
