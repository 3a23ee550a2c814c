"""The stroke data set: real strokes in PyBullet, shaped into the four sensor streams, written in shards.

One shard holds every stroke of one material instance: ``objects_per_instance`` physical objects of that
material (each with its own drawn parameters, size, pose and surface texture), each stroked several times with
randomised target force, speed, length, direction and start point. A shard's content depends only on the data
set's seed and the instance's index, so the data are identical whatever the number of workers, and a rerun
skips shards already written (each is written atomically, then recorded in the manifest, also atomically).

Layout (read by :func:`perception.dataset.load_dataset`)::

    DIR/manifest.json      {"format": "robotdemo-dataset", "version": 1, "env", "seed", "config",
                            "recorder_sha256", "numerics", "complete", "expected_shards",
                            "shards": [{"file", "n_strokes", "sha256", "instance", "failed_strokes",
                                        "failed_attempts": {reason: count}}]}
    DIR/shards/shard-00007-oak.npz   (perception.recording_io stroke file)
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import math
import multiprocessing as mp
import re
import time
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
from tqdm import tqdm

from controllers.stroke import StrokeConfig
from controllers.trajectory import TrajectoryError
from perception.atomic import atomic_write_json
from perception.contact_trace import ObjectInfo
from perception.materials import (Material, MaterialCatalogue, MaterialSample, contact_dynamics, default_catalogue,
                                  sample_material)
from perception.numerics import numeric_environment, numerics_differences
from perception.recording_io import write_strokes
from perception.streams import StrokeRecord
from perception.tactile import ENVIRONMENTS, emulate_stroke
from robotdemo.assets import all_urdfs, urdf_root
from robotdemo.errors import RobotDemoError, SimulationError
from robotdemo.motion import ArmMotion
from robotdemo.robot import GripperPosture
from robotdemo.scene import SHAPES, ObjectSpec, Scene, SceneConfig, body_shape, draw_object_size
from robotdemo.sim import SimConfig
from robotdemo.sorting import SortingConfig, plan_stroke, resting_geometry
from robotdemo.stroking import StrokeExecution, move_pad_above

FORMAT_NAME = "robotdemo-dataset"
FORMAT_VERSION = 1


@dataclass(frozen=True)
class DatasetConfig:
    """What to record.

    Attributes:
        strokes_per_instance: strokes recorded per material instance (one shard per instance).
        objects_per_instance: distinct physical objects per instance; strokes are spread over them. Many
            objects with few strokes each: the robot meets new objects, and a classifier trained on three
            objects per instance learnt those objects (62.6 % on held-out strokes, 52 % on the demo's objects).
        seed: seeds everything (objects, poses, stroke parameters, sensor noise).
        env: sensor environment profile, ``clean`` or ``fire``.
        categories: restrict to these categories (``None``: all seven).
        instances: restrict to these material instances (``None``: all of the chosen categories).
        force_range_n, speed_range_mps, length_range_m: stroke parameter ranges (uniform draws). Speeds start
            at 10 mm/s: the controller's shortest slide, 20 mm, took up to 4 s at the 5 mm/s of earlier data.
        max_slide_s: a drawn length is cut to what the drawn speed covers in this time (not below 20 mm), so a
            slow stroke is a short one (``None``: no cut). The robot's strokes last about a second; the slide
            was most of a recording's time (58 % of one shard's wall time with no cut, when slides of up to
            12 s were drawn).
        max_attempts_per_stroke: a stroke that fails (the object tipped, force never settled) is redrawn.
        solver_iterations: the physics solver's iterations per step while recording (every step mode). The
            sample is clamped and free of the table (:meth:`robotdemo.scene.Scene.clamp`), and the solver then
            holds the pad force with fewer than the 100 the robot's scene needs. 75 is the fewest from which
            every count up to 100 (in steps of 5) keeps the stroke test's cases (pine 2 N, cast iron 4 N, EPDM
            1 N) within its +-20 % on the clamped sample: the worst, pine's near the slide's end, is 1.05-1.18x
            the target from 75 up (1.16x at 100), 1.22x at 70 and 1.18-1.29x from 50 to 65 (``robotdemo bench
            stroke --clamped --solver-iterations 50,55,...,100``; ``tests/test_stroking.py`` checks 75). Over 6
            strokes on each of 7 instances (fire, seed 1, same draws, scratch) the slide force's p5-p95 was
            0.99-1.01x the target at 100 and 0.985-1.018x at 70, and sliding friction over the material's
            kinetic friction 0.999 at all counts, none off by 15 %.
    """

    strokes_per_instance: int = 30
    objects_per_instance: int = 10
    seed: int = 0
    env: str = "clean"
    categories: tuple[str, ...] | None = None
    instances: tuple[str, ...] | None = None
    force_range_n: tuple[float, float] = (0.5, 5.0)
    speed_range_mps: tuple[float, float] = (0.01, 0.05)
    length_range_m: tuple[float, float] = (0.02, 0.06)
    max_slide_s: float | None = 0.8
    max_attempts_per_stroke: int = 3
    solver_iterations: int = 75

    def __post_init__(self) -> None:
        if self.env not in ENVIRONMENTS:
            raise ValueError(f"unknown environment {self.env!r}; expected one of {sorted(ENVIRONMENTS)}")
        if self.strokes_per_instance < 1 or self.objects_per_instance < 1:
            raise ValueError("strokes_per_instance and objects_per_instance must be >= 1")
        if self.max_slide_s is not None and not self.max_slide_s > 0.0:
            raise ValueError(f"max_slide_s must be > 0 s or None, got {self.max_slide_s}")
        if self.solver_iterations < 1:
            raise ValueError(f"solver_iterations must be >= 1, got {self.solver_iterations}")


@dataclass(frozen=True)
class ShardJob:
    index: int
    instance: str
    file: str


def _stroke_planner(config: DatasetConfig) -> SortingConfig:
    """The sorting robot's stroke planning (:func:`robotdemo.sorting.plan_stroke`: spot, direction, the slide
    kept on the face and, on tall objects, behind the centre) with the data set's wider parameter ranges."""
    return SortingConfig(stroke_force_n=config.force_range_n, stroke_speed_mps=config.speed_range_mps,
                         stroke_length_m=config.length_range_m, stroke_max_slide_s=config.max_slide_s)


