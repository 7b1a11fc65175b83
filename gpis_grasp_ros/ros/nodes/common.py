"""Shared rclpy plumbing for the nodes: QoS profiles, declared parameters that apply at run time,
the guarded callbacks, the start-up line and the main() idiom with a graceful shutdown.

* **Parameters** (:func:`declare`, :func:`watch_parameters`): every parameter has a descriptor with
  its description, its numeric range (``FloatingPointRange``/``IntegerRange``, enforced by rclpy on
  every set) and, for string choices, the allowed values (enforced here). A node builds its
  configuration from the parameter values with one function that raises ``ValueError`` on invalid
  values; that function runs at start-up (a bad value ends the process with one line, exit 2) and
  again on every ``ros2 param set`` (rejected with the same reason, otherwise applied to the next
  message/request). Parameters that cannot change at run time are declared read-only.
* **Shutdown** (:func:`run_node`): SIGINT and SIGTERM are handled by the node, not by rclpy's
  default handler, so that in-flight service calls and action goals are answered
  ("shutting down") before the context goes away; the process exits 0 within about 1 s.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterable, Sequence
from typing import Any, NoReturn

import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.exceptions import InvalidHandle, ParameterException
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
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

#: Request/response history of the services. The rmw default keeps 10 requests: a burst of 100
#: concurrent calls lost 90 of them before the node could take them. The node answers every request
#: it takes (planned, or "queue full" at once), so the DDS history only has to hold a burst.
SERVICE_QUEUE_DEPTH = 1000
SERVICE_QOS = QoSProfile(
    depth=SERVICE_QUEUE_DEPTH,
    history=HistoryPolicy.KEEP_LAST,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)

SHUTTING_DOWN = 'shutting down'


def sensor_qos(reliability: str) -> QoSProfile:
    """Camera-input QoS: ``best_effort`` (``qos_profile_sensor_data``, default) or ``reliable``."""
    if reliability == 'reliable':
        return RELIABLE_SENSOR_QOS
    if reliability == 'best_effort':
        return qos_profile_sensor_data
    raise ValueError(f"input_reliability must be 'best_effort' or 'reliable', got '{reliability}'")


def _choices_of(node: Node) -> dict[str, tuple[str, ...]]:
    choices = getattr(node, '_gg_param_choices', None)
    if choices is None:
        choices = {}
        node._gg_param_choices = choices
    return choices


def declare(node: Node, name: str, default: Any, description: str, *,
            low: float | int | None = None, high: float | int | None = None,
            choices: Sequence[str] | None = None, read_only: bool = False) -> Any:
    """Declare a parameter with a :class:`ParameterDescriptor` (description, enforced range, choices)
    and return its value. A value outside the choices raises ValueError (also on every later set,
    see :func:`watch_parameters`)."""
    descriptor = ParameterDescriptor(description=description, read_only=read_only)
    if choices:
        descriptor.additional_constraints = 'one of: ' + ', '.join(choices)
        _choices_of(node)[name] = tuple(choices)
    if low is not None and high is not None:
        if isinstance(default, bool):
            pass
        elif isinstance(default, int):
            descriptor.integer_range = [IntegerRange(from_value=int(low), to_value=int(high), step=0)]
        elif isinstance(default, float):
            descriptor.floating_point_range = [
                FloatingPointRange(from_value=float(low), to_value=float(high), step=0.0)]
    value = node.declare_parameter(name, default, descriptor).value
    check_choice(node, name, value)
    return value


def check_choice(node: Node, name: str, value: Any) -> None:
    """ValueError when ``value`` is not one of the declared choices of parameter ``name``."""
    allowed = _choices_of(node).get(name)
    if allowed and value not in allowed:
        raise ValueError(f"parameter '{name}' must be one of {list(allowed)}, got '{value}'")


def parameter_values(node: Node) -> dict[str, Any]:
    """Current values of all parameters of ``node`` (name → value)."""
    return {name: p.value for name, p in node._parameters.items()}


def watch_parameters(node: Node, build: Callable[[dict[str, Any]], Any], apply: Callable[[Any], None]) -> Any:
    """Build the node's configuration from its parameters now and again after every accepted set.

    ``build(values)`` turns parameter values (name → value) into a configuration object and raises
    ValueError on invalid values; ``apply(config)`` installs it (called with the start-up
    configuration before this returns). A set that ``build`` rejects, or a string outside its
    declared choices, fails with the reason (``ros2 param set`` prints it) and changes nothing.
    Range, type and read-only are enforced by rclpy from the descriptors before this runs.
    Returns the start-up configuration.
    """
    config = build(parameter_values(node))
    apply(config)

    def on_set(params: list) -> SetParametersResult:
        values = parameter_values(node)
        values.update({p.name: p.value for p in params})
        try:
            for p in params:
                check_choice(node, p.name, p.value)
            build(values)
        except (ValueError, TypeError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def post_set(params: list) -> None:
        apply(build(parameter_values(node)))
        changed = ', '.join(f'{p.name}={p.value!r}' for p in params)
        node.get_logger().info(f'parameters applied: {changed}')

    node.add_on_set_parameters_callback(on_set)
    node.add_post_set_parameters_callback(post_set)
    return config


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

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.shutting_down = threading.Event()
        self._in_flight = 0
        self._in_flight_cv = threading.Condition()
        #: Threads the node needs in its executor (blocking service callbacks need their own).
        self.executor_threads = 4
        #: Messages rejected by validation since start-up (each logged as a warning).
        self.rejected = 0

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


def run_node(factory: Callable[[], Node], args: list[str] | None = None, threads: int = 2) -> NoReturn:
    """main() of every node: init, spin a multi-threaded executor, graceful shutdown.

    A bad parameter value at start-up ends the process with a one-line error (exit code 2)
    instead of a stack trace. SIGINT/SIGTERM: the node stops taking work
    (:meth:`GuardedNode.begin_shutdown`), in-flight requests are answered within
    :data:`SHUTDOWN_GRACE` s, then the node and context are destroyed and the process exits 0
    (``os._exit``: this is the process's main function, never call it from a test).
    """
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()

    def on_signal(_signum: int, _frame: Any) -> None:
        stop.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    if {signal.SIGINT, signal.SIGTERM} <= signal.pthread_sigmask(signal.SIG_BLOCK, []):
        # blocked in every thread (see gpis_grasp_ros.ros.nodes): take them here, no handler can swallow them
        def wait_signal() -> None:
            signal.sigwait({signal.SIGINT, signal.SIGTERM})
            stop.set()
        threading.Thread(target=wait_signal, name='signals', daemon=True).start()
    node = None
    executor = None
    spinner = None
    status = 0
    try:
        node = factory()
        executor = MultiThreadedExecutor(num_threads=max(threads, getattr(node, 'executor_threads', threads)))
        executor.add_node(node)

        def spin() -> None:
            try:
                executor.spin()
            except (KeyboardInterrupt, ExternalShutdownException):
                pass
            finally:
                stop.set()

        spinner = threading.Thread(target=spin, name='executor', daemon=True)
        spinner.start()
        while not stop.wait(0.2):
            pass
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ValueError, ParameterException) as exc:
        print(f'error: {exc}', file=sys.stderr)
        status = 2
    except Exception:  # noqa: BLE001 - reported, then the same clean exit path
        traceback.print_exc()
        status = 1
    finally:
        if node is not None:
            if isinstance(node, GuardedNode):
                node.begin_shutdown()
                node.wait_idle(SHUTDOWN_GRACE)
                time.sleep(0.05)  # let the executor send the last responses
        if executor is not None:
            executor.shutdown(timeout_sec=0.1)
        if node is not None:
            try:
                node.destroy_node()
            except InvalidHandle:
                pass
        rclpy.try_shutdown()
        if spinner is not None:
            spinner.join(timeout=0.1)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    # Everything that had to be answered was answered and ROS is shut down. Do not wait for a
    # callback still computing (e.g. a GPIS fit) nor for the interpreter's slow teardown of the
    # numeric and DDS libraries (seconds on a loaded machine): exit now.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)
