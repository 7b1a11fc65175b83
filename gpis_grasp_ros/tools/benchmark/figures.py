"""Figures of the benchmark (PNG): P_F bars, runtime, Fig. 4 panels, per-object grasps."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.tools.benchmark.evaluation import METHOD_BY_KEY, PAPER_TABLE1, BenchmarkResult, ObjectResult
from gpis_grasp_ros.tools.benchmark.report import Cell, _ratio, aggregate
from gpis_grasp_ros.viz.images import draw_grasp, metric_to_pixel, to_color

# ------------------------------------------------------------------------------------------
# Plotting with cv2 primitives
# ------------------------------------------------------------------------------------------

FONT = cv2.FONT_HERSHEY_SIMPLEX
WHITE = (255, 255, 255)
BLACK = (0, 0, 0)
GREY = (200, 200, 200)


def _text(img: np.ndarray, s: str, org: tuple[float, float], scale: float = 0.42, color: tuple[int, int, int] = BLACK,
          anchor: str = 'left', thickness: int = 1) -> None:
    """Text with its baseline at ``org``; ``anchor`` 'left', 'center' or 'right' (horizontal)."""
    (w, _h), _ = cv2.getTextSize(s, FONT, scale, thickness)
    x = org[0] - (w / 2 if anchor == 'center' else w if anchor == 'right' else 0)
    cv2.putText(img, s, (int(round(x)), int(round(org[1]))), FONT, scale, color, thickness, cv2.LINE_AA)


def _vtext(img: np.ndarray, s: str, center: tuple[int, int], scale: float = 0.42) -> None:
    """Text rotated by 90° (reading bottom-up) centred at ``center``."""
    (w, h), base = cv2.getTextSize(s, FONT, scale, 1)
    tile = np.full((h + base + 4, w + 4, 3), 255, np.uint8)
    cv2.putText(tile, s, (2, h + 1), FONT, scale, BLACK, 1, cv2.LINE_AA)
    tile = cv2.rotate(tile, cv2.ROTATE_90_COUNTERCLOCKWISE)
    th, tw = tile.shape[:2]
    y0, x0 = max(0, center[1] - th // 2), max(0, center[0] - tw // 2)
    y1, x1 = min(img.shape[0], y0 + th), min(img.shape[1], x0 + tw)
    img[y0:y1, x0:x1] = np.minimum(img[y0:y1, x0:x1], tile[:y1 - y0, :x1 - x0])


@dataclass
class Axes:
    """Plot area of an image: data (x, y) → pixels, linear or log10 axes."""

    img: np.ndarray
    box: tuple[int, int, int, int]  # left, top, right, bottom (pixels)
    xlim: tuple[float, float]
    ylim: tuple[float, float]
    xlog: bool = False
    ylog: bool = False

    @staticmethod
    def _frac(v: float, lim: tuple[float, float], log: bool) -> float:
        if log:
            v = math.log10(max(v, 1e-300))
            lo, hi = math.log10(lim[0]), math.log10(lim[1])
        else:
            lo, hi = lim
        return (v - lo) / (hi - lo)

    def px(self, x: float, y: float) -> tuple[int, int]:
        left, top, right, bottom = self.box
        fx = self._frac(x, self.xlim, self.xlog)
        fy = self._frac(y, self.ylim, self.ylog)
        return int(round(left + fx * (right - left))), int(round(bottom - fy * (bottom - top)))

    def ypx(self, y: float) -> int:
        return self.px(self.xlim[0], y)[1]

    def xpx(self, x: float) -> int:
        return self.px(x, self.ylim[0])[0]

    def frame(self, title: str, ylabel: str, xlabel: str = '', yticks: Sequence[float] | None = None,
              xticks: Sequence[tuple[float, str]] | None = None, minor_log_grid: bool = True) -> None:
        left, top, right, bottom = self.box
        img = self.img
        if yticks is None:
            yticks = _log_ticks(self.ylim) if self.ylog else list(np.linspace(self.ylim[0], self.ylim[1], 6))
        if self.ylog and minor_log_grid:
            for d in _log_ticks(self.ylim):
                for m in range(2, 10):
                    v = d * m
                    if self.ylim[0] <= v <= self.ylim[1]:
                        cv2.line(img, (left, self.ypx(v)), (right, self.ypx(v)), (238, 238, 238), 1)
        for v in yticks:
            y = self.ypx(v)
            cv2.line(img, (left, y), (right, y), (225, 225, 225), 1)
            cv2.line(img, (left - 4, y), (left, y), BLACK, 1)
            _text(img, _tick_label(v), (left - 7, y + 4), 0.38, anchor='right')
        if xticks:
            for x, label in xticks:
                xp = self.xpx(x)
                cv2.line(img, (xp, bottom), (xp, bottom + 4), BLACK, 1)
                _text(img, label, (xp, bottom + 18), 0.42, anchor='center')
        cv2.rectangle(img, (left, top), (right, bottom), BLACK, 1)
        _text(img, title, ((left + right) / 2, 20), 0.5, anchor='center')
        _vtext(img, ylabel, (14, (top + bottom) // 2))
        if xlabel:
            _text(img, xlabel, ((left + right) / 2, bottom + 38), 0.42, anchor='center')

    def legend(self, entries: Sequence[tuple[str, tuple[int, int, int], str]], y: int) -> None:
        """Entries (label, colour, kind 'box' | 'line' | 'tick') in one row at pixel height ``y``."""
        x = self.box[0]
        for label, color, kind in entries:
            if kind == 'box':
                cv2.rectangle(self.img, (x, y - 9), (x + 12, y + 1), color, -1)
            elif kind == 'tick':
                cv2.line(self.img, (x, y - 4), (x + 12, y - 4), color, 2)
            else:
                cv2.line(self.img, (x, y - 4), (x + 18, y - 4), color, 2, cv2.LINE_AA)
                cv2.circle(self.img, (x + 9, y - 4), 3, color, -1, cv2.LINE_AA)
            (w, _), _ = cv2.getTextSize(label, FONT, 0.4, 1)
            _text(self.img, label, (x + 22, y), 0.4)
            x += 22 + w + 16


def _log_ticks(lim: tuple[float, float]) -> list[float]:
    lo, hi = math.floor(math.log10(lim[0]) + 1e-9), math.ceil(math.log10(lim[1]) - 1e-9)
    return [10.0 ** e for e in range(lo, hi + 1) if lim[0] * (1 - 1e-9) <= 10.0 ** e <= lim[1] * (1 + 1e-9)]


def _tick_label(v: float) -> str:
    if v == 0:
        return '0'
    if abs(v) >= 1000 or abs(v) < 0.01:
        return f'{v:.0e}'.replace('e+0', 'e').replace('e-0', 'e-')
    return f'{v:g}'


def grouped_bar_chart(groups: Sequence[str], series: Sequence[tuple[str, tuple[int, int, int]]], values: np.ndarray,
                      title: str, ylabel: str, ylim: tuple[float, float], ylog: bool = False,
                      whiskers: tuple[np.ndarray, np.ndarray] | None = None, markers: np.ndarray | None = None,
                      marker_label: str = '', annotations: Sequence[str] | None = None,
                      size: tuple[int, int] = (980, 430)) -> np.ndarray:
    """Grouped bars ``values (G, S)`` (BGR image). ``whiskers`` (lo, hi) and ``markers`` (black ticks,
    NaN = none) have the same shape; ``annotations`` one string above each group."""
    width, height = size
    img = np.full((height, width, 3), 255, np.uint8)
    ax = Axes(img, (70, 62, width - 15, height - 50), (0.0, float(len(groups))), ylim, ylog=ylog)
    ax.frame(title, ylabel, xticks=[(i + 0.5, g) for i, g in enumerate(groups)])
    n_s = len(series)
    bar_w = 0.8 / n_s
    base = ylim[0]
    for gi in range(len(groups)):
        for si, (_label, color) in enumerate(series):
            v = float(values[gi, si])
            x0 = gi + 0.1 + si * bar_w
            if math.isfinite(v):
                p0 = ax.px(x0, max(v, ylim[0]) if ylog else v)
                p1 = ax.px(x0 + bar_w * 0.92, base)
                cv2.rectangle(img, (p0[0], min(p0[1], p1[1])), (max(p1[0], p0[0] + 1), p1[1]), color, -1)
            xc = x0 + 0.46 * bar_w
            if whiskers is not None:
                lo, hi = float(whiskers[0][gi, si]), float(whiskers[1][gi, si])
                if math.isfinite(lo) and math.isfinite(hi) and hi > lo:
                    a, b = ax.px(xc, hi), ax.px(xc, lo)
                    cv2.line(img, a, b, (60, 60, 60), 1)
                    cv2.line(img, (a[0] - 2, a[1]), (a[0] + 2, a[1]), (60, 60, 60), 1)
                    cv2.line(img, (b[0] - 2, b[1]), (b[0] + 2, b[1]), (60, 60, 60), 1)
            if markers is not None and math.isfinite(float(markers[gi, si])):
                p = ax.px(xc, float(markers[gi, si]))
                half = max(2, int(0.5 * bar_w * (ax.box[2] - ax.box[0]) / len(groups)))
                cv2.line(img, (p[0] - half, p[1]), (p[0] + half, p[1]), BLACK, 2)
        if annotations:
            _text(img, annotations[gi], (ax.xpx(gi + 0.5), ax.box[1] + 14), 0.38, (60, 60, 60), anchor='center')
    entries = [(label, color, 'box') for label, color in series]
    if markers is not None and marker_label:
        entries.append((marker_label, BLACK, 'tick'))
    ax.legend(entries, 44)
    return img


def line_chart(series: Sequence[tuple[str, tuple[int, int, int], np.ndarray, np.ndarray]], title: str, xlabel: str,
               ylabel: str, xlim: tuple[float, float], ylim: tuple[float, float], xlog: bool = True,
               ylog: bool = True, xticks: Sequence[float] | None = None,
               fits: Sequence[tuple[tuple[int, int, int], float, float]] | None = None,
               size: tuple[int, int] = (820, 470)) -> np.ndarray:
    """Lines with markers (BGR image); ``fits`` (colour, c, k) draw dashed t = c x^k."""
    width, height = size
    img = np.full((height, width, 3), 255, np.uint8)
    rows = math.ceil(len(series) / 3)
    top = 40 + 18 * rows
    ax = Axes(img, (70, top, width - 20, height - 55), xlim, ylim, xlog=xlog, ylog=ylog)
    ticks = [(v, f'{v:g}') for v in (xticks if xticks is not None else np.linspace(*xlim, 5))]
    ax.frame(title, ylabel, xlabel, xticks=ticks)
    for color, c, k in fits or []:
        xs = np.geomspace(xlim[0], xlim[1], 40) if xlog else np.linspace(xlim[0], xlim[1], 40)
        pts = [ax.px(x, c * x ** k) for x in xs]
        for i in range(0, len(pts) - 1, 2):
            cv2.line(img, pts[i], pts[i + 1], color, 1, cv2.LINE_AA)
    for _label, color, xs, ys in series:
        ok = np.isfinite(ys) & (ys > 0 if ylog else True)
        pts = [ax.px(float(x), float(y)) for x, y in zip(xs[ok], ys[ok], strict=True)]
        for a, b in zip(pts[:-1], pts[1:], strict=True):
            cv2.line(img, a, b, color, 2, cv2.LINE_AA)
        for p in pts:
            cv2.circle(img, p, 4, color, -1, cv2.LINE_AA)
    for r in range(rows):
        ax.legend([(label, color, 'line') for label, color, _, _ in series[3 * r:3 * r + 3]], 44 + 18 * r)
    return img


def pf_bar_chart(result: BenchmarkResult) -> np.ndarray:
    """P_F per object and method (mean over seeds, whiskers min–max), the paper's value as a tick."""
    keys = ('gp-m', 'gp-d', 'gp-u', 'gp-p', 'gp-g', 'gp-g-reranked')
    cells = aggregate(result.rows)
    objs = result.objects
    vals = np.array([[cells[(o.object, k)].p_f for k in keys] for o in objs])
    lo = np.array([[cells[(o.object, k)].p_f_min for k in keys] for o in objs])
    hi = np.array([[cells[(o.object, k)].p_f_max for k in keys] for o in objs])
    paper = np.array([[PAPER_TABLE1.get(o.letter, {}).get(k, np.nan) for k in keys] for o in objs])
    s = result.settings
    return grouped_bar_chart([o.letter for o in objs], [(METHOD_BY_KEY[k].label, METHOD_BY_KEY[k].color) for k in keys],
                             vals, f'P_F per object and method (mean of {s.seeds} seed(s), S = {s.shape_samples}; '
                             'whiskers: min-max over seeds)', 'probability of force closure P_F', (0.0, 1.0),
                             whiskers=(lo, hi), markers=paper, marker_label='paper')