def draw_object(material: Material, object_seed: int, name: str = "sample") -> ObjectSpec:
    """One recorded object, drawn from its own seed alone (the ``surface_seed`` in each of its strokes' meta): its
    shape and size as the sorting scene draws them, its physical parameters around ``material``
    (:func:`perception.materials.sample_material`), and where and at what yaw it is dropped on the table."""
    obj_rng = np.random.default_rng(object_seed)
    kind = SHAPES[int(obj_rng.integers(len(SHAPES)))]  # the sorting scene's shapes and sizes
    size = draw_object_size(kind, obj_rng)
    sample = sample_material(material, obj_rng)
    return ObjectSpec(name=name, shape=kind, size_m=size,
                      xy_m=(float(obj_rng.uniform(-0.26, -0.16)), float(obj_rng.uniform(-0.08, 0.08))),
                      yaw_rad=float(obj_rng.uniform(-math.pi / 2, math.pi / 2)), material=sample,
                      dynamics=contact_dynamics(sample, size, body_shape(kind)))


def drawn_material(record: StrokeRecord, catalogue: MaterialCatalogue | None = None) -> MaterialSample:
    """The physical parameters of the object a recorded stroke touched, drawn again from the seed in its meta
    (:func:`draw_object`); the strokes themselves do not store them. For diagnostics that ask how much of the
    material the sensors keep (``robotdemo bench parameters``).

    Raises:
        RobotDemoError: the stroke's meta lacks the seed or size, its instance is not in the catalogue, or the
            object drawn again is not the recorded one (its size differs: other code or another catalogue).
    """
    catalogue = catalogue or default_catalogue()
    seed, size = record.meta.get("surface_seed"), record.meta.get("size_m")
    if seed is None or size is None:
        raise RobotDemoError(f"stroke of {record.instance!r} has no surface_seed or size_m in its meta: "
                             "not recorded by robotdemo dataset")
    if record.instance not in catalogue.instances:
        raise RobotDemoError(f"stroke's instance {record.instance!r} is not in the material catalogue")
    spec = draw_object(catalogue.instance(record.instance), int(seed))
    if not np.allclose(spec.size_m, [float(v) for v in size], rtol=0.0, atol=1e-12):
        raise RobotDemoError(f"stroke {record.meta.get('object_id', '?')} of {record.instance!r}: the object drawn "
                             f"again from its seed is {spec.size_m} m, the recorded one {list(size)} m; the data "
                             "were recorded by other code or with another catalogue")
    return spec.material


