"""Robot arms: URDF descriptions, batched kinematics, differential IK, probe and drill tools.

Kinematic stand-ins for the paper's KUKA LBR Med 14 and Franka FR3 (see ``arm``): batched
forward kinematics and Jacobians on pytorch-kinematics' parsed chains (evaluated by
``serial_chain.SerialChainKinematics``), damped-least-squares IK with
joint position and velocity limits at the 60 Hz control rate, a probe held on the skin
(``SurfaceController``) and base placements relative to the patient (``placement``).
Everything is in the patient frame {P}, metres and radians, batch-first.
"""

from sonogym.robots.arm import REFERENCE_VELOCITY_LIMITS, Arm, ArmConfig, IKResult
from sonogym.robots.description import (
    ARM_MODELS,
    URDF_DIR,
    ArmModel,
    ArmName,
    arm_model,
    assemble_urdf,
)
from sonogym.robots.placement import (
    NAVIGATION_PROBE_BASE,
    OVERHEAD_PROBE_BASE,
    SURGERY_DRILL_BASE,
    SURGERY_PROBE_BASE,
    BasePlacement,
    reference_base_in_voxel_frame,
)
from sonogym.robots.surface_controller import SurfaceController
from sonogym.robots.tools import DRILL_TOOL, PROBE_TOOL, ToolConfig

__all__ = [
    "ARM_MODELS",
    "ArmName",
    "DRILL_TOOL",
    "NAVIGATION_PROBE_BASE",
    "OVERHEAD_PROBE_BASE",
    "PROBE_TOOL",
    "REFERENCE_VELOCITY_LIMITS",
    "SURGERY_DRILL_BASE",
    "SURGERY_PROBE_BASE",
    "URDF_DIR",
    "Arm",
    "ArmConfig",
    "ArmModel",
    "BasePlacement",
    "IKResult",
    "SurfaceController",
    "ToolConfig",
    "arm_model",
    "assemble_urdf",
    "reference_base_in_voxel_frame",
]
