"""The other labelled objects in each unit's ground truth: what the judge counts as obstacles.

    python scripts/truth_obstacles.py MANIFEST [--root DIR]

For every unit of an ``evaluate-real`` manifest (raw captures imported as ``import-rgbd`` would, or bags) prints
the footprint parts that are obstacles of the truth (reaching its grid), the parts under the minimum object area,
the components that could not be built (raw captures only), the obstacle cells (truth cells inside another
object) and the gap (mm) between the target and the nearest obstacle (the target's SDF at the nearest obstacle cell).
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from gpis_grasp_ros.tools.evaluate_real.manifest import load_manifest
from gpis_grasp_ros.tools.evaluate_real.tasks import import_unit, unit_scene


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('manifest')
    ap.add_argument('--root', default=None)
    args = ap.parse_args(argv)
    print('| unit | obstacle parts | small parts | unbuilt | obstacle cells | gap to the target (mm) |')
    print('|---|---:|---:|---:|---:|---:|')
    for unit in load_manifest(args.manifest, args.root):
        entry = unit.entry()
        if entry['bag']:
            scene = unit_scene(entry)[0]
            sdf, obstacles, counts = scene.true_sdf, scene.true_obstacles, ('', '', '')
        else:
            truth = import_unit(entry).truth
            sdf, obstacles = truth.sdf, truth.obstacles
            counts = (truth.obstacle_objects, truth.obstacles_small, truth.obstacles_unbuilt)
        cells = 0 if obstacles is None else int((obstacles < 0).sum())
        near = np.asarray(sdf)[obstacles < 0] if obstacles is not None else np.zeros(0)
        nearest = f'{1e3 * float(near.min()):.1f}' if near.size else '-'
        print(f'| {unit.id} | {counts[0]} | {counts[1]} | {counts[2]} | {cells} | {nearest} |')
    return 0


if __name__ == '__main__':
    sys.exit(main())