def drawn_materials(records: Sequence[StrokeRecord], catalogue: MaterialCatalogue | None = None,
                    progress: bool = False) -> list[MaterialSample]:
    """:func:`drawn_material` of every stroke, with one catalogue (a tqdm bar with ``progress``)."""
    catalogue = catalogue or default_catalogue()
    return [drawn_material(r, catalogue) for r in tqdm(records, desc="materials", unit="stroke", disable=not progress)]


def record_shard(job: ShardJob, config: DatasetConfig, catalogue: MaterialCatalogue | None = None,
                 failures: Counter | None = None) -> list[StrokeRecord]:
    """All strokes of one instance (deterministic in ``config.seed`` and ``job.index``); each failed attempt's
    reason, its numbers replaced by ``#``, is counted in ``failures`` when given."""
    failures = Counter() if failures is None else failures
    catalogue = catalogue or default_catalogue()
    material: Material = catalogue.instance(job.instance)
    seq = np.random.SeedSequence([config.seed, job.index])
    rng = np.random.default_rng(seq)
    env = ENVIRONMENTS[config.env]
    records: list[StrokeRecord] = []
    planner = _stroke_planner(config)
    per_object = [len(a) for a in np.array_split(np.arange(config.strokes_per_instance), config.objects_per_instance)]
    for obj_index, n_strokes in enumerate(per_object):
        if n_strokes == 0:
            continue
        object_seed = int(rng.integers(2**31))
        spec = draw_object(material, object_seed, name=f"{job.instance}_{obj_index}")
        kind, size, sample, shape = spec.shape, spec.size_m, spec.material, body_shape(spec.shape)
        object_id = f"{config.seed}-{job.index}-{obj_index}"
        info = ObjectInfo(material=sample, size_m=size, shape=shape, surface_seed=object_seed)
        # One object, touched by every stroke: sleeping would save nothing (and the data stay those of the
        # commits before objects could sleep).
        scene_config = SceneConfig(n_objects=0, seed=object_seed, object_sleep_speed_mps=None,
                                   sim=SimConfig().with_solver_iterations(config.solver_iterations))
        with Scene(scene_config, catalogue=catalogue, objects=[spec]) as scene:
            obj = scene.objects[0]
            # Clamped where it came to rest, as a lab fixes a sample for stroking: light, tall objects tipped
            # over their leading edge under the pad's friction, wedging the pad (29 % of stroke attempts
            # failed, all on boxes and cylinders taller than half their length; docs/speed-history.md,
            # "How the recording got faster").
            scene.clamp(obj)
            motion = ArmMotion(scene.robot)
            scene.robot.command_gripper(GripperPosture.stroke())
            done = 0
            attempts = 0
            while done < n_strokes and attempts < n_strokes * config.max_attempts_per_stroke:
                attempts += 1
                center_before, _ = scene.object_pose(obj)
                stroke = plan_stroke(resting_geometry(scene, obj), planner, rng)
                params = {"target_force_n": stroke.target_force_n, "speed_mps": stroke.speed_mps,
                          "length_m": stroke.length_m, "direction_rad": stroke.direction_rad,
                          "start_point_m": [float(v) for v in stroke.start_point_m]}
                stroke_seed = int(rng.integers(2**31))
                try:
                    move_pad_above(scene, motion, stroke)
                    execution = StrokeExecution(scene, motion, obj, stroke)
                    while not execution.step():
                        pass
                except SimulationError:
                    raise  # the scene itself broke: stop rather than stroke it again
                except (RobotDemoError, TrajectoryError) as exc:  # unreachable, unplannable: draw another stroke
                    failures[_reason_key(f"{type(exc).__name__}: {exc}")] += 1
                    continue
                result = execution.result()
                moved = np.linalg.norm(scene.object_pose(obj)[0] - center_before)
                if not result.success or moved > 0.005:
                    failures[_reason_key(result.failure_reason if not result.success
                                         else "the object moved more than 5 mm")] += 1
                    continue
                meta = {"object_id": object_id, "object_kind": kind, "size_m": list(size), "env": config.env,
                        "stroke_seed": stroke_seed, "dataset_seed": config.seed, **params}
                records.append(emulate_stroke(result.trace, info, env, np.random.default_rng(stroke_seed), meta=meta))
                done += 1
    return records


