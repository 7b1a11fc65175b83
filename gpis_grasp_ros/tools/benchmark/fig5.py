"""The paper's Fig. 5: GP-GPIS-OPT's grasp on object D under four patterns of shape uncertainty.

Section VII-C varies *where* the toy plane (object D) is uncertain and reports where the grasp
goes: (1) uncertainty only on the tips and edges of the wings and (2) on the entire wings → "a
grasp on the endpoints of the plane"; (3) the nose (cockpit end) unobserved → "a grasp that
leverages a wing and a rear stabilizer"; (4) both ends (nose and rudder/tail with the
stabilisers) unobserved → "the tip of the wings", an unstable grasp.

**Scenes.** Each pattern is the catalogue's toy plane (:func:`gpis_grasp_ros.sim.objects.toy_plane`:
same outline, height, colour, camera, frames and noise seed) with new material regions, written as
a bag by :func:`gpis_grasp_ros.sim.scene.write_scene_bag` into ``<out>/fig5/bags`` at run time;
everything outside the regions is opaque (the shipped bag's specular wings and tailplane are
replaced). Unobserved parts are ``specular`` (the Carmine gets no depth there). The simulator's
``noisy`` and ``dark`` materials raise depth noise and drop-outs, but the 2-D segmentation still
sees those pixels as object, so they add no shape uncertainty (the GPIS σ equals the all-opaque
scene's); pattern (1) therefore uses narrow specular bands (≈ 0.7–1 cm, about one planning cell)
along the wings' leading and trailing edges and tips, i.e. uncertainty exactly on the edges.

**Evaluation.** The bags go through the Table I evaluation (:func:`run_benchmark`: GPIS as the
nodes build it, GP-G and, for reference, GP-P and GP-M, every seed; P_F on S shape samples,
simulated executions on the true shape). The grasp's location is described by the plane parts its
two contacts (found on the true shape, unperturbed grasp) lie on, in the plane's own frame
(x along the fuselage toward the nose, cm): nose (x > 4.5), tail (x < −7, |y| < 1), stabiliser
(x < −5, |y| ≥ 0.9), wing (−0.5 ≤ x ≤ 3.6, |y| ≥ 0.9; "wing tip" for |y| > 5.5), otherwise
fuselage side; and by the angle of the closing line to the fuselage axis.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from gpis_grasp_ros.core.contacts import find_contacts
from gpis_grasp_ros.data.bags import load_bag
from gpis_grasp_ros.sim.objects import CM, mirror_y, rect, rotate, toy_plane
from gpis_grasp_ros.sim.scene import MaterialRegion, SceneSpec, polygon_signed_distance, write_scene_bag
from gpis_grasp_ros.tools.benchmark.evaluation import (
    METHOD_BY_KEY,
    BenchmarkResult,
    BenchmarkSettings,
    run_benchmark,
)
from gpis_grasp_ros.tools.benchmark.figures import draw_grasp_panel
from gpis_grasp_ros.tools.benchmark.report import _f2, _rate, _table, aggregate
from gpis_grasp_ros.tools.evaluation.truth import TrueShape

#: Placement of the toy plane in the scene (sim/objects.toy_plane: rotate by this angle, then shift; cm).
PLANE_ROTATION_DEG = -10.0
PLANE_OFFSET_CM = (0.3, 0.0)
#: The wing's material region of toy_plane() in the plane's frame (cm); used to check the placement.
WING_CM = np.array([[3.4, -0.95], [2.5, -7.2], [0.7, -7.2], [-0.2, -0.95]])
#: Inner part of the wing left observed in the "wing edges" pattern (cm): ~0.7-0.9 cm bands remain.
WING_INNER_CM = np.array([[2.3, -0.5], [1.75, -6.2], [1.45, -6.2], [0.9, -0.5]])
NOSE_CM = rect(3.6, -1.2, 7.3, 1.2)
TAIL_CM = rect(-8.3, -3.4, -5.0, 3.4)

#: Pattern key, title, what the paper reports for it, and the part pairs that count as agreement.
PATTERNS: tuple[tuple[str, str, str, tuple[frozenset[str], ...]], ...] = (
    ('wing_edges', 'wing tips and edges uncertain', 'endpoints of the plane',
     (frozenset({'nose', 'tail'}),)),
    ('wings', 'entire wings unobserved', 'endpoints of the plane', (frozenset({'nose', 'tail'}),)),
    ('nose', 'nose (cockpit end) unobserved', 'a wing and a rear stabiliser',
     (frozenset({'wing', 'stabiliser'}), frozenset({'wing tip', 'stabiliser'}))),
    ('front_back', 'nose and tail ends unobserved', 'the tips of the wings', (frozenset({'wing tip'}),)),
)
FIG5_METHODS = ('gp-g', 'gp-p', 'gp-m')


def plane_to_scene(poly_cm: np.ndarray) -> np.ndarray:
    """Plane-frame polygon (cm) → scene table-plane coordinates (m), as toy_plane() places its parts."""
    return (rotate(np.asarray(poly_cm, dtype=np.float64), PLANE_ROTATION_DEG) + np.asarray(PLANE_OFFSET_CM)) * CM


def scene_to_plane(xy_m: np.ndarray) -> np.ndarray:
    """Scene coordinates (m) → the plane's frame (cm, x toward the nose)."""
    p = np.asarray(xy_m, dtype=np.float64) / CM - np.asarray(PLANE_OFFSET_CM)
    return rotate(p, -PLANE_ROTATION_DEG)


