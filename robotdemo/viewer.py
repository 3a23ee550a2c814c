"""Meshcat view of a robotdemo scene: live in a browser, and recorded into a self-contained HTML replay.

Every Meshcat call of the project lives in this module; the rest of the code hands a :class:`Scene` to
:meth:`SceneViewer.update` once per control tick and knows nothing of Meshcat.

What is drawn (Meshcat paths under ``/meshcat``):

* ``robot/<link>/visual<k>``: the robot's URDF visuals (cylinders and boxes with their rgba), placed by
  Pinocchio forward kinematics of the URDF from ``Robot.arm_q()`` and ``Robot.gripper_q()``;
* ``table``, ``zones/<name>``: the table and the two collection mats, from their URDFs, with the zone name
  written on each mat;
* ``objects/<name>/shape``: each object as simulated (box, slab or cylinder), coloured by material;
* ``labels/<object>/<label>``: the predicted label of an object once known (text above the object and a
  marker sphere in the label's category colour); a changed prediction hides the old label node;
* ``taxels/cell<r><c>``: the 4 x 4 normal pressures as a heat map beside the fingertip (row 0 at the top,
  column 0 at the left, the taxel order of ``perception.sensors.taxels``).

Live view: meshcat-python's own server binds its web port on every interface, so this module runs Meshcat's
ZMQ/websocket bridge in a child process whose web port binds ``127.0.0.1`` only (``ViewerConfig.host``
changes that, with a warning) and whose ZMQ command port always binds ``127.0.0.1``.
:meth:`SceneViewer.close` stops that process (``Visualizer.close()`` of meshcat-python is broken).

Recording: the viewer keeps the whole Meshcat scene tree in memory (the server is not needed for it) and,
when recording, keyframes of every moving node at ``record_fps`` of simulated time;
:meth:`SceneViewer.write_html` writes one HTML file with Meshcat's viewer, the scene and the animation,
which opens in a browser with no server.
"""

from __future__ import annotations

import argparse
import base64
import ipaddress
import math
import os
import re
import selectors
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import time
import warnings
import weakref
import xml.etree.ElementTree as ET
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np

from perception.atomic import atomic_write_text

from robotdemo.errors import RobotDemoError

try:  # meshcat-python pulls in IPython, tornado and zmq: report a missing piece as ViewerUnavailable
    with warnings.catch_warnings():   # its server module imports zmq.eventloop.ioloop, deprecated by pyzmq
        warnings.simplefilter("ignore", DeprecationWarning)
        import meshcat
        import meshcat.geometry as mg
        import umsgpack
        import zmq
        from meshcat.animation import Animation, AnimationClip, AnimationTrack
        from meshcat.commands import SetAnimation
        from meshcat.path import Path as MeshcatPath
        from meshcat.servers.zmqserver import VIEWER_ROOT
except ImportError as _exc:  # pragma: no cover - depends on the installation
    meshcat = None
    _MESHCAT_IMPORT_ERROR: ImportError | None = _exc
else:
    _MESHCAT_IMPORT_ERROR = None


class ViewerUnavailable(RobotDemoError):
    """The Meshcat viewer could not be started (meshcat missing, server failed, address or port unusable)."""


# --------------------------------------------------------------------------------------------------------------
# Configuration

LOOPBACK = "127.0.0.1"


@dataclass(frozen=True)
class ViewerConfig:
    """How the scene is shown and recorded.

    Attributes:
        live: serve the scene to a browser while the demo runs.
        host: address the web page listens on; anything but a loopback address exposes the viewer to the
            network and prints a warning (the ZMQ command port always stays on 127.0.0.1).
        port: web port; ``None`` takes the first free port from 7000 up (Meshcat's default).
        rate_hz: most live updates per second of ``clock`` (the demo may call :meth:`SceneViewer.update`
            every control tick).
        clock: ``"sim"`` throttles on simulated time, ``"wall"`` on wall-clock time.
        record: keep an animation of the run for :meth:`SceneViewer.write_html`.
        record_fps: keyframes per simulated second in the recording.
        taxel_full_scale_n: normal force per taxel drawn at the top of the colour scale, N.
        heatmap_offset_m: heat-map centre relative to the pad centre, world frame, m.
        camera_target_m: point the default camera orbits, world frame, m.
        camera_offset_m: camera position relative to ``camera_target_m``, world frame, m.
        start_timeout_s: how long the server may take to start.
    """

    live: bool = True
    host: str = LOOPBACK
    port: int | None = None
    rate_hz: float = 25.0
    clock: str = "sim"
    record: bool = False
    record_fps: float = 25.0
    taxel_full_scale_n: float = 1.0
    heatmap_offset_m: tuple[float, float, float] = (0.0, 0.10, 0.04)
    camera_target_m: tuple[float, float, float] = (-0.25, 0.0, 0.80)
    camera_offset_m: tuple[float, float, float] = (0.62, 0.36, 0.40)
    start_timeout_s: float = 20.0

    def __post_init__(self) -> None:
        if self.rate_hz <= 0 or self.record_fps <= 0:
            raise ValueError(f"viewer rates must be > 0 (rate_hz={self.rate_hz}, record_fps={self.record_fps})")
        if self.clock not in ("sim", "wall"):
            raise ValueError(f"viewer clock must be 'sim' or 'wall', got {self.clock!r}")
        if self.taxel_full_scale_n <= 0:
            raise ValueError(f"taxel_full_scale_n must be > 0, got {self.taxel_full_scale_n}")
        if self.port is not None and not 0 < self.port < 65536:
            raise ValueError(f"viewer port must be in 1..65535, got {self.port}")


