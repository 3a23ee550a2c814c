"""LMT haptic database converter (perception.lmt), on small .mat files written in that layout."""

from __future__ import annotations

import re

import numpy as np
import pytest
import scipy.io

from perception.dataset import load_dataset
from perception.lmt import LMTConfig, LMTFormatError, convert_lmt, read_lmt_recording, scan_lmt
from perception.streams import NOMINAL_RATE_HZ


def _recording(rng, seconds=0.2):
    n_sound, n_10k = int(seconds * 44_100), int(seconds * 10_000)
    return {"sound": rng.normal(size=n_sound), "normalForce": 2.0 + 0.1 * rng.normal(size=n_10k),
            "frictionForce": 0.5 + 0.05 * rng.normal(size=n_10k), "accelDFT": rng.normal(size=n_10k)}


def _write_layout(root, rng, folders=("C1_S1_M1", "C1_S2_M2", "C3_S1_M5"), per_folder=2):
    for name in folders:
        (root / name).mkdir(parents=True)
        for k in range(per_folder):
            scipy.io.savemat(root / name / f"rec{k}.mat", {"finalMaterialRecording": _recording(rng)})
    (root / "README_not_a_material").mkdir()  # ignored


def test_convert_layout_to_dataset(tmp_path):
    rng = np.random.default_rng(0)
    _write_layout(tmp_path / "lmt", rng)
    config = LMTConfig(category_names={1: "wood"}, combustible_categories=frozenset({"wood"}), shard_size=4)
    convert_lmt(tmp_path / "lmt", tmp_path / "ds", config, progress=False)
    data = load_dataset(tmp_path / "ds")
    assert len(data) == 6 and data.manifest["config"]["source"] == "lmt"
    assert sorted({r.category for r in data.records}) == ["C3", "wood"]
    assert {r.instance for r in data.records} == {"C1_S1_M1", "C1_S2_M2", "C3_S1_M5"}
    for r in data.records:
        assert r.combustible == (r.category == "wood") and r.meta["object_id"] == r.instance
        assert r.streams["sound"].rate_hz == 44_100.0 and r.streams["sound"].data.shape == (8820, 1)
        for key in ("normal", "friction", "accel"):  # resampled to the nominal rates, 0.2 s long
            assert r.streams[key].rate_hz == NOMINAL_RATE_HZ[key]
            assert r.streams[key].data.shape[0] == pytest.approx(0.2 * NOMINAL_RATE_HZ[key], abs=1)
        normal = r.streams["normal"].data
        assert np.allclose(normal.sum(axis=1).mean(), 2.0, atol=0.05)  # taxels sum to the measured force


def test_single_channel_mapping_without_resampling(tmp_path):
    rng = np.random.default_rng(1)
    fields = _recording(rng)
    scipy.io.savemat(tmp_path / "r.mat", {"finalMaterialRecording": fields})
    rec = read_lmt_recording(tmp_path / "r.mat", "C2", "C2_S1_M1", False, LMTConfig(resample=False))
    normal, shear, accel = (rec.streams[k].data for k in ("normal", "friction", "accel"))
    assert rec.streams["normal"].rate_hz == 10_000.0
    assert np.allclose(normal.sum(axis=1), fields["normalForce"], atol=1e-5)
    assert np.allclose(normal, normal[:, :1])  # uniform taxels
    assert np.allclose(shear[:, 0::2].sum(axis=1), fields["frictionForce"], atol=1e-5)
    assert np.all(shear[:, 1::2] == 0)
    assert np.allclose(accel[:, 0], fields["accelDFT"], atol=1e-6) and np.all(accel[:, 1:] == 0)


def test_wrong_layouts_raise_with_the_file(tmp_path):
    with pytest.raises(LMTFormatError, match="not found"):
        scan_lmt(tmp_path / "missing")
    (tmp_path / "flat").mkdir()
    with pytest.raises(LMTFormatError, match="C<category>_S<subcategory>_M<material>"):
        scan_lmt(tmp_path / "flat")
    (tmp_path / "empty" / "C1_S1_M1").mkdir(parents=True)
    with pytest.raises(LMTFormatError, match="no .mat recordings"):
        scan_lmt(tmp_path / "empty")
    rng = np.random.default_rng(2)
    bad = tmp_path / "bad" / "C1_S1_M1"
    bad.mkdir(parents=True)
    scipy.io.savemat(bad / "wrong_struct.mat", {"somethingElse": _recording(rng)})
    with pytest.raises(LMTFormatError, match="wrong_struct.mat.*finalMaterialRecording"):
        convert_lmt(tmp_path / "bad", tmp_path / "out", progress=False)
    (tmp_path / "junk.mat").write_bytes(b"not a mat file")
    with pytest.raises(LMTFormatError, match="junk.mat"):
        read_lmt_recording(tmp_path / "junk.mat", "C1", "x", False)


def _write(path, fields):
    path.parent.mkdir(parents=True, exist_ok=True)
    scipy.io.savemat(path, {"finalMaterialRecording": fields})


@pytest.mark.parametrize("edit, problem", [
    (lambda f: {**f, "normalForce": np.full(len(f["normalForce"]), np.nan)}, "normalForce' contains NaN"),
    (lambda f: {**f, "accelDFT": f["accelDFT"] * (1 + 1j)}, "accelDFT' is complex"),
    (lambda f: {**f, "frictionForce": f["frictionForce"][:10]}, "differ in length (2000 and 10 samples)"),
    (lambda f: {**f, "accelDFT": f["accelDFT"][:600]}, "last different times at the configured rates"),
    (lambda f: {}, "has none of the fields"),
])
def test_malformed_recordings_are_named(tmp_path, edit, problem):
    _write(tmp_path / "r.mat", edit(_recording(np.random.default_rng(3))))
    with pytest.raises(LMTFormatError, match=re.escape(problem)) as info:
        read_lmt_recording(tmp_path / "r.mat", "C1", "x", False)
    assert str(info.value).startswith(str(tmp_path / "r.mat")) and "\n" not in str(info.value)


