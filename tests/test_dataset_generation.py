"""The stroke data set: real strokes, shards written atomically, resumable, identical whatever the workers."""

import json
import shutil

import numpy as np
import pytest

from perception.dataset import DatasetError, load_dataset
from perception.numerics import numeric_environment
from perception.recording_io import read_strokes
from robotdemo import dataset
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
    assert redone["complete"] and redone["expected_shards"] == 2
    assert all(isinstance(s["failed_attempts"], dict) for s in redone["shards"])
    # a manifest entry that no current job writes (an older layout's shard) is dropped, not loaded twice
    manifest_path = tmp_path / "manifest.json"
    listed = json.loads(manifest_path.read_text())
    extra = dict(listed["shards"][0], file="shards/shard-99999-steel.npz")
    shutil.copy(tmp_path / listed["shards"][0]["file"], tmp_path / extra["file"])
    listed["shards"].append(extra)
    manifest_path.write_text(json.dumps(listed))
    assert len(load_dataset(tmp_path).records) == 6  # what the old code kept and loaded: a shard twice
    cleaned = generate_dataset(tmp_path, DatasetConfig(**FAST), workers=1, progress=False)
    assert [s["file"] for s in cleaned["shards"]] == [s["file"] for s in redone["shards"]]
    assert len(load_dataset(tmp_path).records) == 4


def test_an_unfinished_recording_does_not_load_as_a_data_set(one_worker, tmp_path):
    out, _ = one_worker
    shutil.copytree(out, tmp_path / "part")
    manifest = json.loads((tmp_path / "part" / "manifest.json").read_text())
    manifest["complete"] = False  # as the manifest reads while a recording runs (or after it was killed)
    manifest["shards"] = manifest["shards"][:1]
    (tmp_path / "part" / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(DatasetError, match="not finished .1 of 2 shards"):
        load_dataset(tmp_path / "part")


def test_other_options_into_same_folder_refused(one_worker):
    out, _ = one_worker
    with pytest.raises(RobotDemoError, match="another configuration"):
        generate_dataset(out, DatasetConfig(**{**FAST, "seed": 4}), workers=1, progress=False)


def test_a_folder_recorded_by_other_code_is_not_resumed(one_worker, tmp_path, monkeypatch):
    out, manifest = one_worker
    assert manifest["recorder_sha256"] == dataset.recorder_fingerprint()
    shutil.copytree(out, tmp_path / "old")
    urdf = tmp_path / "robot.urdf"
    urdf.write_text("<robot/>")
    monkeypatch.setattr(dataset, "all_urdfs", lambda: [urdf])  # a wheel's URDFs live outside the source tree
    monkeypatch.setattr(dataset, "urdf_root", lambda: tmp_path)
    before = dataset.recorder_fingerprint()
    urdf.write_text('<robot name="edited"/>')
    assert dataset.recorder_fingerprint() != before  # an edited robot description is other code
    monkeypatch.setattr(dataset, "recorder_fingerprint", lambda: "0" * 64)  # as after a change to a sensor model
    with pytest.raises(RobotDemoError, match="recorded by other code"):
        generate_dataset(tmp_path / "old", DatasetConfig(**FAST), workers=1, progress=False)


def test_a_folder_recorded_with_other_numerics_is_not_resumed(one_worker, tmp_path):
    out, manifest = one_worker
    assert manifest["numerics"] == numeric_environment(dataset.RECORDER_LIBRARIES)  # what the strokes depend on
    shutil.copytree(out, tmp_path / "elsewhere")
    path = tmp_path / "elsewhere" / "manifest.json"
    recorded = json.loads(path.read_text())
    recorded["numerics"]["cpu"] = "another CPU"  # another CPU with the same BLAS kernels resumes
    path.write_text(json.dumps(recorded))
    assert generate_dataset(tmp_path / "elsewhere", DatasetConfig(**FAST), workers=1, progress=False)["complete"]
    recorded["numerics"]["blas"][0]["architecture"] = "SomeOtherCore"  # as on a machine whose BLAS sums otherwise
    path.write_text(json.dumps(recorded))
    other = r"recorded with other numerics \(BLAS kernels [^)]*SomeOtherCore[^)]* -> "
    with pytest.raises(RobotDemoError, match=other):
        generate_dataset(tmp_path / "elsewhere", DatasetConfig(**FAST), workers=1, progress=False)
    assert json.loads(path.read_text()) == recorded  # nothing written


def test_cli_unknown_instance_is_one_line(tmp_path, capsys):
    assert main(["dataset", "--out", str(tmp_path / "x"), "--categories", "plutonium", "--quiet"]) == 2
    assert "unknown categories or instances ['plutonium']" in capsys.readouterr().err
    # a misspelt name beside a good one is refused too (it used to record the metal shards only), before any
    # folder is made
    assert main(["dataset", "--out", str(tmp_path / "y"), "--categories", "metal,wodo", "--quiet"]) == 2
    assert "['wodo']" in capsys.readouterr().err
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()
    with pytest.raises(SystemExit):
        main(["dataset", "--out", str(tmp_path / "z"), "--seed", "-1"])
    assert "argument --seed: expected a whole number >= 0, got '-1'" in capsys.readouterr().err


def test_a_subset_records_the_shards_of_the_full_data_set():
    catalogue = dataset.default_catalogue()
    full = {job.instance: job for job in dataset.plan_jobs(DatasetConfig(), catalogue)}
    wood = dataset.plan_jobs(DatasetConfig(categories=("wood",)), catalogue)
    assert wood and all(job == full[job.instance] for job in wood)  # same index, so the same seed and strokes


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


def test_drawn_material_is_the_recorded_objects_own_draw(monkeypatch):
    """``drawn_material`` draws each stroke's object again from the seed in its meta: the very sample that
    ``record_shard`` handed the simulator and the emulation, and it refuses a stroke whose object it cannot
    draw again."""
    import dataclasses

    drawn = []
    sample_material = dataset.sample_material

    def spy(material, rng):
        drawn.append(sample_material(material, rng))
        return drawn[-1]

    monkeypatch.setattr(dataset, "sample_material", spy)
    config = DatasetConfig(**{**FAST, "instances": ("pine",), "strokes_per_instance": 2, "objects_per_instance": 2})
    records = dataset.record_shard(dataset.plan_jobs(config, dataset.default_catalogue())[0], config)
    monkeypatch.setattr(dataset, "sample_material", sample_material)
    assert len(records) == 2 and len(drawn) == 2 and drawn[0] != drawn[1]
    assert [dataset.drawn_material(r) for r in records] == drawn

    moved = dataclasses.replace(records[0], meta={**records[0].meta, "size_m": [0.05, 0.05, 0.05]})
    with pytest.raises(RobotDemoError, match="recorded by other code or with another catalogue"):
        dataset.drawn_material(moved)
    with pytest.raises(RobotDemoError, match="no surface_seed or size_m"):
        dataset.drawn_material(dataclasses.replace(records[0], meta={}))
    with pytest.raises(RobotDemoError, match="not in the material catalogue"):
        dataset.drawn_material(dataclasses.replace(records[0], instance="unobtainium"))
