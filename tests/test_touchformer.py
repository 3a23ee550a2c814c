"""TouchFormer: shapes, padding invariance, missing modalities, MAG gating, gradients, learning.

Also home of :func:`synthetic_batches` and :func:`train_and_score`, which the baseline tests import.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from perception.features import FeatureBatch, FeatureConfig, collate, feature_dims, featurize, fit_norm_stats
from perception.losses import total_loss
from perception.streams import MODALITIES
from perception.touchformer import (GATE_POOLS, CrossModalAttention, ModalityGate, ModelOutput, TouchFormer,
                                    TouchFormerConfig, TouchFormerFusionConfig, TouchFormerMagConfig,
                                    TouchFormerSoftGateConfig, mag_weights)
from tests.test_features import labels_of, make_synthetic_strokes

torch.set_num_threads(2)

FEATURES = FeatureConfig()
DIMS = feature_dims(FEATURES)
IN_DIMS = tuple(DIMS[m] for m in MODALITIES)


def tiny_config(**overrides) -> TouchFormerConfig:
    base = dict(in_dims=IN_DIMS, n_classes=3, d_model=16, n_heads=2, n_layers=1, gate_hidden=8, emb_dim=8,
                dropout=0.0, emb_dropout=0.0)
    base.update(overrides)
    return TouchFormerConfig(**base)


def make_batch(seed: int, n_per_class: int = 2, p_missing: float = 0.0) -> FeatureBatch:
    recs = make_synthetic_strokes(n_per_class, seed=seed, p_missing=p_missing)
    feats = [featurize(r, FEATURES) for r in recs]
    return collate(feats, DIMS, stats=fit_norm_stats(feats, DIMS), labels=labels_of(recs))


def synthetic_batches(seed: int, n_train_per_class: int = 20, n_test_per_class: int = 10,
                      p_missing: float = 0.0) -> tuple[list[FeatureBatch], FeatureBatch]:
    """Train minibatches (size 15) and one held-out batch; statistics fitted on the train split only."""
    recs = make_synthetic_strokes(n_train_per_class + n_test_per_class, seed=seed, p_missing=p_missing)
    n_train = 3 * n_train_per_class
    feats = [featurize(r, FEATURES) for r in recs]
    labels = labels_of(recs)
    stats = fit_norm_stats(feats[:n_train], DIMS)
    train = [collate(feats[i:i + 15], DIMS, stats=stats, labels=labels[i:i + 15]) for i in range(0, n_train, 15)]
    test = collate(feats[n_train:], DIMS, stats=stats, labels=labels[n_train:])
    return train, test


def train_and_score(model: torch.nn.Module, train: list[FeatureBatch], test: FeatureBatch, epochs: int,
                    lr: float = 3e-3, cer_lambda: float = 0.0, cer_tau: float = 0.2) -> float:
    """Adam on the train batches for ``epochs``; returns held-out accuracy in eval mode."""
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    model.train()
    for _ in range(epochs):
        for batch in train:
            out = model(batch)
            loss = total_loss(out.logits, out.embedding, batch.labels, cer_lambda, cer_tau).total
            opt.zero_grad()
            loss.backward()
            opt.step()
    model.eval()
    with torch.no_grad():
        pred = model(test).logits.argmax(dim=1)
    return float((pred == test.labels).float().mean())


@pytest.fixture(scope="module", params=[{}, {"stem_dilations": (1, 2)}, {"stem_dilations": (1, 2), "max_pool": True},
                                        {"gate_pool": "hidden"}, {"head_mlp": True}, {"final_norm": True},
                                        {"residual_base": "plain"}],
                ids=["paper", "dilated_stem", "dilated_stem_max_pool", "hidden_gate_pool", "head_mlp",
                     "final_norm", "plain_residual"])
def model(request) -> TouchFormer:
    """The paper's model (one Conv1D per modality, mean pooling), and the options of residual dilated layers
    after that Conv1D, of mean+max pooling, of the gate pooled after its hidden layer, of MulT's residual
    MLP before the heads, of a LayerNorm closing the intra-modal blocks and of eq. 9's residual from the
    unweighted Z^[0]."""
    torch.manual_seed(0)
    return TouchFormer(tiny_config(**request.param)).eval()


# ----------------------------------------------------------------------------------------------------------


def test_output_record_shapes(model):
    batch = make_batch(seed=10)
    with torch.no_grad():
        out = model(batch)
    assert isinstance(out, ModelOutput)
    assert out.logits.shape == (6, 3) and out.embedding.shape == (6, 8)
    assert out.gates.shape == (6, 4) and out.alphas.shape == (6, 4)
    assert torch.allclose(out.embedding.norm(dim=1), torch.ones(6), atol=1e-5)
    assert torch.allclose(out.alphas.sum(dim=1), torch.ones(6), atol=1e-6)
    assert torch.all((out.gates >= 0) & (out.gates <= 1))


def _pad(batch: FeatureBatch, extra: dict[str, int]) -> FeatureBatch:
    """The same batch with ``extra[m]`` more padded steps on modality m (random values in the padding)."""
    gen = torch.Generator().manual_seed(0)
    x, padding = {}, {}
    for m in MODALITIES:
        b, t, c = batch.x[m].shape
        x[m] = torch.cat([batch.x[m], torch.zeros(b, extra[m], c)], dim=1)
        padding[m] = torch.cat([batch.padding[m], torch.ones(b, extra[m], dtype=torch.bool)], dim=1)
        # values hidden under the padding mask must not matter either
        x[m] = torch.where(padding[m].unsqueeze(-1), torch.randn(x[m].shape, generator=gen), x[m])
    return FeatureBatch(x=x, padding=padding, present=batch.present, labels=batch.labels)


def test_padding_invariance(model):
    batch = make_batch(seed=11)
    padded = _pad(batch, {"sound": 7, "normal": 3, "friction": 11, "accel": 5})
    with torch.no_grad():
        a, b = model(batch), model(padded)
    for name in ModelOutput._fields:
        assert torch.allclose(getattr(a, name), getattr(b, name), atol=1e-5), name


def test_single_stroke_equals_its_row_in_a_batch(model):
    batch = make_batch(seed=12)
    one = FeatureBatch(x={m: batch.x[m][:1] for m in MODALITIES}, padding={m: batch.padding[m][:1] for m in MODALITIES},
                       present={m: batch.present[m][:1] for m in MODALITIES})
    with torch.no_grad():
        assert torch.allclose(model(one).logits, model(batch).logits[:1], atol=1e-5)


def test_missing_modality(model):
    batch = make_batch(seed=13)
    present = dict(batch.present)
    present["friction"] = torch.tensor([False, True, False, True, True, True])
    padding = dict(batch.padding)
    padding["friction"] = padding["friction"] | ~present["friction"][:, None]
    x = dict(batch.x)
    x["friction"] = x["friction"] * present["friction"][:, None, None]
    missing = FeatureBatch(x=x, padding=padding, present=present, labels=batch.labels)
    with torch.no_grad():
        out = model(missing)
    j = MODALITIES.index("friction")
    for field in out:
        assert torch.isfinite(field).all()
    assert torch.all(out.alphas[~present["friction"], j] == 0)
    assert torch.all(out.gates[~present["friction"], j] == 0)
    assert torch.all(out.alphas[present["friction"], j] > 0)
    assert torch.allclose(out.alphas.sum(dim=1), torch.ones(6), atol=1e-6)


def test_only_one_modality_present(model):
    batch = make_batch(seed=14)
    keep = "accel"
    present = {m: batch.present[m] & (m == keep) for m in MODALITIES}
    padding = {m: batch.padding[m] | ~present[m][:, None] for m in MODALITIES}
    x = {m: batch.x[m] * present[m][:, None, None] for m in MODALITIES}
    with torch.no_grad():
        out = model(FeatureBatch(x=x, padding=padding, present=present))
    assert torch.isfinite(out.logits).all()
    assert torch.allclose(out.alphas[:, MODALITIES.index(keep)], torch.ones(6))


def test_mag_weights_threshold_and_softmax():
    gates = torch.tensor([[0.9, 0.05, 0.6, 0.3],
                          [0.01, 0.02, 0.03, 0.04],
                          [0.9, 0.8, 0.7, 0.6]])
    present = torch.tensor([[True, True, True, True],
                            [True, True, True, True],
                            [False, True, True, True]])
    alphas = mag_weights(gates, present, gate_th=0.1)
    kept = torch.tensor([0.9, 0.6, 0.3])
    expected0 = torch.exp(kept) / torch.exp(kept).sum()
    assert torch.allclose(alphas[0], torch.tensor([expected0[0], 0.0, expected0[1], expected0[2]]))
    # every gate below the threshold: the best present modality is kept alone
    assert torch.equal(alphas[1], torch.tensor([0.0, 0.0, 0.0, 1.0]))
    # a missing modality is excluded even with the largest gate
    assert alphas[2, 0] == 0 and torch.allclose(alphas[2].sum(), torch.tensor(1.0))
    # nothing present at all: all zeros, no NaN
    none = mag_weights(gates[:1], torch.zeros(1, 4, dtype=torch.bool), gate_th=0.1)
    assert torch.equal(none, torch.zeros(1, 4))
    # a lower temperature sharpens the weights of the kept modalities
    sharp = mag_weights(gates, present, gate_th=0.1, temperature=0.1)
    assert sharp[0, 0] > alphas[0, 0] and torch.allclose(sharp.sum(dim=1), torch.ones(3))


def test_default_gate_temperature_lets_mag_weigh_a_sensor_down():
    """Eq. 3 at temperature 1 keeps each of four weights >= 1 / (3 e + 1) = 0.109 (one gate 0, three 1);
    TouchFormer's default temperature (0.2, a recorded deviation) can take one to 1 / (3 e^5 + 1) = 0.0022;
    the soft-gate variant keeps eq. 3's temperature."""
    gates = torch.tensor([[0.0, 1.0, 1.0, 1.0]])
    present = torch.ones(1, 4, dtype=torch.bool)
    temperature = TouchFormerConfig(in_dims=IN_DIMS, n_classes=3).gate_temperature
    assert temperature == TouchFormerMagConfig(in_dims=IN_DIMS, n_classes=3).gate_temperature == 0.2
    default = mag_weights(gates, present, gate_th=0.0, temperature=temperature)
    paper = mag_weights(gates, present, gate_th=0.0, temperature=1.0)
    assert float(paper[0, 0]) == pytest.approx(1.0 / (3.0 * torch.e + 1.0), rel=1e-5)
    assert float(default[0, 0]) == pytest.approx(1.0 / (3.0 * torch.e ** 5 + 1.0), rel=1e-4)
    assert TouchFormerSoftGateConfig(in_dims=IN_DIMS, n_classes=3).gate_temperature == 1.0


