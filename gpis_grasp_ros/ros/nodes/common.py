"""Shared rclpy plumbing for the nodes: QoS profiles, the guarded callbacks, the start-up line and
the main() of every node.

* **Parameters** are declared from each node's table (:mod:`gpis_grasp_ros.ros.params`).
* **Shutdown** (:func:`run_node`): the rclpy idiom - ``rclpy.init``, spin, ``KeyboardInterrupt`` /
  ``ExternalShutdownException``, destroy, ``rclpy.try_shutdown``. On SIGINT/SIGTERM in-flight
  service calls and action goals are answered "shutting down" before the node is destroyed and
  the context shut down; the process exits 0. Planning runs in the node's worker threads, so the
  main thread is always free to take the signal.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

import rclpy
from rclpy.exceptions import InvalidHandle, ParameterException
from rclpy.executors import (
    ConditionReachedException,
    ExternalShutdownException,
    MultiThreadedExecutor,
    ShutdownException,
    SingleThreadedExecutor,
    TimeoutException,
)
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from rclpy.signals import SignalHandlerOptions

#: Latched grids and models (like nav2 map_server): late subscribers get the last sample.
LATCHED_QOS = QoSProfile(
    depth=1,
    history=HistoryPolicy.KEEP_LAST,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)

#: Reliable, volatile (for camera inputs when a parameter asks for it, e.g. a reliable replay).
RELIABLE_SENSOR_QOS = QoSProfile(
    depth=10,
    history=HistoryPolicy.KEEP_LAST,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)

#: Request/response history of the services, for servers and clients alike. The rmw default keeps 10
#: requests: a burst of 100 concurrent calls lost 90 of them before the node could take them. A client
#: needs it too: rmw_fastrtps sends every answer to every client of the service (each drops the others'
#: when it takes them), so a client with the default 10 loses its own answer once 10 answers to anyone
#: arrive before it takes it (scripts/repro_shared_response_history.py). The node answers every request
#: it takes (planned, or "queue full" at once), so the DDS history only has to hold a burst.
SERVICE_QUEUE_DEPTH = 1000
SERVICE_QOS = QoSProfile(
    depth=SERVICE_QUEUE_DEPTH,
    history=HistoryPolicy.KEEP_LAST,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)

SHUTTING_DOWN = 'shutting down'


def _libc() -> Any:
    try:
        import ctypes
        libc = ctypes.CDLL('libc.so.6')
        libc.malloc_trim, libc.mallopt  # noqa: B018 - glibc only
        return libc
    except (OSError, AttributeError):
        return None


def _malloc_trim() -> Callable[[], None]:
    libc = _libc()
    return (lambda: None) if libc is None else (lambda: libc.malloc_trim(0) and None)


#: Arrays at least this large (bytes) get their own mapping, returned to the system when freed.
HEAP_MMAP_THRESHOLD = 4 << 20
#: malloc arenas of the process (glibc's default is 8 per core, one more for each busy thread).
HEAP_ARENAS = 2


def bound_heap() -> None:
    """Keep a node's resident memory bounded by what it holds (glibc; a no-op elsewhere).

    Without this, glibc's mmap threshold grows to 32 MB after the first large array is freed, so the
    per-model and per-plan arrays (a GPIS posterior, a 1000-sample SDF bank of ~60 MB) come from the
    heaps of whichever threads made them and stay resident there: planner_node grew from 0.3 to 1 GB
    over 500 models and 80 plans. A fixed threshold of :data:`HEAP_MMAP_THRESHOLD` and
    :data:`HEAP_ARENAS` arenas kept it within 0.34-0.36 GB over the same stream (docs/reliability.md).
    """
    libc = _libc()
    if libc is not None:
        libc.mallopt(-3, HEAP_MMAP_THRESHOLD)  # M_MMAP_THRESHOLD (also stops its dynamic growth)
        libc.mallopt(-8, HEAP_ARENAS)  # M_ARENA_MAX


#: Give the heap's freed pages back to the system (glibc ``malloc_trim``; a no-op elsewhere). A node that
#: replaces large arrays often (a new GPIS model every frame) otherwise keeps the freed pages of every
#: thread's arena resident: RSS creeps up with fragmentation although nothing is held.
trim_heap = _malloc_trim()


class NodeExecutor(MultiThreadedExecutor):
    """A node's executor whose default callback group (the parameter services) has a thread of its own.

    rclpy's executors take everything ready in one spinning thread; under a burst of service calls that
    thread is busy taking requests (and, on 2 loaded cores, waiting for the CPU and the GIL), and a parameter
    request arriving meanwhile waits in DDS until it comes round: planner_node took parameter requests up to
    0.27 s after they arrived (p99 70 ms) during bursts of 200 plan calls. Here the default group is left to
    a second, single-threaded loop (:meth:`start_defaults`) with its own wait set, woken by DDS when a
    parameter request arrives; this executor waits on and runs everything else (docs/reliability.md).
    """

    def __init__(self, num_threads: int, context: Any = None) -> None:
        # both executors exist before the node does: a signal arriving once the node is up never finds an
        # executor half-built (rclpy's Executor.__del__ then reports a missing attribute)
        super().__init__(num_threads=num_threads, context=context)
        self._defaults: Any = None
        self.defaults = _GroupExecutor(context)
        self._defaults_thread = threading.Thread(target=self.defaults.serve, name='parameter-services', daemon=True)

    def add_node(self, node: Node) -> bool:
        self._defaults = node.default_callback_group
        self.defaults.bind(node)
        return super().add_node(node)

    def can_execute(self, entity: Any) -> bool:
        return entity.callback_group is not self._defaults and super().can_execute(entity)

    def start_defaults(self) -> None:
        self._defaults_thread.start()

    def stop_defaults(self) -> None:
        """End the default group's loop (before the node is destroyed)."""
        self.defaults.stop()
        if self._defaults_thread.is_alive():
            self._defaults_thread.join(timeout=2.0)

    def shutdown(self, timeout_sec: float | None = None) -> bool:
        self.stop_defaults()
        self.defaults.shutdown(timeout_sec)
        return super().shutdown(timeout_sec)


