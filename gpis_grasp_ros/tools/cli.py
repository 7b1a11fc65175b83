"""``gpis-grasp`` command line: one entry point, one sub-command per job.

Each sub-command lives in its own module and exposes ``main(argv: list[str] | None) -> int``;
modules are imported lazily so that, e.g., ``make-bag`` does not start ROS.
"""

from __future__ import annotations

import importlib
import sys

COMMANDS: dict[str, tuple[str, str]] = {
    'make-bag': ('gpis_grasp_ros.tools.scene_cli', 'simulate a Carmine looking at an object and write an MCAP bag'),
    'make-bags': ('gpis_grasp_ros.sim.objects', 'regenerate the 8 shipped object bags in bags/'),
    'import-rgbd': ('gpis_grasp_ros.tools.import_rgbd', 'real RGB-D capture (colour, depth, intrinsics) to a bag'),
    'play': ('gpis_grasp_ros.ros.player', 'replay a bag with rclpy publishers (ros2 bag play stand-in)'),
    'demo': ('gpis_grasp_ros.tools.demo', 'replay a bag through the nodes, plan, execute, write images'),
    'benchmark': ('gpis_grasp_ros.tools.benchmark', "reproduce the paper's Table I and runtime scaling"),
    'soak': ('gpis_grasp_ros.tools.soak', 'reliability figures of the nodes as processes (load, faults, shutdown)'),
    'soak-stream': ('gpis_grasp_ros.tools.soak_stream', 'a live 30 Hz camera into the nodes, a plan every second '
                    '(latency, answers, RSS)'),
    'make-dataset': ('gpis_grasp_ros.tools.dataset_cli', 'generate a deterministic object set (manifest, bags)'),
    'evaluate': ('gpis_grasp_ros.tools.evaluate', 'dataset evaluation: serial, process or Dask executor'),
    'tune': ('gpis_grasp_ros.tools.tune', 'k-fold cross-validation of lambda and alpha on a dataset'),
    'evaluate-real': ('gpis_grasp_ros.tools.evaluate_real', 'the planners on a manifest of real captures, as a table'),
}


def usage() -> str:
    lines = ['usage: gpis-grasp COMMAND [options]   (gpis-grasp COMMAND --help for details)', '', 'commands:']
    lines += [f'  {name:<12} {help_text}' for name, (_, help_text) in COMMANDS.items()]
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ('-h', '--help'):
        print(usage())
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"gpis-grasp: unknown command '{name}'\n\n{usage()}", file=sys.stderr)
        return 2
    module = importlib.import_module(COMMANDS[name][0])
    return int(module.main(rest) or 0)


if __name__ == '__main__':
    sys.exit(main())
