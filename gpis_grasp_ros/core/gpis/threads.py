"""BLAS/LAPACK thread limit for the GPIS fits (see :func:`blas_threads`)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

_BLAS_CONTROLLER: list = []  # lazily created threadpoolctl.ThreadpoolController (or None if unavailable)


@contextlib.contextmanager
def blas_threads(n: int | None) -> Iterator[None]:
    """Limit BLAS/LAPACK to ``n`` threads inside the block (``None`` or 0: leave the default).

    The fits are many mid-sized LAPACK calls; on a loaded 2-core robot computer multi-threaded
    OpenBLAS stalls while its threads wait for a busy core, one thread is predictable
    (docs/gpis-model.md, BLAS threads). Uses threadpoolctl when installed.
    """
    if not n:
        yield
        return
    if not _BLAS_CONTROLLER:
        try:
            from threadpoolctl import ThreadpoolController
            _BLAS_CONTROLLER.append(ThreadpoolController())
        except ImportError:  # pragma: no cover - optional dependency
            _BLAS_CONTROLLER.append(None)
    controller = _BLAS_CONTROLLER[0]
    if controller is None:  # pragma: no cover
        yield
        return
    with controller.limit(limits=int(n), user_api='blas'):
        yield
