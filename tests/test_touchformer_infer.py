"""The fused inference TouchFormer computes what the reference model computes, from the same weights."""

from __future__ import annotations

import pytest
import torch

from perception.baselines import build_model
from perception.features import FeatureBatch, FeatureConfig, frame_clock_s
from perception.streams import MODALITIES
from perception.touchformer import TouchFormer
from perception.touchformer_infer import FusedTouchFormer, for_inference
from tests.test_touchformer import IN_DIMS, make_batch, tiny_config


def perturbed_model(seed: int, **overrides) -> TouchFormer:
    """A TouchFormer whose every parameter (LayerNorm gains and biases included) is random, in eval mode."""
    torch.manual_seed(seed)
    model = TouchFormer(tiny_config(**overrides))
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.3 * torch.randn_like(p))
    return model.eval()


def assert_same_outputs(model: TouchFormer, batch: FeatureBatch) -> None:
    fused = FusedTouchFormer(model)
    with torch.inference_mode():
        ref, out = model(batch), fused(batch)
    for field in ref._fields:
        torch.testing.assert_close(getattr(out, field), getattr(ref, field), rtol=1e-4, atol=1e-5,
                                   msg=lambda m: f"{field}: {m}")


@pytest.mark.parametrize("overrides", [{}, {"n_layers": 2, "n_heads": 4}, {"use_mag": False},
                                       {"gate_th": 0.6, "gate_temperature": 0.3}, {"max_pool": True},
                                       {"stem_dilations": (1, 2)}, {"gate_pool": "hidden"}, {"head_mlp": True},
                                       {"final_norm": False}, {"final_norm": True}, {"residual_base": "plain"},
                                       {"inter_modal": False}, {"inter_modal": False, "residual_base": "plain"},
                                       {"time_bias": True, "frame_clock_s": frame_clock_s(FeatureConfig()),
                                        "n_heads": 4}])
def test_fused_matches_reference_with_padding_and_missing_modalities(overrides):
    # p_missing drops streams per stroke; strokes differ in length, so every modality is padded in the batch
    batch = make_batch(seed=3, n_per_class=4, p_missing=0.3)
    assert any(not bool(batch.present[m].all()) for m in MODALITIES)
    assert any(bool(batch.padding[m].any()) for m in MODALITIES)
    assert_same_outputs(perturbed_model(seed=1, **overrides), batch)


def test_fused_matches_reference_for_a_stroke_with_no_stream_at_all():
    batch = make_batch(seed=4, n_per_class=1)
    for m in MODALITIES:  # sample 0 loses every modality
        batch.present[m][0] = False
        batch.padding[m][0] = True
        batch.x[m][0] = 0.0
    assert_same_outputs(perturbed_model(seed=2), batch)


def test_fused_matches_reference_at_batch_one():
    batch = make_batch(seed=5, n_per_class=1)
    single = FeatureBatch(x={m: v[:1] for m, v in batch.x.items()},
                          padding={m: v[:1] for m, v in batch.padding.items()},
                          present={m: v[:1] for m, v in batch.present.items()})
    assert_same_outputs(perturbed_model(seed=3, n_layers=3), single)


def test_fused_model_refuses_training_and_other_models_pass_through():
    fused = for_inference(perturbed_model(seed=0))
    assert isinstance(fused, FusedTouchFormer) and not fused.training
    with pytest.raises(RuntimeError, match="inference only"):
        fused.train()
    _, lstm = build_model("lstm", IN_DIMS, 3)
    assert for_inference(lstm) is lstm and not lstm.training
