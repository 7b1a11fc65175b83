"""Why the oracle (GP-GPIS-OPT planned on the truth) misses on a capture: one figure per unit.

    python scripts/oracle_figure.py MANIFEST CAPTURE [--root DIR] [--variant crop] [--grid-size M] [--seeds 5]
                                    [--out docs/img/oracle_CAPTURE.png]

Left: the 1 mm truth's outline (black), the truth sampled at the planning grid (grey cells: what the oracle plans
on), the oracle's mean-shape outline (blue) and the planned jaws of each seed (closures of 20 and P_F in the
legend). Right: for the first seed, the contacts of 200 perturbed executions on the truth, green = force closure.
"""

from __future__ import annotations

import argparse
import json

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from gpis_grasp_ros.core.contacts import find_contacts, perturb_grasps  # noqa: E402
from gpis_grasp_ros.core.gpis import center_of_mass as sdf_center_of_mass  # noqa: E402
from gpis_grasp_ros.core.planners import PlannerParams, plan  # noqa: E402
from gpis_grasp_ros.core.quality import grasp_quality, torque_scale  # noqa: E402
from gpis_grasp_ros.core.sdf_bank import SdfBank  # noqa: E402
from gpis_grasp_ros.core.sensing.params import SensingParams  # noqa: E402
from gpis_grasp_ros.tools.evaluate_real.manifest import load_manifest  # noqa: E402
from gpis_grasp_ros.tools.evaluate_real.tasks import _prepared  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('manifest')
    p.add_argument('capture')
    p.add_argument('--root', default=None)
    p.add_argument('--variant', default='crop')
    p.add_argument('--grid-size', type=int, default=SensingParams.grid_size)
    p.add_argument('--seeds', type=int, default=5)
    p.add_argument('--out', default=None)
    a = p.parse_args(argv)
    unit = next(u for u in load_manifest(a.manifest, a.root) if u.capture == a.capture and u.variant == a.variant)
    rf, refusal, _ = _prepared(json.dumps(unit.entry(), sort_keys=True), a.grid_size)
    if rf is None:
        raise SystemExit(f'refused: {refusal}')
    post = rf.posterior(oracle=True)
    g, truth = post.geometry, rf.true_shape
    gripper = PlannerParams().gripper
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 6))
    xy = g.cell_centers()
    ax.scatter(xy[rf.truth][:, 0], xy[rf.truth][:, 1], s=(72 * g.resolution * 260) ** 2 / 40, marker='s', c='0.85')
    tsdf, tg = truth.sdf, truth.geometry
    for line in truth.outline():
        ax.plot(*np.vstack([line, line[:1]]).T, 'k-', lw=1.5)
    ax.contour(xy[..., 0], xy[..., 1], post.mean, [0.0], colors='tab:blue', linewidths=1.0)
    grasps = []
    for seed in range(a.seeds):
        r = plan('gp-gpis-opt', post, PlannerParams(), seed=seed)
        if not r.success:
            continue
        ok = truth.execute(r.jaw1, r.jaw2, gripper, 20, np.random.default_rng(seed))
        grasps.append(r)
        ax.plot([r.jaw1[0], r.jaw2[0]], [r.jaw1[1], r.jaw2[1]], '-o', ms=4,
                label=f'seed {seed}: {ok}/20 closed, P_F {r.p_f:.2f}')
    ax.set_aspect('equal')
    ax.set_title(f'{a.capture} {a.variant}: oracle at M = {g.width} ({1000 * g.resolution:.1f} mm cells)')
    ax.legend(fontsize=8, loc='lower left')
    if grasps:
        r = grasps[0]
        bank = SdfBank(tsdf[None], tg)
        com = sdf_center_of_mass(tsdf[None], tg)[0]
        eps = np.random.default_rng(7).standard_normal((200, 2, 2))
        g1, g2 = perturb_grasps(truth.to_true(r.jaw1), truth.to_true(r.jaw2), eps, gripper.sigma_g)
        con = find_contacts(bank, g1, g2, gripper, check_opening=False)
        q = grasp_quality(con, com, gripper, torque_scale(tsdf, tg, com))
        c1, c2 = truth.to_plan(con.c1.reshape(-1, 2)), truth.to_plan(con.c2.reshape(-1, 2))
        good = (q.reshape(-1) > 0)
        for line in truth.outline():
            bx.plot(*np.vstack([line, line[:1]]).T, 'k-', lw=1.0)
        for c, mk in ((c1, 'o'), (c2, 's')):
            bx.scatter(c[good, 0], c[good, 1], s=6, c='tab:green', marker=mk)
            bx.scatter(c[~good, 0], c[~good, 1], s=6, c='tab:red', marker=mk)
        bx.plot([r.jaw1[0], r.jaw2[0]], [r.jaw1[1], r.jaw2[1]], 'k--', lw=0.8)
        lo = np.minimum(r.jaw1, r.jaw2) - 0.015
        hi = np.maximum(r.jaw1, r.jaw2) + 0.015
        bx.set_xlim(lo[0], hi[0])
        bx.set_ylim(lo[1], hi[1])
        bx.set_aspect('equal')
        bx.set_title(f'seed 0 on the truth, sigma_g = {1000 * gripper.sigma_g:g} mm: '
                     f'{int(good.sum())}/{good.size} in force closure')
    out = a.out or f'docs/img/oracle_{a.capture}.png'
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    print(f'wrote {out}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
