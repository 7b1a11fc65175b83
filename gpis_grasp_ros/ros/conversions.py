"""rclpy side of message conversion: the rclpy message factory and the planner's outputs.

The message *layouts* (clouds, images, grids, GpisModel) are interpreted in one place,
:mod:`gpis_grasp_ros.data.messages`, which is ROS-free and duck-typed; this module adds what needs
rclpy message classes: :class:`RclpyFactory` (builds rclpy messages through the same builders),
:func:`rclpy_message_class`, the ``GraspPlan`` response (:func:`fill_grasp_plan_response`) and the
RViz markers of a grasp (:func:`grasp_markers`).
"""

from __future__ import annotations

import array
import importlib
from typing import Any

import numpy as np

from gpis_grasp_ros.core.grid import GridGeometry
from gpis_grasp_ros.data.messages import MessageFactory

# array.array type codes of the ROS primitive types used by the builders (rclpy sequences).
_TYPECODES: dict[np.dtype, str] = {
    np.dtype(np.uint8): 'B', np.dtype(np.int8): 'b', np.dtype(np.uint16): 'H', np.dtype(np.int16): 'h',
    np.dtype(np.uint32): 'I', np.dtype(np.int32): 'i', np.dtype(np.uint64): 'Q', np.dtype(np.int64): 'q',
    np.dtype(np.float32): 'f', np.dtype(np.float64): 'd',
}

# --------------------------------------------------------------------------- rclpy factory
class RclpyFactory:
    """Builds rclpy messages; message classes are imported on first use by ``'pkg/msg/Type'``."""

    def __init__(self) -> None:
        self._classes: dict[str, type] = {}

    def message_class(self, type_name: str) -> type:
        """The rclpy class of ``type_name`` (``'pkg/msg/Type'``)."""
        cls = self._classes.get(type_name)
        if cls is None:
            cls = rclpy_message_class(type_name)
            self._classes[type_name] = cls
        return cls

    def new(self, type_name: str, **fields: Any) -> Any:
        return self.message_class(type_name)(**fields)

    def seq(self, values: np.ndarray, dtype: Any) -> array.array:
        arr = np.ascontiguousarray(np.asarray(values, dtype=dtype).ravel())
        out = array.array(_TYPECODES[arr.dtype])
        if out.itemsize != arr.dtype.itemsize:  # pragma: no cover - exotic platforms only
            raise ValueError(f'array typecode {out.typecode!r} does not match {arr.dtype}')
        out.frombytes(arr.astype(arr.dtype.newbyteorder('='), copy=False).tobytes())
        return out

    def fixed(self, values: np.ndarray, dtype: Any) -> np.ndarray:
        return np.ascontiguousarray(np.asarray(values, dtype=dtype).ravel())


def rclpy_message_class(type_name: str) -> type:
    """Import the rclpy message (or service) class named ``'pkg/msg/Type'``."""
    parts = type_name.split('/')
    if len(parts) == 2:  # 'pkg/Type' shorthand
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3 or not all(parts):
        raise ValueError(f"message type name must look like 'pkg/msg/Type', got '{type_name}'")
    pkg, kind, name = parts
    try:
        module = importlib.import_module(f'{pkg}.{kind}')
        return getattr(module, name)
    except (ImportError, AttributeError) as err:
        raise ValueError(f"cannot import rclpy message type '{type_name}': {err}") from None

# --------------------------------------------------------------------------- grasps
def _yaw_quaternion(f: MessageFactory, axis: np.ndarray) -> Any:
    """Quaternion rotating +x onto the in-plane direction ``axis`` (rotation about z)."""
    a = np.asarray(axis, dtype=np.float64).ravel()
    yaw = float(np.arctan2(a[1], a[0])) if np.isfinite(a[:2]).all() and np.any(a[:2]) else 0.0
    return f.new('geometry_msgs/msg/Quaternion', x=0.0, y=0.0, z=float(np.sin(yaw / 2)), w=float(np.cos(yaw / 2)))


def _pose_stamped(f: MessageFactory, header: Any, xy: np.ndarray, z: float, axis: np.ndarray) -> Any:
    p = np.asarray(xy, dtype=np.float64).ravel()
    x, y = (float(p[0]), float(p[1])) if np.isfinite(p[:2]).all() else (0.0, 0.0)
    pose = f.new('geometry_msgs/msg/Pose', position=f.new('geometry_msgs/msg/Point', x=x, y=y, z=float(z)),
                 orientation=_yaw_quaternion(f, axis))
    return f.new('geometry_msgs/msg/PoseStamped', header=header, pose=pose)


