"""CPU time of each stage of ``segment_frames``, and a check that a change leaves its results as they were.

    python scripts/segmentation_profile.py [--root DATA] [--repeats 5] [--only NAME ...]
    python scripts/segmentation_profile.py --save FILE [--root DATA]     # every SensingResult of every case
    python scripts/segmentation_profile.py --compare FILE [--root DATA]  # ... against a saved FILE
    python scripts/segmentation_profile.py --json FILE ...               # also every run's stage times (ms)

Timing: ``time.process_time`` (CPU, which the other processes on a shared machine do not inflate) of every stage
function ``segment_frames`` calls (each name in ``core/sensing/segment.py`` wrapped), one BLAS thread, min /
median of ``--repeats`` runs after a warm-up; "other" is the rest of the call. Cases: the shipped bags
(top-down and head A, 10 frames; the real D435 bottle, 1 frame), ``bench e2e``'s simulated whole frames
(object A, 10 frames, 640 x 480 and 1280 x 720) and, with ``--root`` (the real captures' directory, see its
README), the real D435 whole frame (ClearGrasp 000000080, 1280 x 720) and the real PrimeSense whole frame
(GQ-CNN single_0, 640 x 480) at their targets' pixels.

``--save`` / ``--compare`` run every shipped bag (``bags/*.mcap``, ``bags/head/*.mcap``, ``bags/real/*.mcap``)
and the whole frames once: ``--compare`` prints, per case, the fields that are not ``np.array_equal`` (NaN = NaN,
same dtype) and the largest change of the SDF, occupancy and noise grids.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from gpis_grasp_ros.core.noise_model import SensorModel
from gpis_grasp_ros.core.sensing import SensingParams, segment_frames
from gpis_grasp_ros.core.sensing import segment as seg_module
from gpis_grasp_ros.data.bags import load_bag

BAGS = Path(__file__).resolve().parents[1] / 'bags'
D400 = SensorModel.named('realsense_d400')
REAL_TARGETS = {'cleargrasp_000000080_bottle': (220.8, 160.8), 'cleargrasp_000000123_flower_box': (200.8, 122.8)}

#: stage label -> the names segment_frames calls for it
STAGES = {
    'average frames': ('validate_frames', 'average_frames'),
    'table plane': ('fit_table',),
    'target window': ('target_point', 'window', 'crop', 'grown', 'uncrop'),
    'soft evidence': ('soft_evidence',),
    'seen-through returns': ('move_seen_through',),
    'sensor shadow': ('sensor_shadow',),
    'feet': ('place_feet',),
    'objects and target': ('isolate_target',),
    'clear body': ('grow_target',),
    'rasterise': ('rasterise',),
}


def _bag_case(path: Path):
    scene = load_bag(path, frames=10)
    name = path.stem
    if name in REAL_TARGETS:
        params = SensingParams(sensor=D400, target='pixel', target_point=REAL_TARGETS[name])
    else:
        params = SensingParams()
    return scene.rgb_frames, scene.depth_frames, scene.intrinsics, params


def _real_case(root: Path, kind: str):
    from gpis_grasp_ros.data import rgbd_import as ri

    if kind == 'cleargrasp':
        d = root / 'cleargrasp-d435'
        cap = ri.load_capture(d / '000000080-transparent-rgb-img.jpg', d / '000000080-transparent-depth-mm.png',
                              d / 'camera_intrinsics.yaml')
        return cap.rgb, cap.depth, cap.intrinsics, SensingParams(sensor=D400, target='pixel', target_point=(882, 522))
    d = root / 'gqcnn-primesense'
    cap = ri.load_capture(d / 'single_color_0.png', d / 'single_depth_0.npy', d / 'primesense.intr')
    return cap.rgb, cap.depth, cap.intrinsics, SensingParams(sensor=SensorModel.named('carmine'), target='pixel',
                                                            target_point=(337, 282))


def _sim_case(width: int, height: int):
    from gpis_grasp_ros.tools.bench_e2e import whole_frame_scene

    rgb, depth, intr = whole_frame_scene(width, height)
    return rgb, depth, intr, SensingParams()


def timing_cases(root: Path | None) -> dict:
    cases = {}
    if root is not None:
        cases['real D435 whole frame 1280x720'] = lambda: _real_case(root, 'cleargrasp')
        cases['real PrimeSense whole frame 640x480'] = lambda: _real_case(root, 'gqcnn')
    cases['real D435 bottle bag'] = lambda: _bag_case(BAGS / 'real' / 'cleargrasp_000000080_bottle.mcap')
    cases['top-down bag A'] = lambda: _bag_case(BAGS / 'A_tape_dispenser.mcap')
    cases['head bag A'] = lambda: _bag_case(BAGS / 'head' / 'A_tape_dispenser.mcap')
    cases['simulated whole frame 640x480'] = lambda: _sim_case(640, 480)
    cases['simulated whole frame 1280x720'] = lambda: _sim_case(1280, 720)
    return cases


def equivalence_cases(root: Path | None) -> dict:
    cases = {}
    for path in sorted(BAGS.glob('*.mcap')) + sorted((BAGS / 'head').glob('*.mcap')) + sorted(
            (BAGS / 'real').glob('*.mcap')):
        cases[str(path.relative_to(BAGS))] = (lambda p=path: _bag_case(p))
    for key, make in timing_cases(root).items():
        if 'whole frame' in key:
            cases[key] = make
    return cases


def run(rgb, depth, intr, params):
    """segment_frames, refused too-wide targets segmented without that check (as scripts/bag_iou.py)."""
    try:
        return segment_frames(rgb, depth, intr, params)
    except ValueError:
        return segment_frames(rgb, depth, intr, dataclasses.replace(params, max_opening_m=0.0))


class StageTimer:
    """Wraps the stage functions of ``segment.py`` to add up their CPU time."""

    def __init__(self) -> None:
        self.times: dict[str, float] = {}
        self._saved: dict[str, object] = {}

    def __enter__(self) -> StageTimer:
        for label, names in STAGES.items():
            for name in names:
                if not hasattr(seg_module, name):
                    continue
                fn = getattr(seg_module, name)
                self._saved[name] = fn

                def timed(*a, _fn=fn, _label=label, **k):
                    t0 = time.process_time()
                    try:
                        return _fn(*a, **k)
                    finally:
                        self.times[_label] = self.times.get(_label, 0.0) + time.process_time() - t0

                setattr(seg_module, name, timed)
        return self

    def __exit__(self, *exc) -> None:
        for name, fn in self._saved.items():
            setattr(seg_module, name, fn)


def profile(case, repeats: int) -> dict[str, list[float]]:
    rgb, depth, intr, params = case
    run(rgb, depth, intr, params)  # warm-up (numba compilation, caches)
    out: dict[str, list[float]] = {label: [] for label in [*STAGES, 'other', 'total']}
    for _ in range(repeats):
        with StageTimer() as timer:
            t0 = time.process_time()
            run(rgb, depth, intr, params)
            total = time.process_time() - t0
        for label in STAGES:
            out[label].append(timer.times.get(label, 0.0))
        out['other'].append(total - sum(timer.times.values()))
        out['total'].append(total)
    return out


def _fields(result) -> dict[str, object]:
    out = {}
    for f in dataclasses.fields(result):
        v = getattr(result, f.name)
        if isinstance(v, np.ndarray):
            out[f.name] = v
        elif v is None or isinstance(v, (int, float, tuple, str)):
            out[f.name] = np.asarray(v if v is not None else np.nan)
        else:  # geometry, table, intrinsics: their repr holds every number
            out[f.name] = np.asarray(repr(v))
    out['sdf'] = result.sdf
    return out


def save(cases: dict, path: Path) -> None:
    store = {}
    for key, make in cases.items():
        for name, value in _fields(run(*make())).items():
            store[f'{key}|{name}'] = value
        print(f'saved {key}', flush=True)
    np.savez_compressed(path, **store)


def compare(cases: dict, path: Path) -> int:
    ref = np.load(path)
    bad = 0
    print('| case | fields not equal | max abs diff SDF (m) | occupancy | noise (m^2) |\n|---|---|---:|---:|---:|')
    for key, make in cases.items():
        fields = _fields(run(*make()))
        differ = []
        diffs = {}
        for name, value in fields.items():
            old = ref[f'{key}|{name}']
            same = old.dtype == value.dtype and old.shape == value.shape and np.array_equal(
                old, value, equal_nan=old.dtype.kind == 'f')
            if not same:
                differ.append(name)
            if name in ('sdf', 'occupancy', 'noise_variance'):
                diffs[name] = float(np.nanmax(np.abs(old - value))) if old.shape == value.shape else float('inf')
        bad += bool(differ)
        print(f'| {key} | {", ".join(differ) or "-"} | {diffs["sdf"]:.3g} | {diffs["occupancy"]:.3g} | '
              f'{diffs["noise_variance"]:.3g} |', flush=True)
    return 1 if bad else 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--root', type=Path, default=None, help='real captures (cleargrasp-d435/, gqcnn-primesense/)')
    ap.add_argument('--repeats', type=int, default=5)
    ap.add_argument('--only', nargs='*', default=None, help='cases whose name contains one of these')
    ap.add_argument('--save', type=Path, default=None)
    ap.add_argument('--compare', type=Path, default=None)
    ap.add_argument('--json', type=Path, default=None, help='also write every run\'s stage times (ms) here')
    args = ap.parse_args(argv)
    with threadpool_limits(1):
        if args.save is not None:
            save(equivalence_cases(args.root), args.save)
            return 0
        if args.compare is not None:
            return compare(equivalence_cases(args.root), args.compare)
        print(f'load average before: {os.getloadavg()[0]:.2f}')
        runs = {}
        for key, make in timing_cases(args.root).items():
            if args.only and not any(s in key for s in args.only):
                continue
            out = profile(make(), args.repeats)
            runs[key] = {label: [1e3 * v for v in values] for label, values in out.items()}
            print(f'\n{key} (CPU ms, min / median of {args.repeats})\n\n| stage | ms |\n|---|---:|')
            for label, values in out.items():
                ms = 1e3 * np.asarray(values)
                print(f'| {label} | {ms.min():.0f} / {np.median(ms):.0f} |')
            sys.stdout.flush()
        print(f'\nload average after: {os.getloadavg()[0]:.2f}')
        if args.json is not None:
            args.json.write_text(json.dumps(runs))
    return 0


if __name__ == '__main__':
    sys.exit(main())
