"""Entry shim: ``python -m gpis_grasp_ros.cli`` runs the ``gpis-grasp`` command line
(:mod:`gpis_grasp_ros.tools.cli`)."""

import sys

from gpis_grasp_ros.tools.cli import main

if __name__ == '__main__':
    sys.exit(main())
