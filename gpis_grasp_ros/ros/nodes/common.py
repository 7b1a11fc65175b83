"""Shared rclpy plumbing for the nodes: QoS profiles, declared parameters, the main() idiom."""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from typing import Any

import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

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


def sensor_qos(reliability: str) -> QoSProfile:
    """Camera-input QoS: ``best_effort`` (``qos_profile_sensor_data``, default) or ``reliable``."""
    if reliability == 'reliable':
        return RELIABLE_SENSOR_QOS
    if reliability == 'best_effort':
        return qos_profile_sensor_data
    raise ValueError(f"input_reliability must be 'best_effort' or 'reliable', got '{reliability}'")


def declare(node: Node, name: str, default: Any, description: str, *,
            low: float | int | None = None, high: float | int | None = None,
            choices: Sequence[str] | None = None, read_only: bool = False) -> Any:
    """Declare a parameter with a :class:`ParameterDescriptor` (description, range) and return its value."""
    descriptor = ParameterDescriptor(description=description, read_only=read_only)
    if choices:
        descriptor.additional_constraints = 'one of: ' + ', '.join(choices)
    if low is not None and high is not None:
        if isinstance(default, bool):
            pass
        elif isinstance(default, int):
            descriptor.integer_range = [IntegerRange(from_value=int(low), to_value=int(high), step=0)]
        elif isinstance(default, float):
            descriptor.floating_point_range = [
                FloatingPointRange(from_value=float(low), to_value=float(high), step=0.0)]
    value = node.declare_parameter(name, default, descriptor).value
    if choices and value not in choices:
        raise ValueError(f"parameter '{name}' must be one of {list(choices)}, got '{value}'")
    return value


def guarded(node: Node, what: str, callback: Callable[[Any], None]) -> Callable[[Any], None]:
    """Subscription callback that logs any unexpected exception instead of killing the executor.

    Expected bad input is reported by the callbacks themselves (``ValueError`` → warning); this
    is the last line of defence so a node never dies on a message.
    """
    def wrapper(msg: Any) -> None:
        try:
            callback(msg)
        except Exception as exc:  # noqa: BLE001 - the node must survive anything a message triggers
            node.get_logger().error(f'{what}: unexpected {type(exc).__name__}: {exc}; message ignored, '
                                    'node keeps running')
    return wrapper


def guarded_service(node: Node, what: str, callback: Callable[[Any, Any], Any]) -> Callable[[Any, Any], Any]:
    """Service callback that answers ``success=false`` with the reason on any unexpected exception."""
    def wrapper(request: Any, response: Any) -> Any:
        try:
            return callback(request, response)
        except Exception as exc:  # noqa: BLE001 - callers always get an answer
            node.get_logger().error(f'{what}: unexpected {type(exc).__name__}: {exc}')
            response.success = False
            response.message = f'internal error in {what}: {type(exc).__name__}: {exc}'
            return response
    return wrapper


def run_node(factory: Callable[[], Node], args: list[str] | None = None, threads: int = 2) -> int:
    """Jazzy main() idiom: init, spin a multi-threaded executor, clean shutdown on Ctrl-C.

    A bad parameter value at start-up ends the process with a one-line error (exit code 2)
    instead of a stack trace.
    """
    rclpy.init(args=args)
    node = None
    try:
        node = factory()
        executor = MultiThreadedExecutor(num_threads=threads)
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ValueError, ParameterException) as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 2
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
