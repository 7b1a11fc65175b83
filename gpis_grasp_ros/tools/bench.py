"""Performance benchmarks (tables printed to stdout; speed targets live here, not in tests).

    python -m gpis_grasp_ros.bench gpis       # GPIS fit / sampling / blur vs scikit-learn
    python -m gpis_grasp_ros.bench planners   # planners' time and P_F, vectorised P_F vs a loop
    python -m gpis_grasp_ros.bench e2e        # camera frames to a grasp: every stage on a few bags
    python -m gpis_grasp_ros.bench pf         # the final P_F's parts; float32 vs float64 shape samples
"""

from __future__ import annotations

import importlib
import sys

SUITES = {
    'gpis': 'gpis_grasp_ros.tools.bench_gpis',
    'planners': 'gpis_grasp_ros.tools.bench_planners',
    'e2e': 'gpis_grasp_ros.tools.bench_e2e',
    'pf': 'gpis_grasp_ros.tools.bench_pf',
}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in SUITES:
        print(f'usage: python -m gpis_grasp_ros.bench {{{",".join(SUITES)}}} [options]', file=sys.stderr)
        return 2
    return int(importlib.import_module(SUITES[argv[0]]).main(argv[1:]) or 0)


if __name__ == '__main__':
    sys.exit(main())
