"""GP-GPIS-OPT and adaptive GP-P P_F at forced M = 25, 50, 100 on shipped top-down bags (a study: docs/planning.md)."""
import sys
from pathlib import Path

from gpis_grasp_ros.core.planners import PlannerParams, plan
from gpis_grasp_ros.core.sensing import SensingParams
from gpis_grasp_ros.data.bags import load_bag, posterior_from_scene

params = PlannerParams()
for bag in sys.argv[1:]:
    scene = load_bag(bag)
    row = []
    for m in (25, 50, 100):
        post = posterior_from_scene(scene, SensingParams(grid_size=m))[0]
        g, p = plan('gp-gpis-opt', post, params, seed=0), plan('gp-p', post, params, seed=0)
        row.append(f'{g.p_f:.2f} / {p.p_f:.2f}')
    print(Path(bag).stem[0], ' | '.join(row), flush=True)
