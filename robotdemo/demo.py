"""The sorting demo: build a scene, sort every object with the state machine, print and report what happened.

Headless by default. One line is printed per object as the machine finishes with it; the JSON report (per object:
true category and instance, prediction and confidence, gate weights, trusted sensors, strokes, zone reached,
success and the failure reason; and a summary: sorting accuracy, grasp success rate, simulated and wall seconds,
real-time factor) is written atomically, also when the run fails midway (then with ``"status": "error"`` and the
error). With ``viewer`` or ``record_path`` the scene is mirrored in :mod:`robotdemo.viewer` (if Meshcat is
available; otherwise the demo says so and goes on headless; a live server that cannot start leaves the recording).
``realtime`` paces the run to the wall clock and ``hold`` keeps the live view served after it, for people
watching from another machine. Ctrl-C stops the sorting at the tick it comes in, even where a library swallows the
KeyboardInterrupt (:class:`_InterruptLatch`); the report and the replay are still written.

Typical use::

    report = run_demo(DemoConfig(n_objects=6, seed=0, environment="fire", report_path=Path("run.json")))
"""

from __future__ import annotations

import io
import signal
import statistics
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from perception.atomic import atomic_write_json
from robotdemo.errors import RobotDemoError
from robotdemo.sorting import NO_FAULTS, Classifier, FaultInjector, SortingConfig, SortingMachine

if TYPE_CHECKING:  # the viewer module loads Meshcat only when a run asks for it
    from robotdemo.viewer import ViewerConfig

DEFAULT_CHECKPOINT = Path(__file__).resolve().parent / "checkpoints" / "touchformer_fire"
"""The material classifier the demo loads unless told otherwise (trained on the ``fire`` environment)."""


@dataclass(frozen=True)
class DemoConfig:
    """One demo run.

    Attributes:
        n_objects: objects on the table.
        seed: seeds the scene and the machine (strokes, sensor noise).
        environment: sensor environment, ``"clean"`` or ``"fire"``.
        checkpoint: classifier checkpoint folder (ignored when a classifier is passed to :func:`run_demo`).
        report_path: JSON report to write (``None``: none).
        viewer: the live Meshcat view (:class:`robotdemo.viewer.ViewerConfig`; ``None``: none unless recording).
        record_path: self-contained HTML replay to write (``None``: none).
        realtime: pace the run to the wall clock (for watching; the simulation runs about 5x faster).
        hold: after the run, keep serving the live view until Ctrl-C.
        max_sim_s: the run fails if sorting takes longer than this (simulated seconds).
        sorting: state-machine settings (its ``environment`` is replaced by ``environment``).
    """

    n_objects: int = 6
    seed: int = 0
    environment: str = "fire"
    checkpoint: Path = DEFAULT_CHECKPOINT
    report_path: Path | None = None
    viewer: ViewerConfig | None = None
    record_path: Path | None = None
    realtime: bool = False
    hold: bool = False
    max_sim_s: float = 900.0
    sorting: SortingConfig = field(default_factory=SortingConfig)


def write_json_atomic(path: Path, data: Any) -> None:
    """Write ``data`` as JSON to ``path`` through a temporary file in the same folder and a rename."""
    atomic_write_json(path, data)


def summarize(machine: SortingMachine | None, n_objects: int, sim_s: float, wall_s: float) -> dict[str, Any]:
    """The run's summary: sorting accuracy (objects resting in the zone of their true combustible flag over all
    objects), placement in the predicted zone, grasp success rate (grasps that held, i.e. neither slipped,
    dropped the object nor closed on nothing, over grasps started), simulated and wall seconds of the sorting
    loop and their ratio."""
    decisions = list(machine.decisions.values()) if machine is not None else []
    attempts = sum(d.grasp_attempts for d in decisions)
    successes = attempts - (machine.grasp_failures if machine is not None else 0)
    correct = sum(d.correct for d in decisions)
    return {
        "objects": n_objects,
        "decided": sum(d.end_time_s is not None for d in decisions),
        "sorted_correctly": correct,
        "sorting_accuracy": correct / n_objects if n_objects else None,
        "placed_in_target_zone": sum(d.success for d in decisions),
        "classified_correctly": sum(d.predicted_category == d.true_category for d in decisions),
        "failed": sum(bool(d.failure_reason) for d in decisions),
        "strokes": sum(d.strokes_taken for d in decisions),
        "grasp_attempts": attempts,
        "grasp_successes": successes,
        "grasp_success_rate": successes / attempts if attempts else None,
        "ticks": machine.tick if machine is not None else 0,
        "sim_s": round(sim_s, 3),
        "wall_s": round(wall_s, 3),
        "real_time_factor": round(sim_s / wall_s, 3) if wall_s > 0 else None,
    }


