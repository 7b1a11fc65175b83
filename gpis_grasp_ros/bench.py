"""Entry shim: ``python -m gpis_grasp_ros.bench {gpis,planners}`` runs the performance benchmarks
(:mod:`gpis_grasp_ros.tools.bench`)."""

import sys

from gpis_grasp_ros.tools.bench import main

if __name__ == '__main__':
    sys.exit(main())