def runtime_chart(result: BenchmarkResult) -> np.ndarray:
    """Worst-case planning time (log scale) of GP-P (brute force and adaptive) and GP-G per object."""
    keys = ('gp-p', 'gp-p-adaptive', 'gp-g', 'gp-g-reranked')
    cells = aggregate(result.rows)
    objs = result.objects
    vals = np.array([[cells[(o.object, k)].time_worst for k in keys] for o in objs])
    finite = vals[np.isfinite(vals) & (vals > 0)]
    lo = 10.0 ** math.floor(math.log10(finite.min())) if finite.size else 1e-3
    hi = 10.0 ** math.ceil(math.log10(finite.max())) if finite.size else 1.0
    if hi <= lo:
        hi = lo * 10
    ratios = [_ratio(cells[(o.object, 'gp-p')].time_worst / max(cells[(o.object, 'gp-g')].time_worst, 1e-9))
              for o in objs]
    return grouped_bar_chart([o.letter for o in objs], [(METHOD_BY_KEY[k].label, METHOD_BY_KEY[k].color) for k in keys],
                             vals, 'Worst-case planning time per object (log scale; label: GP-P / GP-G)',
                             'planning time (s)', (lo, hi), ylog=True, annotations=ratios)


def grasp_panel(blur: np.ndarray, geometry: GridGeometry, outline: Sequence[np.ndarray],
                grasp: tuple[np.ndarray, np.ndarray] | None, color: tuple[int, int, int], title: str, subtitle: str,
                jaw_width: float, panel_px: int = 240) -> np.ndarray:
    """One Fig. 4 panel (BGR): GPIS-Blur, true outline (green), the grasp, a title and a subtitle."""
    h, w = geometry.shape
    scale = max(1, int(round(panel_px / max(h, w))))
    img = cv2.resize(to_color(blur), (w * scale, h * scale), interpolation=cv2.INTER_LINEAR)
    for poly in outline:
        p = np.rint(metric_to_pixel(geometry, poly, scale) * 8 - 4).astype(np.int32)  # 3 fractional bits
        cv2.polylines(img, [p.reshape(-1, 1, 2)], True, (0, 170, 0), 1, cv2.LINE_AA, shift=3)
    if grasp is not None:
        draw_grasp(img, geometry, grasp[0], grasp[1], scale, color, None, jaw_width_m=jaw_width, thickness=2)
    header = np.full((36, img.shape[1], 3), 255, np.uint8)
    _text(header, title, (5, 14), 0.45)
    _text(header, subtitle, (5, 30), 0.36, (60, 60, 60))
    return np.vstack([header, img])


