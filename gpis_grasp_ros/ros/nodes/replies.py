"""Service answers sent later, from any thread, and sent again when the middleware could not deliver them.

A blocking service callback holds an executor thread until its answer is ready, so a deep request
queue needs as many threads. A :class:`DeferredService` takes the request, hands the caller's
:class:`Reply` to the node and returns at once; whoever finishes the work (a planning thread)
calls :meth:`Reply.send`. The rclpy executor still sends the callback's return value with
``Service.send_response(response, header)``: this service takes that call (its own
``send_response``), keeps the request header and sends the real answer when it is there.

rmw_fastrtps waits about 100 ms for the service's response writer to match the caller's response
reader and otherwise drops the answer; rclpy reports that as a ``RuntimeWarning`` ("failed to send
response (timeout)") and returns. The warning is caught here (:func:`send_checked`) and the answer
is sent again a few times over :data:`RESEND_WINDOW` s, by when discovery has caught up. A caller
that still gets no answer (its reader not known to the service at all, which the middleware drops
silently) asks again: see the idempotent planning in planner_node and
:class:`gpis_grasp_ros.ros.client.GraspPlannerClient`.
"""

from __future__ import annotations

import re
import threading
import time
import warnings
from collections.abc import Callable
from typing import Any

from rclpy.exceptions import InvalidHandle

#: rclpy's warning text when rmw_send_response timed out (the answer did not go out).
SEND_TIMEOUT_TEXT = 'failed to send response (timeout)'
#: Delays (s) between the attempts to send an answer the middleware could not deliver.
RESEND_DELAYS = (0.05, 0.1, 0.2, 0.4, 0.8, 1.6, 3.2)
RESEND_WINDOW = sum(RESEND_DELAYS)

_PATTERN = re.escape(SEND_TIMEOUT_TEXT)
_capture = threading.local()
_hook_lock = threading.Lock()


def _showwarning_hook(previous: Callable[..., None]) -> Callable[..., None]:
    def showwarning(message, category, filename, lineno, file=None, line=None):
        if getattr(_capture, 'active', False) and SEND_TIMEOUT_TEXT in str(message):
            _capture.failed = True  # the sending thread looks at this right after the call
            return
        previous(message, category, filename, lineno, file, line)
    showwarning.is_send_timeout_hook = True
    return showwarning


def _install_hook() -> None:
    """Route rclpy's send-timeout warning to the sending thread, every time (not once per location).

    Installed again when someone replaced ``warnings.showwarning`` or the filters since (a test runner)."""
    with _hook_lock:
        if not getattr(warnings.showwarning, 'is_send_timeout_hook', False):
            warnings.showwarning = _showwarning_hook(warnings.showwarning)
        first = warnings.filters[0] if warnings.filters else None
        if first is None or first[0] != 'always' or getattr(first[1], 'pattern', None) != _PATTERN:
            warnings.filterwarnings('always', message=_PATTERN, category=RuntimeWarning)


def send_checked(send: Callable[[Any, Any], None], response: Any, header: Any) -> bool:
    """``send(response, header)``; False when the middleware reported that the answer did not go out."""
    _install_hook()
    _capture.active, _capture.failed = True, False
    try:
        send(response, header)
        return not _capture.failed
    finally:
        _capture.active = False


class Reply:
    """The answer to one request; :meth:`send` may be called once, from any thread."""

    def __init__(self, service: DeferredService, response: Any) -> None:
        self._service = service
        self.response = response            # the executor's response object, filled by the node
        self._header: Any = None
        self._answer: Any = None
        self._lock = threading.Lock()
        self.sent = threading.Event()

    def send(self, response: Any = None) -> None:
        """Answer the caller with ``response`` (default: :attr:`response`)."""
        with self._lock:
            if self._answer is not None:
                return
            self._answer = self.response if response is None else response
            header = self._header
        if header is not None:
            self._service._deliver(self, header)

    def _header_known(self, header: Any) -> None:
        with self._lock:
            self._header = header
            ready = self._answer is not None
        if ready:
            self._service._deliver(self, header)


