"""LSTM and MTCNN baselines and the model registry (perception.baselines)."""

from __future__ import annotations

import pytest
import torch

from perception.baselines import (MODEL_REGISTRY, LSTMClassifier, LSTMConfig, MTCNNClassifier, MTCNNConfig,
                                  build_model, resample_valid)
from perception.features import FeatureBatch
from perception.streams import MODALITIES
from perception.touchformer import ModelOutput, TouchFormer, TouchFormerConfig
from tests.test_touchformer import IN_DIMS, make_batch, synthetic_batches, train_and_score

torch.set_num_threads(2)

TINY = {
    "touchformer": dict(d_model=16, n_heads=2, n_layers=1, gate_hidden=8, emb_dim=8),
    "touchformer_mag": dict(d_model=16, n_heads=2, n_layers=1, gate_hidden=8, emb_dim=8),
    "touchformer_fusion": dict(d_model=16, n_heads=2, n_layers=1, gate_hidden=8, emb_dim=8),
    "touchformer_soft": dict(d_model=16, n_heads=2, n_layers=1, gate_hidden=8, emb_dim=8),
    "lstm": dict(n_steps=12, hidden=16, emb_dim=8),
    "mtcnn": dict(channels=12, dilations=(1, 2), emb_dim=8),
}


def _pad(batch: FeatureBatch, extra: int) -> FeatureBatch:
    x = {m: torch.cat([batch.x[m], torch.zeros(batch.x[m].shape[0], extra, batch.x[m].shape[2])], dim=1)
         for m in MODALITIES}
    padding = {m: torch.cat([batch.padding[m], torch.ones(batch.padding[m].shape[0], extra, dtype=torch.bool)],
                            dim=1) for m in MODALITIES}
    return FeatureBatch(x=x, padding=padding, present=batch.present, labels=batch.labels)


def _assert_padding_invariant(model, batch: FeatureBatch) -> None:
    """The model's outputs do not change when every modality gets 4 more padded steps."""
    with torch.no_grad():
        out, padded = model(batch), model(_pad(batch, 4))
    for a, b in zip(out, padded):
        assert torch.allclose(a, b, atol=1e-5)


def test_registry_lists_every_model_explicitly():
    assert set(MODEL_REGISTRY) == {"touchformer", "touchformer_fusion", "touchformer_mag", "touchformer_soft",
                                   "lstm", "mtcnn"}
    assert MODEL_REGISTRY["lstm"] == (LSTMConfig, LSTMClassifier)
    assert MODEL_REGISTRY["mtcnn"] == (MTCNNConfig, MTCNNClassifier)
    full, _ = build_model("touchformer", IN_DIMS, 3)
    mag, _ = build_model("touchformer_mag", IN_DIMS, 3)
    fusion, _ = build_model("touchformer_fusion", IN_DIMS, 3)
    soft, _ = build_model("touchformer_soft", IN_DIMS, 3)
    assert full.use_mag and full.cer_lambda > 0 and full.gate_th > 0
    assert soft.use_mag and soft.cer_lambda == full.cer_lambda and soft.gate_th == 0.0
    assert mag.use_mag and mag.cer_lambda == 0
    assert not fusion.use_mag and fusion.cer_lambda == 0
    assert not full.final_norm and not mag.final_norm and not fusion.final_norm and soft.final_norm
    assert isinstance(full, TouchFormerConfig)
    with pytest.raises(KeyError, match="known"):
        build_model("transformer", IN_DIMS, 3)


@pytest.mark.parametrize("name", sorted(MODEL_REGISTRY))
def test_every_model_returns_the_same_record(name):
    torch.manual_seed(0)
    config, model = build_model(name, IN_DIMS, 3, **TINY[name])
    model.eval()
    batch = make_batch(seed=20, p_missing=0.3)
    with torch.no_grad():
        out = model(batch)
        padded = model(_pad(batch, 4))
    assert isinstance(out, ModelOutput)
    assert out.logits.shape == (6, 3) and out.embedding.shape == (6, 8)
    assert out.gates.shape == (6, 4) and out.alphas.shape == (6, 4)
    for field in out:
        assert torch.isfinite(field).all()
    assert torch.allclose(out.embedding.norm(dim=1), torch.ones(6), atol=1e-5)
    assert torch.allclose(out.alphas.sum(dim=1), torch.ones(6), atol=1e-6)
    assert torch.all(out.alphas[~batch.present_matrix()] == 0)
    for a, b in zip(out, padded):  # padding invariance
        assert torch.allclose(a, b, atol=1e-5)