def _both(poly: np.ndarray) -> list[np.ndarray]:
    return [poly, mirror_y(poly)]


def pattern_regions(pattern: str) -> list[MaterialRegion]:
    """Material regions (scene metres) of one Fig. 5 pattern; the rest of the plane is opaque."""
    if pattern == 'wing_edges':
        return ([MaterialRegion('specular', plane_to_scene(p)) for p in _both(WING_CM)]
                + [MaterialRegion('opaque', plane_to_scene(p)) for p in _both(WING_INNER_CM)])
    if pattern == 'wings':
        return [MaterialRegion('specular', plane_to_scene(p)) for p in _both(WING_CM)]
    if pattern == 'nose':
        return [MaterialRegion('specular', plane_to_scene(NOSE_CM))]
    if pattern == 'front_back':
        return [MaterialRegion('specular', plane_to_scene(p)) for p in (NOSE_CM, TAIL_CM)]
    raise ValueError(f'unknown Fig. 5 pattern {pattern!r}; valid: {", ".join(p[0] for p in PATTERNS)}')


def pattern_spec(pattern: str, base: SceneSpec | None = None) -> SceneSpec:
    """The toy plane's scene with the regions of ``pattern`` (name ``D_fig5_<pattern>``)."""
    base = toy_plane() if base is None else base
    return dataclasses.replace(base, regions=pattern_regions(pattern), name=f'D_fig5_{pattern}')