def is_loopback(host: str) -> bool:
    """Whether ``host`` names this machine's loopback interface only."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


# --------------------------------------------------------------------------------------------------------------
# Small geometry helpers (float64 ndarrays throughout: meshcat 0.3.2 under NumPy 2 wants them)

def _translation(xyz: Sequence[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = xyz
    return T


def _rotation_xyz(axis: str, angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    R = {"x": [[1, 0, 0], [0, c, -s], [0, s, c]],
         "y": [[c, 0, s], [0, 1, 0], [-s, 0, c]],
         "z": [[c, -s, 0], [s, c, 0], [0, 0, 1]]}[axis]
    T = np.eye(4)
    T[:3, :3] = R
    return T


def _rpy_matrix(xyz: Sequence[float], rpy: Sequence[float]) -> np.ndarray:
    """URDF ``<origin>``: translation, then rotation R = Rz(yaw) Ry(pitch) Rx(roll)."""
    T = _rotation_xyz("z", rpy[2]) @ _rotation_xyz("y", rpy[1]) @ _rotation_xyz("x", rpy[0])
    T[:3, 3] = xyz
    return T


def _pose_matrix(position_m: Sequence[float], quaternion_xyzw: Sequence[float]) -> np.ndarray:
    x, y, z, w = (float(v) for v in quaternion_xyzw)
    T = np.eye(4)
    T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    T[:3, 3] = np.asarray(position_m, dtype=float)
    return T


def _quaternion_xyzw(R: np.ndarray) -> list[float]:
    """Unit quaternion of a rotation matrix, w >= 0 (three.js order x, y, z, w)."""
    m = R
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    sign = -1.0 if q[3] < 0 else 1.0
    norm = math.sqrt(sum(v * v for v in q))
    return [round(sign * v / norm, 6) for v in q]


_CYLINDER_TO_Z = _rotation_xyz("x", math.pi / 2)
"""Meshcat (three.js) cylinders run along their local y axis, URDF cylinders along z."""

_FACING_CAMERA = _rotation_xyz("z", math.pi / 2) @ _rotation_xyz("x", math.pi / 2)
"""Upright panel facing world +x (towards the default camera): local x -> world +y, local y -> world +z."""


def _hex_colour(rgba: Sequence[float]) -> int:
    r, g, b = (int(round(255 * min(max(float(c), 0.0), 1.0))) for c in rgba[:3])
    return (r << 16) | (g << 8) | b


_FALLBACK_RGBA: dict[str, tuple[float, float, float, float]] = {
    "metal": (0.72, 0.74, 0.78, 1.0), "stone": (0.50, 0.50, 0.47, 1.0), "paper": (0.95, 0.93, 0.85, 1.0),
    "polymer": (0.20, 0.60, 0.85, 1.0), "rubber": (0.12, 0.12, 0.12, 1.0), "textiles": (0.70, 0.35, 0.60, 1.0),
    "wood": (0.65, 0.45, 0.25, 1.0),
}
_GREY = (0.8, 0.8, 0.8, 1.0)


def category_rgba(category: str) -> tuple[float, float, float, float]:
    """Display colour of a material category: the scene's palette when it has one, else a built-in one."""
    try:
        from robotdemo.scene import CATEGORY_RGBA as palette
    except ImportError:
        palette = _FALLBACK_RGBA
    return tuple(palette.get(category, _FALLBACK_RGBA.get(category, _GREY)))


def object_rgba(obj: Any) -> tuple[float, float, float, float]:
    """An object's colour: its material's ``rgba`` if the material has one, else its category's colour."""
    rgba = getattr(obj.spec.material, "rgba", None)
    return tuple(rgba) if rgba is not None else category_rgba(obj.category)


def _heat_rgb(fraction: float) -> list[float]:
    """Dark blue -> purple -> orange -> pale yellow for 0..1 (an inferno-like ramp), quantised to 1/32."""
    t = round(min(max(fraction, 0.0), 1.0) * 32) / 32
    stops = [(0.0, (0.10, 0.10, 0.30)), (0.35, (0.55, 0.12, 0.50)), (0.7, (0.95, 0.45, 0.10)),
             (1.0, (1.0, 0.95, 0.45))]
    for (t0, c0), (t1, c1) in zip(stops, stops[1:]):
        if t <= t1:
            a = (t - t0) / (t1 - t0)
            return [round(c0[i] + a * (c1[i] - c0[i]), 4) for i in range(3)]
    return list(stops[-1][1])


def _safe_name(text: str) -> str:
    """A Meshcat path element: no '/', no spaces."""
    return re.sub(r"[^A-Za-z0-9_.+-]", "_", str(text)) or "_"


# --------------------------------------------------------------------------------------------------------------
# URDF visuals and kinematics

@dataclass(frozen=True)
class _Visual:
    """One ``<visual>`` of a URDF link: a primitive placed in the link frame."""

    link: str
    index: int
    kind: str                        # "box", "cylinder" or "sphere"
    dims: tuple[float, ...]          # box: x, y, z sizes; cylinder: radius, length; sphere: radius (m)
    link_T_visual: np.ndarray        # (4, 4)
    rgba: tuple[float, float, float, float]


def urdf_visuals(path: str | Path) -> list[_Visual]:
    """The primitive visuals of every link of a URDF (meshes are not used by this project's descriptions)."""
    root = ET.parse(path).getroot()
    named = {m.get("name"): m for m in root.findall("material")}
    visuals = []
    for link in root.findall("link"):
        for k, vis in enumerate(link.findall("visual")):
            origin = vis.find("origin")
            xyz = [float(v) for v in (origin.get("xyz", "0 0 0") if origin is not None else "0 0 0").split()]
            rpy = [float(v) for v in (origin.get("rpy", "0 0 0") if origin is not None else "0 0 0").split()]
            geom = vis.find("geometry")
            shape = geom[0] if geom is not None and len(geom) else None
            if shape is None or shape.tag not in ("box", "cylinder", "sphere"):
                continue
            if shape.tag == "box":
                dims = tuple(float(v) for v in shape.get("size").split())
            elif shape.tag == "cylinder":
                dims = (float(shape.get("radius")), float(shape.get("length")))
            else:
                dims = (float(shape.get("radius")),)
            rgba = _GREY
            mat = vis.find("material")
            if mat is not None:
                colour = mat.find("color")
                if colour is None and mat.get("name") in named:
                    colour = named[mat.get("name")].find("color")
                if colour is not None:
                    rgba = tuple(float(v) for v in colour.get("rgba").split())
            visuals.append(_Visual(link.get("name"), k, shape.tag, dims, _rpy_matrix(xyz, rpy), rgba))
    return visuals


def _visual_geometry(visual: _Visual) -> tuple["mg.Geometry", np.ndarray]:
    """Meshcat geometry of a URDF visual and its placement in the link frame."""
    if visual.kind == "box":
        return mg.Box(list(visual.dims)), visual.link_T_visual
    if visual.kind == "cylinder":
        return mg.Cylinder(visual.dims[1], visual.dims[0]), visual.link_T_visual @ _CYLINDER_TO_Z
    return mg.Sphere(visual.dims[0]), visual.link_T_visual