def _tile(panels: Sequence[Sequence[np.ndarray]], gap: int = 6) -> np.ndarray:
    """Rows of equally tall panels → one image (rows padded to the widest)."""
    rows = []
    for row in panels:
        parts = []
        for i, p in enumerate(row):
            if i:
                parts.append(np.full((p.shape[0], gap, 3), 255, np.uint8))
            parts.append(p)
        rows.append(np.hstack(parts))
    width = max(r.shape[1] for r in rows)
    out = []
    for i, r in enumerate(rows):
        if i:
            out.append(np.full((gap, width, 3), 255, np.uint8))
        out.append(np.hstack([r, np.full((r.shape[0], width - r.shape[1], 3), 255, np.uint8)]) if r.shape[1] < width
                   else r)
    return np.vstack(out)


def _panel_for(o: ObjectResult, cells: dict[tuple[str, str], Cell], key: str, title_prefix: str = '',
               panel_px: int = 240) -> np.ndarray:
    spec = METHOD_BY_KEY[key]
    row0 = next((r for r in o.rows if r['method'] == key and r['seed'] == 0), None)
    if row0 is None or not row0['success']:
        sub = 'no grasp'
    else:
        qn = f'{row0["q_n"]:.2f}' if math.isfinite(row0['q_n']) else row0['q_n_status']
        sub = f'P_F={row0["p_f"]:.2f}  Q_N={qn}  sim {row0["sim_successes"]}/{row0["sim_trials"]}'
    return grasp_panel(o.blur, o.geometry, o.outline, o.grasps.get(key), spec.color, f'{title_prefix}{spec.label}',
                       sub, o.jaw_width, panel_px)


