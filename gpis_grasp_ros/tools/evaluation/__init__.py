"""One evaluation engine for ``gpis-grasp evaluate``, ``tune``, ``benchmark`` and ``import-rgbd --evaluate``.

* :mod:`~.tasks` — what one evaluation task is: the posterior of a scene (:func:`~.tasks.fit_scene`),
  planning, the executions on the true shape and the result columns (:class:`~.tasks.GraspRecord`);
* :mod:`~.truth` — the ground truth of a scene and the planning-grid → true-grid transform
  (:class:`~.truth.TrueShape`);
* :mod:`~.runner` — serial, process and Dask executors;
* :mod:`~.reports` — result files (JSON lines, CSV, JSON) and Markdown tables;
* :mod:`~.throughput` — tasks/s of the executors.
"""

from gpis_grasp_ros.tools.evaluation.reports import (
    read_results,
    summary_table,
    surface_table,
    write_csv,
    write_json,
)
from gpis_grasp_ros.tools.evaluation.runner import EXECUTORS, EvalRun, dask_client, run_evaluation
from gpis_grasp_ros.tools.evaluation.tasks import (
    SURFACE_COLUMNS,
    TIMING_COLUMNS,
    EvalSettings,
    GraspRecord,
    SceneFit,
    Task,
    fit_scene,
    make_tasks,
    run_task,
)
from gpis_grasp_ros.tools.evaluation.truth import TrueShape

__all__ = [
    'EXECUTORS', 'SURFACE_COLUMNS', 'TIMING_COLUMNS', 'EvalRun', 'EvalSettings', 'GraspRecord', 'SceneFit', 'Task',
    'TrueShape', 'dask_client', 'fit_scene', 'make_tasks', 'read_results', 'run_evaluation', 'run_task',
    'summary_table', 'surface_table', 'write_csv', 'write_json',
]
