"""LMT haptic database converter (perception.lmt), on small .mat files written in that layout."""

from __future__ import annotations

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
    with pytest.raises(LMTFormatError, match="C1_S1_M1.*no .mat"):
        scan_lmt(tmp_path / "empty")
    rng = np.random.default_rng(2)
    bad = tmp_path / "bad" / "C1_S1_M1"
    bad.mkdir(parents=True)
    scipy.io.savemat(bad / "wrong_struct.mat", {"somethingElse": _recording(rng)})
    with pytest.raises(LMTFormatError, match="wrong_struct.mat.*finalMaterialRecording"):
        convert_lmt(tmp_path / "bad", tmp_path / "out", progress=False)
    fields = _recording(rng)
    del fields["accelDFT"]
    scipy.io.savemat(tmp_path / "no_accel.mat", {"finalMaterialRecording": fields})
    with pytest.raises(LMTFormatError, match="no_accel.mat.*accelDFT"):
        read_lmt_recording(tmp_path / "no_accel.mat", "C1", "x", False)
    (tmp_path / "junk.mat").write_bytes(b"not a mat file")
    with pytest.raises(LMTFormatError, match="junk.mat"):
        read_lmt_recording(tmp_path / "junk.mat", "C1", "x", False)
