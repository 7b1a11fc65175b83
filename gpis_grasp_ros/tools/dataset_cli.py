"""``gpis-grasp make-dataset``: a deterministic object set for dataset-scale evaluation.

    gpis-grasp make-dataset --n 200 --seed 0 --out data/set0 [--paper A,B,...|all] [--bag my.mcap ...]
                            [--bags] [--size-range 0.02,0.14] [--frames 10]
    gpis-grasp make-dataset --out data/set0 --bag-of gen_00003     # one object's bag on request

Writes ``manifest.json`` (every object's outline, material regions, camera and noise seed: the
scenes are rendered from it in memory by the evaluation workers) and ``manifest.csv`` (one row per
object: family, size and material class, ...). ``--bags`` also writes ``bags/<id>.mcap`` for every
simulated object; ``--bag-of ID`` writes a single object's bag of an existing dataset. See
:mod:`gpis_grasp_ros.sim.dataset` for the generator.
"""

from __future__ import annotations

import argparse
import collections
import sys
from pathlib import Path

from gpis_grasp_ros.sim import dataset as ds
from gpis_grasp_ros.sim.objects import OBJECTS


def _size_range(text: str) -> tuple[float, float]:
    try:
        lo, hi = (float(x) for x in text.split(','))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected MIN,MAX in metres, e.g. 0.02,0.14, got '{text}'") from None
    return lo, hi


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog='gpis-grasp make-dataset', description=__doc__.split('\n\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--out', required=True, help='dataset folder')
    p.add_argument('--n', type=int, default=0, help='number of generated objects (default: %(default)s)')
    p.add_argument('--seed', type=int, default=0, help='dataset seed (default: %(default)s)')
    p.add_argument('--paper', default='', help="mix in the paper's objects: letters A,B,... or 'all'")
    p.add_argument('--bag', action='append', default=[], help="mix in a user's bag (repeatable)")
    p.add_argument('--bags', action='store_true', help='also write a bag per simulated object (bags/<id>.mcap)')
    p.add_argument('--bag-of', default='', metavar='ID', help="write the bag of object ID of an existing dataset")
    p.add_argument('--size-range', type=_size_range, default=ds.DEFAULT_SIZE_RANGE_M,
                   help='largest extent of generated objects, MIN,MAX in m (default: 0.02,0.14)')
    p.add_argument('--max-opening', type=float, default=ds.DEFAULT_MAX_OPENING_M,
                   help='gripper opening w_g (m) for the size classes (default: %(default)s)')
    p.add_argument('--head-fraction', type=float, default=0.5,
                   help='share of objects seen by a tilted head camera, if the simulator supports it (default: 0.5)')
    p.add_argument('--frames', type=int, default=10, help='camera frames per scene (default: %(default)s)')
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        if args.bag_of:
            dataset = ds.load_dataset(args.out)
            entry = dataset.entry(args.bag_of)
            path = ds.write_entry_bag(entry, dataset.root / 'bags' / f'{entry["id"]}.mcap')
            print(f'{path}  {path.stat().st_size / 1e6:.2f} MB')
            return 0
        paper = list(OBJECTS) if args.paper.strip().lower() == 'all' else \
            [x.strip() for x in args.paper.split(',') if x.strip()]
        dataset = ds.make_dataset(args.out, args.n, args.seed, paper=paper, bags=args.bag, write_bags=args.bags,
                                  size_range_m=args.size_range, max_opening_m=args.max_opening, frames=args.frames,
                                  head_fraction=args.head_fraction)
    except (ValueError, KeyError, OSError) as err:
        print(f'gpis-grasp make-dataset: {err}', file=sys.stderr)
        return 2
    print(f'{len(dataset.entries)} objects in {Path(args.out) / ds.MANIFEST_NAME} '
          f'(digest {ds.manifest_digest(dataset)})')
    for key in ('source', 'family', 'size_class', 'material_class', 'camera'):
        counts = collections.Counter(e[key] for e in dataset.entries)
        print(f'  {key:<15} ' + ', '.join(f'{k} {v}' for k, v in sorted(counts.items())))
    print(f'  note: {dataset.meta["note"]}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