class _GroupExecutor(SingleThreadedExecutor):
    """Runs only the entities of ``node``'s default callback group, in the thread calling :meth:`serve`."""

    def __init__(self, context: Any = None) -> None:
        super().__init__(context=context)
        self._node: Any = None
        self._group: Any = None
        self._nodes_arg: list[Node] = []
        self._stop = threading.Event()

    def bind(self, node: Node) -> None:
        """Serve ``node``'s default callback group."""
        self._node, self._group, self._nodes_arg = node, node.default_callback_group, [node]

    def can_execute(self, entity: Any) -> bool:
        return entity.callback_group is self._group and super().can_execute(entity)

    def serve(self) -> None:
        while not self._stop.is_set() and self._context.ok():
            try:
                handler, _entity, _node = self.wait_for_ready_callbacks(SIGNAL_LATENCY, self._nodes_arg)
            except (ExternalShutdownException, ShutdownException, TimeoutException, ConditionReachedException):
                continue
            except InvalidHandle:  # the node is being destroyed
                return
            handler()
            if handler.exception() is not None and not self._stop.is_set():
                self._node.get_logger().error(f'parameter services: {handler.exception()!r}')

    def stop(self) -> None:
        self._stop.set()
        self.wake()


def sensor_qos(reliability: str) -> QoSProfile:
    """Camera-input QoS: ``best_effort`` (``qos_profile_sensor_data``, default) or ``reliable``."""
    if reliability == 'reliable':
        return RELIABLE_SENSOR_QOS
    if reliability == 'best_effort':
        return qos_profile_sensor_data
    raise ValueError(f"input_reliability must be 'best_effort' or 'reliable', got '{reliability}'")


def log_startup(node: Node, inputs: Iterable[str], outputs: Iterable[str], key_parameters: Iterable[str],
                services: Iterable[str] = (), actions: Iterable[str] = ()) -> None:
    """One start-up line: resolved inputs, outputs, services/actions and the key parameter values."""
    def topics(names: Iterable[str]) -> str:
        return ', '.join(node.resolve_topic_name(n) for n in names) or '-'

    parts = [f'inputs: {topics(inputs)}', f'outputs: {topics(outputs)}']
    srv = [node.resolve_service_name(s) for s in services] + [f'{node.resolve_topic_name(a)} (action)'
                                                              for a in actions]
    if srv:
        parts.append('serving: ' + ', '.join(srv))
    params = ', '.join(f'{name}={node.get_parameter(name).value!r}' for name in key_parameters)
    parts.append(f'parameters: {params}')
    node.get_logger().info('started; ' + '; '.join(parts))


class GuardedNode(Node):
    """A node with a shutdown flag and a count of callbacks in progress (see :func:`run_node`)."""

    #: Most threads the node needs in its executor (blocking service callbacks need their own; the
    #: executor starts them as work arrives).
    executor_threads = 4

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.shutting_down = threading.Event()
        self._in_flight = 0
        self._in_flight_cv = threading.Condition()
        #: Messages rejected by validation since start-up (each logged as a warning).
        self.rejected = 0
        # rclpy.shutdown() (e.g. by whoever owns the context) ends the work too
        self.context.on_shutdown(self.begin_shutdown)

    def reject(self, text: str) -> None:
        """Log a rejected message (warning naming the field) and count it."""
        self.rejected += 1
        self.get_logger().warning(text)

    def begin_shutdown(self) -> None:
        """Stop taking new work; in-flight requests are answered 'shutting down'."""
        self.shutting_down.set()

    def enter_callback(self) -> None:
        with self._in_flight_cv:
            self._in_flight += 1

    def exit_callback(self) -> None:
        with self._in_flight_cv:
            self._in_flight -= 1
            self._in_flight_cv.notify_all()

    def wait_idle(self, timeout: float) -> bool:
        """Wait until no guarded callback is running; True when idle."""
        end = time.monotonic() + timeout
        with self._in_flight_cv:
            while self._in_flight > 0:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._in_flight_cv.wait(left)
        return True