def _open_viewer(config: DemoConfig, out: TextIO) -> Any | None:
    """The viewer the run asks for (:func:`robotdemo.viewer.start_viewer`: a live server that cannot start
    leaves the recording), or None."""
    if config.viewer is None and config.record_path is None:
        return None
    try:
        from robotdemo.viewer import ViewerConfig, ViewerUnavailable, start_viewer
    except ImportError as exc:
        print(f"robotdemo: viewer unavailable ({exc}); running headless", file=out)
        return None
    viewer_config = config.viewer if config.viewer is not None else ViewerConfig(live=False)
    if config.record_path is not None:
        viewer_config = replace(viewer_config, record=True)
    try:
        viewer = start_viewer(viewer_config)
    except (ViewerUnavailable, ValueError, OSError) as exc:
        print(f"robotdemo: viewer unavailable ({exc}); running headless", file=out)
        return None
    return viewer  # start_viewer has printed the URL it serves


def _hold(viewer: Any, out: TextIO) -> None:
    """Keep the live view served until Ctrl-C (which ends the hold, not the run)."""
    print("meshcat: the run is over; still serving the view, Ctrl-C to stop", file=out, flush=True)
    try:
        while True:
            time.sleep(0.5)
    except KeyboardInterrupt:
        print("meshcat: stopped", file=out)


class _InterruptLatch:
    """Ctrl-C stops the sorting loop even where a library swallows the KeyboardInterrupt.

    Python raises KeyboardInterrupt wherever the main thread happens to be when SIGINT arrives; inside a
    dependency's bare ``except:`` (or a C-level ``hasattr``) it is lost and the run would go on to the end. While
    the latch is held, SIGINT also sets a flag that :meth:`check` turns into a KeyboardInterrupt once per tick.
    It takes over only Python's default handler, in the main thread, and puts it back on exit.
    """

    def __init__(self) -> None:
        self.requested = False
        self._previous: Any = None

    def __enter__(self) -> "_InterruptLatch":
        if (threading.current_thread() is threading.main_thread()
                and signal.getsignal(signal.SIGINT) is signal.default_int_handler):
            self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
            self._previous = None

    def _handle(self, signum: int, frame: Any) -> None:
        self.requested = True
        raise KeyboardInterrupt

    def check(self) -> None:
        """Raise KeyboardInterrupt if Ctrl-C came while the latch was held (however it was handled then)."""
        if self.requested:
            raise KeyboardInterrupt


def _taxel_normals(machine: SortingMachine) -> np.ndarray | None:
    """The 16 taxel normal forces of the current stroke's last physics step (for the viewer), N."""
    stroke = machine.stroke_execution
    if stroke is None or len(stroke.recorder.t_s) < 2:
        return None
    from perception.contact_trace import ContactTraceError
    from perception.sensors.taxels import taxel_forces
    try:
        trace = stroke.recorder.to_trace(last=2)
    except ContactTraceError:
        return None
    return taxel_forces(trace)[-1, :, 2]


def _object_line(d) -> str:
    predicted = f"{d.predicted_category} ({d.confidence:.2f})" if d.predicted_category else "-"
    outcome = "ok" if d.success else f"FAILED: {d.failure_reason}" if d.failure_reason else "wrong zone"
    return (f"{d.name:<30} {d.true_category:<9} {predicted:<17} {d.strokes_taken:>7} {d.grasp_attempts:>6}  "
            f"{d.zone_reached or '-':<15} {outcome}")


