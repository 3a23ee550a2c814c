"""CER supervised contrastive loss and the total loss (perception.losses)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from perception.losses import cross_instance_contrastive_loss, total_loss, unimodal_cross_entropy

torch.set_num_threads(2)


def reference_loss(z: np.ndarray, y: list[int], tau: float) -> float:
    """The paper's equation with explicit loops; anchors without positives are skipped."""
    terms = []
    for i in range(len(y)):
        num = sum(math.exp(z[i] @ z[j] / tau) for j in range(len(y)) if j != i and y[j] == y[i])
        den = sum(math.exp(z[i] @ z[j] / tau) for j in range(len(y)) if j != i)
        if num > 0:
            terms.append(-math.log(num / den))
    return float(np.mean(terms)) if terms else 0.0


def test_hand_computed_tiny_example():
    # z0 = (1, 0), z1 = (0, 1), z2 = (-1, 0); labels 0, 0, 1; tau = 1.
    # anchor 0: S01 = 0, S02 = -1 -> -log(1 / (1 + e^-1)); anchor 1: S10 = 0, S12 = 0 -> -log(1 / 2);
    # anchor 2 has no positive: left out of the mean.
    z = torch.tensor([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])
    loss = cross_instance_contrastive_loss(z, torch.tensor([0, 0, 1]), tau=1.0)
    expected = (math.log(1 + math.exp(-1)) + math.log(2)) / 2
    assert loss.item() == pytest.approx(expected, rel=1e-6)


def test_sum_over_positives_is_inside_the_log():
    gen = torch.Generator().manual_seed(0)
    z = F.normalize(torch.randn(10, 5, generator=gen), dim=1)
    y = [0, 0, 0, 1, 1, 2, 2, 2, 2, 3]  # anchor 9 has no positive
    loss = cross_instance_contrastive_loss(z, torch.tensor(y), tau=0.2)
    assert loss.item() == pytest.approx(reference_loss(z.numpy().astype(np.float64), y, 0.2), rel=1e-5)


def test_anchors_without_positives_give_zero_not_nan():
    z = F.normalize(torch.randn(4, 3, generator=torch.Generator().manual_seed(1)), dim=1).requires_grad_()
    loss = cross_instance_contrastive_loss(z, torch.tensor([0, 1, 2, 3]), tau=0.1)
    assert torch.isfinite(loss) and loss.item() == 0.0
    loss.backward()
    assert torch.isfinite(z.grad).all()


def test_batch_of_one():
    z = torch.tensor([[0.6, 0.8]], requires_grad=True)
    loss = cross_instance_contrastive_loss(z, torch.tensor([0]), tau=0.2)
    loss.backward()
    assert loss.item() == 0.0 and torch.isfinite(z.grad).all()


def test_small_temperature_stays_finite():
    z = F.normalize(torch.randn(8, 4, generator=torch.Generator().manual_seed(2)), dim=1).requires_grad_()
    y = torch.tensor([0, 0, 1, 1, 2, 2, 3, 4])
    loss = cross_instance_contrastive_loss(z, y, tau=0.01)
    loss.backward()
    assert torch.isfinite(loss) and 0.0 <= loss.item() < 1e3
    assert torch.isfinite(z.grad).all()


def test_loss_is_lower_for_clustered_embeddings():
    y = torch.tensor([0, 0, 1, 1])
    clustered = torch.tensor([[1.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [-1.0, 0.0]])
    mixed = torch.tensor([[1.0, 0.0], [-1.0, 0.0], [1.0, 0.0], [-1.0, 0.0]])
    assert cross_instance_contrastive_loss(clustered, y, 0.2) < cross_instance_contrastive_loss(mixed, y, 0.2)


def test_rejects_non_positive_temperature():
    with pytest.raises(ValueError, match="tau"):
        cross_instance_contrastive_loss(torch.ones(2, 2), torch.tensor([0, 0]), tau=0.0)


def test_total_loss_combines_terms():
    gen = torch.Generator().manual_seed(3)
    logits = torch.randn(6, 3, generator=gen, requires_grad=True)
    emb = F.normalize(torch.randn(6, 4, generator=gen), dim=1).requires_grad_()
    y = torch.tensor([0, 1, 2, 0, 1, 2])
    terms = total_loss(logits, emb, y, cer_lambda=0.5, cer_tau=0.2)
    assert terms.ce.item() == pytest.approx(F.cross_entropy(logits, y).item())
    assert terms.total.item() == pytest.approx(terms.ce.item() + 0.5 * terms.contrastive.item(), rel=1e-6)
    terms.total.backward()
    assert emb.grad.abs().sum() > 0 and logits.grad.abs().sum() > 0
    off = total_loss(logits, emb, y, cer_lambda=0.0, cer_tau=0.2)
    assert off.total.item() == pytest.approx(off.ce.item())
    smooth = total_loss(logits, emb, y, cer_lambda=0.0, cer_tau=0.2, label_smoothing=0.1)
    uniform = -F.log_softmax(logits, dim=1).mean(dim=1).mean()  # cross-entropy against the uniform target
    assert smooth.ce.item() == pytest.approx(0.9 * off.ce.item() + 0.1 * uniform.item(), rel=1e-6)


def test_total_loss_blends_the_cross_entropy_of_mixup_partners_and_keeps_cer_on_the_larger_share():
    gen = torch.Generator().manual_seed(5)
    logits = torch.randn(6, 3, generator=gen)
    emb = F.normalize(torch.randn(6, 4, generator=gen), dim=1)
    y, partner = torch.tensor([0, 1, 2, 0, 1, 2]), torch.tensor([1, 1, 0, 2, 0, 2])
    mixed = total_loss(logits, emb, y, cer_lambda=0.5, cer_tau=0.2, partner_labels=partner, share=0.7)
    expected = 0.7 * F.cross_entropy(logits, y) + 0.3 * F.cross_entropy(logits, partner)
    assert mixed.ce.item() == pytest.approx(expected.item(), rel=1e-6)
    assert mixed.contrastive.item() == pytest.approx(cross_instance_contrastive_loss(emb, y, 0.2).item())
    plain = total_loss(logits, emb, y, cer_lambda=0.5, cer_tau=0.2)
    unblended = total_loss(logits, emb, y, cer_lambda=0.5, cer_tau=0.2, partner_labels=partner, share=1.0)
    assert unblended.total.item() == plain.total.item()  # share 1: the partner does not count


def test_unimodal_cross_entropy_averages_present_modalities_only():
    gen = torch.Generator().manual_seed(4)
    logits = torch.randn(3, 4, 5, generator=gen)  # (B, M, K)
    y = torch.tensor([0, 3, 4])
    present = torch.tensor([[True, False, True, True], [False, False, False, True], [True, True, True, True]])
    pairs = [F.cross_entropy(logits[b, m][None], y[b][None]).item()
             for b in range(3) for m in range(4) if present[b, m]]
    assert unimodal_cross_entropy(logits, y, present).item() == pytest.approx(float(np.mean(pairs)), rel=1e-6)
    # a missing modality's scores do not matter, however wrong they are
    wrong = logits.clone()
    wrong[0, 1] = 1e4 * F.one_hot(torch.tensor(1), 5)
    assert unimodal_cross_entropy(wrong, y, present).item() == pytest.approx(float(np.mean(pairs)), rel=1e-6)
    none = unimodal_cross_entropy(logits.requires_grad_(), y, torch.zeros(3, 4, dtype=torch.bool))
    assert none.item() == 0.0
    none.backward()
    assert torch.isfinite(logits.grad).all()
