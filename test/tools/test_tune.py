"""k-fold cross-validation of λ and α (tools/tune.py): the selection logic on synthetic scores
against a direct computation, ties, exclusions, and the command end to end on a tiny dataset."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from gpis_grasp_ros.core.planners.params import UNCERTAINTY_PENALTY
from gpis_grasp_ros.sim import dataset as ds
from gpis_grasp_ros.tools import evaluate, tune
from gpis_grasp_ros.tools.evaluation.reports import read_results


def _rows(scores: dict[str, dict[tuple[float, float], list[float]]], status: dict[str, str] | None = None):
    """Task rows with the given success rates per object, (λ, α) and seed."""
    rows = []
    for obj, per in scores.items():
        for (lam, a), values in per.items():
            for seed, v in enumerate(values):
                st = (status or {}).get(obj, 'ok')
                rows.append({'object': obj, 'lambda': lam, 'alpha': a, 'seed': seed, 'status': st,
                             'success': st == 'ok' and not np.isnan(v), 'sim_trials': 20,
                             'sim_success_rate': v})
    return rows


def test_cross_validation_matches_a_direct_computation():
    rng = np.random.default_rng(3)
    lambdas, alphas = [0.0, 1.0, 4.0], [0.5, 2.0]
    settings = [(lam, a) for lam in lambdas for a in alphas]
    truth = rng.uniform(0, 1, (11, len(settings)))  # objects x settings, two seeds averaging to it
    scores = {f'o{i:02d}': {s: [truth[i, j] - 0.05, truth[i, j] + 0.05] for j, s in enumerate(settings)}
              for i in range(11)}
    cv = tune.run_cv(_rows(scores), lambdas, alphas, k=4, seed=7)
    assert cv.objects == sorted(scores) and cv.settings == settings
    np.testing.assert_allclose(cv.scores, truth, atol=1e-12)
    assert sorted(i for f in cv.folds for i in f) == list(range(11)) and len(cv.folds) == 4
    for f, test_idx in enumerate(cv.folds):
        train_idx = [i for i in range(11) if i not in test_idx]
        assert cv.fold_choice[f] == int(np.argmax(truth[train_idx].mean(axis=0)))
        np.testing.assert_allclose(cv.fold_heldout[f], truth[test_idx].mean(axis=0))
    assert cv.chosen == int(np.argmax(cv.fold_heldout.mean(axis=0)))
    assert cv.bootstrap_wins.sum() == pytest.approx(1.0) and np.all(cv.bootstrap_wins >= 0)


def test_a_clearly_best_lambda_is_chosen_by_every_fold_and_the_bootstrap():
    lambdas, alphas = [0.0, 0.5, 2.0, 8.0], [0.5]
    rng = np.random.default_rng(0)
    scores = {}
    for i in range(10):
        base = rng.uniform(0.2, 0.6)
        scores[f'o{i}'] = {(lam, 0.5): [base + (0.3 if lam == 2.0 else 0.0)] for lam in lambdas}
    cv = tune.run_cv(_rows(scores), lambdas, alphas, k=5)
    best = cv.settings.index((2.0, 0.5))
    assert cv.chosen == best and cv.fold_choice == [best] * 5 and cv.bootstrap_wins[best] == 1.0
    text = tune.report_markdown(cv)
    assert '**λ = 2, α = 0.5**' in text and '5/5' in text


def test_ties_go_to_the_smaller_lambda_and_unusable_objects_are_left_out():
    lambdas, alphas = [0.0, 1.0], [0.5, 1.0]
    same = {(lam, a): [0.5] for lam in lambdas for a in alphas}
    scores = {f'o{i}': dict(same) for i in range(4)}
    scores['blind'] = dict(same)
    scores['partial'] = {(0.0, 0.5): [0.9]}
    cv = tune.run_cv(_rows(scores, status={'blind': 'no_gpis'}), lambdas, alphas, k=2)
    assert cv.settings[cv.chosen] == (0.0, 0.5)
    assert cv.excluded == {'blind': 'no_gpis', 'partial': 'incomplete (missing or failed tasks)'}
    assert len(cv.objects) == 4
    with pytest.raises(ValueError, match='folds'):
        tune.run_cv(_rows(scores), lambdas, alphas, k=9)
    # a planner that found no grasp scores 0
    assert tune.task_score({'status': 'no_grasp', 'success': False, 'sim_trials': 0, 'sim_success_rate': 0}) == 0.0


def test_tune_command_end_to_end(tmp_path, capsys):
    data = ds.make_dataset(tmp_path / 'set', 4, seed=5)
    out = tmp_path / 'tune'
    tiny = ['--grid-size', '12', '--frames', '2', '--grasp-samples', '20', '--shape-samples', '20',
            '--initial-grasps', '2', '--trials', '8', '--no-progress']
    # an evaluation of GP-GPIS-OPT at the default λ (5e4 per m²) and α (0.5): the default-λ column of the tune
    evaluation = tmp_path / 'eval'
    args = ['--dataset', str(data.root), '--out', str(evaluation), '--methods', 'gp-gpis-opt']
    assert evaluate.main(args + tiny) == 0
    evaluated = {r['object']: r for r in read_results(evaluation)}
    assert {(r['lambda'], r['alpha']) for r in evaluated.values()} == {(UNCERTAINTY_PENALTY, 0.5)}
    capsys.readouterr()
    args = ['--dataset', str(data.root), '--out', str(out), '--lambda', f'0,{UNCERTAINTY_PENALTY:g}', '--alpha', '0.5',
            '--folds', '2'] + tiny
    assert tune.main(args + ['--reuse', str(evaluation)]) == 0
    text = capsys.readouterr().out
    assert 'Chosen by 2-fold cross-validation' in text
    assert '8 tasks: 4 run now, 0 from earlier runs in this folder, 4 reused' in text
    result = json.loads((out / 'tune.json').read_text())
    assert (result['chosen']['lambda'], result['chosen']['alpha']) in [(0.0, 0.5), (UNCERTAINTY_PENALTY, 0.5)]
    assert len(result['fold_choice']) == 2
    image = cv2.imread(str(out / 'tune.png'))
    assert image is not None and image.shape[0] > 200 and image.shape[1] > 300 and image.std() > 5
    runs = [json.loads(x) for x in (out / 'runs' / 'results.jsonl').read_text().splitlines()]
    assert len(runs) == 8 and {r['method'] for r in runs} == {'gp-gpis-opt'}
    assert {r['lambda'] for r in runs} == {0.0, UNCERTAINTY_PENALTY}
    # the reused rows are the evaluation's, relabelled with the tune's task ids
    for r in runs:
        if r['lambda'] == UNCERTAINTY_PENALTY:
            assert r['reused_from'] == str(evaluation) and r['task_id'].endswith(
                f'|lambda={UNCERTAINTY_PENALTY!r}|alpha=0.5|seed=0')
            assert {k: v for k, v in r.items() if k not in ('task_id', 'reused_from')} == \
                {k: v for k, v in evaluated[r['object']].items() if k != 'task_id'}
        else:
            assert 'reused_from' not in r
    # the class breakdown covers every cross-validated object once per dimension
    assert 'Mean success by class' in text
    for dim in tune.CLASS_DIMENSIONS:
        counts = [int(line.split('|')[2]) for line in text.splitlines() if line.startswith(f'| {dim}: ')]
        assert sum(counts) == len(result['objects'])
    # running it again resumes every task; nothing is reused twice
    assert tune.main(args) == 0
    assert '8 tasks: 0 run now, 8 from earlier runs in this folder, 0 reused' in capsys.readouterr().out
    assert tune.main(args[:-1] + ['--no-progress', '--folds', '9']) == 2
    assert tune.main(['--dataset', str(data.root), '--out', str(out), '--alpha', '-1']) == 2
    # a folder run with other settings is refused
    other = ['--out', str(tmp_path / 'other'), '--trials', '9']
    assert tune.main(args + other + ['--reuse', str(out / 'runs')]) == 2
    assert 'other settings' in capsys.readouterr().err
    assert tune.main(args + other + ['--reuse', str(tmp_path / 'set')]) == 2
    assert 'no run.json' in capsys.readouterr().err
