"""Per-sensor MAG use (perception.sensor_use): mean weights and the share of strokes the gate dropped each sensor
on, over the strokes that carry it; every training run records it and warns when the gate shut a sensor out."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from perception.dataset import write_dataset
from perception.sensor_use import SensorUse, presence_matrix, sensor_use, shut_out, shut_out_warning
from perception.streams import MODALITIES
from perception.touchformer import mag_weights
from robotdemo.cli import main
from tests.test_dataset import make_material_strokes

TINY_TOUCHFORMER = ["--model-option", "d_model=16", "--model-option", "n_heads=2", "--model-option", "n_layers=1",
                    "--model-option", "gate_hidden=8", "--model-option", "emb_dim=16"]


def test_counts_only_the_strokes_that_carry_the_sensor():
    alphas = np.array([[0.5, 0.0, 0.5, 0.0],
                       [0.4, 0.0, 0.3, 0.3],
                       [1.0, 0.0, 0.0, 0.0]])
    present = np.array([[True, True, True, False],  # accel absent: its 0 is not a drop
                        [True, True, True, True],
                        [True, False, True, False]])
    use = sensor_use(alphas, present)
    assert list(use) == list(MODALITIES)
    sound, normal, friction, accel = (use[m] for m in MODALITIES)
    assert sound == SensorUse(n_strokes=3, mean_alpha=pytest.approx(0.6333333), dropped_share=0.0)
    assert normal.n_strokes == 2 and normal.mean_alpha == 0.0 and normal.dropped_share == 1.0
    assert friction.n_strokes == 3 and friction.dropped_share == pytest.approx(1 / 3)
    assert accel.n_strokes == 1 and accel.mean_alpha == pytest.approx(0.3) and accel.dropped_share == 0.0
    assert shut_out(use) == {"normal": 1.0}


def test_a_sensor_no_stroke_carries_has_no_figures():
    use = sensor_use(np.array([[1.0, 0.0, 0.0, 0.0]]), np.array([[True, False, False, False]]))
    assert use["normal"] == SensorUse(n_strokes=0, mean_alpha=None, dropped_share=None)
    assert json.loads(json.dumps(use["normal"].to_dict())) == {"n_strokes": 0, "mean_alpha": None,
                                                               "dropped_share": None}
    assert shut_out(use) == {} and shut_out_warning(use) is None


def test_reads_the_drops_of_the_models_own_gate():
    """Gates under gate_th give alpha 0 (mag_weights, the model's step 2); sensor_use counts exactly those."""
    gen = torch.Generator().manual_seed(0)
    gates = torch.rand(200, 4, generator=gen)
    gates[:, 1] *= 0.2  # the normal force's gate mostly under the threshold
    present = torch.ones(200, 4, dtype=torch.bool)
    present[:50, 3] = False
    alphas = mag_weights(gates * present, present, gate_th=0.1).numpy()
    use = sensor_use(alphas, present.numpy())
    expected_normal = float(np.mean(gates[:, 1].numpy() < 0.1))
    assert use["normal"].dropped_share == pytest.approx(expected_normal)
    assert use["accel"].n_strokes == 150
    assert use["accel"].dropped_share == pytest.approx(float(np.mean(gates[50:, 3].numpy() < 0.1)))
    assert sum(u.mean_alpha * u.n_strokes for u in use.values()) == pytest.approx(200.0, rel=1e-5)  # rows sum to 1


@pytest.mark.parametrize("alphas, present, message", [
    (np.zeros((2, 3)), np.ones((2, 3), bool), "shape (N, 4)"),
    (np.zeros((2, 4)), np.ones((3, 4), bool), "shape (N, 4)"),
    (np.full((1, 4), np.nan), np.ones((1, 4), bool), "NaN or inf"),
    (np.full((1, 4), -0.5), np.ones((1, 4), bool), "must lie in [0, 1]"),
])
def test_bad_alphas_are_refused(alphas, present, message):
    with pytest.raises(ValueError) as info:
        sensor_use(alphas, present)
    assert message in str(info.value)


def test_presence_matrix_and_the_warning_line():
    feats = [{"sound": np.zeros((3, 2)), "normal": None, "friction": np.zeros((3, 2))}, {m: 1 for m in MODALITIES}]
    assert presence_matrix(feats).tolist() == [[True, False, True, False], [True] * 4]
    assert presence_matrix([]).shape == (0, 4)
    use = {"sound": SensorUse(10, 0.9, 0.0), "normal": SensorUse(10, 0.0, 1.0), "friction": SensorUse(10, 0.05, 0.8),
           "accel": SensorUse(10, 0.05, 0.5)}
    line = shut_out_warning(use)
    assert line is not None and "\n" not in line
    assert "normal on 100 %, friction on 80 %" in line and "accel" not in line  # 0.5 is not more than half
    assert "gate_straight_through" in line


def test_a_training_run_records_sensor_use_and_warns_when_the_gate_shuts_sensors_out(tmp_path, capsys):
    recs = make_material_strokes(4, n_categories=2, n_instances=2, n_objects=2, n_strokes=3, duration_s=0.2)
    write_dataset(tmp_path / "ds", recs, env="clean", seed=4)
    # A threshold no gate reaches after one epoch: every stroke keeps only its largest gate, so three of the four
    # sensors are dropped on every stroke, and the run says so.
    code = main(["train", "--data", str(tmp_path / "ds"), "--out", str(tmp_path / "shut"), "--epochs", "1",
                 "--quiet", "--model-option", "gate_th=0.99", *TINY_TOUCHFORMER])
    assert code == 0
    captured = capsys.readouterr()
    metrics = json.loads((tmp_path / "shut" / "metrics.json").read_text())
    use = metrics["val_sensor_use"]
    assert set(use) == set(MODALITIES)
    assert all(u["n_strokes"] == metrics["n_val"] for u in use.values())
    assert sum(u["dropped_share"] for u in use.values()) == pytest.approx(3.0)
    assert sum(u["mean_alpha"] for u in use.values()) == pytest.approx(1.0, abs=1e-6)
    assert "warning: the gate dropped" in captured.err and len(captured.err.strip().splitlines()) == 1
    # A baseline without a gate weighs its sensors evenly: nothing dropped, no warning.
    code = main(["train", "--data", str(tmp_path / "ds"), "--out", str(tmp_path / "mtcnn"), "--epochs", "1",
                 "--quiet", "--model", "mtcnn", "--model-option", "channels=8"])
    assert code == 0
    assert "warning" not in capsys.readouterr().err
    use = json.loads((tmp_path / "mtcnn" / "metrics.json").read_text())["val_sensor_use"]
    assert all(u["dropped_share"] == 0.0 and u["mean_alpha"] == pytest.approx(0.25) for u in use.values())