class _UrdfKinematics:
    """World placement of every link frame of a URDF from named joint positions (Pinocchio, built once)."""

    def __init__(self, path: str | Path) -> None:
        import pinocchio as pin

        self._pin = pin
        self.model = pin.buildModelFromUrdf(str(path))
        self.data = self.model.createData()
        self.q = pin.neutral(self.model)
        self.links = [f.name for f in self.model.frames if f.type == pin.BODY]
        self.frame_ids = {name: self.model.getFrameId(name, pin.BODY) for name in self.links}

    def joint_slots(self, names: Sequence[str]) -> list[int]:
        """Index into ``q`` of each named single-dof joint."""
        slots = []
        for name in names:
            if not self.model.existJointName(name):
                raise ValueError(f"joint {name!r} is not in the URDF model")
            slots.append(self.model.joints[self.model.getJointId(name)].idx_q)
        return slots

    def link_poses(self, q: np.ndarray, world_T_base: np.ndarray) -> dict[str, np.ndarray]:
        """World placement (4, 4) of every link frame for configuration ``q``."""
        self._pin.framesForwardKinematics(self.model, self.data, q)
        return {name: world_T_base @ self.data.oMf[fid].homogeneous for name, fid in self.frame_ids.items()}


class _PlaneGeometry(mg.Geometry if meshcat is not None else object):
    """three.js PlaneGeometry (meshcat-python 0.3.2 has no class for it): a w x h rectangle, normal +z."""

    def __init__(self, width_m: float, height_m: float) -> None:
        super().__init__()
        self.width_m = width_m
        self.height_m = height_m

    def lower(self, object_data: dict) -> dict:
        return {"uuid": self.uuid, "type": "PlaneGeometry", "width": self.width_m, "height": self.height_m}


def _text_material(text: str, font_size_px: int = 64) -> "mg.MeshBasicMaterial":
    """A transparent material with ``text`` drawn by the viewer on a 256 x 256 canvas (Meshcat's ``_text``)."""
    texture = mg.GenericTexture({"type": "_text", "text": str(text), "font_size": font_size_px,
                                 "font_face": "sans-serif"})
    return mg.MeshBasicMaterial(map=texture, transparent=True, opacity=1.0)


# --------------------------------------------------------------------------------------------------------------
# The scene tree, kept in memory, optionally mirrored to a live server

class _Node:
    __slots__ = ("children", "object", "transform", "properties")

    def __init__(self) -> None:
        self.children: dict[str, _Node] = {}
        self.object: bytes | None = None
        self.transform: bytes | None = None
        self.properties: dict[str, bytes] = {}


def _pack_str(text: str) -> bytes:
    raw = text.encode("utf-8")
    if len(raw) < 32:
        return bytes((0xA0 | len(raw),)) + raw
    if len(raw) < 256:
        return b"\xd9" + bytes((len(raw),)) + raw
    return b"\xda" + struct.pack(">H", len(raw)) + raw


_PACKED_MATRIX = struct.Struct(">" + "Bd" * 16)
_BATCH_HEADER = struct.Struct(">III")
"""A batch for the server is one frame of records: lengths of (type, path, data), then the three."""


def _unpack_batch(payload: bytes) -> Iterator[list[bytes]]:
    offset = 0
    while offset < len(payload):
        n_kind, n_path, n_data = _BATCH_HEADER.unpack_from(payload, offset)
        offset += _BATCH_HEADER.size
        kind = payload[offset:offset + n_kind]
        path = payload[offset + n_kind:offset + n_kind + n_path]
        data = payload[offset + n_kind + n_path:offset + n_kind + n_path + n_data]
        offset += n_kind + n_path + n_data
        yield [kind, path, data]


def _pack_set_transform(path: str, matrix: np.ndarray) -> bytes:
    """``umsgpack.packb(SetTransform(matrix, path).lower())``, byte for byte, without its per-value overhead
    (the hot command: ~25 per drawn frame)."""
    values = [0xCB if i % 2 == 0 else 0.0 for i in range(32)]
    values[1::2] = matrix.T.reshape(16).tolist()                # column-major, as three.js wants it
    return (b"\x83" + _pack_str("type") + _pack_str("set_transform") + _pack_str("path") + _pack_str(path)
            + _pack_str("matrix") + b"\xdc\x00\x10" + _PACKED_MATRIX.pack(*values))


class _TreeWindow:
    """Stands in for meshcat's ``ViewerWindow``: keeps the scene tree (as packed commands) so a static page can
    be written without a server, and queues each command that changes something for the live server, which
    gets them in one message per :meth:`flush` (one ZMQ round trip per drawn frame)."""

    def __init__(self) -> None:
        self.root = _Node()
        self.zmq_socket = None
        self._zmq_address: tuple[str, float] | None = None
        self.lost_reason: str | None = None
        self.pending: list[tuple[bytes, bytes, bytes]] = []
        self.forwarded = 0

    def connect(self, zmq_url: str, timeout_s: float = 3.0) -> None:
        self._zmq_address = (zmq_url, timeout_s)
        socket = zmq.Context.instance().socket(zmq.REQ)
        socket.setsockopt(zmq.LINGER, 0)
        socket.setsockopt(zmq.RCVTIMEO, int(timeout_s * 1000))
        socket.setsockopt(zmq.SNDTIMEO, int(timeout_s * 1000))
        socket.connect(zmq_url)
        self.zmq_socket = socket

    def close(self) -> None:
        self.pending.clear()
        if self.zmq_socket is not None:
            self.zmq_socket.close(linger=0)
            self.zmq_socket = None

    def _find(self, entries: Sequence[str]) -> _Node:
        node = self.root
        for name in entries:
            node = node.children.setdefault(name, _Node())
        return node

    def send(self, command: Any) -> None:
        """meshcat's window interface (``Visualizer`` calls it): keep and queue one command."""
        data = command.lower()
        self.apply(data["type"], data["path"], umsgpack.packb(data), data.get("property"))

    def set_transform(self, path: str, matrix: np.ndarray) -> None:
        self.apply("set_transform", path, _pack_set_transform(path, matrix))

    def apply(self, kind: str, path: str, packed: bytes, prop: str | None = None) -> None:
        entries = [e for e in path.split("/") if e]
        if kind == "delete":
            if entries:
                self._find(entries[:-1]).children.pop(entries[-1], None)
            else:
                self.root = _Node()
        else:
            node = self._find(entries)
            if kind == "set_object":
                node.object = packed
                node.properties = {}
            elif kind == "set_transform":
                if node.transform == packed:
                    return
                node.transform = packed
            elif kind == "set_property":
                if node.properties.get(prop) == packed:
                    return
                node.properties[prop] = packed
            else:
                raise ValueError(f"command {kind!r} is not kept in the scene tree")
        if self.zmq_socket is not None:
            self.pending.append((kind.encode(), path.encode(), packed))

    def flush(self) -> None:
        """Send the queued commands to the live server in one batch (see ``_serve``)."""
        if self.zmq_socket is None or not self.pending:
            self.pending.clear()
            return
        payload = b"".join(_BATCH_HEADER.pack(len(kind), len(path), len(data)) + kind + path + data
                           for kind, path, data in self.pending)
        try:
            self.zmq_socket.send_multipart([b"batch", payload])
            self.zmq_socket.recv()
            self.forwarded += len(self.pending)
        except zmq.ZMQError as exc:
            self.lost_reason = f"the Meshcat server stopped answering ({exc})"
            self.close()
        except BaseException:  # interrupted between request and reply (Ctrl-C): a REQ socket then refuses the
            self.close()       # next request, so start a fresh one for the final frame
            self.connect(*self._zmq_address)
            raise
        finally:
            self.pending.clear()

    def commands(self) -> Iterator[bytes]:
        """Every command that rebuilds the current scene, parents before children."""
        stack = [self.root]
        while stack:
            node = stack.pop()
            if node.object is not None:
                yield node.object
            yield from node.properties.values()
            if node.transform is not None:
                yield node.transform
            stack.extend(reversed(list(node.children.values())))

    def static_html(self, extra_commands: Sequence[bytes] = ()) -> str:
        """A self-contained page: Meshcat's viewer script and every command, applied in order when it loads."""
        js = (Path(VIEWER_ROOT) / "main.min.js").read_text(encoding="utf-8")
        encoded = ",\n".join(f'"{base64.b64encode(c).decode("ascii")}"'
                             for c in [*self.commands(), *extra_commands])
        return _PAGE.format(mainminjs=js, commands=encoded)


