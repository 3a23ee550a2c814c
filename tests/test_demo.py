"""The demo command end to end (short runs), its JSON report (also on a failure midway), the classifier built
from a checkpoint, and the demo benchmark's plumbing.

The checkpoint here is a tiny untrained TouchFormer whose output layer is biased towards one class: it checks
the plumbing (loading, featurizing, gate weights, report), not the perception.
"""

import io
import json

import numpy as np
import pytest
import torch

from perception.baselines import build_model
from perception.checkpoint import save_checkpoint
from perception.contact_trace import ObjectInfo, synthetic_press_slide_trace
from perception.features import FeatureConfig, NormStats, feature_dims
from perception.materials import default_catalogue, sample_material
from perception.streams import MODALITIES
from perception.tactile import ENVIRONMENTS, emulate_stroke
from robotdemo import sorting
from robotdemo.classifier import Classification, TouchFormerClassifier
from robotdemo.cli import main
from robotdemo.classifier import OracleClassifier
from robotdemo.demo import run_demo_bench
from robotdemo.errors import SimulationError

CATEGORIES = default_catalogue().categories


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    """An untrained TouchFormer, output biased to 'rubber' (the material of scene seed 0's first object)."""
    torch.manual_seed(0)
    fc = FeatureConfig()
    dims = feature_dims(fc)
    config, model = build_model("touchformer", tuple(dims[m] for m in MODALITIES), len(CATEGORIES), d_model=16,
                                n_heads=2, n_layers=1, gate_hidden=8, emb_dim=8)
    with torch.no_grad():
        model.classifier.weight.zero_()
        model.classifier.bias.zero_()
        model.classifier.bias[CATEGORIES.index("rubber")] = 8.0
    stats = NormStats(mean={m: (0.0,) * dims[m] for m in MODALITIES}, std={m: (1.0,) * dims[m] for m in MODALITIES})
    return save_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny", "touchformer", model, config, fc, stats,
                           CATEGORIES, meta={"note": "untrained, for tests"})


def _record(drop: tuple[str, ...] = ()):
    material = sample_material(default_catalogue().instance("oak"), np.random.default_rng(0))
    record = emulate_stroke(synthetic_press_slide_trace(friction_coefficient=material.friction_kinetic),
                            ObjectInfo(material, (0.06, 0.05, 0.04)), ENVIRONMENTS["clean"], np.random.default_rng(1))
    if drop:
        from dataclasses import replace
        record = replace(record, streams={m: (None if m in drop else s) for m, s in record.streams.items()})
    return record


def test_classifier_from_checkpoint_reports_gate_weights(tiny_checkpoint):
    classify = TouchFormerClassifier.from_checkpoint(tiny_checkpoint)
    result = classify(_record())
    assert isinstance(result, Classification)
    assert result.category == "rubber" and result.confidence > 0.9
    assert set(result.probabilities) == set(CATEGORIES) and sum(result.probabilities.values()) == pytest.approx(1.0)
    assert set(result.gate_weights) == set(MODALITIES) and sum(result.gate_weights.values()) == pytest.approx(1.0)
    dropped = classify(_record(drop=("accel",)))
    assert dropped.gate_weights["accel"] == 0.0 and "accel" not in dropped.modalities_present


def test_classifier_applies_the_checkpoints_temperature(tiny_checkpoint, tmp_path):
    """A calibrated checkpoint (temperature 4: logit 8 -> 2) gives the same category, less sure: what the
    robot's re-stroke threshold is compared with. The probabilities are softmax(logits / T)."""
    import shutil

    from perception.checkpoint import set_temperature

    calibrated = shutil.copytree(tiny_checkpoint, tmp_path / "calibrated")
    set_temperature(calibrated, 4.0)
    sure = TouchFormerClassifier.from_checkpoint(tiny_checkpoint)(_record())
    soft = TouchFormerClassifier.from_checkpoint(calibrated)(_record())
    assert soft.category == sure.category == "rubber"
    assert sure.confidence == pytest.approx(np.exp(8) / (np.exp(8) + len(CATEGORIES) - 1), rel=1e-3)
    assert soft.confidence == pytest.approx(np.exp(2) / (np.exp(2) + len(CATEGORIES) - 1), rel=1e-3)


def test_demo_runs_end_to_end_and_writes_the_report(tiny_checkpoint, tmp_path, capsys):
    report_path = tmp_path / "out" / "report.json"
    rc = main(["demo", "--objects", "1", "--seed", "0", "--env", "fire", "--checkpoint", str(tiny_checkpoint),
               "--report", str(report_path)])
    out = capsys.readouterr().out
    assert rc == 0
    assert "object0_neoprene" in out and "real-time factor" in out
    report = json.loads(report_path.read_text())
    assert report["status"] == "done" and report["error"] is None
    (obj,) = report["objects"]
    for key in ("true_category", "true_instance", "predicted_category", "confidence", "combustible_probability",
                "gate_weights",
                "trusted_sensors", "strokes_taken", "zone_reached", "success", "failure_reason"):
        assert key in obj
    assert obj["true_category"] == obj["predicted_category"] == "rubber"
    assert obj["success"] and obj["zone_reached"] == "combustible" and obj["strokes_taken"] >= 1
    summary = report["summary"]
    assert summary["sorting_accuracy"] == 1.0 and summary["grasp_success_rate"] == 1.0
    assert summary["sim_s"] > 1.0 and summary["wall_s"] > 0 and summary["real_time_factor"] > 0
    assert not list(report_path.parent.glob(".*.tmp"))  # written atomically


