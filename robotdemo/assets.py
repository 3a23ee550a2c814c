"""Locates the robot and scene descriptions, whether the project is installed editable or from a wheel.

In a source checkout (and an editable install) they are the top-level ``urdf/`` folder; a wheel carries the
same folder as ``robotdemo/_urdf``.
"""

from __future__ import annotations

from pathlib import Path

from robotdemo.errors import AssetError

_PACKAGE_DIR = Path(__file__).resolve().parent

ARM_URDF = "realman_rm65b/rm65b.urdf"
GRIPPER_URDF = "dg3f_lite/dg3f_lite.urdf"
ROBOT_URDF = "rm65b_dg3f/rm65b_dg3f.urdf"
TABLE_URDF = "scene/table.urdf"
FLOOR_URDF = "scene/floor.urdf"
ZONE_URDFS = {"noncombustible": "scene/zone_noncombustible.urdf", "combustible": "scene/zone_combustible.urdf"}

TOOL_FRAME = "pad_center"
"""Name of the tool frame: centre of the tactile pad's sensing surface, z out of the pad."""

ARM_JOINTS: tuple[str, ...] = tuple(f"joint{i}" for i in range(1, 7))
GRIPPER_JOINTS: tuple[str, ...] = tuple(f"finger{f}_joint{j}" for f in range(3) for j in (1, 2))


def urdf_root() -> Path:
    """The folder holding every description (``urdf/`` in a checkout, ``robotdemo/_urdf`` in a wheel)."""
    for candidate in (_PACKAGE_DIR / "_urdf", _PACKAGE_DIR.parent / "urdf"):
        if (candidate / ROBOT_URDF).is_file():
            return candidate
    raise AssetError(f"robot descriptions not found (looked in {_PACKAGE_DIR / '_urdf'} and {_PACKAGE_DIR.parent / 'urdf'})")


def urdf_path(relative: str) -> Path:
    """Absolute path of a description, e.g. ``urdf_path(ROBOT_URDF)``; a clear error if it is missing."""
    path = urdf_root() / relative
    if not path.is_file():
        raise AssetError(f"{path}: URDF file not found")
    return path


def all_urdfs() -> list[Path]:
    """Every ``.urdf`` file shipped with the project, sorted."""
    return sorted(urdf_root().rglob("*.urdf"))
