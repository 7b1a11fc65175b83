"""``gpis-grasp tune``: k-fold cross-validation of λ and α on a dataset (paper section VI-A).

    gpis-grasp tune --dataset DIR --out DIR --lambda 0,1e4,2e4,5e4,1e5,2e5,5e5 --alpha 0.25,0.5,1,2 --folds 5
                    [--method gp-gpis-opt] [--seeds 1] [--executor serial|process|dask] [--workers N]
                    [--reuse EVAL_DIR] ...

**What is tuned.** λ is ``uncertainty_penalty`` of :class:`~gpis_grasp_ros.core.planners.PlannerParams`,
the penalty on the SDF variance at the contacts in eq. 4/6 (per m² of variance, so independent of the grid; the
paper picks λ = 2 per cell² "based on a grid search using the set of validation shapes" and says "λ can be set using
cross-validation over a set of validation shapes"). α is ``antipodal_alpha``, the bound of the first
antipodal constraint of eq. 5, ‖n1 + n2‖² <= α ("α may be set using cross-validation", section VI-B):
with unit normals ‖n1 + n2‖² = 4 sin²(φ/2), φ the angle between n1 and −n2, so α = 0.5 allows
φ <= 41° and α >= 4 switches the constraint off. It is not the GP-U/GP-D choice and not a GP
hyperparameter. Both only affect GP-GPIS-OPT (and λ also GP-U), so ``--method`` defaults to
``gp-gpis-opt``.

**Score.** Every object × (λ, α) × seed is one task of :mod:`gpis_grasp_ros.tools.evaluation` (same
executors, incremental results and resume): the planned grasp is executed ``--trials`` times on the
TRUE shape by the simulated gripper; the score of a task is its success rate (0 when the planner
returns no grasp). Objects whose scene yields no GPIS or that have no ground truth are left out of
the folds (counted in the report). Scores are averaged over seeds per object.

**Cross-validation.** Objects are shuffled (``--cv-seed``) and split into k folds. For each fold the
(λ, α) with the best mean score on the other k − 1 folds is chosen (ties: smaller λ, then smaller
α — the least penalised setting) and scored on the held-out fold. The reported choice is the setting
with the best mean held-out score over the folds (the usual CV estimate); its spread is given by the
per-fold choices and by a bootstrap over objects (how often each λ wins when the objects are
resampled). Outputs in ``--out``: ``tune.md`` (tables), ``tune.json``, ``cv_scores.csv``,
``tune.png`` (held-out score vs λ per α, mean ± std over folds) and the task results in ``runs/``.
``tune.md`` also breaks the mean success per setting down by material class, size class and
camera (:func:`class_table`): which kind of object a λ helps or hurts.

**Reusing an evaluation.** ``--reuse DIR`` takes the rows of an earlier ``gpis-grasp evaluate`` (or
tune ``runs/``) folder that are tasks of this tune — same dataset digest and settings (``run.json``),
same method, object, seed, λ and α (a default λ/α is matched by its value) — instead of running them
again (:func:`reuse_rows`): e.g. the default-λ column of a tune is the GP-GPIS-OPT column of an
evaluation at the default λ. Rows are identical whatever the run (see :mod:`~gpis_grasp_ros.tools.evaluation`)
as long as the code is the same; each reused row records its source in ``reused_from``.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gpis_grasp_ros.tools.evaluate import add_run_arguments, floats, load_entries, settings_from_args
from gpis_grasp_ros.tools.evaluation.reports import prepare_out, read_results, write_json
from gpis_grasp_ros.tools.evaluation.runner import fingerprint, run_evaluation
from gpis_grasp_ros.tools.evaluation.tasks import Task, make_tasks

DEFAULT_LAMBDAS = (0.0, 1e4, 2e4, 5e4, 1e5, 2e5, 5e5)  # per m² of SDF variance
DEFAULT_ALPHAS = (0.5,)


def task_score(row: dict[str, Any]) -> float:
    """Simulated success rate of a task on the true shape; 0 without a grasp, NaN if not scorable."""
    if row['status'] in ('no_gpis', 'no_ground_truth'):
        return float('nan')
    if not row['success'] or not row['sim_trials']:
        return 0.0
    return float(row['sim_success_rate'])


@dataclass
class CvResult:
    """Score matrix and cross-validation outcome (settings are (λ, α) pairs in grid order)."""

    settings: list[tuple[float, float]]
    objects: list[str]
    scores: np.ndarray  # (objects, settings) mean success over seeds
    folds: list[list[int]]  # object indices per fold
    fold_choice: list[int]  # chosen setting per fold (trained on the other folds)
    fold_heldout: np.ndarray  # (folds, settings) held-out mean score of every setting
    chosen: int  # best mean held-out score
    bootstrap_wins: np.ndarray  # (settings,) fraction of bootstrap resamples in which each setting wins
    excluded: dict[str, str]  # object -> reason


def score_matrix(rows: Sequence[dict[str, Any]], settings: Sequence[tuple[float, float]]
                 ) -> tuple[list[str], np.ndarray, dict[str, str]]:
    """(objects, scores (objects, settings), excluded objects with reasons) from task rows."""
    index = {s: j for j, s in enumerate(settings)}
    per: dict[str, dict[int, list[float]]] = {}
    excluded: dict[str, str] = {}
    for r in rows:
        s = task_score(r)
        if math.isnan(s):
            excluded[r['object']] = r['status']
            continue
        j = index.get((float(r['lambda']), float(r['alpha'])))
        if j is not None:
            per.setdefault(r['object'], {}).setdefault(j, []).append(s)
    objects = sorted(o for o in per if o not in excluded)
    scores = np.full((len(objects), len(settings)), np.nan)
    for i, o in enumerate(objects):
        for j, vals in per[o].items():
            scores[i, j] = float(np.mean(vals))
    complete = ~np.isnan(scores).any(axis=1)
    for i in np.flatnonzero(~complete):
        excluded[objects[i]] = 'incomplete (missing or failed tasks)'
    keep = [o for o, c in zip(objects, complete, strict=True) if c]
    return keep, scores[complete], excluded


def _best(mean_scores: np.ndarray) -> int:
    """Index of the best setting; ties go to the first (grid order: smaller λ, then smaller α)."""
    return int(np.flatnonzero(mean_scores >= np.max(mean_scores) - 1e-12)[0])


def cross_validate(scores: np.ndarray, k: int, seed: int = 0, n_bootstrap: int = 500) -> tuple[
        list[list[int]], list[int], np.ndarray, int, np.ndarray]:
    """k-fold CV over objects (rows of ``scores``): folds, per-fold choice, held-out scores, choice, bootstrap."""
    n = scores.shape[0]
    if not 2 <= k <= n:
        raise ValueError(f'--folds must be between 2 and the number of usable objects ({n}), got {k}')
    rng = np.random.default_rng(seed)
    order = rng.permutation(n)
    folds = [sorted(int(i) for i in f) for f in np.array_split(order, k)]
    choice, heldout = [], np.zeros((k, scores.shape[1]))
    for f, test in enumerate(folds):
        train = np.setdiff1d(np.arange(n), test)
        choice.append(_best(scores[train].mean(axis=0)))
        heldout[f] = scores[test].mean(axis=0)
    chosen = _best(heldout.mean(axis=0))
    wins = np.zeros(scores.shape[1])
    for _ in range(n_bootstrap):
        wins[_best(scores[rng.integers(n, size=n)].mean(axis=0))] += 1
    return folds, choice, heldout, chosen, wins / max(1, n_bootstrap)


def run_cv(rows: Sequence[dict[str, Any]], lambdas: Sequence[float], alphas: Sequence[float], k: int,
           seed: int = 0) -> CvResult:
    settings = [(float(lam), float(a)) for lam in lambdas for a in alphas]
    objects, scores, excluded = score_matrix(rows, settings)
    folds, choice, heldout, chosen, wins = cross_validate(scores, k, seed)
    return CvResult(settings, objects, scores, folds, choice, heldout, chosen, wins, excluded)


def report_markdown(cv: CvResult) -> str:
    s = cv.settings
    n = len(cv.objects)
    lines = ['| λ | α | mean success (all objects) ± s.e. | held-out success, mean ± std over folds | '
             'folds choosing it | bootstrap wins |', '|---|---|---|---|---|---|']
    for j, (lam, a) in enumerate(s):
        col = cv.scores[:, j]
        se = float(np.std(col, ddof=1) / math.sqrt(n)) if n > 1 else float('nan')
        mark = ' **(chosen)**' if j == cv.chosen else ''
        lines.append(f'| {lam:g}{mark} | {a:g} | {col.mean():.3f} ± {se:.3f} | {cv.fold_heldout[:, j].mean():.3f} ± '
                     f'{cv.fold_heldout[:, j].std():.3f} | {cv.fold_choice.count(j)}/{len(cv.folds)} | '
                     f'{cv.bootstrap_wins[j]:.2f} |')
    lam_c, a_c = s[cv.chosen]
    fold_lams = [s[c][0] for c in cv.fold_choice]
    fold_alphas = [s[c][1] for c in cv.fold_choice]
    lam_wins: dict[float, float] = {}
    for j, (lam, _a) in enumerate(s):
        lam_wins[lam] = lam_wins.get(lam, 0.0) + float(cv.bootstrap_wins[j])
    best = cv.fold_heldout[:, cv.chosen]
    lines += ['', f'Chosen by {len(cv.folds)}-fold cross-validation on {n} objects: **λ = {lam_c:g}, α = {a_c:g}** '
              f'(held-out success {best.mean():.3f} ± {best.std():.3f} over folds).',
              f'Per-fold choices (trained on the other folds): λ = {", ".join(f"{v:g}" for v in fold_lams)}; '
              f'α = {", ".join(f"{v:g}" for v in fold_alphas)} (λ median {np.median(fold_lams):g}, '
              f'range {min(fold_lams):g}–{max(fold_lams):g}).',
              'Bootstrap over objects (share of resamples in which each λ wins): '
              + ', '.join(f'λ={lam:g}: {w:.2f}' for lam, w in lam_wins.items()) + '.']
    if cv.excluded:
        reasons: dict[str, int] = {}
        for r in cv.excluded.values():
            reasons[r] = reasons.get(r, 0) + 1
        lines.append('Objects left out: ' + ', '.join(f'{v} ({k})' for k, v in sorted(reasons.items())) + '.')
    return '\n'.join(lines)


CLASS_DIMENSIONS = ('material_class', 'size_class', 'camera')


def class_table(rows: Sequence[dict[str, Any]], cv: CvResult, by: Sequence[str] = CLASS_DIMENSIONS) -> str:
    """Mean success (all cross-validated objects of a class) per setting, by material, size and camera.

    Not a cross-validated figure: it shows where the settings differ (e.g. whether a larger λ helps
    on transparent objects and hurts on opaque ones), not which one to choose."""
    info: dict[str, dict[str, Any]] = {}
    for r in rows:
        info.setdefault(r['object'], r)
    one_alpha = len({a for _, a in cv.settings}) == 1
    names = [f'λ={lam:g}' if one_alpha else f'λ={lam:g}, α={a:g}' for lam, a in cv.settings]
    lines = [f"| class | objects | {' | '.join(names)} | best |", '|---' * (len(names) + 3) + '|']
    for dim in by:
        for g in sorted({str(info[o].get(dim, '')) for o in cv.objects}):
            idx = [i for i, o in enumerate(cv.objects) if str(info[o].get(dim, '')) == g]
            mean = cv.scores[idx].mean(axis=0)
            best = ', '.join(names[j] for j in np.flatnonzero(mean >= mean.max() - 1e-12))
            lines.append(f"| {dim}: {g} | {len(idx)} | {' | '.join(f'{v:.3f}' for v in mean)} | {best} |")
    return '\n'.join(lines)


def reuse_rows(source: str | Path, tasks: Sequence[Task], dataset_digest: str) -> list[dict[str, Any]]:
    """Rows of an earlier run folder that are exactly tasks of this tune, relabelled with their task ids.

    The folder's ``run.json`` must record the same settings and dataset digest as ``tasks``;
    a row matches a task by object, method, seed and the λ, α values the planner used."""
    src = Path(source)
    run_json = src / 'run.json'
    if not run_json.exists():
        raise ValueError(f'--reuse {src}: no run.json (not an evaluate/tune results folder)')
    if json.loads(run_json.read_text(encoding='utf8')) != fingerprint(tasks, dataset_digest):
        raise ValueError(f'--reuse {src}: it was run with other settings or on another dataset (see {run_json})')
    from gpis_grasp_ros.core.planners import PlannerParams

    d = PlannerParams()
    want = {(t.entry['id'], t.method, int(t.seed),
             float(d.uncertainty_penalty if t.uncertainty_penalty is None else t.uncertainty_penalty),
             float(d.antipodal_alpha if t.antipodal_alpha is None else t.antipodal_alpha)): t.task_id for t in tasks}
    out = []
    for r in read_results(src):
        tid = want.get((r['object'], r['method'], int(r['seed']), float(r['lambda']), float(r['alpha'])))
        if tid is not None:
            out.append({**r, 'task_id': tid, 'reused_from': str(src)})
    return out


def add_reused(out: Path, tasks: Sequence[Task], sources: Sequence[str], dataset_digest: str,
               fresh: bool) -> int:
    """Append the reusable rows of ``sources`` that ``out`` does not hold yet; how many were added."""
    files = prepare_out(out, fingerprint(tasks, dataset_digest), fresh)
    have = {r['task_id'] for r in read_results(files.results)}
    added = 0
    with open(files.results, 'a', encoding='utf8') as fh:
        for src in sources:
            for r in reuse_rows(src, tasks, dataset_digest):
                if r['task_id'] not in have:
                    fh.write(json.dumps(r, sort_keys=True) + '\n')
                    have.add(r['task_id'])
                    added += 1
    return added


def plot(cv: CvResult, path: Path) -> None:
    """Held-out success vs λ (symlog x), one line per α, mean ± std over folds; chosen setting ringed."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    lambdas = sorted({lam for lam, _ in cv.settings})
    alphas = sorted({a for _, a in cv.settings})
    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=110)
    for a in alphas:
        idx = [cv.settings.index((lam, a)) for lam in lambdas]
        mean = cv.fold_heldout[:, idx].mean(axis=0)
        std = cv.fold_heldout[:, idx].std(axis=0)
        ax.errorbar(lambdas, mean, yerr=std, marker='o', capsize=3, label=f'α = {a:g}')
    lam_c, a_c = cv.settings[cv.chosen]
    ax.plot([lam_c], [cv.fold_heldout[:, cv.chosen].mean()], 'o', ms=14, mfc='none', mec='k', label='chosen')
    ax.set_xscale('symlog', linthresh=min([v for v in lambdas if v > 0] or [1.0]))
    ax.set_xticks(lambdas)
    ax.set_xticklabels([f'{v:g}' for v in lambdas])
    ax.minorticks_off()
    ax.set_xlabel('λ (uncertainty penalty, per m² of SDF variance)')
    ax.set_ylabel('held-out simulated success rate')
    ax.set_title(f'{len(cv.folds)}-fold cross-validation, {len(cv.objects)} objects')
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def write_outputs(cv: CvResult, out: Path, rows: Sequence[dict[str, Any]] = ()) -> str:
    text = report_markdown(cv)
    if rows:
        text += '\n\nMean success by class (all cross-validated objects; not itself cross-validated):\n\n' + \
            class_table(rows, cv)
    (out / 'tune.md').write_text(text + '\n', encoding='utf8')
    lam_c, a_c = cv.settings[cv.chosen]
    write_json(out / 'tune.json', {
        'chosen': {'lambda': lam_c, 'alpha': a_c}, 'settings': cv.settings, 'objects': cv.objects,
        'folds': cv.folds, 'fold_choice': [cv.settings[c] for c in cv.fold_choice],
        'fold_heldout': cv.fold_heldout.tolist(), 'bootstrap_wins': cv.bootstrap_wins.tolist(),
        'excluded': cv.excluded}, indent=1)
    with open(out / 'cv_scores.csv', 'w', newline='', encoding='utf8') as fh:
        w = csv.writer(fh, lineterminator='\n')
        w.writerow(['object'] + [f'lambda={lam:g};alpha={a:g}' for lam, a in cv.settings])
        for o, row in zip(cv.objects, cv.scores, strict=True):
            w.writerow([o] + [f'{v:.6g}' for v in row])
    plot(cv, out / 'tune.png')
    return text


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog='gpis-grasp tune', description=__doc__.split('\n\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_run_arguments(p)
    p.add_argument('--lambda', dest='lambdas', type=floats, default=list(DEFAULT_LAMBDAS),
                   help='λ grid, per m² of SDF variance (default: 0,1e4,2e4,5e4,1e5,2e5,5e5)')
    p.add_argument('--alpha', dest='alphas', type=floats, default=list(DEFAULT_ALPHAS),
                   help='α grid (default: 0.5)')
    p.add_argument('--folds', type=int, default=5)
    p.add_argument('--cv-seed', type=int, default=0, help='seed of the fold split and the bootstrap')
    p.add_argument('--method', default='gp-gpis-opt', help='planner whose λ/α are tuned (default: %(default)s)')
    p.add_argument('--reuse', action='append', default=[], metavar='DIR',
                   help='take matching task rows from this earlier evaluate/tune results folder (same settings '
                        'and dataset) instead of running them; may be repeated')
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    out = Path(args.out)
    try:
        if not args.lambdas or not args.alphas:
            raise ValueError('--lambda and --alpha need at least one value each')
        if any(v < 0 for v in args.lambdas) or any(v <= 0 for v in args.alphas):
            raise ValueError('λ must be >= 0 and α > 0')
        entries, digest = load_entries(args.dataset, args.objects)
        if args.folds > len(entries):
            raise ValueError(f'--folds {args.folds} is more than the {len(entries)} objects of the dataset')
        tasks = make_tasks(entries, [args.method], range(max(1, args.seeds)), args.lambdas, args.alphas,
                              settings_from_args(args))
        fresh = args.fresh
        reused = 0
        if args.reuse:
            reused = add_reused(out / 'runs', tasks, args.reuse, digest, fresh)
            fresh = False
        run = run_evaluation(tasks, out / 'runs', args.executor, args.workers, args.scheduler, fresh=fresh,
                                progress=not args.no_progress, dataset_digest=digest, affinity=args.affinity)
        cv = run_cv(run.rows, args.lambdas, args.alphas, args.folds, args.cv_seed)
    except ValueError as err:
        print(f'gpis-grasp tune: {err}', file=sys.stderr)
        return 2
    print(write_outputs(cv, out, run.rows))
    print(f'\n{len(tasks)} tasks: {run.ran} run now, {run.resumed - reused} from earlier runs in this folder, '
          f'{reused} reused from {", ".join(args.reuse) or "-"}')
    print(f'\nwrote {out / "tune.md"}, {out / "tune.png"}, {out / "cv_scores.csv"}; task results in {out / "runs"}')
    if run.failures:
        print(f'gpis-grasp tune: {len(run.failures)} task(s) failed after retry (see '
              f'{out / "runs" / "failures.jsonl"}); their objects were left out', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