def write_pattern_bags(out_dir: str | Path, patterns: Sequence[str] | None = None) -> list[Path]:
    """Write one bag per pattern into ``out_dir`` (overwriting); returns the paths in pattern order."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    base = toy_plane()
    keys = [p[0] for p in PATTERNS] if patterns is None else list(patterns)
    return [write_scene_bag(pattern_spec(k, base), out_dir / f'D_fig5_{k}.mcap', overwrite=True) for k in keys]


def part_of(point_cm: np.ndarray) -> str:
    """Which part of the plane a point (plane frame, cm) lies on (see the module docstring)."""
    x, y = float(point_cm[0]), abs(float(point_cm[1]))
    if x > 4.5:
        return 'nose'
    if x < -7.0 and y < 1.0:
        return 'tail'
    if x < -5.0 and y >= 0.9:
        return 'stabiliser'
    if -0.5 <= x <= 3.6 and y >= 0.9:
        return 'wing tip' if y > 5.5 else 'wing'
    return 'fuselage'


UNCERTAIN_TOL_M = 0.003  # a contact within 3 mm of an unobserved region counts as on it


def on_uncertain(points_m: np.ndarray, regions: Sequence[MaterialRegion], tol: float = UNCERTAIN_TOL_M) -> np.ndarray:
    """Whether scene points (m) lie on (within ``tol`` of) the pattern's specular regions and not inside an
    opaque override region (the observed inner wing of the edge pattern)."""
    pts = np.atleast_2d(np.asarray(points_m, dtype=np.float64))
    near = np.zeros(pts.shape[0], dtype=bool)
    for r in regions:
        d = polygon_signed_distance(pts, np.asarray(r.polygon))
        if r.kind == 'specular':
            near |= d < tol
        else:
            near &= ~(d < -tol)
    return near


def describe_grasp(truth: TrueShape, jaw1: np.ndarray, jaw2: np.ndarray, gripper: Any,
                   regions: Sequence[MaterialRegion] = ()) -> dict[str, Any]:
    """Parts under the two contacts (true shape, unperturbed grasp in planning-grid m), the closing line's
    angle to the fuselage, and how many contacts lie on the pattern's unobserved regions (the true grid of
    the top-down scenes is the scene's table frame)."""
    con = find_contacts(truth.bank, truth.to_true(np.asarray(jaw1)[None]), truth.to_true(np.asarray(jaw2)[None]),
                        gripper)
    if not bool(con.valid[0]):
        return {'parts': ('none', 'none'), 'angle_deg': float('nan'), 'on_uncertain': -1}
    c1, c2 = scene_to_plane(con.c1[0]), scene_to_plane(con.c2[0])
    d = c2 - c1
    angle = math.degrees(math.atan2(abs(d[1]), abs(d[0])))  # 0 = along the fuselage, 90 = across
    n_unc = int(np.count_nonzero(on_uncertain(np.stack([con.c1[0], con.c2[0]]), regions)))
    return {'parts': tuple(sorted((part_of(c1), part_of(c2)))), 'angle_deg': angle, 'on_uncertain': n_unc}


def agrees(parts: Sequence[str], expected: Sequence[frozenset[str]]) -> bool:
    """Whether a contact pair matches one of the paper's descriptions (a set matches pairs of its parts)."""
    s = frozenset(parts)
    return any(s == e or (len(e) == 1 and s <= e) for e in expected)


def run_fig5(out_dir: str | Path, settings: BenchmarkSettings, workers: int = 1, progress: bool = True
             ) -> tuple[BenchmarkResult, list[dict[str, Any]]]:
    """Write the pattern bags, evaluate them, and describe every seed's GP-G grasp per pattern."""
    bags = write_pattern_bags(Path(out_dir) / 'bags')
    s = dataclasses.replace(settings, methods=FIG5_METHODS, calibration_candidates=0)
    result = run_benchmark(bags, s, workers, progress=progress, desc='fig5')
    summary = []
    for (key, title, paper, expected), o, bag in zip(PATTERNS, result.objects, bags, strict=True):
        scene = load_bag(bag)
        truth = TrueShape(scene.true_sdf, scene.true_geometry, o.geometry, obstacles=scene.true_obstacles)
        gripper = s.planner_params(METHOD_BY_KEY['gp-g']).gripper
        seeds = []
        for r in (r for r in o.rows if r['method'] == 'gp-g'):
            d = describe_grasp(truth, np.array([r['jaw1_x'], r['jaw1_y']]), np.array([r['jaw2_x'], r['jaw2_y']]),
                               gripper, pattern_regions(key)) if r['success'] else {
                'parts': ('none', 'none'), 'angle_deg': float('nan'), 'on_uncertain': -1}
            seeds.append(d | {'seed': r['seed'], 'agrees': agrees(d['parts'], expected)})
        summary.append({'pattern': key, 'title': title, 'paper': paper, 'object': o.object, 'seeds': seeds,
                        'agree_seeds': sum(1 for d in seeds if d['agrees']),
                        'avoid_seeds': sum(1 for d in seeds if d['on_uncertain'] == 0)})
    return result, summary


