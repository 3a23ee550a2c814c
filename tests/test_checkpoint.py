"""Checkpoint round trip and clear errors for bad checkpoints (perception.checkpoint)."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import pytest
import safetensors.torch
import torch

from perception.baselines import MODEL_REGISTRY, build_model
from perception.checkpoint import (CONFIG_FILE, WEIGHTS_FILE, CheckpointError, load_checkpoint, save_checkpoint,
                                  set_temperature)
from perception.features import FeatureConfig, feature_dims, featurize, fit_norm_stats, frame_clock_s
from perception.streams import MODALITIES
from tests.test_baselines import TINY
from tests.test_features import make_synthetic_strokes
from tests.test_touchformer import IN_DIMS, make_batch

torch.set_num_threads(2)

CLASSES = ("class0", "class1", "class2")


def _save(directory: Path, name: str = "touchformer"):
    torch.manual_seed(0)
    config, model = build_model(name, IN_DIMS, 3, **TINY[name])
    cfg = FeatureConfig()
    feats = [featurize(r, cfg) for r in make_synthetic_strokes(1, seed=30)]
    stats = fit_norm_stats(feats, feature_dims(cfg))
    save_checkpoint(directory, name, model, config, cfg, stats, CLASSES,
                    meta={"command": "robotdemo train --model " + name, "seed": 0})
    return model.eval(), stats


def _edit_config(directory: Path, edit) -> None:
    path = directory / CONFIG_FILE
    record = json.loads(path.read_text())
    edit(record)
    path.write_text(json.dumps(record))


def _expect_error(directory: Path, file_name: str, match: str) -> CheckpointError:
    with pytest.raises(CheckpointError, match=match) as info:
        load_checkpoint(directory)
    message = str(info.value)
    assert "\n" not in message and file_name in message
    return info.value


@pytest.mark.parametrize("name", sorted(MODEL_REGISTRY))
def test_round_trip_gives_identical_outputs(tmp_path, name):
    model, stats = _save(tmp_path, name)
    loaded = load_checkpoint(tmp_path)
    assert loaded.model_name == name and loaded.class_names == CLASSES
    assert loaded.model_config == model.config and loaded.feature_config == FeatureConfig()
    assert loaded.norm_stats == stats and loaded.meta["seed"] == 0
    assert not loaded.model.training
    batch = make_batch(seed=31, p_missing=0.2)
    with torch.no_grad():
        for a, b in zip(model(batch), loaded.model(batch)):
            assert torch.equal(a, b)


def test_config_saved_before_final_norm_existed_loads_with_the_closing_layernorm(tmp_path):
    model, _ = _save(tmp_path, "touchformer")
    assert not model.config.final_norm  # the default since session 22
    with_norm = model.config.__class__(**{**model.config.__dict__, "final_norm": True})
    torch.manual_seed(0)
    old_model = type(model)(with_norm)
    safetensors.torch.save_file(old_model.state_dict(), str(tmp_path / WEIGHTS_FILE))
    _edit_config(tmp_path, lambda r: r["model_config"].pop("final_norm"))  # as written before the field existed
    loaded = load_checkpoint(tmp_path)
    assert loaded.model_config.final_norm and isinstance(loaded.model.intra["sound"].ln_f, torch.nn.LayerNorm)
    # the robot's committed checkpoint was trained before the field existed and still loads, with it
    robot_dir = Path(__file__).resolve().parents[1] / "robotdemo" / "checkpoints" / "touchformer_fire"
    robot = load_checkpoint(robot_dir)
    saved = json.loads((robot_dir / CONFIG_FILE).read_text())["model_config"]
    assert robot.model_config.final_norm == saved.get("final_norm", True)


def test_time_biased_touchformer_round_trips_and_a_clock_other_than_its_front_ends_is_refused(tmp_path):
    cfg = FeatureConfig()
    torch.manual_seed(0)
    config, model = build_model("touchformer", IN_DIMS, 3, time_bias=True, frame_clock_s=frame_clock_s(cfg),
                                **TINY["touchformer"])
    stats = fit_norm_stats([featurize(r, cfg) for r in make_synthetic_strokes(1, seed=30)], feature_dims(cfg))
    save_checkpoint(tmp_path, "touchformer", model, config, cfg, stats, CLASSES)
    loaded = load_checkpoint(tmp_path)
    assert loaded.model_config == config and loaded.model_config.frame_clock_s == frame_clock_s(cfg)
    batch = make_batch(seed=31, p_missing=0.2)
    with torch.no_grad():
        assert torch.equal(model.eval()(batch).logits, loaded.model(batch).logits)
    # the frames' clock must be the front ends': a changed hop moves every frame's instant
    _edit_config(tmp_path, lambda r: r["feature_config"]["accel"].update(hop_s=0.064))
    _expect_error(tmp_path, CONFIG_FILE, "frame_clock_s")


def test_missing_files(tmp_path):
    _expect_error(tmp_path / "nowhere", CONFIG_FILE, "not found")
    _save(tmp_path)
    (tmp_path / WEIGHTS_FILE).unlink()
    _expect_error(tmp_path, WEIGHTS_FILE, "not found")


def test_truncated_and_corrupt_weights(tmp_path):
    _save(tmp_path)
    path = tmp_path / WEIGHTS_FILE
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    _expect_error(tmp_path, WEIGHTS_FILE, "corrupt or truncated")
    path.write_bytes(b"\x00garbage" * 10)
    _expect_error(tmp_path, WEIGHTS_FILE, "corrupt or truncated")


def test_non_finite_weights_and_norm_stats(tmp_path):
    model, _ = _save(tmp_path)
    state = {k: v.contiguous().clone() for k, v in model.state_dict().items()}
    key = next(k for k, v in state.items() if v.is_floating_point())
    state[key].view(-1)[0] = float("nan")
    safetensors.torch.save_file(state, str(tmp_path / WEIGHTS_FILE))
    _expect_error(tmp_path, WEIGHTS_FILE, f"tensor '{key}' holds NaN or infinite values")
    _save(tmp_path)
    _edit_config(tmp_path, lambda r: r["norm_stats"]["mean"]["sound"].__setitem__(0, float("nan")))
    _expect_error(tmp_path, CONFIG_FILE, "norm_stats for sound hold NaN")
    _save(tmp_path)
    _edit_config(tmp_path, lambda r: r["norm_stats"]["std"]["accel"].__setitem__(0, 0.0))
    _expect_error(tmp_path, CONFIG_FILE, "norm_stats for accel hold NaN, infinite or non-positive std")


def test_wrong_tensor_shapes(tmp_path):
    _save(tmp_path)
    _edit_config(tmp_path, lambda r: r["model_config"].update(gate_hidden=4))
    _expect_error(tmp_path, WEIGHTS_FILE, "shape")


def test_missing_and_unexpected_keys(tmp_path):
    model, _ = _save(tmp_path)
    state = {k: v.contiguous() for k, v in model.state_dict().items()}
    dropped = dict(state)
    dropped.pop("classifier.bias")
    safetensors.torch.save_file(dropped, str(tmp_path / WEIGHTS_FILE))
    _expect_error(tmp_path, WEIGHTS_FILE, r"missing \['classifier.bias'\]")
    safetensors.torch.save_file({**state, "extra.weight": torch.zeros(2)}, str(tmp_path / WEIGHTS_FILE))
    _expect_error(tmp_path, WEIGHTS_FILE, r"unexpected \['extra.weight'\]")


def test_config_json_problems(tmp_path):
    _save(tmp_path)
    path = tmp_path / CONFIG_FILE
    original = path.read_text()
    path.write_text(original[:40])
    _expect_error(tmp_path, CONFIG_FILE, "not valid JSON")
    path.write_text(original)
    _edit_config(tmp_path, lambda r: r["model_config"].update(n_experts=3))
    _expect_error(tmp_path, CONFIG_FILE, "n_experts")
    path.write_text(original)
    _edit_config(tmp_path, lambda r: r.update(model_name="gpt"))
    _expect_error(tmp_path, CONFIG_FILE, "unknown model 'gpt'")
    path.write_text(original)
    _edit_config(tmp_path, lambda r: r["feature_config"]["sound"].update(n_coeffs=13))
    _expect_error(tmp_path, CONFIG_FILE, "in_dims")
    path.write_text(original)
    _edit_config(tmp_path, lambda r: r.update(class_names=["a", "b"]))
    _expect_error(tmp_path, CONFIG_FILE, "class names")
    path.write_text(original)
    _edit_config(tmp_path, lambda r: r.update(format="something-else"))
    _expect_error(tmp_path, CONFIG_FILE, "not a robotdemo-checkpoint")
    path.write_text(original)
    _edit_config(tmp_path, lambda r: r["norm_stats"]["mean"].update(accel=[0.0]))
    _expect_error(tmp_path, CONFIG_FILE, "norm_stats for accel")
    path.write_text(original)
    _edit_config(tmp_path, lambda r: r.update(temperature=-1.0))
    _expect_error(tmp_path, CONFIG_FILE, "temperature must be a positive number")


def test_temperature_is_stored_beside_the_weights(tmp_path):
    """A checkpoint without a temperature loads with 1.0; a fitted one is stored in config.json, the weights
    file untouched, and a bad one is refused before anything is written."""
    _save(tmp_path)
    weights = (tmp_path / WEIGHTS_FILE).read_bytes()
    assert load_checkpoint(tmp_path).temperature == 1.0
    set_temperature(tmp_path, 2.5)
    assert load_checkpoint(tmp_path).temperature == 2.5
    assert (tmp_path / WEIGHTS_FILE).read_bytes() == weights
    config = (tmp_path / CONFIG_FILE).read_text()
    with pytest.raises(ValueError, match="positive"):
        set_temperature(tmp_path, float("nan"))
    assert (tmp_path / CONFIG_FILE).read_text() == config


def test_save_checks_config_type(tmp_path):
    config, model = build_model("lstm", IN_DIMS, 3, **TINY["lstm"])
    with pytest.raises(TypeError, match="LSTMConfig"):
        save_checkpoint(tmp_path, "mtcnn", model, config, FeatureConfig(), None, CLASSES)


def test_never_unpickles(tmp_path, monkeypatch):
    _save(tmp_path)

    def forbidden(*args, **kwargs):
        raise AssertionError("a checkpoint must not be unpickled")

    monkeypatch.setattr(torch, "load", forbidden)
    monkeypatch.setattr(pickle, "load", forbidden)
    monkeypatch.setattr(pickle, "loads", forbidden)
    assert load_checkpoint(tmp_path).model_name == "touchformer"


def test_modalities_order_is_part_of_the_contract():
    assert MODALITIES == ("sound", "normal", "friction", "accel")