def run_demo(config: DemoConfig, classifier: Classifier | None = None, out: TextIO | None = None,
             faults: FaultInjector = NO_FAULTS) -> dict[str, Any]:
    """Run the demo and return its report (also written to ``config.report_path``, even if the run fails).

    Args:
        config: the run.
        classifier: a ``StrokeRecord -> Classification`` callable; ``None`` loads ``config.checkpoint``.
        out: where the progress lines go (``None``: standard output).
        faults: faults to inject.

    Raises:
        RobotDemoError: the checkpoint cannot be loaded, or the run failed (after writing the report).
    """
    from dataclasses import replace

    from robotdemo.scene import Scene, SceneConfig

    out = out if out is not None else sys.stdout
    report: dict[str, Any] = {
        "status": "running", "error": None,
        "config": {"objects": config.n_objects, "seed": config.seed, "environment": config.environment,
                   "checkpoint": None if classifier is not None else str(config.checkpoint)},
        "objects": [], "events": [], "summary": None,
    }
    machine: SortingMachine | None = None
    scene = viewer = None
    wall_start = time.perf_counter()
    loop_wall = 0.0
    sim_start = 0.0
    try:
        if classifier is None:
            from robotdemo.classifier import TouchFormerClassifier
            classifier = TouchFormerClassifier.from_checkpoint(config.checkpoint)
        scene = Scene(SceneConfig(n_objects=config.n_objects, seed=config.seed))
        sorting = replace(config.sorting, environment=config.environment)
        machine = SortingMachine(scene, classifier, sorting, seed=config.seed, faults=faults)
        viewer = _open_viewer(config, out)
        print(f"demo: {config.n_objects} objects, seed {config.seed}, environment {config.environment}", file=out)
        print(f"{'object':<30} {'true':<9} {'predicted':<17} {'strokes':>7} {'grasps':>6}  {'zone':<15} outcome",
              file=out, flush=True)
        reported: set[str] = set()
        sim_start = scene.sim.time_s
        loop_start = time.perf_counter()
        with _InterruptLatch() as interrupt:
            while not machine.done:
                machine.step()
                if viewer is not None:
                    # the viewer calls it only for the frames it draws
                    viewer.update(scene, taxel_normal_n=lambda: _taxel_normals(machine), labels=machine.labels())
                if config.realtime:  # no faster than the wall clock
                    ahead_s = (scene.sim.time_s - sim_start) - (time.perf_counter() - loop_start)
                    if ahead_s > 0:
                        time.sleep(ahead_s)
                for name, d in machine.decisions.items():
                    if d.end_time_s is not None and name not in reported:
                        reported.add(name)
                        print(_object_line(d), file=out, flush=True)
                if scene.sim.time_s - sim_start > config.max_sim_s:
                    raise RobotDemoError(f"sorting took more than {config.max_sim_s:g} simulated seconds")
                loop_wall = time.perf_counter() - loop_start
                interrupt.check()
        report["status"] = "done"
    except BaseException as exc:
        report["status"] = "error"
        report["error"] = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        raise
    finally:
        sim_s = scene.sim.time_s - sim_start if scene is not None and scene.sim.client >= 0 else 0.0
        if machine is not None:
            report["objects"] = [d.to_dict() for d in machine.decisions.values()]
            report["events"] = [{"tick": e.tick, "time_s": round(e.time_s, 3), "state": e.state.value,
                                 "object": e.object_name, "message": e.message} for e in machine.events]
        report["summary"] = summarize(machine, config.n_objects, sim_s, loop_wall)
        report["summary"]["total_wall_s"] = round(time.perf_counter() - wall_start, 3)
        try:
            if viewer is not None:
                if config.record_path is not None and scene is not None:
                    viewer.update(scene, labels=machine.labels() if machine else None, force=True)
                    viewer.write_html(config.record_path)
                    print(f"recording: {config.record_path}", file=out)
                if config.hold and report["status"] == "done" and viewer.url:
                    _hold(viewer, out)
                viewer.close()
        finally:
            if scene is not None:
                scene.close()
            if config.report_path is not None:
                write_json_atomic(config.report_path, report)
    s = report["summary"]
    print(f"sorted {s['sorted_correctly']}/{s['objects']} into the right zone; grasps {s['grasp_successes']}/"
          f"{s['grasp_attempts']}; {s['sim_s']:.1f} s simulated in {s['wall_s']:.1f} s "
          f"(real-time factor {s['real_time_factor']})", file=out, flush=True)
    if config.report_path is not None:
        print(f"report: {config.report_path}", file=out)
    return report


def run_demo_bench(seeds: int, n_objects: int = 6, environment: str = "fire",
                   checkpoint: Path = DEFAULT_CHECKPOINT, classifier: Classifier | None = None,
                   first_seed: int = 0, oracle: bool = False) -> dict[str, Any]:
    """The demo over seeds ``first_seed .. first_seed + seeds - 1``, headless: medians over seeds, and pooled
    accuracy and grasp success over all objects. ``oracle`` replaces the classifier by
    :class:`~robotdemo.classifier.OracleClassifier` (the robot's handling alone; a diagnostic)."""
    if seeds < 1:
        raise ValueError(f"--seeds must be >= 1, got {seeds}")
    source = "passed in" if classifier is not None else str(checkpoint)
    if oracle:
        from robotdemo.classifier import OracleClassifier
        classifier, source = OracleClassifier(), "oracle (true labels: a diagnostic of the robot's handling)"
    if classifier is None:
        from robotdemo.classifier import TouchFormerClassifier
        classifier = TouchFormerClassifier.from_checkpoint(checkpoint)
    runs = []
    for seed in range(first_seed, first_seed + seeds):
        report = run_demo(DemoConfig(n_objects=n_objects, seed=seed, environment=environment), classifier,
                          out=io.StringIO())
        runs.append(report["summary"] | {"seed": seed, "failures": [o["failure_reason"] for o in report["objects"]
                                                                     if o["failure_reason"]]})

    def median(key: str) -> float | None:
        values = [r[key] for r in runs if r[key] is not None]
        return round(statistics.median(values), 4) if values else None

    attempts = sum(r["grasp_attempts"] for r in runs)
    return {
        "seeds": seeds, "objects_per_seed": n_objects, "environment": environment,
        "classifier": source,
        "median": {k: median(k) for k in ("sorting_accuracy", "grasp_success_rate", "wall_s", "sim_s",
                                          "real_time_factor")},
        "pooled": {"sorting_accuracy": (sum(r["sorted_correctly"] for r in runs) / (n_objects * seeds)
                                        if n_objects else None),
                   "grasp_success_rate": (sum(r["grasp_successes"] for r in runs) / attempts) if attempts else None,
                   "classified_correctly": (sum(r["classified_correctly"] for r in runs) / (n_objects * seeds)
                                            if n_objects else None),
                   "strokes": sum(r["strokes"] for r in runs)},
        "runs": runs,
    }