def fill_grasp_plan_response(response: Any, result: Any, header: Any, z: float | None = None) -> Any:
    """Copy a planner ``GraspResult`` into a ``GraspPlan`` response (rclpy), in place; returns it.

    Jaw and grasp poses are in ``header``'s frame at depth ``z`` (m; pass ``posterior.geometry.z``,
    the table plane; 0 when omitted), x axis along the closing direction jaw1 → jaw2. Non-finite
    positions (failed plans) are written as 0.
    """
    f = RclpyFactory()
    z = 0.0 if z is None else float(z)
    response.success = bool(result.success)
    response.message = str(result.message)
    response.jaw1 = _pose_stamped(f, header, result.jaw1, z, result.axis)
    response.jaw2 = _pose_stamped(f, header, result.jaw2, z, result.axis)
    response.grasp_pose = _pose_stamped(f, header, result.center, z, result.axis)

    def num(v: Any) -> float:
        return float(v) if v is not None else float('nan')

    response.width = num(result.width)
    response.probability_force_closure = num(result.p_f)
    response.probability_force_closure_std_error = num(result.p_f_std_error)
    response.ferrari_canny_on_mean = num(result.q_mean)
    response.objective = num(result.objective)
    response.planning_time = num(result.planning_time)
    response.method = str(result.method)
    response.iterations = int(getattr(result, 'iterations', 0) or 0)
    return response


def grasp_markers(result: Any, header: Any, geometry: GridGeometry, jaw_width: float,
                  jaw_thickness: float = 0.004, jaw_height: float = 0.02,
                  contacts_xy: np.ndarray | None = None) -> Any:
    """RViz ``visualization_msgs/MarkerArray`` (rclpy) of a planned grasp: two jaw plates (CUBE)
    and the closing arrow jaw1 → jaw2, coloured by P_F (red 0 → yellow → green 1), the contacts
    ``contacts_xy`` ((2, 2) m, e.g. on the mean shape; skipped when None or not finite) as spheres,
    and a text label with the method and P_F. Sizes in m; drawn half a jaw height above the table
    plane (``geometry.z``; the optical z axis points down). The first marker deletes earlier ones."""
    f = RclpyFactory()
    z = float(geometry.z) - jaw_height / 2.0
    axis = np.asarray(result.axis, dtype=np.float64)

    def color(r: float, g: float, b: float, a: float = 0.9) -> Any:
        return f.new('std_msgs/msg/ColorRGBA', r=r, g=g, b=b, a=a)

    def marker(mid: int, mtype: int, **fields: Any) -> Any:
        return f.new('visualization_msgs/msg/Marker', header=header, ns='grasp', id=mid, type=mtype,
                     action=0, **fields)

    clear = f.new('visualization_msgs/msg/Marker', header=header, ns='grasp', id=0, action=3)
    markers = [clear]
    p_f = float(np.clip(np.nan_to_num(float(result.p_f)), 0.0, 1.0))
    pf_rgb = (min(1.0, 2.0 * (1.0 - p_f)), min(1.0, 2.0 * p_f), 0.1)
    if bool(result.success):
        for mid, jaw in ((1, result.jaw1), (2, result.jaw2)):
            pose = _pose_stamped(f, header, jaw, z, axis).pose
            markers.append(marker(mid, 1, pose=pose, color=color(*pf_rgb),
                                  scale=f.new('geometry_msgs/msg/Vector3', x=float(jaw_thickness),
                                              y=float(jaw_width), z=float(jaw_height))))
        points = [f.new('geometry_msgs/msg/Point', x=float(p[0]), y=float(p[1]), z=z)
                  for p in (np.asarray(result.jaw1, dtype=np.float64), np.asarray(result.jaw2, dtype=np.float64))]
        markers.append(marker(3, 0, points=points, color=color(*pf_rgb),
                              scale=f.new('geometry_msgs/msg/Vector3', x=0.002, y=0.005, z=0.006)))
        if contacts_xy is not None:
            for mid, c in enumerate(np.asarray(contacts_xy, dtype=np.float64).reshape(-1, 2), start=5):
                if np.all(np.isfinite(c)):
                    pose = _pose_stamped(f, header, c, z, axis).pose
                    markers.append(marker(mid, 2, pose=pose, color=color(1.0, 1.0, 1.0),
                                          scale=f.new('geometry_msgs/msg/Vector3', x=0.004, y=0.004, z=0.004)))
        centre = _pose_stamped(f, header, result.center, z - jaw_height, axis).pose
        markers.append(marker(4, 9, pose=centre, color=color(1.0, 1.0, 1.0),
                              scale=f.new('geometry_msgs/msg/Vector3', x=0.0, y=0.0, z=0.01),
                              text=f'{result.method}: P_F = {float(result.p_f):.2f}'))
    return f.new('visualization_msgs/msg/MarkerArray', markers=markers)
