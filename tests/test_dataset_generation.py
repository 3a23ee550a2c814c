"""The stroke data set: real strokes, shards written atomically, resumable, identical whatever the workers."""


import numpy as np
import pytest

from perception.recording_io import read_strokes
from robotdemo.cli import main
from robotdemo.dataset import DatasetConfig, generate_dataset
from robotdemo.errors import RobotDemoError

FAST = dict(strokes_per_instance=2, objects_per_instance=1, instances=("steel", "pine"), seed=3,
            speed_range_mps=(0.03, 0.05), length_range_m=(0.02, 0.025), force_range_n=(1.0, 3.0))


@pytest.fixture(scope="module")
def one_worker(tmp_path_factory):
    out = tmp_path_factory.mktemp("ds1")
    return out, generate_dataset(out, DatasetConfig(**FAST), workers=1, progress=False)


def test_writes_labelled_strokes_with_four_streams(one_worker):
    out, manifest = one_worker
    assert manifest["format"] == "robotdemo-dataset" and len(manifest["shards"]) == 2
    records = [r for s in manifest["shards"] for r in read_strokes(out / s["file"])]
    assert len(records) == 4
    for rec in records:
        assert rec.category in ("metal", "wood") and rec.combustible == (rec.category == "wood")
        assert {"target_force_n", "speed_mps", "length_m", "object_id", "stroke_seed"} <= set(rec.meta)
        for key, rate in (("sound", 44100.0), ("normal", 100.0), ("friction", 100.0), ("accel", 500.0)):
            stream = rec.streams[key]
            assert stream is not None and stream.rate_hz == rate and np.all(np.isfinite(stream.data))
        # the pad pressed: normal force of the taxels reaches about the commanded force
        peak = np.percentile(rec.streams["normal"].data.sum(axis=1), 90)
        assert 0.5 * rec.meta["target_force_n"] < peak < 2.0 * rec.meta["target_force_n"]


def test_same_data_with_two_workers_and_resume_skips(one_worker, tmp_path):
    out1, manifest1 = one_worker
    manifest2 = generate_dataset(tmp_path, DatasetConfig(**FAST), workers=2, progress=False)
    assert [s["sha256"] for s in manifest1["shards"]] == [s["sha256"] for s in manifest2["shards"]]
    # resume: nothing to redo, files untouched
    mtimes = {s["file"]: (tmp_path / s["file"]).stat().st_mtime_ns for s in manifest2["shards"]}
    again = generate_dataset(tmp_path, DatasetConfig(**FAST), workers=1, progress=False)
    assert again["shards"] == manifest2["shards"]
    assert all((tmp_path / f).stat().st_mtime_ns == t for f, t in mtimes.items())
    # a shard lost (interrupted run) is redone, the other kept
    lost = tmp_path / manifest2["shards"][0]["file"]
    lost.unlink()
    redone = generate_dataset(tmp_path, DatasetConfig(**FAST), workers=1, progress=False)
    assert [s["sha256"] for s in redone["shards"]] == [s["sha256"] for s in manifest2["shards"]]


def test_other_options_into_same_folder_refused(one_worker):
    out, _ = one_worker
    with pytest.raises(RobotDemoError, match="another configuration"):
        generate_dataset(out, DatasetConfig(**{**FAST, "seed": 4}), workers=1, progress=False)


def test_cli_unknown_instance_is_one_line(tmp_path, capsys):
    assert main(["dataset", "--out", str(tmp_path), "--categories", "plutonium", "--quiet"]) == 2
    assert "no material instance matches" in capsys.readouterr().err


def test_bad_slide_time_refused(tmp_path, capsys):
    with pytest.raises(ValueError, match="max_slide_s"):
        DatasetConfig(max_slide_s=-1.0)
    for text, message in (("soon", "--max-slide-s must be a number of seconds or 'none'"),
                          ("0", "max_slide_s must be > 0 s")):
        assert main(["dataset", "--out", str(tmp_path / "x"), "--max-slide-s", text]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("robotdemo: error:") and message in err and "\n" not in err
    assert not (tmp_path / "x").exists()


def test_bad_solver_iterations_refused(tmp_path, capsys):
    with pytest.raises(ValueError, match="solver_iterations must be >= 1"):
        DatasetConfig(solver_iterations=0)
    assert main(["dataset", "--out", str(tmp_path / "x"), "--solver-iterations", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("robotdemo: error:") and "solver_iterations must be >= 1" in err and "\n" not in err
    assert not (tmp_path / "x").exists()


def test_shard_strokes_the_clamped_sample_at_the_configured_iterations(monkeypatch):
    """``record_shard`` builds its scene at ``DatasetConfig.solver_iterations`` and clamps the sample free of
    the table (``Scene.clamp``) before stroking it."""
    import pybullet as p

    import robotdemo.dataset as dataset
    from robotdemo.scene import Scene

    seen = []
    clamp = Scene.clamp

    def spy(scene, obj):
        clamp(scene, obj)
        seen.append((scene.config.sim.solver_iterations,
                     p.getPhysicsEngineParameters(physicsClientId=scene.sim.client)["numSolverIterations"],
                     len(p.getContactPoints(scene.table, obj.body, physicsClientId=scene.sim.client))))

    monkeypatch.setattr(Scene, "clamp", spy)
    config = DatasetConfig(**{**FAST, "instances": ("steel",), "strokes_per_instance": 1, "solver_iterations": 60})
    records = dataset.record_shard(dataset.plan_jobs(config, dataset.default_catalogue())[0], config)
    assert len(records) == 1 and seen == [(60, 60, 0)]
    assert DatasetConfig().solver_iterations == 75