_PAGE = """<!DOCTYPE html>
<html>
<head><meta charset="utf-8"><title>robotdemo - Meshcat replay</title>
<style>body {{ margin: 0; }} #meshcat-pane {{ width: 100vw; height: 100vh; overflow: hidden; }}</style>
</head>
<body>
<div id="meshcat-pane"></div>
<script>
{mainminjs}
</script>
<script>
var viewer = new MeshCat.Viewer(document.getElementById("meshcat-pane"));
(function () {{
  // Commands are applied synchronously, in order (objects before the animation that targets them).
  var commands = [
{commands}
  ];
  for (var i = 0; i < commands.length; i++) {{
    var raw = atob(commands[i]);
    var bytes = new Uint8Array(raw.length);
    for (var j = 0; j < raw.length; j++) bytes[j] = raw.charCodeAt(j);
    viewer.handle_command_bytearray(bytes);
  }}
}})();
</script>
</body>
</html>
"""


# --------------------------------------------------------------------------------------------------------------
# Recording: keyframes per (path, property), written as a meshcat Animation

class _Track:
    """Keyframes of one animated property; a value held over many frames is stored as its two ends only."""

    __slots__ = ("jstype", "frames", "values", "last_frame", "last_value")

    def __init__(self, jstype: str) -> None:
        self.jstype = jstype
        self.frames: list[int] = []
        self.values: list[Any] = []
        self.last_frame = -1
        self.last_value: Any = None

    def add(self, frame: int, value: Any) -> None:
        if self.frames and value == self.last_value:
            self.last_frame = frame
            return
        if self.frames and frame == self.frames[-1]:    # redrawn within the same frame: keep the newest
            self.values[-1] = value
            self.last_value = value
            return
        if self.frames and self.last_frame > self.frames[-1]:
            self.frames.append(self.last_frame)       # hold the old value until just before the change
            self.values.append(self.last_value)
        self.frames.append(frame)
        self.values.append(value)
        self.last_frame, self.last_value = frame, value

    def keys(self) -> tuple[list[int], list[Any]]:
        if self.frames and self.last_frame > self.frames[-1]:
            return self.frames + [self.last_frame], self.values + [self.last_value]
        return list(self.frames), list(self.values)


class _Recording:
    def __init__(self, fps: float) -> None:
        self.fps = fps
        self.start_time_s: float | None = None
        self.frame = -1
        self.tracks: dict[tuple[tuple[str, ...], str], _Track] = {}

    def frame_at(self, time_s: float) -> int:
        if self.start_time_s is None:
            return 0
        return int(math.floor((time_s - self.start_time_s) * self.fps + 1e-6))

    def begin_frame(self, time_s: float) -> None:
        if self.start_time_s is None:
            self.start_time_s = time_s
        self.frame = max(self.frame, self.frame_at(time_s))

    def add(self, path: tuple[str, ...], prop: str, jstype: str, value: Any, initial: Any = None) -> None:
        """Keyframe ``value`` at the current frame; a track that starts late first holds ``initial`` from 0."""
        key = (path, prop)
        track = self.tracks.get(key)
        if track is None:
            track = self.tracks[key] = _Track(jstype)
            if initial is not None and self.frame > 0:
                track.add(0, initial)
        track.add(self.frame, value)

    def add_transform(self, path: tuple[str, ...], T: np.ndarray) -> None:
        self.add(path, "position", "vector3", [round(float(v), 5) for v in T[:3, 3]])
        self.add(path, "quaternion", "quaternion", _quaternion_xyzw(T[:3, :3]))

    @property
    def n_frames(self) -> int:
        return self.frame + 1 if self.start_time_s is not None else 0

    def animation(self) -> "Animation":
        fps = int(round(self.fps)) if abs(self.fps - round(self.fps)) < 1e-9 else self.fps
        anim = Animation(default_framerate=fps)
        for (path, prop), track in self.tracks.items():
            clip = anim.clips.setdefault(MeshcatPath(path), AnimationClip(fps=fps))
            frames, values = track.keys()
            clip.tracks[prop] = AnimationTrack(prop, track.jstype, frames, values)
        return anim


# --------------------------------------------------------------------------------------------------------------
# The live server, in a child process

_CHILD_CODE = "import sys; from robotdemo.viewer import _serve; _serve(sys.argv[1], sys.argv[2], int(sys.argv[3]))"


