"""Does the GPIS stay uncertain where the sensor failed? z-scores of the posterior against the true SDF.

    python scripts/uncertainty_report.py [BAG ...] [--manifest MANIFEST [--root DIR]]

For every scene (default: ``bags/*.mcap``, ``bags/head/*.mcap``, ``bags/real/*.mcap``; more bags as arguments,
e.g. one made with ``gpis-grasp make-bag --region transparent:...``; ``--manifest`` adds the captures of an
``evaluate-real`` manifest, whole frame and crop) the scene is segmented as the nodes do (the bags as
``scripts/bag_iou.py``, a real bag or capture at its target pixel), the GPIS fitted on the published grids,
and at each planning-grid cell centre inside the truth's grid z = |posterior mean - true SDF| / posterior sigma.
Cells are grouped by what the sensor gave them (:func:`cell_classes`): **failed** - no return (missing), the
masks disagree (colour-only evidence or depth-only), mostly foreign no-return pixels, a clear body's prism or
the table seen through it - and **measured** (observed, trained, none of those). Printed per scene: the cells of each
group, z at the 90th percentile and the median posterior sigma (mm). A calibrated posterior has z P90 about
1.64 (Gaussian errors); above 2 on the failed cells means confidently wrong where nothing was measured.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'scripts'))

from bag_iou import segment  # noqa: E402

from gpis_grasp_ros.core.pipeline import posterior_from_grids, publishable_grids  # noqa: E402
from gpis_grasp_ros.core.sensing import SensingParams, SensingResult  # noqa: E402
from gpis_grasp_ros.data.bags import load_bag  # noqa: E402
from gpis_grasp_ros.tools.evaluation.truth import TrueShape  # noqa: E402

#: target pixels of the shipped real bags (bags/real/README.md)
REAL_TARGETS = {'cleargrasp_000000080_bottle': (220.8, 160.8), 'cleargrasp_000000123_flower_box': (200.8, 122.8)}


def cell_classes(result: SensingResult) -> dict[str, np.ndarray]:
    """(M, M) masks: ``missing``, ``disagree`` (rho above the uncertainty threshold), ``clear`` (a clear body's
    prism and the table seen through it), ``failed`` (their union and the foreign no-return cells) and
    ``measured`` (observed, trained, not failed)."""
    body = np.zeros(result.geometry.shape, dtype=bool) if result.clear_body is None else result.clear_body
    behind = np.zeros_like(body) if result.seen_behind is None else result.seen_behind
    clear = body | behind
    rho_max = SensingParams().uncertainty_threshold
    disagree = result.observed & ~result.missing & ~clear & (result.disagreement > rho_max)
    failed = result.uncertain | clear
    measured = result.observed & result.train_mask & ~failed & ~result.occluded
    return {'missing': result.missing, 'disagree': disagree, 'clear': clear, 'failed': failed, 'measured': measured}


def zscores(result: SensingResult, true_sdf: np.ndarray, true_geometry) -> tuple[np.ndarray, np.ndarray, dict]:
    """(z, sigma m, classes) on the planning grid of ``result``."""
    occ, noise, geometry = publishable_grids(result)
    post = posterior_from_grids(occ, noise, geometry)
    shape = TrueShape(true_sdf, true_geometry, geometry)
    centres = geometry.cell_centers()
    truth = shape.values_at(centres)
    # the truth is known on its own grid only (beyond it the sampled SDF is clamped): cells inside it, one true
    # cell in from its border
    xy = shape.to_true(centres)
    lo = np.array([true_geometry.origin_x, true_geometry.origin_y]) + 1.5 * true_geometry.resolution
    hi = lo + (np.array(true_geometry.shape[::-1]) - 3) * true_geometry.resolution
    inside = np.all((xy >= lo) & (xy <= hi), axis=-1)
    sigma = np.sqrt(np.maximum(post.variance, 1e-18))
    return np.abs(post.mean - truth) / sigma, sigma, {k: m & inside for k, m in cell_classes(result).items()}


def _row(name: str, z: np.ndarray, sigma: np.ndarray, classes: dict) -> str:
    cols = []
    for key in ('failed', 'missing', 'disagree', 'clear', 'measured'):
        m = classes[key]
        if m.any():
            cols.append(f'{int(m.sum())}, {np.percentile(z[m], 90):.2f}, {1e3 * np.median(sigma[m]):.1f}')
        else:
            cols.append('0')
    return f'| {name} | ' + ' | '.join(cols) + ' |'


def bag_scenes(paths: list[Path]):
    for path in paths:
        scene = load_bag(path, frames=1 if path.stem in REAL_TARGETS or path.parent.name == 'real' else 10)
        if path.stem in REAL_TARGETS:
            from gpis_grasp_ros.tools.evaluation.real import sensing_params

            result = segment(scene, sensing_params(REAL_TARGETS[path.stem]))
        else:
            result = segment(scene)
        label = f'{path.parent.name}/{path.stem}' if path.parent != ROOT / 'bags' else path.stem
        yield label, result, scene.true_sdf, scene.true_geometry


def manifest_scenes(manifest: Path, root: str | None):
    from gpis_grasp_ros.tools.evaluate_real.manifest import load_manifest
    from gpis_grasp_ros.tools.evaluate_real.tasks import unit_scene
    from gpis_grasp_ros.tools.evaluation.real import sensing_params

    for unit in load_manifest(manifest, root):
        entry = unit.entry()
        scene, target = unit_scene(entry)
        try:
            result = segment(scene, sensing_params(target, entry['sensor'], 25, entry['clear_body_height_m']))
        except ValueError as exc:
            print(f'| {unit.id} | refused: {exc} |')
            continue
        yield unit.id, result, scene.true_sdf, scene.true_geometry


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('bags', nargs='*', type=Path)
    ap.add_argument('--manifest', type=Path)
    ap.add_argument('--root')
    ap.add_argument('--no-shipped', action='store_true', help='only the bags given and the manifest')
    args = ap.parse_args(argv)
    paths = [] if args.no_shipped else sorted((ROOT / 'bags').glob('*.mcap')) + sorted(
        (ROOT / 'bags' / 'head').glob('*.mcap')) + sorted((ROOT / 'bags' / 'real').glob('*.mcap'))
    paths += list(args.bags)
    print('| scene | failed: cells, z P90, median sigma mm | missing | masks disagree | clear body + behind | '
          'measured |')
    print('|---|---|---|---|---|---|')
    pooled: dict[str, list[np.ndarray]] = {'failed': [], 'measured': []}
    scenes = list(bag_scenes(paths))
    sources = iter(scenes) if args.manifest is None else (s for g in (scenes, manifest_scenes(args.manifest,
                                                                                               args.root)) for s in g)
    for name, result, true_sdf, true_geometry in sources:
        z, sigma, classes = zscores(result, true_sdf, true_geometry)
        print(_row(name, z, sigma, classes))
        sys.stdout.flush()
        for key in pooled:
            pooled[key].append(z[classes[key]])
    for key, zs in pooled.items():
        allz = np.concatenate(zs) if zs else np.zeros(0)
        if allz.size:
            print(f'pooled {key}: {allz.size} cells, z P90 {np.percentile(allz, 90):.2f}, P50 {np.median(allz):.2f}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