def test_straight_through_gate_keeps_the_values_and_lets_dropped_gates_learn():
    gates = torch.tensor([[0.9, 0.05, 0.6, 0.3]], requires_grad=True)
    present = torch.ones(1, 4, dtype=torch.bool)
    weight = torch.tensor([[0.0, 1.0, 0.0, 0.0]])  # a loss that wants more of the dropped modality
    hard = mag_weights(gates, present, gate_th=0.1)
    (hard * weight).sum().backward()
    assert gates.grad[0, 1] == 0  # the plain threshold: the dropped gate gets nothing
    gates.grad = None
    st = mag_weights(gates, present, gate_th=0.1, straight_through=True)
    assert torch.allclose(st, hard.detach()) and st[0, 1] == 0
    (st * weight).sum().backward()
    assert gates.grad[0, 1] > 0  # it would rise


def test_straight_through_gate_only_while_training():
    torch.manual_seed(4)
    batch = make_batch(seed=18)
    plain = TouchFormer(tiny_config(gate_th=0.5))
    st = TouchFormer(tiny_config(gate_th=0.5, gate_straight_through=True))
    st.load_state_dict(plain.state_dict())
    with torch.no_grad():
        for m in (plain, st):
            m.gate.fc2.bias.fill_(0.0)  # gates near 0.5: some dropped, some kept
    for mode in ("train", "eval"):
        torch.manual_seed(5)
        a = getattr(plain, mode)()(batch)
        torch.manual_seed(5)
        b = getattr(st, mode)()(batch)
        assert torch.allclose(a.logits, b.logits, atol=1e-6) and torch.equal(a.alphas == 0, b.alphas == 0)


