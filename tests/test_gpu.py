"""The CUDA path (``--device auto`` on a machine with a GPU, or ``cuda``): training, resuming, checkpoints and
the evaluation.

These tests carry the ``gpu`` mark, which ``make test`` leaves out (CI has no GPU); ``make test-gpu`` runs them.
Where CUDA is missing they fail instead of skipping, so a run that was meant to check the GPU cannot pass
without one.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from perception.baselines import build_model
from perception.checkpoint import load_checkpoint
from perception.evaluate import evaluate
from perception.features import collate, feature_dims
from perception.train import TrainConfig, predict, resolve_device
from tests.test_evaluate import _write_toy_clean_and_fire
from tests.test_train import _config, _fit, _test_accuracy, toy  # noqa: F401 (toy is a fixture)

pytestmark = pytest.mark.gpu


@pytest.fixture(autouse=True)
def cuda() -> None:
    if not torch.cuda.is_available():
        pytest.fail("CUDA is not available: the gpu tests (make test-gpu) need a machine with a GPU")


@pytest.mark.parametrize("model", ["touchformer", "touchformer_soft", "lstm", "mtcnn"])
def test_auto_trains_on_the_gpu_and_the_checkpoint_predicts_the_same_on_the_cpu(toy, tmp_path, model):  # noqa: F811
    assert resolve_device("auto").type == "cuda"
    result = _fit(toy, _config(model, device="auto"), tmp_path / model)
    assert result.device.startswith("cuda")
    assert result.history[-1]["train_loss"] < result.history[0]["train_loss"]
    assert _test_accuracy(toy, result.checkpoint_dir) >= 0.6  # on the CPU; chance is 1/3
    on_gpu, on_cpu = load_checkpoint(result.checkpoint_dir, "cuda"), load_checkpoint(result.checkpoint_dir, "cpu")
    assert next(on_gpu.model.parameters()).is_cuda and not next(on_cpu.model.parameters()).is_cuda
    feats = [toy["feats"][i] for i in toy["test"]]
    dims = feature_dims(on_cpu.feature_config)
    gpu = predict(on_gpu.model, feats, dims, stats=on_gpu.norm_stats, device="cuda")
    cpu = predict(on_cpu.model, feats, dims, stats=on_cpu.norm_stats, device="cpu")
    np.testing.assert_allclose(gpu.logits, cpu.logits, atol=1e-3, rtol=1e-3)
    np.testing.assert_allclose(gpu.alphas, cpu.alphas, atol=1e-4)
    assert np.array_equal(gpu.pred, cpu.pred)


def test_forward_with_padding_and_a_missing_sensor_matches_the_cpu(toy):  # noqa: F811
    torch.manual_seed(0)
    dims = feature_dims(TrainConfig().feature_config)
    _, model = build_model("touchformer", tuple(dims.values()), 3, d_model=16, n_heads=2, n_layers=1, gate_hidden=8,
                           emb_dim=16)
    model.eval()
    feats = [dict(toy["feats"][i]) for i in range(6)]
    feats[1]["sound"] = None  # an absent microphone
    feats[2]["accel"] = None
    for m in ("sound", "normal"):  # shorter strokes: padded
        feats[3][m] = feats[3][m][: len(feats[3][m]) // 2]
    batch = collate(feats, dims)
    assert not bool(batch.present["sound"][1]) and bool(batch.padding["normal"][3].any())  # masks are exercised
    with torch.no_grad():
        cpu = model(batch)
        gpu = model.to("cuda")(batch.to("cuda"))
    for name in ("logits", "embedding", "alphas"):
        torch.testing.assert_close(getattr(gpu, name).cpu(), getattr(cpu, name), atol=1e-4, rtol=1e-4, msg=name)
    assert float(gpu.alphas[1, 0]) == 0.0  # the missing sound gets no weight on the GPU either


def test_bfloat16_forward_on_the_gpu_agrees_with_float32(toy):  # noqa: F811
    torch.manual_seed(0)
    dims = feature_dims(TrainConfig().feature_config)
    _, model = build_model("touchformer", tuple(dims.values()), 3, d_model=16, n_heads=2, n_layers=1, gate_hidden=8,
                           emb_dim=16)
    feats = [dict(toy["feats"][i]) for i in range(8)]
    feats[1]["sound"] = None
    batch = collate(feats, dims).to("cuda")
    half = dataclasses.replace(batch, x={m: v.to(torch.bfloat16) for m, v in batch.x.items()})
    model = model.eval().to("cuda")
    with torch.no_grad():
        ref = model(batch)
        out = model.to(torch.bfloat16)(half)
    assert out.logits.dtype == torch.bfloat16 and bool(torch.isfinite(out.logits.float()).all())
    torch.testing.assert_close(out.alphas.float(), ref.alphas, atol=0.05, rtol=0.05)
    assert float(out.alphas[1, 0]) == 0.0  # the missing sound gets no weight in bfloat16 either
    torch.testing.assert_close(out.logits.float(), ref.logits, atol=0.02, rtol=0.02)  # seen: within 0.0033
    assert (out.logits.float().argmax(dim=1) == ref.logits.argmax(dim=1)).float().mean() >= 0.75

def test_a_run_begun_on_the_gpu_resumes_on_the_gpu_and_on_the_cpu(toy, tmp_path):  # noqa: F811
    config = _config(epochs=3, device="cuda")

    class Interrupt(Exception):
        pass

    def stop_after_two(row):
        if row["epoch"] == 2:
            raise Interrupt

    for where in ("cuda", "cpu"):
        with pytest.raises(Interrupt):
            _fit(toy, config, tmp_path / where, on_epoch_end=stop_after_two)
        resumed = _fit(toy, dataclasses.replace(config, device=where), tmp_path / where)
        assert resumed.resumed_from_epoch == 2 and len(resumed.history) == 3 and resumed.device.startswith(where)
        assert resumed.history[-1]["train_loss"] < resumed.history[0]["train_loss"]
        assert not list(tmp_path.glob(f"{where}.stale-*"))


def _check_gpu_report(out: Path) -> None:
    saved = json.loads((out / "results.json").read_text())
    assert saved["provenance"]["device"].startswith("cuda")
    runs = sorted((out / "runs").rglob("train_result.json"))
    assert len(runs) > 30 and (out / "runs" / "fire" / "seed0" / "finetuned_touchformer" / "train_result.json") in runs
    for run in runs:  # every run, the ones trained by forked workers too
        assert json.loads(run.read_text())["device"].startswith("cuda"), run
    for task in ("ssmc", "usmc", "fine"):
        assert 0.0 <= saved["table1"][task]["touchformer"]["accuracy"]["mean"] <= 1.0
    assert (out / "REPORT.md").is_file() and (out / "robustness.png").stat().st_size > 0


def test_evaluate_command_with_workers_trains_on_the_gpu(tmp_path):
    """A fresh process, as `robotdemo evaluate --workers 2` is: its forked workers train on the GPU."""
    _write_toy_clean_and_fire(tmp_path)
    out = tmp_path / "report"
    done = subprocess.run([sys.executable, "-m", "robotdemo", "evaluate", "--data", str(tmp_path / "clean"), "--fire",
                           str(tmp_path / "fire"), "--quick", "--quiet", "--workers", "2", "--out", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    _check_gpu_report(out)


def test_evaluate_with_workers_after_cuda_was_used_here_trains_in_this_process(tmp_path, capsys):
    torch.zeros(1, device="cuda")  # CUDA initialised in this process: a forked worker could not use it
    assert torch.cuda.is_initialized()
    _write_toy_clean_and_fire(tmp_path)
    evaluate(tmp_path / "clean", tmp_path / "report", quick=True, fire_dir=tmp_path / "fire", progress=False,
             device="auto", workers=2, command="robotdemo evaluate --quick --workers 2")
    assert "forked workers could not use it" in capsys.readouterr().err
    _check_gpu_report(tmp_path / "report")