class _ServerProcess:
    """Meshcat's ZMQ/websocket bridge in a child process, web port bound to ``host`` only."""

    def __init__(self, host: str, port: int | None, timeout_s: float) -> None:
        package_root = str(Path(__file__).resolve().parent.parent)
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (package_root, env.get("PYTHONPATH", "")) if p)
        self.log = tempfile.TemporaryFile()
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-u", "-c", _CHILD_CODE, host, "auto" if port is None else str(port), str(os.getpid())],
                stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=self.log, env=env,
                start_new_session=True)  # a terminal's Ctrl-C reaches the demo, which then stops the server itself
        except OSError as exc:
            self.log.close()
            raise ViewerUnavailable(f"cannot start the Meshcat server process ({exc})") from None
        self._finalizer = weakref.finalize(self, _ServerProcess._stop, self.proc, self.log)
        try:
            urls = self._read_urls(timeout_s)
        except ViewerUnavailable:
            self.close()
            raise
        self.zmq_url, self.web_url = urls["zmq_url"], urls["web_url"]
        self.pid = self.proc.pid

    def _read_urls(self, timeout_s: float) -> dict[str, str]:
        urls: dict[str, str] = {}
        deadline = time.monotonic() + timeout_s
        buffer = b""
        with selectors.DefaultSelector() as sel:
            sel.register(self.proc.stdout, selectors.EVENT_READ)
            while len(urls) < 2:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise ViewerUnavailable(f"the Meshcat server did not start within {timeout_s:.0f} s"
                                            + self._log_tail())
                if not sel.select(remaining):
                    continue
                chunk = os.read(self.proc.stdout.fileno(), 4096)
                if not chunk:
                    self.proc.wait(timeout=5)
                    raise ViewerUnavailable(f"the Meshcat server exited (status {self.proc.returncode})"
                                            + self._log_tail())
                buffer += chunk
                *lines, buffer = buffer.split(b"\n")
                for line in lines:
                    key, _, value = line.decode("utf-8", "replace").strip().partition("=")
                    if key == "error":
                        raise ViewerUnavailable(f"the Meshcat server could not start: {value}")
                    if key in ("zmq_url", "web_url"):
                        urls[key] = value
        return urls

    def _log_tail(self) -> str:
        self.log.seek(0)
        lines = [ln for ln in self.log.read().decode("utf-8", "replace").splitlines() if ln.strip()]
        return f": {lines[-1].strip()}" if lines else ""

    @property
    def running(self) -> bool:
        return self.proc.poll() is None

    def close(self) -> None:
        self._finalizer()

    @staticmethod
    def _stop(proc: subprocess.Popen, log: Any) -> None:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()
        log.close()


def _serve(host: str, port: str, parent_pid: int) -> None:
    """Child-process entry point: run Meshcat's bridge with the web port on ``host`` and ZMQ on loopback.

    Prints ``zmq_url=...`` and ``web_url=...`` once listening; exits when the parent process is gone.
    """
    import asyncio

    import tornado.ioloop
    from meshcat.servers.zmqserver import ZMQWebSocketBridge, find_node

    class _NoReply:
        def send(self, *args: Any, **kwargs: Any) -> None:
            pass

    class LoopbackBridge(ZMQWebSocketBridge):
        def make_app(self):
            app = super().make_app()
            listen = app.listen

            def listen_on_host(port: int, address: str | None = None, **kwargs: Any):
                # meshcat's own bridge calls app.listen(port) with no address: every interface.
                return listen(port, address=self.host, **kwargs)

            app.listen = listen_on_host
            return app

        def setup_zmq(self, url: str):
            sock, stream, _ = super().setup_zmq(url)
            return sock, stream, sock.getsockopt_string(zmq.LAST_ENDPOINT)

        def handle_zmq(self, frames):
            if frames[0] == b"batch" and len(frames) == 2:     # many commands, one reply
                reply_socket, self.zmq_socket = self.zmq_socket, _NoReply()
                try:
                    for command in _unpack_batch(frames[1]):
                        self.handle_zmq(command)
                finally:
                    self.zmq_socket = reply_socket
                reply_socket.send(b"ok")
                return
            # meshcat's tree appends every set_property; keep only the latest value per property.
            if len(frames) == 3 and frames[0] == b"set_property":
                path = [p for p in frames[1].decode("utf-8").split("/") if p]
                key = umsgpack.unpackb(frames[2])["property"]
                node = find_node(self.tree, path)
                node.properties = [p for p in node.properties if umsgpack.unpackb(p)["property"] != key]
            super().handle_zmq(frames)

    async def main() -> None:
        kwargs = {"zmq_url": f"tcp://{LOOPBACK}:*", "host": host}
        if port != "auto":
            kwargs["port"] = int(port)
        try:
            with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
                probe.bind((host, 0))     # a clear message for an address this machine does not have
            bridge = LoopbackBridge(**kwargs)
            if ":" in host:                # an IPv6 address goes in brackets in a URL
                bridge.web_url = f"http://[{host}]:{bridge.fileserver_port}/static/"
        except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises ViewerUnavailable
            print(f"error=cannot serve on {host}:{port}: {exc}", flush=True)
            os._exit(1)
        print(f"zmq_url={bridge.zmq_url}", flush=True)
        print(f"web_url={bridge.web_url}", flush=True)

        def exit_if_orphaned() -> None:
            if os.getppid() != parent_pid:
                os._exit(0)

        tornado.ioloop.PeriodicCallback(exit_if_orphaned, 500).start()
        await asyncio.Event().wait()

    try:
        asyncio.run(main())
    except KeyboardInterrupt:
        pass


# --------------------------------------------------------------------------------------------------------------
# The viewer

HEATMAP_ROWS = 4
HEATMAP_COLS = 4
HEATMAP_CELL_M = 0.016
HEATMAP_GAP_M = 0.002


