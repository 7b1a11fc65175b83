"""Why a grasp planned on the truth itself slips: its contacts on the fine truth against the planner's view of it.

    python scripts/oracle_contacts.py MANIFEST --root DATA --unit UNIT [--seeds 0 1 2 3 4] [--trials 20] [--grid-size M]

For one unit of an ``evaluate-real`` manifest (e.g. ``"gqcnn_single_0|whole"``) and each planner seed, the oracle's
GP-GPIS-OPT grasp (planned on the truth sampled at the planning grid's cell centres, as ``evaluate-real --oracle``)
is executed ``--trials`` times with the execution seed's jaw perturbations, as ``evaluate-real`` does, on two shapes:
the fine truth the benchmark judges on, and the oracle posterior's mean (the truth as the planner sees it on its
cells). Printed per seed: the oracle's P_F, the closures on each, and for the jaw whose contact normal is further off
the closing line, that angle (median and max over the trials, degrees) on each shape against the friction cone's
half-angle, and the distance between the two shapes' contacts (median, mm).
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from gpis_grasp_ros.core.contacts import find_contacts, perturb_grasps
from gpis_grasp_ros.core.gpis import center_of_mass
from gpis_grasp_ros.core.planners import PlannerParams, plan
from gpis_grasp_ros.core.quality import grasp_quality, torque_scale
from gpis_grasp_ros.core.sdf_bank import SdfBank
from gpis_grasp_ros.tools.evaluate_real.manifest import load_manifest
from gpis_grasp_ros.tools.evaluate_real.tasks import ORACLE_PLANNER, _prepared


def _off_axis_deg(normals: np.ndarray, closing: np.ndarray) -> np.ndarray:
    """Angle (deg) between contact normals (K, 2) and the closing directions (K, 2), either sense."""
    n = normals / np.linalg.norm(normals, axis=-1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.abs(np.sum(n * closing, axis=-1)), 0.0, 1.0)))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('manifest')
    ap.add_argument('--root', required=True, help='directory the manifest paths are relative to')
    ap.add_argument('--unit', required=True, help='unit id, e.g. "gqcnn_single_0|whole"')
    ap.add_argument('--seeds', type=int, nargs='+', default=[0, 1, 2, 3, 4])
    ap.add_argument('--trials', type=int, default=20)
    ap.add_argument('--grid-size', type=int, default=0, help='force M of the planning grid (default 0: the cell rule)')
    args = ap.parse_args(argv)
    units = [u for u in load_manifest(args.manifest, args.root) if u.id == args.unit]
    if not units:
        ap.error(f'no unit {args.unit!r} in {args.manifest}')
    rf, why, _ = _prepared(json.dumps(units[0].entry(), sort_keys=True), args.grid_size)
    if rf is None:
        print(f'{args.unit}: refused ({why})')
        return 1
    post, truth, gripper = rf.posterior(oracle=True), rf.true_shape, rf.gripper
    mean, geo = np.asarray(post.mean), post.geometry
    mean_bank = SdfBank(mean[None], geo)
    mean_com = center_of_mass(mean[None], geo)[0]
    mean_rho = torque_scale(mean, geo, mean_com)
    cone = float(np.degrees(np.arctan(gripper.friction_coef)))
    print(f'{args.unit}: planning cells {geo.resolution * 1000:.1f} mm, jaw noise {gripper.sigma_g * 1000:.1f} mm, '
          f'friction cone {cone:.1f} deg\n')
    print("| seed | P_F | closed on the truth | on the oracle's mean | worse jaw off the closing line, truth: "
          "median / max (deg) | oracle's mean | contacts apart (mm) |")
    print('|---:|---:|---:|---:|---|---|---:|')
    for seed in args.seeds:
        grasp = plan(ORACLE_PLANNER, post, PlannerParams(), seed=seed)
        if not grasp.success:
            print(f'| {seed} | - | planning failed: {grasp.message} | | | | |')
            continue
        eps = np.random.default_rng(seed).standard_normal((args.trials, 2, 2))  # the execution's perturbations
        g1, g2 = perturb_grasps(grasp.jaw1, grasp.jaw2, eps, gripper.sigma_g)
        on_truth = find_contacts(truth.bank, np.array([truth.to_true(p) for p in g1]),
                                 np.array([truth.to_true(p) for p in g2]), gripper, check_opening=False)
        on_mean = find_contacts(mean_bank, g1, g2, gripper, check_opening=False)
        closed_t = grasp_quality(on_truth, truth.com, gripper, truth.rho) > 0
        closed_m = grasp_quality(on_mean, mean_com, gripper, mean_rho) > 0
        closing = (g2 - g1) / np.linalg.norm(g2 - g1, axis=-1, keepdims=True)
        worse_t = np.maximum(_off_axis_deg(on_truth.n1, closing), _off_axis_deg(on_truth.n2, closing))
        worse_m = np.maximum(_off_axis_deg(on_mean.n1, closing), _off_axis_deg(on_mean.n2, closing))
        apart = [np.linalg.norm(np.array([truth.to_plan(c) for c in getattr(on_truth, f'c{j}')]) -
                                getattr(on_mean, f'c{j}'), axis=-1) for j in (1, 2)]
        print(f'| {seed} | {grasp.p_f:.3f} | {int(closed_t.sum())} | {int(closed_m.sum())} | '
              f'{np.nanmedian(worse_t):.1f} / {np.nanmax(worse_t):.1f} | {np.nanmedian(worse_m):.1f} / '
              f'{np.nanmax(worse_m):.1f} | {np.nanmedian(np.maximum(*apart)) * 1000:.1f} |', flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
