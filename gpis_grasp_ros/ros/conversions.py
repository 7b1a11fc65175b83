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

from gpis_grasp_ros.core import contacts
from gpis_grasp_ros.core.grid import GridGeometry, rotation_to_quaternion
from gpis_grasp_ros.core.gripper import GripperParams
from gpis_grasp_ros.core.sdf_bank import SdfBank
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
#: Default height (m) of a jaw pad along the approach direction (markers, grasp-height clamp).
DEFAULT_JAW_HEIGHT = 0.02


def grasp_frame(geometry: GridGeometry, axis: np.ndarray) -> np.ndarray:
    """Orientation (3 x 3, columns = axes in the sensor frame) of a grasp on a grid in the table plane.

    z = approach direction, towards the table (−table normal = the grid's z axis); x = closing direction
    jaw1 → jaw2 (``axis``, grid (x, y)) in the table plane; y = z × x. A non-finite or zero ``axis``
    gives the grid's x axis.
    """
    r = geometry.rotation_matrix
    a = np.asarray(axis, dtype=np.float64).ravel()[:2]
    n = float(np.hypot(a[0], a[1])) if a.size == 2 and np.isfinite(a).all() else 0.0
    a = a / n if n > 0 else np.array([1.0, 0.0])
    x = r @ np.array([a[0], a[1], 0.0])
    z = r[:, 2]
    return np.stack([x, np.cross(z, x), z], axis=1)


def _quaternion(f: MessageFactory, rotation: np.ndarray) -> Any:
    q = rotation_to_quaternion(rotation)
    return f.new('geometry_msgs/msg/Quaternion', x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))


def _point(f: MessageFactory, p: np.ndarray, type_name: str = 'geometry_msgs/msg/Point') -> Any:
    p = np.asarray(p, dtype=np.float64).ravel()
    x, y, z = (float(v) for v in p) if np.isfinite(p).all() else (0.0, 0.0, 0.0)
    return f.new(type_name, x=x, y=y, z=z)


def _pose(f: MessageFactory, position: np.ndarray, rotation: np.ndarray) -> Any:
    return f.new('geometry_msgs/msg/Pose', position=_point(f, position), orientation=_quaternion(f, rotation))


def _pose_stamped(f: MessageFactory, header: Any, position: np.ndarray, rotation: np.ndarray) -> Any:
    return f.new('geometry_msgs/msg/PoseStamped', header=header, pose=_pose(f, position, rotation))


def _on_plane(geometry: GridGeometry, xy: Any, height: float) -> np.ndarray:
    """Grid point(s) (..., 2) at ``height`` above the table → sensor frame; non-finite stays NaN."""
    return geometry.to_sensor(np.asarray(xy, dtype=np.float64), height)


def grasp_height_for(grasp_height: float, object_height: float, jaw_height: float = DEFAULT_JAW_HEIGHT) -> float:
    """Height (m) above the table, along its normal, at which the jaws close.

    ``grasp_height >= 0``: that height. Negative (automatic): half the object's height above the table,
    clamped to the jaw geometry: at least half a jaw pad's height ``jaw_height`` (the pad centre at the
    jaw pose; its lower edge then stays at or above the table). An unknown object height
    (``object_height <= 0``) gives that lowest height, the pads resting just above the table.
    """
    if grasp_height >= 0:
        return float(grasp_height)
    return max(0.5 * max(float(object_height), 0.0), 0.5 * float(jaw_height))


def mean_shape_contacts(posterior: Any, result: Any, jaw_width: float) -> np.ndarray | None:
    """Contacts (2, 2) (grid m) of the closing jaws on the GPIS mean shape, or None when either jaw finds
    none (the contact model of :func:`gpis_grasp_ros.core.contacts.find_contacts`, opening not checked)."""
    jaws = np.concatenate([np.ravel(result.jaw1), np.ravel(result.jaw2)])
    if not bool(result.success) or not np.isfinite(jaws).all():
        return None
    bank = SdfBank(posterior.mean[None], posterior.geometry, posterior.gradient[None],
                   obstacles=posterior.obstacles)
    con = contacts.find_contacts(bank, result.jaw1, result.jaw2, GripperParams(jaw_width=jaw_width),
                                 check_opening=False)
    if not bool(np.ravel(con.valid)[0]):
        return None
    return np.stack([np.reshape(con.c1, (-1, 2))[0], np.reshape(con.c2, (-1, 2))[0]])


