"""How well strokes executed in PyBullet track their commands: pad tracking error, force band, slide length
and speed, on a soft and two hard materials (the cases of tests/test_stroking.py); on the robot's scene (the
object free on the table, 100 solver iterations) or on the data set's fixture (the object clamped and free of
the table, :meth:`robotdemo.scene.Scene.clamp`) at chosen solver iterations."""

from __future__ import annotations

import itertools
from typing import Sequence

import numpy as np

from controllers.stroke import StrokeConfig, StrokePhase
from robotdemo.motion import ArmMotion
from robotdemo.scene import Scene, SceneConfig
from robotdemo.sim import SimConfig
from robotdemo.stroking import cruise_speed_mps, move_pad_above, run_stroke, top_surface_point

CASES = (("rubber", 1, 1.0), ("metal", 1, 4.0), ("wood", 0, 2.0))


def run_stroke_benchmark(speed_mps: float = 0.02, length_m: float = 0.03, clamped: bool = False,
                         solver_iterations: Sequence[int] = (100,)) -> dict:
    """Every case at every count of ``solver_iterations``; ``clamped``: on the data set's fixture."""
    rows = []
    for (category, seed, force_n), iterations in itertools.product(CASES, solver_iterations):
        scene_config = SceneConfig(n_objects=1, seed=seed, categories=(category,), shapes=("box",),
                                   sim=SimConfig().with_solver_iterations(iterations))
        with Scene(scene_config) as scene:
            obj = scene.objects[0]
            if clamped:
                scene.clamp(obj)
            motion = ArmMotion(scene.robot)
            config = StrokeConfig(target_force_n=force_n, speed_mps=speed_mps, length_m=length_m,
                                  start_point_m=tuple(top_surface_point(scene, obj, (-0.015, 0.0))))
            move_pad_above(scene, motion, config)
            result = run_stroke(scene, motion, obj, config)
            sliding = np.array([phase is StrokePhase.SLIDE for phase in result.phase_log])
            force = result.force_log_n[sliding][int(0.1 / motion.config.control_period_s):]
            distance = (float(np.linalg.norm(result.slide_end_m - result.slide_start_m))
                        if result.slide_end_m is not None else 0.0)
            rows.append({
                "material": obj.instance, "solver_iterations": iterations, "clamped": clamped,
                "contact_stiffness_n_per_m": round(obj.spec.dynamics.contact_stiffness_n_per_m),
                "success": result.success, "failure": result.failure_reason, "target_force_n": force_n,
                "slide_force_min_n": round(float(force.min()), 3) if len(force) else None,
                "slide_force_max_n": round(float(force.max()), 3) if len(force) else None,
                "slide_force_worst_ratio": (round(float(force[np.argmax(np.abs(force - force_n))] / force_n), 3)
                                            if len(force) else None),
                "slide_length_m": round(distance, 5), "requested_length_m": length_m,
                "cruise_speed_mps": round(cruise_speed_mps(result, motion.config.control_period_s), 5),
                "requested_speed_mps": speed_mps,
                "tracking_error_median_mm": round(float(np.median(result.tracking_error_m)) * 1000, 3),
                "tracking_error_max_mm": round(float(np.max(result.tracking_error_m)) * 1000, 3),
            })
    return {"strokes": rows}