class SceneViewer:
    """Mirrors a robotdemo :class:`~robotdemo.scene.Scene` in Meshcat, live and/or recorded.

    Example::

        with SceneViewer(ViewerConfig(record=True)) as viewer:   # serves http://127.0.0.1:7000/static/
            print("viewer at", viewer.url)
            for tick in ...:
                scene.sim.step()
                viewer.update(scene, taxel_normal_n=normals, labels={"object0_oak": "wood"})
            viewer.write_html("run.html")

    Raises:
        ViewerUnavailable: from the constructor, when the live server cannot be started.
    """

    def __init__(self, config: ViewerConfig = ViewerConfig()) -> None:
        if _MESHCAT_IMPORT_ERROR is not None:
            raise ViewerUnavailable(f"meshcat is not importable ({_MESHCAT_IMPORT_ERROR})")
        self.config = config
        self._window = _TreeWindow()
        self._vis = meshcat.Visualizer(window=self._window)
        self._server: _ServerProcess | None = None
        self._recording = _Recording(config.record_fps) if config.record else None
        self._kinematics: dict[str, _UrdfKinematics] = {}
        self._scene_ref: weakref.ref | None = None     # the scene drawn (weak: the caller owns it)
        self._last_live_t = -math.inf
        self._last_clock_t = -math.inf
        self._labels_shown: dict[str, str] = {}      # object name -> label node currently visible
        self._label_nodes: dict[str, set[str]] = {}  # object name -> every label node created
        self._taxels = np.zeros((HEATMAP_ROWS, HEATMAP_COLS))
        self._taxel_rgb: dict[tuple[int, int], list[float]] = {}   # colour last sent per cell
        self.frames_drawn = 0
        self._warned_lost = False
        if config.live:
            if not is_loopback(config.host):
                print(f"robotdemo: warning: the Meshcat viewer listens on {config.host} (not loopback): anyone who "
                      f"can reach this machine can watch the scene; its command port stays on {LOOPBACK}",
                      file=sys.stderr)
            try:
                ipaddress.ip_address(config.host)
            except ValueError:
                if config.host != "localhost":
                    raise ViewerUnavailable(f"--meshcat-host {config.host!r} is not an IP address") from None
            self._server = _ServerProcess(config.host, config.port, config.start_timeout_s)
            try:
                self._window.connect(self._server.zmq_url)
            except zmq.ZMQError as exc:
                self.close()
                raise ViewerUnavailable(f"cannot connect to the Meshcat server ({exc})") from None
        self._draw_environment_defaults()
        self._window.flush()

    # -- public ---------------------------------------------------------------------------------------------
    @property
    def url(self) -> str | None:
        """The live page's address (``http://127.0.0.1:7000/static/``), or ``None`` without a live server."""
        return self._server.web_url if self._server is not None else None

    @property
    def server_pid(self) -> int | None:
        return self._server.pid if self._server is not None else None

    @property
    def recording(self) -> bool:
        return self._recording is not None

    @property
    def recorded_frames(self) -> int:
        return self._recording.n_frames if self._recording is not None else 0

    def update(self, scene: Any, taxel_normal_n: np.ndarray | Callable[[], np.ndarray | None] | None = None,
               labels: Mapping[str, str] | None = None, force: bool = False) -> bool:
        """Mirror the scene's current state; cheap to call every control tick (it throttles itself).

        Args:
            scene: a :class:`~robotdemo.scene.Scene` (reads ``robot``, ``objects``, ``zones``, ``sim.time_s``).
            taxel_normal_n: the 16 normal forces of the tactile pad (N), taxel order (16,) or (4, 4);
                ``None`` keeps the last values; a callable returning them is called only when a frame is
                drawn (the demo's taxel forces are too costly to compute every control tick).
            labels: predicted label per object name, for the objects classified so far.
            force: draw now whatever the rate limit says (e.g. the final state before :meth:`write_html`).

        Returns:
            Whether a frame was drawn (live or recorded).
        """
        if not callable(taxel_normal_n):
            self._set_taxels(taxel_normal_n)
        new_scene = self._scene_ref is None or self._scene_ref() is not scene
        if new_scene:                           # build it (a recording covers one scene), draw at once
            self._build_scene(scene)
        sim_t = float(scene.sim.time_s)
        clock_t = sim_t if self.config.clock == "sim" else time.monotonic()
        if clock_t < self._last_clock_t:        # a rewound clock: draw at once
            self._last_live_t = -math.inf
        self._last_clock_t = clock_t
        live_due = self._window.zmq_socket is not None and clock_t - self._last_live_t >= 1.0 / self.config.rate_hz - 1e-9
        rec = self._recording
        rec_due = rec is not None and (rec.start_time_s is None or rec.frame_at(sim_t) > rec.frame)
        if not (force or new_scene or live_due or rec_due):
            return False
        if callable(taxel_normal_n):
            self._set_taxels(taxel_normal_n())
        if rec is not None:
            rec.begin_frame(sim_t)
        self._draw(scene, labels or {}, rec)
        self._window.flush()
        self._last_live_t = clock_t
        self.frames_drawn += 1
        if self._window.lost_reason and not self._warned_lost:
            self._warned_lost = True
            print(f"robotdemo: warning: {self._window.lost_reason}; the live view stops here", file=sys.stderr)
        return True

    def static_html(self) -> str:
        """The current scene (and the recorded animation, when recording) as one self-contained HTML page."""
        extra = []
        if self._recording is not None and self._recording.n_frames > 1:
            anim = SetAnimation(self._recording.animation(), play=True, repetitions=1)
            extra.append(umsgpack.packb(anim.lower()))
        return self._window.static_html(extra)

    def write_html(self, path: str | Path) -> Path:
        """Write :meth:`static_html` to ``path`` atomically (a temporary file in the same folder, renamed).

        Raises:
            ValueError: nothing has been drawn yet (call :meth:`update` first).
        """
        if self._scene_ref is None:
            raise ValueError("the viewer has drawn no scene yet: call update(scene) before write_html")
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        html = self.static_html()
        return atomic_write_text(path, html)

    def close(self) -> None:
        """Stop the live server process and drop the connection (idempotent)."""
        self._window.close()
        if self._server is not None:
            self._server.close()

    def __enter__(self) -> "SceneViewer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- drawing --------------------------------------------------------------------------------------------
    def _draw_environment_defaults(self) -> None:
        # Meshcat's orbit controls always look at the page's origin: shift the whole scene so that the camera
        # target sits there, instead of moving the camera (whose look-at would still aim at the origin).
        self._vis.set_transform(_translation(-np.asarray(self.config.camera_target_m, dtype=float)))
        dx, dy, dz = self.config.camera_offset_m
        # The camera node's frame is three.js y-up: world (x, y, z) -> (x, z, -y).
        self._vis["/Cameras/default/rotated/<object>"].set_property("position", [float(dx), float(dz), float(-dy)])
        self._vis["/Grid"].set_property("visible", False)      # the floor is drawn from its URDF instead
        self._vis["/Axes"].set_property("visible", False)

    def _kinematics_for(self, urdf: str | Path) -> _UrdfKinematics:
        key = str(urdf)
        if key not in self._kinematics:
            self._kinematics[key] = _UrdfKinematics(urdf)
        return self._kinematics[key]

    def _build_scene(self, scene: Any) -> None:
        """Create every object of a scene (once per scene; a new scene replaces the old one)."""
        from robotdemo.assets import ARM_JOINTS, FLOOR_URDF, GRIPPER_JOINTS, TABLE_URDF, ZONE_URDFS, urdf_path

        vis = self._vis
        for top in ("robot", "floor", "table", "zones", "objects", "labels", "taxels"):
            vis[top].delete()
        self._labels_shown.clear()
        self._label_nodes.clear()
        self._taxel_rgb.clear()
        if self._recording is not None and self._recording.n_frames:
            self._recording = _Recording(self.config.record_fps)   # a recording covers one scene
        self._last_live_t = self._last_clock_t = -math.inf
        robot = scene.robot
        self._robot_kin = self._kinematics_for(robot.urdf)
        self._arm_slots = self._robot_kin.joint_slots(ARM_JOINTS)
        self._gripper_slots = self._robot_kin.joint_slots(GRIPPER_JOINTS)
        self._world_T_base = np.eye(4)
        self._world_T_base[:3, :3] = np.asarray(robot.base_rotation, dtype=float)
        self._world_T_base[:3, 3] = np.asarray(robot.base_position_m, dtype=float)
        self._robot_links = sorted({v.link for v in urdf_visuals(robot.urdf)})
        for visual in urdf_visuals(robot.urdf):
            geometry, link_T = _visual_geometry(visual)
            node = vis[f"robot/{visual.link}/visual{visual.index}"]
            node.set_object(geometry, mg.MeshPhongMaterial(color=_hex_colour(visual.rgba), opacity=visual.rgba[3]))
            node.set_transform(link_T)

        self._draw_static_urdf("floor", urdf_path(FLOOR_URDF), np.eye(4))
        self._draw_static_urdf("table", urdf_path(TABLE_URDF), np.eye(4))
        top_z = float(scene.table_top_z_m)
        for zone in scene.zones:
            world_T_zone = _translation((*zone.center_xy_m, top_z))
            if zone.name in ZONE_URDFS:
                self._draw_static_urdf(f"zones/{_safe_name(zone.name)}", urdf_path(ZONE_URDFS[zone.name]), world_T_zone)
            else:
                size = 2 * zone.half_size_m
                vis[f"zones/{_safe_name(zone.name)}/mat"].set_object(
                    mg.Box([size, size, 0.002]), mg.MeshPhongMaterial(color=0xd94033 if zone.combustible else 0x3366cc))
                vis[f"zones/{_safe_name(zone.name)}/mat"].set_transform(world_T_zone @ _translation((0, 0, 0.001)))
            text = vis[f"zones/{_safe_name(zone.name)}/name"]
            text.set_object(_PlaneGeometry(2 * zone.half_size_m, 2 * zone.half_size_m), _text_material(zone.name, 40))
            text.set_transform(world_T_zone @ _translation((0, 0, 0.0035)) @ _rotation_xyz("z", math.pi / 2))

        for obj in scene.objects:
            sx, sy, sz = (float(s) for s in obj.spec.size_m)
            colour = object_rgba(obj)
            material = mg.MeshPhongMaterial(color=_hex_colour(colour), opacity=float(colour[3]) if len(colour) > 3 else 1.0)
            node = vis[f"objects/{_safe_name(obj.name)}/shape"]
            if obj.spec.shape == "cylinder":
                node.set_object(mg.Cylinder(sz, 0.5 * sx), material)
                node.set_transform(_CYLINDER_TO_Z)
            else:
                node.set_object(mg.Box([sx, sy, sz]), material)

        panel = HEATMAP_COLS * HEATMAP_CELL_M + (HEATMAP_COLS + 1) * HEATMAP_GAP_M
        vis["taxels/backing"].set_object(mg.Box([panel, panel, 0.002]), mg.MeshPhongMaterial(color=0x202020))
        vis["taxels/backing"].set_transform(_translation((0, 0, -0.002)))
        vis["taxels/title"].set_object(_PlaneGeometry(panel * 1.6, panel * 1.6), _text_material("taxels (N)", 40))
        vis["taxels/title"].set_transform(_translation((0, 0.62 * panel, 0.001)))
        pitch = HEATMAP_CELL_M + HEATMAP_GAP_M
        for r in range(HEATMAP_ROWS):
            for c in range(HEATMAP_COLS):
                cell = vis[f"taxels/cell{r}{c}"]
                cell.set_object(mg.Box([HEATMAP_CELL_M, HEATMAP_CELL_M, 0.002]),
                                mg.MeshBasicMaterial(color=_hex_colour(_heat_rgb(0.0))))
                cell.set_transform(_translation(((c - (HEATMAP_COLS - 1) / 2) * pitch,
                                                 ((HEATMAP_ROWS - 1) / 2 - r) * pitch, 0.0)))
        self._scene_ref = weakref.ref(scene)

    def _draw_static_urdf(self, prefix: str, path: Path, world_T_root: np.ndarray) -> None:
        kin = self._kinematics_for(path)
        poses = kin.link_poses(kin.q, world_T_root)
        for visual in urdf_visuals(path):
            geometry, link_T = _visual_geometry(visual)
            node = self._vis[f"{prefix}/{visual.link}/visual{visual.index}"]
            node.set_object(geometry, mg.MeshPhongMaterial(color=_hex_colour(visual.rgba), opacity=visual.rgba[3]))
            node.set_transform(np.round(poses[visual.link] @ link_T, 6))

    def _set_transform(self, rel_path: str, T: np.ndarray, rec: _Recording | None) -> None:
        T = np.round(T, 6)
        self._window.set_transform(f"/meshcat/{rel_path}", T)
        if rec is not None:
            rec.add_transform(("meshcat", *rel_path.split("/")), T)

    def _set_taxels(self, taxel_normal_n: np.ndarray | None) -> None:
        if taxel_normal_n is None:
            return
        values = np.asarray(taxel_normal_n, dtype=float)
        if values.size != HEATMAP_ROWS * HEATMAP_COLS:
            raise ValueError(f"taxel_normal_n must hold {HEATMAP_ROWS * HEATMAP_COLS} values, got shape {values.shape}")
        self._taxels = values.reshape(HEATMAP_ROWS, HEATMAP_COLS)

    def _draw(self, scene: Any, labels: Mapping[str, str], rec: _Recording | None) -> None:
        robot = scene.robot
        kin = self._robot_kin
        q = kin.q.copy()
        q[self._arm_slots] = robot.arm_q()
        q[self._gripper_slots] = robot.gripper_q()
        poses = kin.link_poses(q, self._world_T_base)
        for link in self._robot_links:
            self._set_transform(f"robot/{link}", poses[link], rec)

        object_poses = {}
        for obj in scene.objects:
            position, quaternion = scene.object_pose(obj)
            object_poses[obj.name] = _pose_matrix(position, quaternion)
            self._set_transform(f"objects/{_safe_name(obj.name)}", object_poses[obj.name], rec)

        self._draw_labels(scene, labels, object_poses, rec)

        pad = poses.get("pad_center", poses[self._robot_links[-1]])
        world_T_panel = _translation(pad[:3, 3] + np.asarray(self.config.heatmap_offset_m)) @ _FACING_CAMERA
        self._set_transform("taxels", world_T_panel, rec)
        for r in range(HEATMAP_ROWS):
            for c in range(HEATMAP_COLS):
                rgb = _heat_rgb(float(self._taxels[r, c]) / self.config.taxel_full_scale_n)
                if self._taxel_rgb.get((r, c)) != rgb:
                    self._taxel_rgb[(r, c)] = rgb
                    self._vis[f"taxels/cell{r}{c}"].set_property("color", [*rgb, 1.0])
                if rec is not None:
                    rec.add(("meshcat", "taxels", f"cell{r}{c}", "<object>"), "material.color", "color", rgb)

    def _draw_labels(self, scene: Any, labels: Mapping[str, str], object_poses: dict[str, np.ndarray],
                     rec: _Recording | None) -> None:
        by_name = {obj.name: obj for obj in scene.objects}
        for name, label in labels.items():
            if name not in by_name or label is None:
                continue
            label_node = _safe_name(label)
            base = f"labels/{_safe_name(name)}"
            if self._labels_shown.get(name) != label_node:
                nodes = self._label_nodes.setdefault(name, set())
                if label_node not in nodes:
                    nodes.add(label_node)
                    self._vis[f"{base}/{label_node}/text"].set_object(_PlaneGeometry(0.16, 0.16), _text_material(label))
                    self._vis[f"{base}/{label_node}/text"].set_transform(_translation((0, 0, 0.02)))
                    self._vis[f"{base}/{label_node}/plate"].set_object(
                        _PlaneGeometry(0.15, 0.045), mg.MeshBasicMaterial(color=0xffffff, opacity=0.75))
                    self._vis[f"{base}/{label_node}/plate"].set_transform(_translation((0, 0.02, -0.001)))
                    self._vis[f"{base}/{label_node}/marker"].set_object(
                        mg.Sphere(0.008), mg.MeshPhongMaterial(color=_hex_colour(category_rgba(label))))
                    self._vis[f"{base}/{label_node}/marker"].set_transform(_translation((-0.065, 0.02, 0.0)))
                for other in nodes:
                    self._vis[f"{base}/{other}"].set_property("visible", other == label_node)
                self._labels_shown[name] = label_node
            height = float(by_name[name].spec.size_m[2])
            position = object_poses[name][:3, 3] + np.array([0.0, 0.0, 0.5 * height + 0.03])
            self._set_transform(base, _translation(position) @ _FACING_CAMERA, rec)
        if rec is not None:
            for name, nodes in self._label_nodes.items():
                for node in nodes:
                    rec.add(("meshcat", "labels", _safe_name(name), node), "visible", "boolean",
                            node == self._labels_shown.get(name), initial=False)