def test_hidden_gate_pool_sees_the_energy_of_zero_mean_noise():
    # the same mean over time, one sequence flat and one with zero-mean noise on top
    torch.manual_seed(6)
    flat = torch.full((1, 40, 8), 0.2)  # (B, T, d)
    noisy = flat + 2.0 * torch.randn(1, 40, 8)
    noisy = noisy - noisy.mean(dim=1, keepdim=True) + flat.mean(dim=1, keepdim=True)  # the mean kept exactly
    valid = torch.ones(1, 40, dtype=torch.bool)
    gates = {}
    for pool in GATE_POOLS:
        torch.manual_seed(7)
        gate = ModalityGate(8, 16, pool)
        with torch.no_grad():
            gates[pool] = (float(gate([flat], [valid])), float(gate([noisy], [valid])))
    assert gates["input"][0] == pytest.approx(gates["input"][1], abs=1e-6)  # the mean hides the noise
    assert abs(gates["hidden"][0] - gates["hidden"][1]) > 0.01  # the per-step ReLU does not
    with pytest.raises(ValueError, match="gate_pool"):
        tiny_config(gate_pool="median")


def test_gate_th_drops_low_gates_in_the_model():
    torch.manual_seed(1)
    batch = make_batch(seed=15)
    model = TouchFormer(tiny_config(gate_th=0.5)).eval()
    with torch.no_grad():
        model.gate.fc2.bias.fill_(-20.0)  # every gate ~ 0 < gate_th
        low = model(batch)
        model.gate.fc2.bias.fill_(20.0)  # every gate ~ 1 >= gate_th
        high = model(batch)
    assert torch.all((low.alphas == 0).sum(dim=1) == 3)  # only the fallback modality is kept
    assert torch.allclose(low.alphas.max(dim=1).values, torch.ones(6))
    assert torch.allclose(high.alphas, torch.full((6, 4), 0.25), atol=1e-6)