def fill_grasp_plan_response(response: Any, result: Any, header: Any, z: float | None = None,
                             geometry: GridGeometry | None = None, grasp_height: float = 0.0,
                             contacts_xy: np.ndarray | None = None) -> Any:
    """Copy a planner ``GraspResult`` into a ``GraspPlan`` response (or ``PlanGrasp`` result), in place.

    Frames and meaning (also in GraspPlan.srv): everything is in ``header``'s frame (the sensor
    frame of the GPIS), metres. ``geometry`` is the GPIS grid (its pose gives the table plane; when
    omitted, a top-down grid at depth ``z``). ``jaw1``/``jaw2`` are the planned jaw positions (grid
    (x, y)) lifted to ``grasp_height`` (m) above the table along its normal; ``grasp_pose`` is their
    midpoint; all three share the grasp orientation of :func:`grasp_frame` (z = approach towards
    the table, x = closing direction jaw1 → jaw2). ``contact1``/``contact2`` are the contacts of the
    closing jaws on the GPIS mean shape (``contacts_xy`` (2, 2) grid metres, at ``grasp_height``);
    ``width`` is their distance, the opening the gripper needs (NaN, and said in ``message``, when the
    jaws find no contact on the mean shape); ``jaw_separation`` is ‖jaw2 − jaw1‖, the planned
    approach opening. Non-finite positions (failed plans) are written as 0.
    """
    f = RclpyFactory()
    if geometry is None:
        geometry = GridGeometry(0.0, 0.0, 1.0, 1, 1, 0.0 if z is None else float(z))
    h = float(grasp_height)
    rot = grasp_frame(geometry, result.axis)
    response.success = bool(result.success)
    response.message = str(result.message)
    jaw1, jaw2 = _on_plane(geometry, result.jaw1, h), _on_plane(geometry, result.jaw2, h)
    response.jaw1 = _pose_stamped(f, header, jaw1, rot)
    response.jaw2 = _pose_stamped(f, header, jaw2, rot)
    response.grasp_pose = _pose_stamped(f, header, _on_plane(geometry, result.center, h), rot)

    def num(v: Any) -> float:
        return float(v) if v is not None else float('nan')

    touches = None if contacts_xy is None else np.asarray(contacts_xy, dtype=np.float64).reshape(2, 2)
    if touches is not None and not np.isfinite(touches).all():
        touches = None
    c3 = _on_plane(geometry, touches, h) if touches is not None else np.full((2, 3), np.nan)
    if hasattr(response, 'contact1'):
        response.contact1 = f.new('geometry_msgs/msg/PointStamped', header=header, point=_point(f, c3[0]))
        response.contact2 = f.new('geometry_msgs/msg/PointStamped', header=header, point=_point(f, c3[1]))
        response.grasp_height = h
        response.jaw_separation = float(np.linalg.norm(jaw2 - jaw1))  # of the published points (NaN: no grasp)
        response.width = float(np.linalg.norm(c3[1] - c3[0]))
        if response.success and touches is None:
            response.message += '; the jaws find no contact on the mean shape: width unknown (NaN)'
    else:  # interface without the contact fields: the planned jaw separation
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
                  jaw_thickness: float = 0.004, jaw_height: float = DEFAULT_JAW_HEIGHT,
                  contacts_xy: np.ndarray | None = None, grasp_height: float | None = None) -> Any:
    """RViz ``visualization_msgs/MarkerArray`` (rclpy) of a planned grasp: two jaw plates (CUBE,
    ``jaw_thickness`` along the closing direction, ``jaw_width`` across, ``jaw_height`` along the
    approach) and the closing arrow jaw1 → jaw2, coloured by P_F (red 0 → yellow → green 1), the
    contacts ``contacts_xy`` ((2, 2) grid m, e.g. on the mean shape; skipped when None or not finite)
    as spheres, and a text label with the method and P_F. Sizes in m. Everything is drawn in the
    table plane of ``geometry`` at ``grasp_height`` above the table (default: half a jaw height),
    oriented like the ``GraspPlan`` poses (:func:`grasp_frame`). The first marker deletes earlier ones."""
    f = RclpyFactory()
    h = float(jaw_height) / 2.0 if grasp_height is None else float(grasp_height)
    rot = grasp_frame(geometry, result.axis)

    def color(r: float, g: float, b: float, a: float = 0.9) -> Any:
        return f.new('std_msgs/msg/ColorRGBA', r=r, g=g, b=b, a=a)

    def marker(mid: int, mtype: int, **fields: Any) -> Any:
        return f.new('visualization_msgs/msg/Marker', header=header, ns='grasp', id=mid, type=mtype,
                     action=0, **fields)

    def vec(x: float, y: float, z: float) -> Any:
        return f.new('geometry_msgs/msg/Vector3', x=float(x), y=float(y), z=float(z))

    clear = f.new('visualization_msgs/msg/Marker', header=header, ns='grasp', id=0, action=3)
    markers = [clear]
    p_f = float(np.clip(np.nan_to_num(float(result.p_f)), 0.0, 1.0))
    pf_rgb = (min(1.0, 2.0 * (1.0 - p_f)), min(1.0, 2.0 * p_f), 0.1)
    if bool(result.success):
        jaws = [_on_plane(geometry, jaw, h) for jaw in (result.jaw1, result.jaw2)]
        for mid, jaw in ((1, jaws[0]), (2, jaws[1])):
            markers.append(marker(mid, 1, pose=_pose(f, jaw, rot), color=color(*pf_rgb),
                                  scale=vec(jaw_thickness, jaw_width, jaw_height)))
        markers.append(marker(3, 0, points=[_point(f, p) for p in jaws], color=color(*pf_rgb),
                              scale=vec(0.002, 0.005, 0.006)))
        if contacts_xy is not None:
            for mid, c in enumerate(np.asarray(contacts_xy, dtype=np.float64).reshape(-1, 2), start=5):
                if np.all(np.isfinite(c)):
                    markers.append(marker(mid, 2, pose=_pose(f, _on_plane(geometry, c, h), rot),
                                          color=color(1.0, 1.0, 1.0), scale=vec(0.004, 0.004, 0.004)))
        label = _on_plane(geometry, result.center, h + jaw_height)
        markers.append(marker(4, 9, pose=_pose(f, label, rot), color=color(1.0, 1.0, 1.0), scale=vec(0.0, 0.0, 0.01),
                              text=f'{result.method}: P_F = {float(result.p_f):.2f}'))
    return f.new('visualization_msgs/msg/MarkerArray', markers=markers)
