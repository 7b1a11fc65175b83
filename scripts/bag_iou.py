"""Mean-shape and occupancy IoU of the shipped bags, top-down (``bags/``) vs head camera (``bags/head/``).

Segmentation as the nodes run it (``SensingParams()``, the benchmark's fallback without the
too-wide check when the target is refused), GPIS as :func:`~gpis_grasp_ros.data.bags.posterior_from_scene`;
the mean shape is compared with the truth on the truth's own 1 mm grid (``TrueShape.iou_fine``: the GPIS
mean interpolated there; parts of the object off the planning grid count as missed) and, as before, with the
truth sampled at the planning grid's cell centres (``TrueShape.iou_on``), both through the camera frame.
``python scripts/bag_iou.py`` prints the table (about 1 min); ``--shifts`` the spread of both measures over
sub-cell shifts of the planning grid (about 5 min), ``--holes`` the placement error of no-return pixels,
``--timing`` segmentation times.
"""

from __future__ import annotations

import contextlib
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from gpis_grasp_ros.core.pipeline import posterior_from_grids, publishable_grids
from gpis_grasp_ros.core.sensing import SensingParams, SensingResult, segment_frames
from gpis_grasp_ros.core.table_frame import TableFrame
from gpis_grasp_ros.data.bags import BagScene, load_bag
from gpis_grasp_ros.tools.evaluation.truth import TrueShape

BAG_DIR = Path(__file__).resolve().parents[1] / 'bags'


def segment(scene: BagScene, params: SensingParams = SensingParams()) -> SensingResult:
    """Segmentation with the node defaults; a refused too-wide target is segmented without that check."""
    try:
        return segment_frames(scene.rgb_frames, scene.depth_frames, scene.intrinsics, params, scene.frame_id)
    except ValueError:
        return segment_frames(scene.rgb_frames, scene.depth_frames, scene.intrinsics,
                              dataclasses.replace(params, max_opening_m=0.0), scene.frame_id)


def bag_iou(path: Path) -> tuple[float, float, float, float, float]:
    """(mean-shape IoU on the true 1 mm grid, mean-shape IoU at the planning grid's cell centres, occupancy IoU
    at the cell centres, measured object height m, segmentation time s) of one bag."""
    scene = load_bag(path)
    t0 = time.perf_counter()
    result = segment(scene)
    seconds = time.perf_counter() - t0
    occ, noise, geometry = publishable_grids(result)
    posterior = posterior_from_grids(occ, noise, geometry)
    truth_shape = TrueShape(scene.true_sdf, scene.true_geometry, geometry)
    truth = truth_shape.values_at(geometry.cell_centers()) < 0

    def iou(a: np.ndarray) -> float:
        return float((a & truth).sum() / max((a | truth).sum(), 1))

    height = float(getattr(result, 'object_height', float('nan')))
    return (truth_shape.iou_fine(geometry, posterior.mean), iou(posterior.mean < 0), iou(result.occupancy >= 0.5),
            height, seconds)


@contextlib.contextmanager
def shifted_grid(sx: float, sy: float):
    """Segmentation's planning grid moved by (sx, sy) cells in the table plane (a sub-cell shift of where the
    grid's cells fall on the object; every other use of ``TableFrame.grid`` - 1 x 1 frames - is unchanged)."""
    original = TableFrame.grid

    def grid(self, origin_x, origin_y, resolution, width, height, frame_id=''):
        if width > 1 or height > 1:
            origin_x, origin_y = origin_x + sx * resolution, origin_y + sy * resolution
        return original(self, origin_x, origin_y, resolution, width, height, frame_id)

    TableFrame.grid = grid
    try:
        yield
    finally:
        TableFrame.grid = original