def test_fusion_only_ablation_has_uniform_alphas():
    torch.manual_seed(2)
    config = TouchFormerFusionConfig(**{f.name: getattr(tiny_config(), f.name)
                                        for f in dataclasses.fields(TouchFormerConfig)
                                        if f.name not in ("use_mag", "cer_lambda")})
    assert not config.use_mag and config.cer_lambda == 0.0
    batch = make_batch(seed=16, p_missing=0.4)
    with torch.no_grad():
        out = TouchFormer(config).eval()(batch)
    present = batch.present_matrix().float()
    assert torch.allclose(out.alphas, present / present.sum(dim=1, keepdim=True))


def test_gradient_reaches_every_part():
    torch.manual_seed(3)
    model = TouchFormer(tiny_config())
    batch = make_batch(seed=17)
    out = model(batch)
    total_loss(out.logits, out.embedding, batch.labels, cer_lambda=0.1, cer_tau=0.2).total.backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    for prefix in ("embed.", "gate.", "cross.", "intra.", "classifier.", "embedding_head."):
        norm = sum(p.grad.abs().sum() for n, p in model.named_parameters() if n.startswith(prefix))
        assert norm > 0, prefix


def test_config_validation():
    with pytest.raises(ValueError, match="divisible"):
        tiny_config(d_model=15)
    with pytest.raises(ValueError, match="odd"):
        tiny_config(kernel_sizes=(4, 3, 3, 3))
    with pytest.raises(ValueError, match="gate_th"):
        tiny_config(gate_th=1.5)
    with pytest.raises(ValueError, match="stem_dilations"):
        tiny_config(stem_dilations=(1, 0))
    with pytest.raises(ValueError, match="residual_base"):
        tiny_config(residual_base="none")
    with pytest.raises(ValueError, match="unimodal_lambda"):
        tiny_config(unimodal_lambda=-0.5)
    with pytest.raises(ValueError, match="unimodal_at"):
        tiny_config(unimodal_lambda=1.0, unimodal_at="fused")