class DeferredService:
    """A service whose ``handler(request, reply)`` answers through ``reply.send()``, now or later.

    The handler runs in the executor like any service callback and must not block; an exception it raises
    is answered ``success=false`` with the reason. Counters: ``answers_sent``, ``send_timeouts`` (attempts
    the middleware refused), ``answers_lost`` (answers not delivered after every retry).
    """

    def __init__(self, node: Any, srv_type: Any, name: str, handler: Callable[[Any, Reply], None],
                 qos_profile: Any, callback_group: Any = None) -> None:
        self._node = node
        self._name = name
        self._handler = handler
        self._requests: dict[int, Any] = {}  # id(response) -> request, between the two executor calls
        self._lock = threading.Lock()
        self.answers_sent = 0
        self.send_timeouts = 0
        self.answers_lost = 0
        self._retry_cv = threading.Condition()
        self._retries: list[tuple[float, int, Reply, Any]] = []  # (due, attempt, reply, header)
        self._closed = False
        self.service = node.create_service(srv_type, name, self._on_request, qos_profile=qos_profile,
                                           callback_group=callback_group)
        self._send = self.service.send_response
        self.service.send_response = self._on_executor_send  # the executor hands us the request header
        self._retrier = threading.Thread(target=self._retry_loop, name=f'{name}-resend', daemon=True)
        self._retrier.start()

    # ------------------------------------------------------------------ executor side
    def _on_request(self, request: Any, response: Any) -> Any:
        """First half of a call (the executor has the request, not yet its header)."""
        with self._lock:
            self._requests[id(response)] = request
        return response

    def _on_executor_send(self, response: Any, header: Any) -> None:
        """Second half: the executor would send ``response`` now; the handler decides when."""
        with self._lock:
            request = self._requests.pop(id(response), None)
        reply = Reply(self, response)
        reply._header_known(header)
        if request is None:  # not taken by _on_request: answer as rclpy would
            reply.send()
            return
        try:
            self._handler(request, reply)
        except Exception as exc:  # noqa: BLE001 - callers always get an answer
            self._node.get_logger().error(f'{self._name}: unexpected {type(exc).__name__}: {exc}')
            if hasattr(response, 'success'):
                response.success = False
                response.message = f'internal error in {self._name}: {type(exc).__name__}: {exc}'
            reply.send()

    # ------------------------------------------------------------------ sending
    def _deliver(self, reply: Reply, header: Any, attempt: int = 0) -> None:
        try:
            ok = send_checked(self._send, reply._answer, header)
        except InvalidHandle:  # the service was destroyed (shutdown)
            reply.sent.set()
            return
        if ok:
            self.answers_sent += 1
            reply.sent.set()
            return
        self.send_timeouts += 1
        if attempt >= len(RESEND_DELAYS) or self._closed:
            self.answers_lost += 1
            reply.sent.set()
            self._node.get_logger().warning(f'{self._name}: an answer could not be delivered after {attempt + 1} '
                                            'attempts (the caller may ask again)')
            return
        self._node.get_logger().info(f'{self._name}: the middleware could not deliver an answer (the caller not '
                                     f'matched yet); sending it again in {RESEND_DELAYS[attempt]:g} s')
        with self._retry_cv:
            self._retries.append((time.monotonic() + RESEND_DELAYS[attempt], attempt + 1, reply, header))
            self._retry_cv.notify()

    def _retry_loop(self) -> None:
        while True:
            with self._retry_cv:
                while not self._closed and not self._retries:
                    self._retry_cv.wait()
                if self._closed:
                    return
                self._retries.sort(key=lambda r: r[0])
                due, attempt, reply, header = self._retries[0]
                wait = due - time.monotonic()
                if wait > 0:
                    self._retry_cv.wait(wait)
                    continue
                self._retries.pop(0)
            self._deliver(reply, header, attempt)

    def pending_retries(self) -> int:
        """Answers waiting to be sent again."""
        with self._retry_cv:
            return len(self._retries)

    def close(self) -> None:
        """Stop the resend thread (answers still waiting for a retry are given up)."""
        with self._retry_cv:
            self._closed = True
            self._retry_cv.notify_all()
