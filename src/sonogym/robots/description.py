"""Robot descriptions: the arm models we ship and the URDF of an arm with a tool attached.

The URDF files in ``urdf/`` were written for SonoGym from the manufacturers' published kinematic
parameters and joint limits (sources in each file's header comment).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from sonogym.robots.tools import ToolConfig

#: Folder holding the .urdf files (packaged with sonogym).
URDF_DIR = Path(__file__).resolve().parent / "urdf"


@dataclass(frozen=True)
class ArmModel:
    """A 7-DoF arm description.

    Attributes:
        urdf: file name in ``URDF_DIR``.
        base_link: the root link (the robot's mounting frame, z up along the first axis).
        flange_link: the flange frame (z out of the flange), where tools are mounted.
        default_joints: a nominal configuration within the limits, rad.
    """

    urdf: str
    base_link: str
    flange_link: str
    default_joints: tuple[float, ...]


#: Names of the known arm models (the keys of ``ARM_MODELS``).
ArmName = Literal["kuka_med14", "franka_fr3"]

#: Known arm models by name.
ARM_MODELS: dict[str, ArmModel] = {
    # Default joints: the reference implementation's probe-arm start in the navigation task.
    "kuka_med14": ArmModel(
        urdf="kuka_lbr_med14_r820.urdf",
        base_link="lbr_link_0",
        flange_link="lbr_link_ee",
        default_joints=(1.5, -0.1, 0.0, -1.6, 0.0, 1.6, 0.0),
    ),
    # Default joints: the reference implementation's FR3 probe-arm start in the surgery task.
    "franka_fr3": ArmModel(
        urdf="franka_fr3.urdf",
        base_link="fr3_link0",
        flange_link="fr3_link8",
        default_joints=(1.5, -0.5, 0.0, -1.0, 0.0, 1.6, 0.0),
    ),
}


def arm_model(name: str) -> ArmModel:
    """The ArmModel called ``name``; raises ValueError listing the known names otherwise."""
    try:
        return ARM_MODELS[name]
    except KeyError:
        raise ValueError(f"unknown arm model {name!r}; known: {sorted(ARM_MODELS)}") from None


def urdf_path(file_name: str) -> Path:
    """Path of a shipped URDF file; raises FileNotFoundError with the folder's content."""
    path = URDF_DIR / file_name
    if not path.is_file():
        known = sorted(p.name for p in URDF_DIR.glob("*.urdf"))
        raise FileNotFoundError(f"no robot description {path}; shipped files: {known}")
    return path


def _fmt(values: tuple[float, ...]) -> str:
    return " ".join(repr(float(v)) for v in values)


def assemble_urdf(model: str, tool: ToolConfig | None = None) -> str:
    """URDF text of arm ``model`` with ``tool`` mounted on its flange.

    The tool's root link is attached to the flange by a fixed joint with the identity pose; the
    tool's tip joint origin is rewritten from ``tool.tip_pos`` / ``tool.tip_rotvec``.
    """
    m = arm_model(model)
    robot = ET.parse(urdf_path(m.urdf)).getroot()
    if tool is None:
        return ET.tostring(robot, encoding="unicode")
    tool_root = ET.parse(urdf_path(tool.urdf)).getroot()
    links = {e.get("name") for e in tool_root.iter("link")}
    for name in (tool.mount_link, tool.tip_link):
        if name not in links:
            raise ValueError(f"{tool.urdf} has no link {name!r}; links: {sorted(links)}")
    tip_joint = next((j for j in tool_root.iter("joint") if j.get("name") == tool.tip_joint), None)
    if tip_joint is None or tip_joint.get("type") != "fixed":
        raise ValueError(f"{tool.urdf} has no fixed joint {tool.tip_joint!r}")
    if tip_joint.find("parent").get("link") != tool.mount_link:
        raise ValueError(f"{tool.tip_joint!r} must have parent {tool.mount_link!r}")
    origin = tip_joint.find("origin")
    if origin is None:
        origin = ET.SubElement(tip_joint, "origin")
    origin.set("xyz", _fmt(tool.tip_pos))
    origin.set("rpy", _fmt(tool.tip_rpy))

    name = f"{m.flange_link}_to_{tool.mount_link}"
    mount = ET.SubElement(robot, "joint", name=name, type="fixed")
    ET.SubElement(mount, "parent", link=m.flange_link)
    ET.SubElement(mount, "child", link=tool.mount_link)
    ET.SubElement(mount, "origin", xyz="0 0 0", rpy="0 0 0")
    for element in list(tool_root):
        if element.tag in ("link", "joint"):
            robot.append(element)
    return ET.tostring(robot, encoding="unicode")
