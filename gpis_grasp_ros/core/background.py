"""One function call on a thread of its own, whose result (or exception) the caller collects later.

The machine has two cores and the replanning chain is sequential; where a stage's later input is already known
(the final P_F's shape samples while the planner searches) it is computed on the other core. The numeric kernels
release the GIL (BLAS, the compiled loops), so the two threads run in parallel.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable


class Background[T]:
    """``fn(*args)`` started on a daemon thread named ``name``.

    :meth:`result` waits for it and re-raises its exception in the caller's thread (nothing is swallowed);
    :meth:`cpu_time` is the CPU time (s) the call has used so far, so callers that report their own CPU time can
    keep it out. A result nobody collects is dropped with the object when the thread ends."""

    def __init__(self, fn: Callable[..., T], *args, name: str = 'background') -> None:
        self._value: T | None = None
        self._error: BaseException | None = None
        self._cpu = 0.0
        self._thread = threading.Thread(target=self._run, args=(fn, args), name=name, daemon=True)
        self._thread.start()

    def _run(self, fn: Callable[..., T], args: tuple) -> None:
        start = time.thread_time()
        try:
            self._value = fn(*args)
        except BaseException as exc:  # re-raised by result() in the caller's thread
            self._error = exc
        finally:
            self._cpu = time.thread_time() - start

    def cpu_time(self) -> float:
        """CPU time (s) of the call so far."""
        if self._thread.is_alive():
            try:
                return time.clock_gettime(time.pthread_getcpuclockid(self._thread.ident))
            except (AttributeError, OSError):  # no per-thread clock here, or the thread just ended
                pass
        self._thread.join()
        return self._cpu

    def result(self) -> T:
        """The call's return value, once it has returned (its exception, raised here, if it failed)."""
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._value  # type: ignore[return-value]