def fig5_markdown(result: BenchmarkResult, summary: Sequence[dict[str, Any]]) -> str:
    """``fig5.md``: per pattern the paper's grasp, ours (parts, angle), P_F and simulated success."""
    cells = aggregate(result.rows)
    s = result.settings
    lines = ['# Fig. 5 — GP-GPIS-OPT on object D under four patterns of shape uncertainty', '',
             f'{s.seeds} seed(s); P_F on S = {s.shape_samples} shape samples (mean over seeds); simulated executions '
             f'on the true shape ({s.trials} per seed, summed). "Contacts" are the plane parts under the GP-G grasp\'s '
             'two contacts on the true shape (seed 0), "angle" its closing line\'s angle to the fuselage (0° = '
             'along, 90° = across); "off the unobserved parts": seeds whose two contacts are both more than 3 mm '
             'from the pattern\'s unobserved regions. GP-G\'s opening is w_g = 9 cm: a nose-to-tail grasp (15 cm) '
             'or a tip-to-tip grasp (14 cm) is out of reach.', '']
    header = ['pattern', 'paper: grasp on', 'GP-G contacts (seed 0)', 'angle', 'seeds as the paper',
              'seeds off the unobserved parts', 'GP-G P_F', 'GP-G sim', 'GP-P P_F', 'GP-P sim', 'GP-M P_F']
    body = []
    for entry, o in zip(summary, result.objects, strict=True):
        d0 = entry['seeds'][0] if entry['seeds'] else {'parts': ('none', 'none'), 'angle_deg': float('nan')}
        g, p, m = (cells[(o.object, k)] for k in FIG5_METHODS)
        body.append([entry['title'], entry['paper'], ' – '.join(d0['parts']), f'{d0["angle_deg"]:.0f}°',
                     f'{entry["agree_seeds"]}/{len(entry["seeds"])}',
                     f'{entry["avoid_seeds"]}/{len(entry["seeds"])}', _f2(g.p_f),
                     _rate(g.sim_successes, g.sim_trials), _f2(p.p_f), _rate(p.sim_successes, p.sim_trials),
                     _f2(m.p_f)])
    lines += _table(header, body, 'llllrrrrrrr')
    lines += ['', 'All seeds (GP-G): ' + '; '.join(
        f'{e["pattern"]}: ' + ', '.join(f'{" – ".join(d["parts"])} ({d["angle_deg"]:.0f}°)' for d in e['seeds'])
        for e in summary), '']
    return '\n'.join(lines)


def fig5_figure(result: BenchmarkResult, summary: Sequence[dict[str, Any]]) -> Figure:
    """One panel per pattern: GPIS-Blur, true outline, GP-G's seed-0 grasp, P_F and simulated success."""
    n = len(result.objects)
    fig = Figure(figsize=(3.1 * n, 3.6))
    spec = METHOD_BY_KEY['gp-g']
    for i, (o, entry) in enumerate(zip(result.objects, summary, strict=True)):
        ax = fig.add_subplot(1, n, i + 1)
        row = next((r for r in o.rows if r['method'] == 'gp-g' and r['seed'] == 0), None)
        sub = 'no grasp' if row is None or not row['success'] else (
            f'$P_F$={row["p_f"]:.2f}  sim {row["sim_successes"]}/{row["sim_trials"]}\n'
            f'contacts: {" – ".join(entry["seeds"][0]["parts"])}')
        draw_grasp_panel(ax, o.blur, o.geometry, o.outline, o.grasps.get('gp-g'), spec.color,
                         f'({i + 1}) {entry["title"]}', sub, o.jaw_width)
    fig.suptitle('Fig. 5: GP-GPIS-OPT on object D with different patterns of shape uncertainty '
                 '(GPIS-Blur, green: true outline)', fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.9))
    return fig