def _stopping(node: Node) -> bool:
    flag = getattr(node, 'shutting_down', None)
    return bool(flag is not None and flag.is_set()) or not node.context.ok()


def guarded(node: Node, what: str, callback: Callable[[Any], None]) -> Callable[[Any], None]:
    """Subscription callback that logs any unexpected exception instead of killing the executor.

    Expected bad input is reported by the callbacks themselves (``ValueError`` → warning); this
    is the last line of defence so a node never dies on a message. Messages arriving during
    shutdown are ignored; errors caused by the shutdown itself are not reported as errors.
    """
    def wrapper(msg: Any) -> None:
        if _stopping(node):
            return
        try:
            callback(msg)
        except InvalidHandle:
            if not _stopping(node):
                node.get_logger().error(f'{what}: publisher destroyed while the node is running')
        except Exception as exc:  # noqa: BLE001 - the node must survive anything a message triggers
            if _stopping(node):
                return
            node.get_logger().error(f'{what}: unexpected {type(exc).__name__}: {exc}; message ignored, '
                                    'node keeps running')
    return wrapper


def guarded_service(node: Node, what: str, callback: Callable[[Any, Any], Any]) -> Callable[[Any, Any], Any]:
    """Service callback that answers ``success=false`` with the reason on any unexpected exception,
    and 'shutting down' once the node is stopping."""
    def wrapper(request: Any, response: Any) -> Any:
        enter = getattr(node, 'enter_callback', None)
        if enter is not None:
            enter()
        try:
            if _stopping(node):
                response.success = False
                response.message = f'{node.get_name()} is {SHUTTING_DOWN}'
                return response
            return callback(request, response)
        except Exception as exc:  # noqa: BLE001 - callers always get an answer
            if not _stopping(node):
                node.get_logger().error(f'{what}: unexpected {type(exc).__name__}: {exc}')
            response.success = False
            response.message = f'internal error in {what}: {type(exc).__name__}: {exc}'
            return response
        finally:
            leave = getattr(node, 'exit_callback', None)
            if leave is not None:
                leave()
    return wrapper


#: Seconds given to in-flight requests to be answered after SIGINT/SIGTERM.
SHUTDOWN_GRACE = 0.6
#: Longest the main thread waits in the executor before Python looks at pending signals (s).
SIGNAL_LATENCY = 0.1


def run_node(node_class: type[GuardedNode], args: list[str] | None = None) -> int:
    """main() of every node: init, spin a multi-threaded executor, answer what is in flight, shut down.

    SIGINT and SIGTERM raise ``KeyboardInterrupt`` in the spinning main thread (Python's handler;
    rclpy's is not installed because it shuts the context down at once, and an action goal in
    flight could then not be answered: its status is published). The node stops taking work
    (:meth:`GuardedNode.begin_shutdown`), in-flight requests are answered "shutting down" within
    :data:`SHUTDOWN_GRACE` s, then the node is destroyed and the context shut down. A bad parameter
    value at start-up ends the process with a one-line error (exit code 2) instead of a stack
    trace. Returns the exit code.
    """
    bound_heap()
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGTERM, signal.default_int_handler)  # SIGTERM ends the node like Ctrl-C
    node = executor = None
    status = 0
    try:
        executor = NodeExecutor(node_class.executor_threads)
        node = node_class()
        executor.add_node(node)
        executor.start_defaults()
        while rclpy.ok():
            executor.spin_once(timeout_sec=SIGNAL_LATENCY)  # back in Python this often: signals are taken
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ValueError, ParameterException) as exc:
        print(f'error: {exc}', file=sys.stderr)
        status = 2
    finally:
        if node is not None:
            node.begin_shutdown()
            if executor is not None:
                _answer_in_flight(executor, node)
                executor.stop_defaults()
            node.destroy_node()
        if executor is not None:
            # release the executors' guard conditions while rclpy is intact: left to the garbage collector at
            # interpreter exit, their __del__ runs after rclpy's modules are torn down and prints a traceback
            executor.shutdown(timeout_sec=SHUTDOWN_GRACE)
        rclpy.try_shutdown()
    return status


def _answer_in_flight(executor: NodeExecutor, node: GuardedNode, settle: float = 0.1) -> None:
    """Keep spinning until the node's callbacks in progress returned (at most :data:`SHUTDOWN_GRACE` s) and
    ``settle`` s more: the executor sends their answers (service responses, action results) afterwards."""
    end = time.monotonic() + SHUTDOWN_GRACE
    idle_since = None
    while rclpy.ok() and time.monotonic() < end:
        executor.spin_once(timeout_sec=0.02)
        if not node.wait_idle(0.0):
            idle_since = None
        elif idle_since is None:
            idle_since = time.monotonic()
        elif time.monotonic() - idle_since > settle:
            return