RECORDER_SOURCES: tuple[str, ...] = (
    "controllers/*.py", "perception/contact_trace.py", "perception/materials.py", "perception/materials.toml",
    "perception/tactile.py", "perception/streams.py", "perception/recording_io.py", "perception/sensors/*.py",
    "robotdemo/dataset.py", "robotdemo/motion.py", "robotdemo/robot.py", "robotdemo/scene.py", "robotdemo/sim.py",
    "robotdemo/sorting.py", "robotdemo/stroking.py")
"""The source files whose content decides what a recording holds (paths from the project root); the robot and
scene descriptions (:func:`robotdemo.assets.all_urdfs`, in a checkout or a wheel) and the versions of the
libraries that simulate and sample count too."""

RECORDER_LIBRARIES: tuple[str, ...] = ("pybullet", "pin", "ruckig", "numpy", "scipy")


def recorder_fingerprint() -> str:
    """sha256 over the recorder's source files (:data:`RECORDER_SOURCES`), names and bytes: a resume refuses a
    folder recorded by other code, so that a changed sensor model or simulator never mixes with older shards."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for path in sorted({f for pattern in RECORDER_SOURCES for f in root.glob(pattern) if f.is_file()}):
        h.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    for path in all_urdfs():
        h.update(b"urdf/" + path.relative_to(urdf_root()).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    for name in RECORDER_LIBRARIES:
        try:
            version = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            version = "absent"
        h.update(f"{name}=={version}\0".encode())
    return h.hexdigest()


def _reason_key(reason: str) -> str:
    """A failure reason with its numbers replaced by ``#``, so that reasons of one kind count together."""
    return re.sub(r"[-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?", "#", reason)[:200]


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def plan_jobs(config: DatasetConfig, catalogue: MaterialCatalogue) -> list[ShardJob]:
    """One job per chosen instance. Its index is the instance's place in the whole catalogue, so a shard of a
    subset recording is the same shard as in the full data set (same seed, same strokes)."""
    known_categories = {m.category for m in catalogue.instances.values()}
    unknown = [c for c in config.categories or () if c not in known_categories]
    unknown += [i for i in config.instances or () if i not in catalogue.instances]
    if unknown:
        raise RobotDemoError(f"unknown categories or instances {unknown}; the catalogue has categories "
                             f"{sorted(known_categories)}")
    jobs = [ShardJob(index=i, instance=name, file=f"shards/shard-{i:05d}-{name}.npz")
            for i, (name, m) in enumerate(catalogue.instances.items())
            if (config.categories is None or m.category in config.categories)
            and (config.instances is None or name in config.instances)]
    if not jobs:
        raise RobotDemoError(f"no material instance matches categories={config.categories} instances={config.instances}")
    return jobs


def _run_job(args: tuple[ShardJob, DatasetConfig, str]) -> tuple[ShardJob, int, float, dict[str, int]]:
    job, config, out_dir = args
    t0 = time.perf_counter()
    failures: Counter = Counter()
    records = record_shard(job, config, failures=failures)
    write_strokes(Path(out_dir) / job.file, records)
    return job, len(records), time.perf_counter() - t0, dict(failures.most_common())


