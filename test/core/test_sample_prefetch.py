"""The final P_F's shape samples drawn on a second thread during the search: the same samples, errors surfaced."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from gpis_grasp_ros.core.planners import PlannerParams, PlanningContext, plan
from gpis_grasp_ros.core.planners import context as planning_context
from gpis_grasp_ros.core.planners.context import evaluation_samples, streams
from gpis_grasp_ros.core.quality import probability_force_closure
from support.synthetic_shapes import transparent_part_posterior

POST, _ = transparent_part_posterior()
PARAMS = PlannerParams(n_shape_samples=300)


@pytest.mark.parametrize('method', ['gp-gpis-opt', 'gp-p', 'gp-m'])
@pytest.mark.parametrize('seed', [3, 11])
def test_prefetched_samples_give_the_sequential_p_f(method: str, seed: int) -> None:
    """The plan's P_F equals the one estimated afterwards, on one thread, from the evaluation stream of its seed."""
    res = plan(method, POST, PARAMS, seed=seed)
    ctx = PlanningContext(POST, PARAMS)
    samples = evaluation_samples(ctx, streams(seed)['evaluation'])
    est = probability_force_closure(res.jaw1[None], res.jaw2[None], samples, PARAMS.gripper, ctx.sigma_g)
    assert res.p_f == float(est.p[0])
    assert res.p_f_std_error == float(est.std_error[0])
    assert 0.0 <= res.planning_cpu_time < 60.0


def test_a_failed_drawing_is_raised_by_the_plan(monkeypatch: pytest.MonkeyPatch) -> None:
    """An error while drawing the samples on the other thread reaches the caller of plan, not a log."""
    def broken(ctx, rng):
        raise np.linalg.LinAlgError('sampling failed')

    monkeypatch.setattr(planning_context, 'evaluation_samples', broken)
    with pytest.raises(np.linalg.LinAlgError, match='sampling failed'):
        plan('gp-m', POST, PARAMS, seed=0)


def test_the_sampling_threads_end() -> None:
    """No drawing thread outlives its plan for long (a cancelled or empty plan's thread finishes its draw)."""
    for seed in range(3):
        plan('gp-m', POST, PARAMS, seed=seed)
    for thread in [t for t in threading.enumerate() if t.name == 'pf-samples']:
        thread.join(timeout=30.0)
        assert not thread.is_alive()


@pytest.mark.parametrize('shape', [(1, 1), (7, 3), (64, 200), (300, 17)])
def test_the_gil_free_triangular_product_is_scipys(shape: tuple[int, int]) -> None:
    """The samples' triangular product through ctypes (which releases the GIL) is scipy's strmm bit for bit."""
    from scipy.linalg.blas import strmm

    from gpis_grasp_ros.core.gpis.posterior import _lower_trmm

    m, n = shape
    rng = np.random.default_rng(m * 1000 + n)
    a = np.asfortranarray(np.tril(rng.standard_normal((m, m))), dtype=np.float32)
    b = rng.standard_normal((n, m)).astype(np.float32).T  # Fortran (m, n), as sample_deviations passes it
    expected = strmm(1.0, a, b.copy(order='F'), side=0, lower=1)
    assert np.array_equal(_lower_trmm(a, b), expected)
    with pytest.raises(ValueError, match='Fortran-ordered float32'):
        _lower_trmm(np.ascontiguousarray(a) if m > 1 else a.astype(np.float64), b)


def test_background_returns_raises_and_counts_its_cpu() -> None:
    """A background call gives its value, or its exception in the caller; its CPU time is its own thread's."""
    from gpis_grasp_ros.core.background import Background

    def busy(n: int) -> int:
        return int(np.sum(np.arange(n) % 7))

    job = Background(busy, 3_000_000)
    assert job.result() == busy(3_000_000)
    assert 0.0 < job.cpu_time() < 60.0
    idle = Background(lambda: 5)
    assert idle.result() == 5 and idle.cpu_time() < job.cpu_time()
    failing = Background(lambda: 1 / 0, name='failing')
    with pytest.raises(ZeroDivisionError):
        failing.result()