def test_unimodal_heads_add_a_training_signal_and_leave_the_prediction_alone():
    # unimodal_lambda > 0 adds one linear head per sensor on its own pooled feature; the model's logits,
    # embedding and weights are those of the same network without the heads, and each head's gradient
    # reaches its own sensor's branch
    torch.manual_seed(7)
    plain = TouchFormer(tiny_config()).eval()
    torch.manual_seed(7)
    aux = TouchFormer(tiny_config(unimodal_lambda=1.0)).eval()
    assert plain.unimodal_heads is None and set(aux.unimodal_heads) == set(MODALITIES)
    batch = make_batch(seed=20, p_missing=0.3)
    with torch.no_grad():
        ref, (out, heads) = plain(batch), aux.forward_with_unimodal(batch)
    assert plain.forward_with_unimodal(batch)[1] is None
    for name in ModelOutput._fields:
        torch.testing.assert_close(getattr(out, name), getattr(ref, name))
        torch.testing.assert_close(getattr(aux(batch), name), getattr(ref, name))
    assert heads.shape == (batch.labels.shape[0], len(MODALITIES), 3)
    aux.train()
    heads = aux.forward_with_unimodal(batch)[1]
    heads[:, MODALITIES.index("friction")].sum().backward()
    assert aux.unimodal_heads["friction"].weight.grad.abs().sum() > 0
    sound_grad = aux.unimodal_heads["sound"].weight.grad
    assert sound_grad is None or not sound_grad.any()
    assert aux.intra["friction"].blocks[0].mlp.fc.weight.grad.abs().sum() > 0


def test_residual_base_sets_how_much_of_its_own_stream_a_sensor_keeps():
    # Same weights, the two readings of eq. 9. With alpha_m on the residual ("gated"), a sensor's own stream
    # enters its intra-modal blocks scaled by alpha_m; from eq. 6's unweighted Z^[0] ("plain") it does not.
    # With uniform alphas (no MAG) over four sensors, the gated base is exactly a quarter of the plain one,
    # so the outputs differ; a stroke with a single sensor has alpha = 1 and both readings agree on it.
    torch.manual_seed(5)
    gated = TouchFormer(tiny_config(use_mag=False)).eval()
    plain = TouchFormer(tiny_config(use_mag=False, residual_base="plain")).eval()
    plain.load_state_dict(gated.state_dict())
    batch = make_batch(seed=18)
    with torch.no_grad():
        assert not torch.allclose(gated(batch).logits, plain(batch).logits, atol=1e-4)
        only_sound = FeatureBatch(x=batch.x, padding=batch.padding, labels=batch.labels,
                                  present={m: batch.present[m] & (m == "sound") for m in MODALITIES})
        torch.testing.assert_close(gated(only_sound).logits, plain(only_sound).logits)


def test_without_inter_modal_attention_a_sensors_pooled_feature_sees_no_other_sensor():
    # inter_modal=False leaves step 3 out: no cross-attention is built, and with uniform alphas (no MAG, all
    # sensors present) each sensor's pooled feature, read by its unimodal head, is a function of its own
    # stream alone. The control: with step 3 the other sensors' heads move when the sound changes.
    batch = make_batch(seed=21)
    torch.manual_seed(21)
    louder = FeatureBatch(x={**batch.x, "sound": batch.x["sound"] + torch.randn_like(batch.x["sound"])},
                          padding=batch.padding, labels=batch.labels, present=batch.present)
    others = [i for i, m in enumerate(MODALITIES) if m != "sound"]
    for inter_modal in (False, True):
        torch.manual_seed(9)
        model = TouchFormer(tiny_config(use_mag=False, unimodal_lambda=1.0, inter_modal=inter_modal)).eval()
        assert (len(model.cross) == 0) == (not inter_modal)
        with torch.no_grad():
            before, after = model.forward_with_unimodal(batch)[1], model.forward_with_unimodal(louder)[1]
        moved = (after - before)[:, others].abs().max()
        assert (moved < 1e-6) == (not inter_modal), (inter_modal, float(moved))
        assert (after - before)[:, MODALITIES.index("sound")].abs().max() > 1e-3
    with pytest.raises(ValueError, match="inter_modal=False"):
        tiny_config(inter_modal=False, time_bias=True, frame_clock_s=((0.1, 0.05),) * 4)


