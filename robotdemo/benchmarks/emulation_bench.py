"""Wall time of recording strokes: the PyBullet stroke and the sensor emulation, measured in one run."""

from __future__ import annotations

import time

import numpy as np

from robotdemo.dataset import DatasetConfig, ShardJob, record_shard


def _record(n_strokes: int, seed: int, instance: str, solver_iterations: int) -> dict:
    config = DatasetConfig(strokes_per_instance=n_strokes, objects_per_instance=1, seed=seed,
                           solver_iterations=solver_iterations)
    t0 = time.perf_counter()
    records = record_shard(ShardJob(0, instance, "bench.npz"), config)
    wall = time.perf_counter() - t0
    stroke_s = np.array([r.streams["accel"].duration_s if r.streams["accel"] is not None else
                         r.streams["normal"].duration_s for r in records])
    return {"solver_iterations": solver_iterations, "strokes": len(records), "wall_s": round(wall, 3),
            "wall_s_per_stroke": round(wall / max(1, len(records)), 3),
            "recorded_s_per_stroke_median": round(float(np.median(stroke_s)), 3),
            "wall_s_per_recorded_s": round(wall / max(1e-9, float(stroke_s.sum())), 3)}


def run_emulation_benchmark(n_strokes: int = 6, seed: int = 0, instance: str = "oak",
                            peer_solver_iterations: int | None = 100) -> dict:
    """Record ``n_strokes`` default-distribution strokes on one instance and report wall time per stroke and per
    simulated second (median over strokes is not separable from the scene, so totals and ratios are given).
    The peer, measured in the same run, records the same draws with ``peer_solver_iterations`` (the robot
    scene's 100 by default; ``None``: no peer)."""
    result = _record(n_strokes, seed, instance, DatasetConfig().solver_iterations)
    if peer_solver_iterations is not None:
        peer = _record(n_strokes, seed, instance, peer_solver_iterations)
        result["peer"] = peer
        result["wall_ratio_to_peer"] = round(result["wall_s"] / peer["wall_s"], 3)
    result["target"] = "1260 strokes (7 x 6 x 30) with 2 workers in <= 600 s, i.e. <= 0.95 s per stroke per worker"
    return result