def shift_spread(shifts: tuple[tuple[float, float], ...] = tuple((x, y) for x in (0.0, 0.25, 0.5, 0.75)
                                                                   for y in (0.0, 0.5))) -> None:
    """Min / median / max of both mean-shape IoUs over sub-cell shifts of the planning grid, per bag."""
    names = sorted(p.name for p in BAG_DIR.glob('*.mcap'))
    print('| object | 1 mm truth, top-down | head | planning cells, top-down | head |  (min / median / max over '
          f'{len(shifts)} grid shifts)')
    print('|---|---|---|---|---|')
    medians = []
    for name in names:
        cols = []
        for path in (BAG_DIR / name, BAG_DIR / 'head' / name):
            vals = []
            for sx, sy in shifts:
                with shifted_grid(sx, sy):
                    vals.append(bag_iou(path)[:2])
            cols.append(np.array(vals))
        medians.append([np.median(c[:, k]) for k in (0, 1) for c in cols])
        cells = [f'{c[:, k].min():.2f} / {np.median(c[:, k]):.2f} / {c[:, k].max():.2f}' for k in (0, 1) for c in cols]
        print(f'| {name[0]} | ' + ' | '.join(cells) + ' |')
        sys.stdout.flush()
    m = np.array(medians)  # columns: fine top, fine head, cells top, cells head
    for k, what in ((0, '1 mm truth'), (2, 'planning cells')):
        within = int(np.sum(np.abs(m[:, k + 1] - m[:, k]) <= 0.05))
        not_worse = int(np.sum(m[:, k + 1] >= m[:, k] - 0.05))
        print(f'medians, head within 0.05 of top-down ({what}): {within} / {len(names)}; not worse by more than '
              f'0.05: {not_worse} / {len(names)}')


def hole_errors(letters: str = 'BCDEH') -> None:
    """Median / 90th percentile (mm) of the distance between where segmentation puts the no-return pixels of each
    head bag (the orthographic foot of their placed point) and the foot of the surface the simulator's ray hits."""
    from gpis_grasp_ros.core.sensing import occlusion
    from gpis_grasp_ros.sim.objects import head_spec
    from gpis_grasp_ros.sim.scene import L_SPECULAR, Scene

    place = occlusion._missing_height
    for path in sorted((BAG_DIR / 'head').glob('*.mcap')):
        if path.name[0] not in letters:
            continue
        captured: dict = {}

        def spy(*args, captured=captured, **kwargs):
            captured['args'], captured['h'] = args, place(*args, **kwargs)
            return captured['h']

        occlusion._missing_height = spy
        try:
            segment(load_bag(path))
        finally:
            occlusion._missing_height = place
        _, above, missing, rays, table = captured['args'][:5]
        h = captured['h'][0] if isinstance(captured['h'], tuple) else captured['h']  # (heights, tested) or heights
        sim = Scene(head_spec(path.name[0]))
        _, depth, is_wall, _ = sim.tracer.trace(sim.static.rays)
        placed = table.to_table(rays * ((h - table.offset_m) / (rays @ table.n))[..., None] - h[..., None] * table.n)[0]
        err = np.linalg.norm(placed - table.to_table(rays * depth[..., None])[0], axis=-1) * 1000
        spec = sim.static.label == L_SPECULAR
        kinds = {'specular top': spec & ~is_wall, 'specular wall': spec & is_wall,
                 'projector shadow': sim.static.shadow_px}
        print(path.name[0], '  '.join(f'{k} ({(c & missing).sum()} px): {np.median(err[c & missing]):.1f} / '
                                      f'{np.percentile(err[c & missing], 90):.1f} mm'
                                      for k, c in kinds.items() if (c & missing).any()))