def test_mtcnn_mean_pooling_option_drops_the_maximum():
    torch.manual_seed(0)
    config, model = build_model("mtcnn", IN_DIMS, 3, max_pool=False, **TINY["mtcnn"])
    model.eval()
    assert model.fuse[0].in_features == 4 * config.channels + 4  # the mean of each sensor, and presence
    _assert_padding_invariant(model, make_batch(seed=21, p_missing=0.3))
    _, default = build_model("mtcnn", IN_DIMS, 3, **TINY["mtcnn"])
    assert default.fuse[0].in_features == 2 * 4 * config.channels + 4  # mean and maximum by default


def test_mtcnn_linear_head_option_puts_the_heads_on_the_fused_vector():
    torch.manual_seed(0)
    config, model = build_model("mtcnn", IN_DIMS, 3, mlp_head=False, **TINY["mtcnn"])
    model.eval()
    assert not any(isinstance(mod, torch.nn.Linear) for mod in model.fuse)  # no hidden layer
    assert model.classifier.in_features == 2 * 4 * config.channels + 4  # pooled sensors and presence
    _assert_padding_invariant(model, make_batch(seed=23, p_missing=0.3))
    _, default = build_model("mtcnn", IN_DIMS, 3, **TINY["mtcnn"])
    assert default.classifier.in_features == 2 * config.channels  # the MLP head's hidden width by default


def test_mtcnn_step_norm_option_normalises_each_step_before_pooling():
    torch.manual_seed(0)
    config, model = build_model("mtcnn", IN_DIMS, 3, step_norm=True, **TINY["mtcnn"])
    model.eval()
    batch = make_batch(seed=22, p_missing=0.3)
    seen = []
    hook = model.step_norm["sound"].register_forward_hook(lambda mod, inp, out: seen.append(out))
    _assert_padding_invariant(model, batch)  # the hook sees the unpadded batch first
    hook.remove()
    steps = seen[0][~batch.padding["sound"]]  # (valid steps, ch) of the unpadded batch
    assert len(steps) > 0
    assert torch.allclose(steps.mean(dim=-1), torch.zeros(len(steps)), atol=1e-5)  # each step: mean 0, std 1
    assert torch.allclose(steps.std(dim=-1, unbiased=False), torch.ones(len(steps)), atol=1e-2)
    _, default = build_model("mtcnn", IN_DIMS, 3, **TINY["mtcnn"])
    assert not any(isinstance(mod, torch.nn.LayerNorm) for mod in default.modules())  # off by default


def test_resample_valid_interpolates_the_valid_prefix():
    ramp = torch.arange(8, dtype=torch.float32).view(1, 8, 1)
    x = torch.cat([ramp, torch.full((1, 4, 1), 99.0)], dim=1)  # 4 padded steps of junk
    valid = torch.tensor([[True] * 8 + [False] * 4])
    out = resample_valid(x, valid, 4)
    assert torch.allclose(out.view(-1), torch.tensor([0.5, 2.5, 4.5, 6.5]))
    empty = resample_valid(x, torch.zeros_like(valid), 3)
    assert torch.equal(empty, torch.zeros(1, 3, 1))
    one = resample_valid(x, torch.tensor([[True] + [False] * 11]), 3)
    assert torch.equal(one.view(-1), torch.zeros(3))


def test_lstm_flags_missing_modality():
    torch.manual_seed(1)
    model = LSTMClassifier(LSTMConfig(in_dims=IN_DIMS, n_classes=3, **TINY["lstm"])).eval()
    batch = make_batch(seed=21)
    zeros = dict(batch.x)
    zeros["sound"] = torch.zeros_like(batch.x["sound"])
    present_zero = FeatureBatch(x=zeros, padding=batch.padding, present=batch.present)
    missing = FeatureBatch(x=zeros, padding=batch.padding,
                           present={**batch.present, "sound": torch.zeros(6, dtype=torch.bool)})
    with torch.no_grad():
        a, b = model(present_zero).logits, model(missing).logits
    assert not torch.allclose(a, b)  # the indicator channel tells "missing" from "silent"


@pytest.mark.parametrize("name", ["lstm", "mtcnn"])
def test_baseline_learns_held_out(name):
    torch.manual_seed(2)
    train, test = synthetic_batches(seed=22, p_missing=0.15)
    _, model = build_model(name, IN_DIMS, 3, **TINY[name])
    acc = train_and_score(model, train, test, epochs=10, lr=5e-3)
    assert acc >= 0.7, acc  # chance is 1/3


def test_touchformer_in_registry_is_touchformer():
    _, model = build_model("touchformer_fusion", IN_DIMS, 3, **TINY["touchformer_fusion"])
    assert isinstance(model, TouchFormer) and not model.config.use_mag