class Recorder(SceneViewer):
    """A :class:`SceneViewer` that only records (no server): ``update`` every tick, then ``write_html``."""

    def __init__(self, fps: float = 25.0, config: ViewerConfig = ViewerConfig()) -> None:
        super().__init__(replace(config, live=False, record=True, record_fps=fps))


# --------------------------------------------------------------------------------------------------------------
# Command-line helpers (the CLI parses once at the edge and calls these)

def add_viewer_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--meshcat``, ``--meshcat-host``, ``--meshcat-port``, ``--viewer-rate`` and ``--record-html``."""
    group = parser.add_argument_group("viewer (Meshcat)")
    group.add_argument("--meshcat", action="store_true",
                       help="show the scene live in a browser (Meshcat, served on 127.0.0.1)")
    group.add_argument("--meshcat-host", metavar="ADDRESS", default=None,
                       help="serve the live view on ADDRESS instead of 127.0.0.1, e.g. 0.0.0.0: exposes it to the "
                            "network (a warning is printed); implies --meshcat")
    group.add_argument("--meshcat-port", metavar="PORT", type=int, default=None,
                       help="web port of the live view (default: first free from 7000)")
    group.add_argument("--viewer-rate", metavar="HZ", type=float, default=25.0,
                       help="live view and recording rate, per simulated second (default 25)")
    group.add_argument("--record-html", "--record", dest="record_html", metavar="PATH", type=Path, default=None,
                       help="write a self-contained HTML replay of the run (opens in a browser, no server)")


def viewer_config_from_args(args: argparse.Namespace) -> ViewerConfig | None:
    """The viewer the parsed arguments ask for, or ``None`` for none."""
    live = bool(args.meshcat or args.meshcat_host)
    record = args.record_html is not None
    if not (live or record):
        return None
    return ViewerConfig(live=live, host=args.meshcat_host or LOOPBACK, port=args.meshcat_port,
                        rate_hz=args.viewer_rate, record=record, record_fps=args.viewer_rate)


def start_viewer(config: ViewerConfig | None) -> SceneViewer | None:
    """Start the viewer, or go on without it: a live server that cannot start is reported on stderr, and a
    recording still goes ahead without the live view. Returns ``None`` when there is nothing to show."""
    if config is None:
        return None
    try:
        viewer = SceneViewer(config)
    except ViewerUnavailable as exc:
        if not config.record:
            print(f"robotdemo: warning: viewer unavailable ({exc}); running headless", file=sys.stderr)
            return None
        print(f"robotdemo: warning: live viewer unavailable ({exc}); recording only", file=sys.stderr)
        viewer = SceneViewer(replace(config, live=False))
    if viewer.url is not None:
        print(f"robotdemo: Meshcat viewer at {viewer.url}", file=sys.stderr)
    return viewer