def timing(repeats: int = 7) -> None:
    """Best-of-``repeats`` wall time (s) of segmentation per bag (top-down, head) and on a VGA tilted scene."""
    from tilted_scene import Box, TiltedScene

    def best(scene_args: tuple) -> float:
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            segment(BagScene(*scene_args, frame_id='', stamp_ns=0))
            times.append(time.perf_counter() - t0)
        return min(times)

    for folder in (BAG_DIR, BAG_DIR / 'head'):
        t = [best((s.rgb_frames, s.depth_frames, s.intrinsics)) for s in map(load_bag, sorted(folder.glob('*.mcap')))]
        print(f'{folder.name}: ' + ' '.join(f'{v * 1000:.0f}' for v in t) + f' ms, mean {np.mean(t) * 1000:.0f} ms')
    scene = TiltedScene(50.0, boxes=[Box(0.0, 0.0, 0.03, 0.02, 0.04)])
    rgb, depth, _ = scene.frames(10, seed=1)
    print(f'VGA 640 x 480, 10 frames, 50 deg: {best((rgb, depth, scene.intrinsics)) * 1000:.0f} ms')
    # clutter: 24 boxes 8 cm high fill 16 % of the frame; the see-through test's columns on their own
    from gpis_grasp_ros.core.noise_model import SensorModel
    from gpis_grasp_ros.core.sensing import see_through_pixels
    from gpis_grasp_ros.core.table_frame import TableFrame
    d400 = SensorModel.named('realsense_d400')
    scene = TiltedScene(50.0, boxes=[Box(x, y, 0.02, 0.02, 0.08) for x in np.linspace(-0.25, 0.25, 6)
                                     for y in np.linspace(-0.15, 0.15, 4)])
    _, depth, _ = scene.frames(1, seed=0, model=d400)
    table = TableFrame.from_plane(*scene.normal, scene.offset)
    points = scene.intrinsics.rays() * depth[0][..., None]
    height = points @ table.n + table.offset_m
    solid = np.isfinite(height) & (height > 0.005)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        see_through_pixels(points, height, solid, depth[0], table, scene.intrinsics, d400)
        times.append(time.perf_counter() - t0)
    print(f'see-through test alone, VGA, 24 boxes 8 cm high, {int(solid.sum())} pixels above the table: '
          f'{min(times) * 1000:.0f} ms')


def main() -> None:
    if '--holes' in sys.argv:
        return hole_errors()
    if '--timing' in sys.argv:
        return timing()
    if '--shifts' in sys.argv:
        return shift_spread()
    names = sorted(p.name for p in BAG_DIR.glob('*.mcap'))
    print('| object | top-down mean-shape IoU (1 mm truth) | head | head - top-down | at the planning cells, top-down '
          '/ head | occupancy IoU top-down / head | object height top-down / head (mm) | segmentation s top-down / '
          'head |')
    print('|---|---|---|---|---|---|---|---|')
    rows = []
    for name in names:
        top, head = bag_iou(BAG_DIR / name), bag_iou(BAG_DIR / 'head' / name)
        rows.append((top, head))
        print(f'| {name[0]} | {top[0]:.2f} | {head[0]:.2f} | {head[0] - top[0]:+.2f} | {top[1]:.2f} / {head[1]:.2f} '
              f'| {top[2]:.2f} / {head[2]:.2f} | {top[3] * 1000:.1f} / {head[3] * 1000:.1f} '
              f'| {top[4]:.3f} / {head[4]:.3f} |')
        sys.stdout.flush()
    t, h = np.array([r[0] for r in rows]), np.array([r[1] for r in rows])
    print(f'| mean | {t[:, 0].mean():.2f} | {h[:, 0].mean():.2f} | {h[:, 0].mean() - t[:, 0].mean():+.2f} '
          f'| {t[:, 1].mean():.2f} / {h[:, 1].mean():.2f} | {t[:, 2].mean():.2f} / {h[:, 2].mean():.2f} | '
          f'| {t[:, 4].mean():.3f} / {h[:, 4].mean():.3f} |')
    for k, what in ((0, '1 mm truth'), (1, 'planning cells')):
        within = int(np.sum(np.abs(h[:, k] - t[:, k]) <= 0.05))
        not_worse = int(np.sum(h[:, k] >= t[:, k] - 0.05))
        print(f'head within 0.05 of top-down ({what}): {within} / {len(rows)}; not worse by more than 0.05: '
              f'{not_worse} / {len(rows)}')


if __name__ == '__main__':
    main()