def test_a_wrong_rate_is_caught_by_the_durations(tmp_path):
    """Forces and acceleration recorded at 3 kHz but read at the default 10 kHz would last 0.3 of the sound."""
    rng = np.random.default_rng(4)
    n_sound, n_3k = int(0.2 * 44_100), int(0.2 * 3_000)
    _write(tmp_path / "r.mat", {"sound": rng.normal(size=n_sound), "normalForce": 2 + rng.normal(size=n_3k),
                                "frictionForce": 0.5 + rng.normal(size=n_3k), "accelDFT": rng.normal(size=n_3k)})
    with pytest.raises(LMTFormatError, match="sound 0.2 s, forces 0.06 s, accelDFT 0.06 s"):
        read_lmt_recording(tmp_path / "r.mat", "C1", "x", False)
    rec = read_lmt_recording(tmp_path / "r.mat", "C1", "x", False, LMTConfig(force_rate_hz=3000, accel_rate_hz=3000))
    assert rec.streams["normal"].data.shape[0] == pytest.approx(0.2 * NOMINAL_RATE_HZ["normal"], abs=1)
    # streams that do differ in length pass with a looser guard
    loose = read_lmt_recording(tmp_path / "r.mat", "C1", "x", False, LMTConfig(max_duration_mismatch=3.0))
    assert loose.streams["normal"].data.shape[0] == pytest.approx(0.06 * NOMINAL_RATE_HZ["normal"], abs=1)


def test_missing_fields_are_absent_streams_and_constant_forces_stay_constant(tmp_path):
    fields = _recording(np.random.default_rng(5))
    del fields["accelDFT"]
    fields["sound"] = np.zeros(0)  # empty: absent too
    fields["normalForce"] = np.full(len(fields["normalForce"]), 2.0)
    _write(tmp_path / "r.mat", fields)
    rec = read_lmt_recording(tmp_path / "r.mat", "C1", "x", False)
    assert rec.streams["accel"] is None and rec.streams["sound"] is None
    # the resampler extrapolates at the ends instead of padding with zeros (which rang by about 9 %)
    np.testing.assert_allclose(rec.streams["normal"].data.sum(axis=1), 2.0, rtol=1e-3)


def test_nested_layout_skipped_files_and_bad_recordings_are_counted(tmp_path):
    rng = np.random.default_rng(6)
    root = tmp_path / "lmt"
    _write(root / "C1" / "S2" / "M3" / "a.mat", _recording(rng))   # nested layout
    _write(root / "deep" / "C4_S1_M1" / "b.MAT", _recording(rng))  # flat layout one level down, upper case
    _write(root / "C5_S1_M2" / "bad.mat", {**_recording(rng), "sound": np.full(10, np.nan)})
    _write(root / "loose.mat", _recording(rng))                     # outside any material folder
    _write(root / "C6_S1" / "c.mat", _recording(rng))               # not a material folder name
    scan = scan_lmt(root)
    assert [f.path.relative_to(root).as_posix() for f in scan.folders] == ["C1/S2/M3", "C5_S1_M2", "deep/C4_S1_M1"]
    assert sorted(p.name for p in scan.skipped) == ["c.mat", "loose.mat"]
    with pytest.raises(LMTFormatError, match="bad.mat: field 'sound' contains NaN"):
        convert_lmt(root, tmp_path / "ds", progress=False)
    result = convert_lmt(root, tmp_path / "ds", LMTConfig(skip_bad=True), progress=False)
    assert result.n_recordings == 2 and len(result.skipped_outside) == 2
    assert [(p.name, problem) for p, problem in result.skipped_bad] == [("bad.mat", "field 'sound' contains NaN or inf")]
    data = load_dataset(tmp_path / "ds")
    assert sorted(r.instance for r in data.records) == ["C1_S2_M3", "C4_S1_M1"]
    assert sorted(r.category for r in data.records) == ["C1", "C4"]
    assert data.manifest["config"]["skipped_outside"] == 2 and data.manifest["config"]["skipped_bad"] == 1


def test_convert_lmt_command(tmp_path, capsys):
    from robotdemo.cli import main

    rng = np.random.default_rng(7)
    _write(tmp_path / "lmt" / "C1_S1_M1" / "a.mat", _recording(rng))
    _write(tmp_path / "lmt" / "C2_S1_M1" / "b.mat", _recording(rng))
    _write(tmp_path / "lmt" / "C2_S1_M1" / "bad.mat", {**_recording(rng), "normalForce": np.full(5, np.nan)})
    args = ["convert-lmt", str(tmp_path / "lmt"), "--out", str(tmp_path / "ds"), "--quiet"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "bad.mat: field 'normalForce'" in err and len(err.strip().splitlines()) == 1
    assert main([*args, "--skip-bad", "--combustible", "C2"]) == 0
    out = capsys.readouterr().out
    assert "2 recordings" in out and "1 skipped as malformed" in out
    data = load_dataset(tmp_path / "ds")
    assert {r.category: r.combustible for r in data.records} == {"C1": False, "C2": True}
