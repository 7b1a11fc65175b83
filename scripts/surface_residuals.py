"""How far the GPIS mean lies from the true surface, against the standard deviation it claims there.

    python scripts/surface_residuals.py MANIFEST [--root DATA] [--grid-size 0]

For every unit of an ``evaluate-real`` manifest (segmented and fitted exactly as ``evaluate-real`` does): the planning
cells within 1.5 cells of the true outline (|true SDF| < 1.5 res), the residual r = mu - true SDF there (RMS, mm),
the posterior standard deviation sigma (median, mm), and the z-score |r| / sigma (RMS and 90th percentile), also with
sigma widened by the grid's quantisation q = res / sqrt(12) (a boundary lies anywhere within its cell):
sqrt(sigma^2 + q^2). A calibrated posterior has z RMS ~1 and a 90th percentile ~1.6.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np


def residuals(rf) -> dict[str, float]:
    """Near-surface residual statistics of one prepared unit (``tools.evaluate_real.tasks._prepared``)."""
    post = rf.fit.posterior
    g = post.geometry
    true_sdf = rf.true_shape.values_at(g.cell_centers().reshape(-1, 2)).reshape(g.shape)
    near = np.abs(true_sdf) < 1.5 * g.resolution
    r = (post.mean - true_sdf)[near]
    sd = np.sqrt(np.maximum(post.variance[near], 0.0))
    z = np.abs(r) / sd
    q = g.resolution / np.sqrt(12.0)
    zq = np.abs(r) / np.sqrt(sd ** 2 + q ** 2)
    return {'cells': int(near.sum()), 'r_rms_mm': float(np.sqrt(np.mean(r ** 2)) * 1e3),
            'sigma_median_mm': float(np.median(sd) * 1e3), 'q_mm': q * 1e3,
            'z_rms': float(np.sqrt(np.mean(z ** 2))), 'z_p90': float(np.percentile(z, 90)),
            'zq_rms': float(np.sqrt(np.mean(zq ** 2))), 'zq_p90': float(np.percentile(zq, 90))}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('manifest')
    p.add_argument('--root', default=None, help='data root (default: the manifest\'s)')
    p.add_argument('--grid-size', type=int, default=0, help='forced M (0: the cell rule, evaluate-real\'s default)')
    a = p.parse_args(argv)
    from threadpoolctl import threadpool_limits

    from gpis_grasp_ros.tools.evaluate_real.manifest import load_manifest
    from gpis_grasp_ros.tools.evaluate_real.tasks import _prepared

    print('| unit | cells | residual RMS (mm) | sigma median (mm) | q (mm) | z RMS | z p90 | with q: z RMS | z p90 |')
    print('|---|---:|---:|---:|---:|---:|---:|---:|---:|')
    with threadpool_limits(1):
        for unit in load_manifest(a.manifest, a.root):
            entry = unit.entry()
            rf, refusal, _ = _prepared(json.dumps(entry, sort_keys=True), a.grid_size)
            if rf is None:
                print(f'| {entry["id"]} | refused: {refusal} |')
                continue
            s = residuals(rf)
            print(f'| {entry["id"]} | {s["cells"]} | {s["r_rms_mm"]:.1f} | {s["sigma_median_mm"]:.2f} | '
                  f'{s["q_mm"]:.2f} | {s["z_rms"]:.1f} | {s["z_p90"]:.1f} | {s["zq_rms"]:.1f} | {s["zq_p90"]:.1f} |',
                  flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
