"""Writes every robot and scene description under ``urdf/`` from the figures in each folder's README.

Run ``python urdf/generate.py`` after changing a figure here; ``tests/test_urdf.py`` checks that the committed
files are exactly what this script writes, so the two never drift apart. Only the standard library is used.

Conventions: SI units (m, kg, rad, N m, rad/s); every link's inertia is that of its primitive collision shape
with the link's mass (solid cylinder or box), so the dynamics match the geometry PyBullet collides.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
PI = math.pi


def fmt(*values: float) -> str:
    return " ".join(f"{v:.10g}" for v in values)


@dataclass(frozen=True)
class Shape:
    """A primitive: ``cylinder`` (radius, length along local z) or ``box`` (x, y, z sizes), placed by xyz/rpy."""

    kind: str
    dims: tuple[float, ...]
    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def geometry(self) -> str:
        if self.kind == "cylinder":
            return f'<cylinder radius="{self.dims[0]:.10g}" length="{self.dims[1]:.10g}"/>'
        return f'<box size="{fmt(*self.dims)}"/>'

    def principal_inertia(self, mass: float) -> tuple[float, float, float]:
        if self.kind == "cylinder":
            r, h = self.dims
            ixx = mass * (3 * r * r + h * h) / 12.0
            return ixx, ixx, mass * r * r / 2.0
        x, y, z = self.dims
        return mass * (y * y + z * z) / 12.0, mass * (x * x + z * z) / 12.0, mass * (x * x + y * y) / 12.0


def link(name: str, shape: Shape | None, mass: float, rgba: str, collide: bool = True) -> str:
    if shape is None:
        ixx = iyy = izz = 1e-7
        inertial_origin = '<origin xyz="0 0 0"/>'
        body = ""
    else:
        ixx, iyy, izz = shape.principal_inertia(mass)
        inertial_origin = f'<origin xyz="{fmt(*shape.xyz)}" rpy="{fmt(*shape.rpy)}"/>'
        origin = f'<origin xyz="{fmt(*shape.xyz)}" rpy="{fmt(*shape.rpy)}"/>'
        geom = f"<geometry>{shape.geometry()}</geometry>"
        body = (f'    <visual>{origin}{geom}<material name="{name}_color"><color rgba="{rgba}"/></material></visual>\n')
        if collide:
            body += f"    <collision>{origin}{geom}</collision>\n"
    return (f'  <link name="{name}">\n'
            f'    <inertial>{inertial_origin}<mass value="{mass:.10g}"/>'
            f'<inertia ixx="{ixx:.10g}" ixy="0" ixz="0" iyy="{iyy:.10g}" iyz="0" izz="{izz:.10g}"/></inertial>\n'
            f"{body}  </link>\n")


def joint(name: str, kind: str, parent: str, child: str, xyz=(0.0, 0.0, 0.0), rpy=(0.0, 0.0, 0.0),
          axis=(0.0, 0.0, 1.0), lower: float = 0.0, upper: float = 0.0, effort: float = 0.0,
          velocity: float = 0.0, damping: float = 0.0) -> str:
    text = (f'  <joint name="{name}" type="{kind}">\n'
            f'    <parent link="{parent}"/><child link="{child}"/>\n'
            f'    <origin xyz="{fmt(*xyz)}" rpy="{fmt(*rpy)}"/>\n')
    if kind != "fixed":
        text += (f'    <axis xyz="{fmt(*axis)}"/>\n'
                 f'    <limit lower="{lower:.10g}" upper="{upper:.10g}" effort="{effort:.10g}" velocity="{velocity:.10g}"/>\n'
                 f'    <dynamics damping="{damping:.10g}" friction="0"/>\n')
    return text + "  </joint>\n"


# --------------------------------------------------------------------------------------------------------------
# RealMan RM65-B arm (figures: urdf/realman_rm65b/README.md)
ARM_GREY = "0.82 0.83 0.86 1"
ARM_DARK = "0.25 0.27 0.30 1"
DEG = PI / 180.0


def rm65b_body(prefix_root: str = "base_link") -> str:
    """Links and joints of the arm; the root link is ``base_link``, the flange link ``link6``."""
    h = PI / 2
    parts = [
        link("base_link", Shape("cylinder", (0.06, 0.10), (0, 0, 0.05)), 1.862, ARM_DARK),
        link("link1", Shape("cylinder", (0.05, 0.13), (0, 0, -0.075)), 1.51, ARM_GREY),
        link("link2", Shape("cylinder", (0.045, 0.256), (0.128, 0, 0), (0, h, 0)), 1.653, ARM_GREY),
        link("link3", Shape("cylinder", (0.04, 0.21), (0, -0.105, 0), (h, 0, 0)), 0.726, ARM_GREY),
        link("link4", Shape("cylinder", (0.035, 0.07), (0, 0, 0)), 0.671, ARM_DARK),
        link("link5", Shape("cylinder", (0.035, 0.10), (0, -0.07, 0), (h, 0, 0)), 0.647, ARM_GREY),
        link("link6", Shape("cylinder", (0.032, 0.02), (0, 0, -0.01)), 0.104, ARM_DARK),
        # (origin xyz, rpy, lower/upper deg, effort N m, speed deg/s)
    ]
    spec = [
        ("joint1", "base_link", "link1", (0, 0, 0.2405), (0, 0, 0), 178, 60, 180),
        ("joint2", "link1", "link2", (0, 0, 0), (h, -h, 0), 130, 60, 180),
        ("joint3", "link2", "link3", (0.256, 0, 0), (0, 0, h), 135, 30, 225),
        ("joint4", "link3", "link4", (0, -0.21, 0), (h, 0, 0), 178, 10, 225),
        ("joint5", "link4", "link5", (0, 0, 0), (-h, 0, 0), 128, 10, 225),
        ("joint6", "link5", "link6", (0, -0.144, 0), (h, 0, 0), 360, 10, 225),
    ]
    for name, parent, child, xyz, rpy, limit_deg, effort, speed_deg in spec:
        parts.append(joint(name, "revolute", parent, child, xyz, rpy, lower=-limit_deg * DEG, upper=limit_deg * DEG,
                           effort=effort, velocity=speed_deg * DEG, damping=0.5))
    return "".join(parts)


# --------------------------------------------------------------------------------------------------------------
# DG-3F-lite three-fingered gripper (figures: urdf/dg3f_lite/README.md)
FINGER_BASE_RADIUS_M = 0.0266
PALM_HEIGHT_M = 0.05
PROXIMAL_M = 0.05
DISTAL_M = 0.05
TIP_M = 0.02
FINGER_THICKNESS_M = 0.016
FINGER_WIDTH_M = 0.02
PAD_SIZE_M = 0.016
PAD_THICKNESS_M = 0.004
FINGER_GREY = "0.35 0.36 0.40 1"
PAD_COLOR = "0.95 0.55 0.15 1"


def dg3f_body(root: str = "gripper_base") -> str:
    """Links and joints of the gripper; the root link is ``root``; the thumb (finger 0) carries the pad."""
    parts = [link(root, Shape("cylinder", (0.042, PALM_HEIGHT_M), (0, 0, PALM_HEIGHT_M / 2)), 0.37, ARM_DARK)]
    # Finger 0 (thumb) at 0 deg closes towards -x; fingers 1 and 2 at +-120 deg close towards +x, parallel to
    # each other, opposing the thumb (the DG-3F's pinch posture with its abduction joints fixed).
    bases = [(0.0, PI), (120.0, 0.0), (-120.0, 0.0)]
    for i, (angle_deg, yaw) in enumerate(bases):
        a = angle_deg * DEG
        xyz = (FINGER_BASE_RADIUS_M * math.cos(a), FINGER_BASE_RADIUS_M * math.sin(a), PALM_HEIGHT_M)
        f = f"finger{i}"
        seg = lambda length: Shape("box", (FINGER_THICKNESS_M, FINGER_WIDTH_M, length), (0, 0, length / 2))
        parts += [
            link(f"{f}_proximal", seg(PROXIMAL_M), 0.09, FINGER_GREY),
            link(f"{f}_distal", seg(DISTAL_M), 0.08, FINGER_GREY),
            link(f"{f}_tip", seg(TIP_M), 0.04, FINGER_GREY),
            joint(f"{f}_joint1", "revolute", root, f"{f}_proximal", xyz, (0, 0, yaw), axis=(0, 1, 0),
                  lower=-0.7, upper=1.2, effort=10.0, velocity=5.0, damping=0.05),
            joint(f"{f}_joint2", "revolute", f"{f}_proximal", f"{f}_distal", (0, 0, PROXIMAL_M), axis=(0, 1, 0),
                  lower=-1.4, upper=1.4, effort=10.0, velocity=5.0, damping=0.05),
            joint(f"{f}_tip_joint", "fixed", f"{f}_distal", f"{f}_tip", (0, 0, DISTAL_M)),
        ]
    parts += [
        link("tactile_pad", Shape("box", (PAD_SIZE_M, PAD_SIZE_M, PAD_THICKNESS_M), (0, 0, PAD_THICKNESS_M / 2)),
             0.005, PAD_COLOR),
        joint("tactile_pad_joint", "fixed", "finger0_tip", "tactile_pad", (0, 0, TIP_M)),
        # Tool frame: centre of the pad's sensing surface, z out of the pad, x along the thumb's closing direction.
        link("pad_center", None, 0.0, ""),
        joint("pad_center_joint", "fixed", "tactile_pad", "pad_center", (0, 0, PAD_THICKNESS_M)),
    ]
    return "".join(parts)


def robot(name: str, body: str) -> str:
    return f'<?xml version="1.0"?>\n<!-- Generated by urdf/generate.py; edit that script, not this file. -->\n<robot name="{name}">\n{body}</robot>\n'


def combined() -> str:
    return robot("rm65b_dg3f", rm65b_body() + dg3f_body() +
                 joint("flange_to_gripper", "fixed", "link6", "gripper_base"))


# --------------------------------------------------------------------------------------------------------------
# Scene content, kept apart from the robots (figures: urdf/scene/README.md)
TABLE_SIZE_M = (1.2, 1.0, 0.04)
TABLE_HEIGHT_M = 0.70


def table() -> str:
    x, y, z = TABLE_SIZE_M
    leg = 0.05
    body = link("table_top", Shape("box", (x, y, z), (0, 0, TABLE_HEIGHT_M - z / 2)), 30.0, "0.55 0.42 0.30 1")
    for i, (sx, sy) in enumerate([(1, 1), (1, -1), (-1, 1), (-1, -1)]):
        h = TABLE_HEIGHT_M - z
        body += link(f"leg{i}", Shape("box", (leg, leg, h), (0, 0, h / 2)), 2.0, "0.40 0.30 0.22 1")
        body += joint(f"leg{i}_joint", "fixed", "table_top", f"leg{i}", (sx * (x / 2 - leg), sy * (y / 2 - leg), 0))
    return robot("table", body)


def floor() -> str:
    return robot("floor", link("floor", Shape("box", (6.0, 6.0, 0.02), (0, 0, -0.01)), 0.0, "0.30 0.30 0.32 1"))


def zone(name: str, rgba: str) -> str:
    """A 2 mm coloured mat marking a collection zone (visual only: objects rest on the table under it)."""
    return robot(name, link(name, Shape("box", (0.22, 0.22, 0.002), (0, 0, 0.001)), 0.0, rgba, collide=False))


FILES = {
    "realman_rm65b/rm65b.urdf": lambda: robot("rm65b", rm65b_body()),
    "dg3f_lite/dg3f_lite.urdf": lambda: robot("dg3f_lite", dg3f_body()),
    "rm65b_dg3f/rm65b_dg3f.urdf": combined,
    "scene/table.urdf": table,
    "scene/floor.urdf": floor,
    "scene/zone_noncombustible.urdf": lambda: zone("zone_noncombustible", "0.20 0.45 0.85 0.9"),
    "scene/zone_combustible.urdf": lambda: zone("zone_combustible", "0.85 0.25 0.20 0.9"),
}


def render_all() -> dict[str, str]:
    return {rel: make() for rel, make in FILES.items()}


def main() -> None:
    for rel, text in render_all().items():
        path = HERE / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        print(f"wrote {path.relative_to(HERE.parent)}")


if __name__ == "__main__":
    main()