def object_figure(o: ObjectResult, cells: dict[tuple[str, str], Cell]) -> np.ndarray:
    """Every method's seed-0 grasp on the object's GPIS-Blur, 2 rows x 3 panels (BGR)."""
    keys = ('gp-m', 'gp-d', 'gp-u', 'gp-p', 'gp-g', 'gp-g-reranked')
    panels = [_panel_for(o, cells, k, f'{o.letter}: ') for k in keys]
    body = _tile([panels[:3], panels[3:]])
    header = np.full((28, body.shape[1], 3), 255, np.uint8)
    _text(header, f'{o.object}: GPIS-Blur (dark = object), true outline green, seed-0 grasps', (5, 19), 0.5)
    return np.vstack([header, body])


def fig4_figure(result: BenchmarkResult) -> np.ndarray:
    """The paper's Fig. 4: objects A-D (or the first four) x GP-M, GP-P, GP-G (BGR)."""
    cells = aggregate(result.rows)
    objs = [o for o in result.objects if o.letter in 'ABCD'] or result.objects[:4]
    rows = [[_panel_for(o, cells, k, f'{o.letter}: ', 220) for k in ('gp-m', 'gp-p', 'gp-g')] for o in objs[:4]]
    body = _tile(rows)
    header = np.full((28, body.shape[1], 3), 255, np.uint8)
    _text(header, 'Fig. 4: GP-M / GP-P / GP-G on GPIS-Blur (green: true outline)', (5, 19), 0.5)
    return np.vstack([header, body])




def _write_png(path: Path, img_bgr: np.ndarray) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), img_bgr, [cv2.IMWRITE_PNG_COMPRESSION, 9]):
        raise OSError(f'could not write {path}')
    return path



