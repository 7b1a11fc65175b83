"""``gpis-grasp evaluate-real``: the planners on a manifest of real captures with ground truth.

* :mod:`~.manifest` — the YAML manifest and its units (capture × whole / crop / bag);
* :mod:`~.tasks` — one grasp of one unit (the evaluation of ``import-rgbd --evaluate``) as a result row;
* :mod:`~.report` — the per-unit table, the summary and the reliability diagram;
* :mod:`~.cli` — the command, run by the evaluation engine's executors.
"""

from gpis_grasp_ros.tools.evaluate_real.cli import main

__all__ = ['main']