def generate_dataset(out_dir: str | Path, config: DatasetConfig, workers: int = 1, progress: bool = True) -> dict:
    """Record (or resume recording) the data set into ``out_dir``. Returns the manifest."""
    out = Path(out_dir)
    catalogue = default_catalogue()
    jobs = plan_jobs(config, catalogue)  # before anything is written: a bad category leaves no folder behind
    (out / "shards").mkdir(parents=True, exist_ok=True)
    manifest_path = out / "manifest.json"
    manifest = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "env": config.env, "seed": config.seed,
                "config": asdict(config), "recorder_sha256": recorder_fingerprint(),
                "numerics": numeric_environment(RECORDER_LIBRARIES), "complete": False,
                "expected_shards": len(jobs), "shards": []}
    if manifest_path.is_file():
        try:
            previous = json.loads(manifest_path.read_text())
        except json.JSONDecodeError as exc:
            raise RobotDemoError(f"{manifest_path}: not valid JSON ({exc}); move it away to start over") from None
        if not isinstance(previous, dict) or not isinstance(previous.get("shards", []), list) or not all(
                isinstance(s, dict) and isinstance(s.get("file"), str) and isinstance(s.get("sha256"), str)
                for s in previous.get("shards", [])):
            raise RobotDemoError(f"{manifest_path}: not a data set manifest (its shard list is malformed); move "
                                 "it away to start over")
        if previous.get("config") != json.loads(json.dumps(asdict(config))):
            raise RobotDemoError(f"{manifest_path}: written with another configuration; use another --out "
                                 "or the same options to resume")
        if previous.get("recorder_sha256") != manifest["recorder_sha256"]:
            raise RobotDemoError(f"{manifest_path}: recorded by other code (the sensor models, simulator or "
                                 "controllers differ, see RECORDER_SOURCES); its shards would not match new ones: "
                                 "use another --out, or move the folder away to start over")
        # library versions already count in the fingerprint; what it cannot see is the BLAS kernels chosen here
        if "numerics" in previous and (changed := numerics_differences(manifest["numerics"], previous["numerics"],
                                                                       results_only=True)):
            raise RobotDemoError(f"{manifest_path}: its shards were recorded with other numerics "
                                 f"({'; '.join(changed)}); new ones would not match them bit for bit: use another "
                                 "--out, or record where they were recorded (perception/numerics.py says how to "
                                 "choose the BLAS kernels)")
        planned = {job.file for job in jobs}  # a shard no current job writes (an older layout) is not kept
        manifest["shards"] = [s for s in previous.get("shards", []) if s["file"] in planned
                              and (out / s["file"]).is_file() and _sha256(out / s["file"]) == s["sha256"]]
    finished = {s["file"] for s in manifest["shards"]}
    todo = [job for job in jobs if job.file not in finished]
    total_strokes = config.strokes_per_instance * len(jobs)
    bar = tqdm(total=total_strokes, initial=sum(s["n_strokes"] for s in manifest["shards"]), unit="stroke",
               desc=f"dataset {config.env}", disable=not progress, dynamic_ncols=True)
    args = [(job, config, str(out)) for job in todo]
    pool = mp.get_context("spawn").Pool(workers) if workers > 1 and len(todo) > 1 else None
    try:
        results: Iterator = pool.imap_unordered(_run_job, args) if pool else map(_run_job, args)
        for job, n, _seconds, reasons in results:
            manifest["shards"].append({"file": job.file, "instance": job.instance, "n_strokes": n,
                                       "failed_strokes": config.strokes_per_instance - n,
                                       "failed_attempts": reasons, "sha256": _sha256(out / job.file)})
            manifest["shards"].sort(key=lambda s: s["file"])
            atomic_write_json(manifest_path, manifest, indent=1, sort_keys=True)
            bar.update(n)
    finally:
        if pool is not None:
            pool.terminate()
        bar.close()
    manifest["complete"] = True
    atomic_write_json(manifest_path, manifest, indent=1, sort_keys=True)
    return manifest
