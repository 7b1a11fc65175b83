"""Compiled batch of eq. 6 on the mean shape: SCP points -> Q_F of every perturbed trial, variance, constraints.

One call per batch of SCP points does what :meth:`planners.objective.MeanGraspObjective.details_reference`
does with numpy around the contact kernel: perturbed jaws (:func:`contacts.perturb_grasps`), cell coordinates,
the contact search (:func:`contact_kernel.exact_contacts`), normals (:func:`contact_kernel.unit_normals` or
:func:`contact_kernel.unit_normals_from_values`), the validity flags of :func:`contacts.find_contacts`
(no normal, contact on an obstacle), Q_F (:func:`quality._quality_kernel`), the posterior variance at the
nominal contacts and the constraints of eq. 5. The same floating-point operations in the same order as the
numpy path, so the results are bit for bit the same (the tests check this); the per-call numpy work (a few
dozen small array operations per batch) was as costly as the contact search on the small batches the SCP
makes. The sigmoid and the mean over the trials stay in numpy (its ``exp`` and pairwise sum define the
reference's rounding).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from gpis_grasp_ros.core.contact_kernel import exact_contacts, unit_normals, unit_normals_from_values
from gpis_grasp_ros.core.quality import _quality_kernel


@njit(cache=True, nogil=True, inline='always')
def _bilinear_metric(grid, ox, oy, res, x, y):
    """:func:`sdf_bank.bilinear` of one (H, W) grid at one metric point (clamped to the grid)."""
    h, w = grid.shape
    u = min(max((x - ox) / res - 0.5, 0.0), w - 1.0)
    v = min(max((y - oy) / res - 0.5, 0.0), h - 1.0)
    j0 = min(int(u), max(w - 2, 0))
    i0 = min(int(v), max(h - 2, 0))
    j1 = min(j0 + 1, w - 1)
    i1 = min(i0 + 1, h - 1)
    fx = u - j0
    fy = v - i0
    top = grid[i0, j0] * (1 - fx) + grid[i0, j1] * fx
    bottom = grid[i1, j0] * (1 - fx) + grid[i1, j1] * fx
    return top * (1 - fy) + bottom * fy


@njit(cache=True, nogil=True)
def eq6_batch(x, eps, unit_m, sigma_g, ox, oy, res, grids, lipschitz, positive, pad, offsets, patch_tol,
              gradients, gradients_given, min_norm, obstacles, has_obstacles, reach, com, gamma, rho, variance,
              max_variance, max_opening, antipodal, beta, alpha, q, unc, cons, valid_nominal):
    """Eq. 6 terms of B SCP points ``x`` (B, 4) (jaws / ``unit_m``) with K perturbation draws ``eps`` (K, 2, 2).

    The bank: ``grids``, ``lipschitz``, ``positive``, ``pad`` (:class:`sdf_bank.SdfBank`'s padded grids and
    their bounds), ``gradients`` (B', H, W, 2, read when ``gradients_given``, else finite differences of the
    grids), ``obstacles`` (H, W, read when ``has_obstacles``; a contact within ``reach`` m is on an obstacle).
    Grid origin (``ox``, ``oy``) and ``res`` (m per cell). Fills ``q`` (B, K + 1) Q_F of the unperturbed
    grasp (column 0) and of every perturbed trial (−inf when invalid), ``unc`` (B,) σ²(c1) + σ²(c2) at the
    nominal contacts (2 ``max_variance`` without contact), ``cons`` (B, 3 or 6) the constraints (non-finite
    -> 10) and ``valid_nominal`` (B,).
    """
    n_b = x.shape[0]
    n_k = eps.shape[0] + 1
    n_t = n_b * n_k
    ax = np.empty(n_t)
    ay = np.empty(n_t)
    ux = np.empty(n_t)
    uy = np.empty(n_t)
    length = np.empty(n_t)
    for b in range(n_b):
        j1x = x[b, 0] * unit_m
        j1y = x[b, 1] * unit_m
        j2x = x[b, 2] * unit_m
        j2y = x[b, 3] * unit_m
        for k in range(n_k):
            e00 = 0.0 if k == 0 else eps[k - 1, 0, 0]
            e01 = 0.0 if k == 0 else eps[k - 1, 0, 1]
            e10 = 0.0 if k == 0 else eps[k - 1, 1, 0]
            e11 = 0.0 if k == 0 else eps[k - 1, 1, 1]
            g1x = j1x + sigma_g * e00
            g1y = j1y + sigma_g * e01
            g2x = (g1x + (j2x - j1x)) + sigma_g * e10
            g2y = (g1y + (j2y - j1y)) + sigma_g * e11
            t = b * n_k + k
            cx = (g1x - ox) / res - 0.5
            cy = (g1y - oy) / res - 0.5
            dx = ((g2x - ox) / res - 0.5) - cx
            dy = ((g2y - oy) / res - 0.5) - cy
            ln = math.hypot(dx, dy)
            ax[t] = cx
            ay[t] = cy
            length[t] = ln
            if ln <= 1e-12:
                ux[t] = 1.0
                uy[t] = 0.0
            else:
                ux[t] = dx / ln
                uy[t] = dy / ln
    index = np.zeros(n_t, dtype=np.intp)
    c = np.empty((2, n_t, 2))
    no_contact = np.empty(n_t, dtype=np.bool_)
    inside = np.empty(n_t, dtype=np.bool_)
    clear = np.empty((2, n_t))
    exact_contacts(grids, lipschitz, positive, index, ax, ay, ux, uy, length, offsets, pad, patch_tol, c, no_contact,
                   inside, clear, res)
    normals = np.empty((2, n_t, 2))
    if gradients_given:
        unit_normals(gradients, index, c, min_norm, normals)
    else:
        unit_normals_from_values(grids, int(pad), res, index, c, min_norm, normals)
    # contacts (m) and normals in the (T, 2, 2) layout of the quality kernel, NaN as find_contacts leaves them
    cq = np.empty((n_t, 2, 2))
    nq = np.empty((n_t, 2, 2))
    valid = np.empty(n_t, dtype=np.bool_)
    for t in range(n_t):
        no_normal = False
        on_obstacle = False
        for side in range(2):
            nx = normals[side, t, 0]
            ny = normals[side, t, 1]
            if not (nx != 0 or ny != 0):  # a vanishing gradient: no normal
                no_normal = True
                nx = ny = math.nan
            if no_contact[t]:
                cq[t, side, 0] = cq[t, side, 1] = math.nan
                nq[t, side, 0] = nq[t, side, 1] = math.nan
            else:
                mx = ox + (c[side, t, 0] + 0.5) * res
                my = oy + (c[side, t, 1] + 0.5) * res
                cq[t, side, 0] = mx
                cq[t, side, 1] = my
                nq[t, side, 0] = nx
                nq[t, side, 1] = ny
                if has_obstacles and _bilinear_metric(obstacles, ox, oy, res, mx, my) <= reach:
                    on_obstacle = True
        no_normal = no_normal and not no_contact[t]
        valid[t] = not (no_contact[t] or inside[t] or no_normal or on_obstacle)
    q_flat = np.empty(n_t)
    _quality_kernel(cq, nq, com, valid, gamma, rho, q_flat)
    for b in range(n_b):
        t = b * n_k
        for k in range(n_k):
            q[b, k] = q_flat[t + k]
        if no_contact[t]:
            unc[b] = max_variance + max_variance
        else:
            unc[b] = (_bilinear_metric(variance, ox, oy, res, cq[t, 0, 0], cq[t, 0, 1])
                      + _bilinear_metric(variance, ox, oy, res, cq[t, 1, 0], cq[t, 1, 1]))
        wx = x[b, 2] * unit_m - x[b, 0] * unit_m
        wy = x[b, 3] * unit_m - x[b, 1] * unit_m
        width = math.sqrt(wx * wx + wy * wy)
        cons[b, 0] = (width - max_opening) / unit_m
        cons[b, 1] = -clear[0, t] / unit_m
        cons[b, 2] = -clear[1, t] / unit_m
        if antipodal:
            # eq. 5 on the contact line v = (c1 − c2)/‖c1 − c2‖ (see docs/planning.md)
            lx = cq[t, 0, 0] - cq[t, 1, 0]
            ly = cq[t, 0, 1] - cq[t, 1, 1]
            dist = math.hypot(lx, ly)
            if valid[t] and dist > 1e-9 * unit_m:
                vx = lx / dist
                vy = ly / dist
                n1x, n1y, n2x, n2y = nq[t, 0, 0], nq[t, 0, 1], nq[t, 1, 0], nq[t, 1, 1]
                sx = n1x + n2x
                sy = n1y + n2y
                cons[b, 3] = (sx * sx + sy * sy) - alpha
                cons[b, 4] = beta - (n1x * vx + n1y * vy)
                cons[b, 5] = beta + (n2x * vx + n2y * vy)
            else:
                cons[b, 3] = 4.0 - alpha
                cons[b, 4] = 1.0 + beta
                cons[b, 5] = 1.0 + beta
        for i in range(cons.shape[1]):
            if not math.isfinite(cons[b, i]):
                cons[b, i] = 10.0
        valid_nominal[b] = valid[t] and width <= max_opening * (1 + 1e-9)
