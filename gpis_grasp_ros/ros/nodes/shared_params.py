"""Parameters shared by several nodes: the gripper (planner_node, gripper_sim_node, segmentation_node)
and the input-grid limits (gpis_node, planner_node).

The gripper is defined once, in metres (``GripperParams``; docs/planning.md, "Resolution and λ"): the
planner's P_F and the simulated gripper close the same jaws with the same noise and pad on any grid.
"""

from __future__ import annotations

from typing import Any

from gpis_grasp_ros.core.gripper import GripperParams
from gpis_grasp_ros.ros import validation
from gpis_grasp_ros.ros.conversions import DEFAULT_JAW_HEIGHT
from gpis_grasp_ros.ros.params import Param

_G = GripperParams

#: The gripper, by parameter name. Nodes take the entries they use (``GRIPPER['max_opening']``).
GRIPPER: dict[str, Param] = {p.name: p for p in (
    Param('jaw_width', float, 'w_j: width of each jaw face', _G, unit='m', low=0.0, high=0.2),
    Param('max_opening', float, 'w_g: maximum jaw opening', _G, unit='m', low=0.005, high=0.5),
    Param('friction_coefficient', float, 'gamma: Coulomb friction coefficient', _G, 'friction_coef',
          low=0.0, high=5.0),
    Param('position_noise', float, 'sigma_g: std of the jaw positioning error per axis and jaw on the table '
          '(arm accuracy and camera-to-arm calibration)', _G, unit='m', low=0.0, high=0.1),
    Param('contact_patch', float, 'pad compliance: surface points within this distance of the first touch share '
          'the contact', _G, unit='m', low=0.0, high=0.05),
    Param('jaw_height', float, 'height of a jaw pad along the approach direction (grasp_height clamp, markers)',
          default=DEFAULT_JAW_HEIGHT, unit='m', low=0.001, high=0.2),
)}


def check_gripper(values: dict[str, Any]) -> None:
    """The jaws must fit in the opening (ValueError naming both parameters)."""
    if values['jaw_width'] >= values['max_opening']:
        raise ValueError(f"jaw_width={values['jaw_width']} m must be smaller than "
                         f"max_opening={values['max_opening']} m")


def gripper_params(names: tuple[str, ...], **defaults: float) -> list[Param]:
    """The gripper entries ``names``, with node-specific ``defaults`` (name → value)."""
    return [GRIPPER[n].replace(default=defaults[n]) if n in defaults else GRIPPER[n] for n in names]


def grid_limits(what: str, max_cells_high: int, cells_note: str = '') -> list[Param]:
    """Limits of an incoming grid (``what``: the message) → ``validation.Limits``."""
    lim = validation.Limits
    return [
        Param('max_grid_cells', int, f'largest {what} grid accepted{cells_note}', lim, unit='cells',
              low=16, high=max_cells_high),
        Param('min_resolution', float, f'smallest {what} cell size accepted', lim, unit='m', low=1e-6, high=0.1),
        Param('max_resolution', float, f'largest {what} cell size accepted', lim, unit='m', low=1e-3, high=10.0),
    ]


def check_resolutions(values: dict[str, Any]) -> None:
    """min_resolution < max_resolution."""
    if values['min_resolution'] >= values['max_resolution']:
        raise ValueError('min_resolution must be smaller than max_resolution')