def test_demo_records_even_when_the_live_view_cannot_start(tiny_checkpoint, tmp_path, capsys):
    """192.0.2.1 (TEST-NET-1) is no address of this machine: the live server cannot bind it, the warning says
    so, and the replay asked for is still written."""
    replay = tmp_path / "run.html"
    rc = main(["demo", "--objects", "1", "--checkpoint", str(tiny_checkpoint), "--meshcat-host", "192.0.2.1",
               "--record", str(replay)])
    err = capsys.readouterr().err
    assert rc == 0 and "live viewer unavailable" in err and "recording only" in err
    assert replay.is_file() and replay.stat().st_size > 10_000


def test_realtime_paces_the_run_to_the_wall_clock(tiny_checkpoint, tmp_path, capsys):
    from robotdemo.demo import DemoConfig, run_demo

    report = run_demo(DemoConfig(n_objects=1, seed=0, checkpoint=tiny_checkpoint, realtime=True), out=io.StringIO())
    summary = report["summary"]
    assert summary["sim_s"] > 1.0 and summary["real_time_factor"] <= 1.0
    assert main(["demo", "--objects", "1", "--realtime"]) == 2
    assert "add --meshcat" in capsys.readouterr().err


def test_hold_serves_until_ctrl_c(monkeypatch):
    from robotdemo import demo

    def interrupt(_seconds):
        raise KeyboardInterrupt

    monkeypatch.setattr(demo.time, "sleep", interrupt)
    out = io.StringIO()
    demo._hold(object(), out)
    assert out.getvalue().splitlines() == ["meshcat: the run is over; still serving the view, Ctrl-C to stop",
                                           "meshcat: stopped"]


def test_ctrl_c_that_a_library_swallows_still_stops_the_demo_at_that_tick(tiny_checkpoint, tmp_path):
    """SIGINT raises KeyboardInterrupt wherever the main thread is; inside a dependency's bare ``except:`` it
    would be lost and the run would sort every object. The demo's loop still stops at the tick it came in."""
    import os
    import signal
    import time

    from robotdemo.demo import DemoConfig, run_demo

    classify = TouchFormerClassifier.from_checkpoint(tiny_checkpoint)
    calls = []

    def swallowing(record):
        calls.append(record)
        try:  # a library's bare except around work that Ctrl-C interrupts
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
        except BaseException:  # noqa: BLE001 - swallowing it is the point
            pass
        return classify(record)

    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    report_path = tmp_path / "report.json"
    with pytest.raises(KeyboardInterrupt):
        run_demo(DemoConfig(n_objects=2, seed=0, checkpoint=tiny_checkpoint, report_path=report_path),
                 classifier=swallowing, out=io.StringIO())
    assert len(calls) == 1  # the first classification's tick, not the end of the run
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # put back
    report = json.loads(report_path.read_text())
    assert report["status"] == "error" and report["error"] == "KeyboardInterrupt"
    assert sum(o["zone_reached"] is not None for o in report["objects"]) == 0


def test_demo_writes_a_partial_report_when_the_run_fails(tiny_checkpoint, tmp_path, capsys, monkeypatch):
    real_step = sorting.SortingMachine.step

    def failing_step(self):
        if self.tick == 60:
            raise SimulationError("simulation diverged: injected for the test")
        return real_step(self)

    monkeypatch.setattr(sorting.SortingMachine, "step", failing_step)
    report_path = tmp_path / "report.json"
    rc = main(["demo", "--objects", "2", "--checkpoint", str(tiny_checkpoint), "--report", str(report_path)])
    err = capsys.readouterr().err
    assert rc == 2 and "robotdemo: error: simulation diverged: injected" in err and "Traceback" not in err
    report = json.loads(report_path.read_text())
    assert report["status"] == "error" and "injected for the test" in report["error"]
    assert len(report["objects"]) == 2 and report["summary"]["ticks"] == 60
    assert report["events"][-1]["state"] == "approach"


def test_demo_without_checkpoint_says_so_in_one_line(tmp_path, capsys):
    rc = main(["demo", "--objects", "1", "--checkpoint", str(tmp_path / "missing"), "--report",
               str(tmp_path / "r.json")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("robotdemo: error: checkpoint folder")
    assert json.loads((tmp_path / "r.json").read_text())["status"] == "error"


def test_demo_bench_reports_medians_over_seeds():
    def oracle(record):
        probs = {c: (0.94 if c == record.category else 0.01) for c in CATEGORIES}
        return Classification(record.category, 0.94, probs, {}, record.present)

    result = run_demo_bench(seeds=2, n_objects=0, classifier=oracle)
    assert result["seeds"] == 2 and len(result["runs"]) == 2 and result["classifier"] == "passed in"
    assert set(result["median"]) == {"sorting_accuracy", "grasp_success_rate", "wall_s", "sim_s", "real_time_factor"}


def test_oracle_classifier_answers_the_true_label_for_diagnosis():
    record = _record(drop=("sound",))
    result = OracleClassifier()(record)
    assert result.category == record.category and result.confidence == 1.0
    assert sum(result.probabilities.values()) == 1.0 and result.gate_weights["sound"] == 0.0
