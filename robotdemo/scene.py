"""The sorting scene: floor, table, the robot on the table, two collection zones and N objects.

Objects are boxes, cylinders and slabs of varied sizes, placed without overlap inside the arm's reach, each
with a material drawn from :mod:`perception.materials` whose physical parameters set PyBullet's dynamics.
Everything is drawn from one seeded generator, so the same seed gives the same scene.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from perception.materials import (ContactDynamics, MaterialCatalogue, MaterialSample, contact_dynamics,
                                  load_catalogue, sample_material)
from robotdemo.assets import FLOOR_URDF, TABLE_URDF, ZONE_URDFS, urdf_path
from robotdemo.robot import Robot
from robotdemo.sim import SimConfig, Simulator

SHAPES = ("box", "cylinder", "slab")

CATEGORY_RGBA: dict[str, tuple[float, float, float, float]] = {
    "metal": (0.72, 0.74, 0.78, 1.0), "stone": (0.50, 0.50, 0.47, 1.0), "paper": (0.95, 0.93, 0.85, 1.0),
    "polymer": (0.20, 0.60, 0.85, 1.0), "rubber": (0.12, 0.12, 0.12, 1.0), "textiles": (0.70, 0.35, 0.60, 1.0),
    "wood": (0.65, 0.45, 0.25, 1.0),
}
"""Display colours by category (for people watching; nothing the robot senses depends on them)."""


@dataclass(frozen=True)
class Zone:
    """A square collection zone on the table top (world frame)."""

    name: str
    combustible: bool
    center_xy_m: tuple[float, float]
    half_size_m: float

    def contains(self, xy_m: Sequence[float]) -> bool:
        return (abs(xy_m[0] - self.center_xy_m[0]) <= self.half_size_m
                and abs(xy_m[1] - self.center_xy_m[1]) <= self.half_size_m)


@dataclass(frozen=True)
class SceneConfig:
    """What to build.

    Attributes:
        n_objects: number of objects on the table.
        seed: seeds the layout, the shapes, sizes and materials.
        categories: restrict materials to these categories (``None``: all seven).
        object_region_m: (x_min, x_max, y_min, y_max) of object centres, world frame.
        min_gap_m: clearance between the footprints of two objects.
        max_reach_m: largest horizontal distance of an object's centre from the robot base (the pad, pointing
            down, reaches about 0.40 m at 0.12 m above the table; the margin leaves room for the stroke).
        object_sleep_speed_mps: an object whose linear (m/s) and angular (rad/s) speeds stay below this for
            Bullet's deactivation time (2 s) falls asleep: the solver skips its contacts with the table until
            something touches it, which wakes it (a force alone does not). A scratch timing on a loaded
            machine: a fine step cost 0.35 ms with six resting objects, 0.21 ms with none. ``None``: never.
    """

    n_objects: int = 6
    seed: int = 0
    categories: tuple[str, ...] | None = None
    shapes: tuple[str, ...] = SHAPES
    table_height_m: float = 0.70
    robot_base_xy_m: tuple[float, float] = (-0.45, 0.0)
    robot_yaw_rad: float = math.pi
    object_region_m: tuple[float, float, float, float] = (-0.29, -0.10, -0.17, 0.17)
    max_reach_m: float = 0.36
    min_gap_m: float = 0.03
    zone_half_size_m: float = 0.11
    noncombustible_zone_xy_m: tuple[float, float] = (-0.30, 0.32)
    combustible_zone_xy_m: tuple[float, float] = (-0.30, -0.32)
    table_friction: float = 1.5
    settle_s: float = 0.3
    object_sleep_speed_mps: float | None = 0.005
    sim: SimConfig = field(default_factory=SimConfig)

    def __post_init__(self) -> None:
        if self.n_objects < 0:
            raise ValueError(f"n_objects must be >= 0, got {self.n_objects}")
        unknown = set(self.shapes) - set(SHAPES)
        if unknown:
            raise ValueError(f"unknown object shapes {sorted(unknown)}; expected some of {SHAPES}")


@dataclass(frozen=True)
class ObjectSpec:
    """An object before it is created: its shape, size (m: x, y, z full extents), pose and material."""

    name: str
    shape: str
    size_m: tuple[float, float, float]
    xy_m: tuple[float, float]
    yaw_rad: float
    material: MaterialSample
    dynamics: ContactDynamics

    @property
    def footprint_radius_m(self) -> float:
        return 0.5 * math.hypot(self.size_m[0], self.size_m[1])


@dataclass(frozen=True)
class SceneObject:
    """An object in the simulation."""

    body: int
    spec: ObjectSpec

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def category(self) -> str:
        return self.spec.material.category

    @property
    def instance(self) -> str:
        return self.spec.material.instance

    @property
    def combustible(self) -> bool:
        return self.spec.material.combustible


def body_shape(shape: str) -> str:
    """The solid a scene shape is for physics, contact and sound: ``"cylinder"``, or ``"box"`` (boxes, slabs)."""
    return "cylinder" if shape == "cylinder" else "box"


def draw_object_size(shape: str, rng: np.random.Generator) -> tuple[float, float, float]:
    """Full extents (x, y, z), m, of a ``box``, upright ``cylinder`` (diameter, diameter, height) or ``slab``."""
    if shape == "box":
        return (float(rng.uniform(0.04, 0.07)), float(rng.uniform(0.04, 0.07)), float(rng.uniform(0.035, 0.07)))
    if shape == "cylinder":
        d = float(rng.uniform(0.04, 0.07))
        return (d, d, float(rng.uniform(0.035, 0.07)))
    return (float(rng.uniform(0.06, 0.09)), float(rng.uniform(0.045, 0.065)), float(rng.uniform(0.02, 0.03)))


def plan_objects(config: SceneConfig, catalogue: MaterialCatalogue, rng: np.random.Generator) -> list[ObjectSpec]:
    """Draw shapes, sizes, materials and non-overlapping positions for ``config.n_objects`` objects."""
    instances = [inst for inst in catalogue.instances.values()
                 if config.categories is None or inst.category in config.categories]
    if not instances:
        raise ValueError(f"no material instance in categories {config.categories}")
    x0, x1, y0, y1 = config.object_region_m
    specs: list[ObjectSpec] = []
    for i in range(config.n_objects):
        shape = config.shapes[int(rng.integers(len(config.shapes)))]
        size = draw_object_size(shape, rng)
        material = sample_material(instances[int(rng.integers(len(instances)))], rng)
        yaw = float(rng.uniform(-math.pi / 4, math.pi / 4))
        specs.append(ObjectSpec(name=f"object{i}_{material.instance}", shape=shape, size_m=size, xy_m=(0.0, 0.0),
                                yaw_rad=yaw, material=material,
                                dynamics=contact_dynamics(material, size, body_shape(shape))))
    # Positions: whole layouts are drawn until one has every pair of footprints apart by min_gap_m.
    for _layout in range(200):
        placed: list[ObjectSpec] = []
        for spec in specs:
            for _attempt in range(100):
                xy = (float(rng.uniform(x0, x1)), float(rng.uniform(y0, y1)))
                if math.dist(xy, config.robot_base_xy_m) > config.max_reach_m:
                    continue
                if all(math.dist(xy, o.xy_m) >= spec.footprint_radius_m + o.footprint_radius_m + config.min_gap_m
                       for o in placed):
                    placed.append(replace(spec, xy_m=xy))
                    break
            else:
                break
        if len(placed) == len(specs):
            return placed
    raise ValueError(f"cannot place {config.n_objects} objects without overlap in region {config.object_region_m}")


class Scene:
    """A built scene; owns its :class:`Simulator` (close it, or use as a context manager)."""

    def __init__(self, config: SceneConfig, catalogue: MaterialCatalogue | None = None,
                 objects: Sequence[ObjectSpec] | None = None) -> None:
        """Build the scene; ``objects`` replaces the seeded draw of ``config.n_objects`` objects when given."""
        self.config = config
        self.catalogue = catalogue if catalogue is not None else load_catalogue()
        self.rng = np.random.default_rng(config.seed)
        self.sim = Simulator(config.sim)
        top = config.table_height_m
        self.floor = self.sim.load_urdf(urdf_path(FLOOR_URDF), fixed_base=True)
        self.table = self.sim.load_urdf(urdf_path(TABLE_URDF), fixed_base=True)
        # An anti-slip mat on the table top: objects stay put while the pad drags across them.
        self.sim.set_dynamics(self.table, -1, lateralFriction=config.table_friction)
        self.zones = (
            Zone("noncombustible", False, config.noncombustible_zone_xy_m, config.zone_half_size_m),
            Zone("combustible", True, config.combustible_zone_xy_m, config.zone_half_size_m),
        )
        self.zone_bodies = tuple(
            self.sim.load_urdf(urdf_path(ZONE_URDFS[zone.name]), (*zone.center_xy_m, top), fixed_base=True)
            for zone in self.zones)
        self.robot = Robot(self.sim, (*config.robot_base_xy_m, top), config.robot_yaw_rad)
        specs = plan_objects(config, self.catalogue, self.rng) if objects is None else list(objects)
        self.objects: list[SceneObject] = [self._create(spec) for spec in specs]
        self.sim.step(int(round(config.settle_s / config.sim.time_step_s)))
        self.sim.check_state_finite()

    def _create(self, spec: ObjectSpec) -> SceneObject:
        top = self.config.table_height_m
        half_yaw = 0.5 * spec.yaw_rad
        geom = body_shape(spec.shape)
        body = self.sim.create_primitive(geom, spec.size_m, spec.dynamics.mass_kg,
                                         (spec.xy_m[0], spec.xy_m[1], top + spec.size_m[2] / 2 + 0.0005),
                                         (0.0, 0.0, math.sin(half_yaw), math.cos(half_yaw)),
                                         CATEGORY_RGBA.get(spec.material.category, (0.8, 0.8, 0.8, 1.0)))
        d = spec.dynamics
        self.sim.set_dynamics(body, lateralFriction=d.lateral_friction, spinningFriction=d.spinning_friction,
                              rollingFriction=d.rolling_friction, restitution=d.restitution,
                              contactStiffness=d.contact_stiffness_n_per_m, contactDamping=d.contact_damping_n_s_per_m)
        if self.config.object_sleep_speed_mps is not None:
            self.sim.enable_sleeping(body, self.config.object_sleep_speed_mps)
        return SceneObject(body=body, spec=spec)

    def clamp(self, obj: SceneObject) -> None:
        """Fix ``obj`` where it rests, as a lab clamps a sample for stroking: a fixed joint to the world
        (:meth:`robotdemo.sim.Simulator.clamp_in_place`), and no more contact with the table, floor and zones,
        which would only push against the clamp. Those contacts cost the solver a fifth of a stroke step
        (0.41 vs 0.32 ms, scratch probe during a slide on steel), and with them the solver needed 100 iterations
        to hold the pad force (see ``DatasetConfig.solver_iterations``). Only the robot touches it afterwards."""
        self.sim.clamp_in_place(obj.body)
        for body in (self.floor, self.table, *self.zone_bodies):
            self.sim.disable_collisions(body, obj.body)

    # -- queries ----------------------------------------------------------------------------------------------
    @property
    def table_top_z_m(self) -> float:
        return self.config.table_height_m

    def object_pose(self, obj: SceneObject) -> tuple[np.ndarray, np.ndarray]:
        """World position (m) and orientation quaternion (x, y, z, w) of an object's centre."""
        return self.sim.base_pose(obj.body)

    def zone_of(self, obj: SceneObject) -> Zone | None:
        """The zone whose square contains the object's centre, if it rests on the table there."""
        pos, _ = self.object_pose(obj)
        if pos[2] > self.table_top_z_m + obj.spec.size_m[2]:  # lifted, not resting
            return None
        return next((z for z in self.zones if z.contains(pos[:2])), None)

    def zone_for(self, combustible: bool) -> Zone:
        return next(z for z in self.zones if z.combustible == combustible)

    def summary(self) -> list[dict]:
        """One JSON-ready row per object."""
        rows = []
        for obj in self.objects:
            pos, _ = self.object_pose(obj)
            rows.append({"name": obj.name, "shape": obj.spec.shape, "size_mm": [round(s * 1000, 1) for s in obj.spec.size_m],
                         "category": obj.category, "instance": obj.instance, "combustible": obj.combustible,
                         "mass_kg": round(obj.spec.dynamics.mass_kg, 4),
                         "position_m": [round(float(v), 4) for v in pos]})
        return rows

    def close(self) -> None:
        self.sim.close()

    def __enter__(self) -> "Scene":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