@pytest.mark.parametrize("use_mag", [True, False])
def test_model_runs_in_bfloat16(use_mag):
    # the positional embedding and the uniform weights follow the model's dtype instead of forcing float32
    torch.manual_seed(6)
    model = TouchFormer(tiny_config(use_mag=use_mag)).eval()
    batch = make_batch(seed=19, p_missing=0.3)
    half = FeatureBatch(x={m: v.to(torch.bfloat16) for m, v in batch.x.items()}, padding=batch.padding,
                        present=batch.present, labels=batch.labels)
    with torch.no_grad():
        ref = model(batch)
        out = model.to(torch.bfloat16)(half)
    assert out.logits.dtype == torch.bfloat16 and torch.isfinite(out.logits.float()).all()
    assert (out.logits.float().argmax(dim=1) == ref.logits.argmax(dim=1)).float().mean() >= 0.8


def test_tiny_touchformer_learns_held_out():
    torch.manual_seed(4)
    train, test = synthetic_batches(seed=18, p_missing=0.15)
    model = TouchFormer(tiny_config())
    acc = train_and_score(model, train, test, epochs=8, cer_lambda=0.1)
    assert acc >= 0.8, acc  # chance is 1/3


def test_embedding_heads_see_their_own_sensor_only():
    # unimodal_at="embedding": a head reads step 1's features of its sensor, before the cross-attention, so
    # changing another sensor's stream leaves it unchanged; the "pooled" heads read features mixed with it
    batch = make_batch(seed=21)
    other = FeatureBatch(x={**batch.x, "sound": batch.x["sound"] + 3.0}, padding=batch.padding,
                         present=batch.present, labels=batch.labels)
    friction = MODALITIES.index("friction")
    for at, unchanged in (("embedding", True), ("pooled", False)):
        torch.manual_seed(8)
        model = TouchFormer(tiny_config(unimodal_lambda=1.0, unimodal_at=at)).eval()
        with torch.no_grad():
            a, b = model.forward_with_unimodal(batch)[1], model.forward_with_unimodal(other)[1]
        assert torch.allclose(a[:, friction], b[:, friction], atol=1e-6) == unchanged, at


def test_time_bias_makes_a_steep_head_read_the_source_frame_nearest_in_time():
    # frames of 0.1 s (target) against 0.25 s (source): with the query and key maps at zero, a head's
    # logits are its time bias alone, so a steep slope picks the source frame closest to each target frame
    torch.manual_seed(3)
    cross = CrossModalAttention(d_model=8, n_heads=2, dropout=0.0, time_bias=True)
    with torch.no_grad():
        cross.attn.q.weight.zero_()
        cross.attn.q.bias.zero_()
        cross.time_slope.fill_(1e4)
    t_target = 0.05 + 0.1 * torch.arange(10)  # (10,) s
    t_source = 0.1 + 0.25 * torch.arange(4)  # (4,) s, no target frame halfway between two
    gap = (t_target[:, None] - t_source[None, :]).abs()  # (10, 4)
    target, source = torch.randn(1, 10, 8), torch.randn(1, 4, 8)
    valid = torch.ones(1, 4, dtype=torch.bool)
    with torch.no_grad():
        out = cross(target, source, valid, gap)  # (1, 10, 8)
        v = cross.attn.kv(cross.ln_source(source)).split(8, dim=-1)[1]  # (1, 4, 8)
        expected = cross.attn.proj(v[:, gap.argmin(dim=1)])  # (1, 10, 8)
    torch.testing.assert_close(out, expected, rtol=1e-4, atol=1e-5)
    # the slopes are parameters: they learn, and a model without time_bias has none
    assert cross.time_slope.requires_grad
    assert CrossModalAttention(8, 2, 0.0).time_slope is None
    with pytest.raises(ValueError, match="time gaps"):
        cross(target, source, valid)
    with pytest.raises(ValueError, match="frame_clock_s"):
        tiny_config(time_bias=True)
