"""Training losses: Cross-Instance Embedding Regularisation (CER, sec. 3.3) and the total loss (sec. 3.4).

The CER term is the paper's supervised contrastive loss, with the sum over positives *inside* the log:

    L_C = -1/|A| sum_{i in A} log( sum_{j != i, y_j = y_i} exp(S_ij / tau) / sum_{j != i} exp(S_ij / tau) ),

S_ij = z_i^T z_j on l2-normalised embeddings. A is the set of anchors with at least one positive in the batch:
an anchor without a positive contributes 0 and is left out of the mean (the paper's 1/N over all anchors
would take log 0 for it). With no anchor in A the loss is 0 and still differentiable.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F


class LossTerms(NamedTuple):
    """total = ce + cer_lambda * contrastive (scalars)."""

    total: torch.Tensor
    ce: torch.Tensor
    contrastive: torch.Tensor


def cross_instance_contrastive_loss(embedding: torch.Tensor, labels: torch.Tensor, tau: float) -> torch.Tensor:
    """CER supervised contrastive loss L_C.

    Args:
        embedding: (B, E) l2-normalised embeddings.
        labels: (B,) integer class labels.
        tau: temperature (> 0).

    Returns:
        Scalar loss: mean over anchors that have a positive; 0 when none has.
    """
    if tau <= 0:
        raise ValueError(f"temperature tau must be positive, got {tau}")
    b = embedding.shape[0]
    sim = embedding @ embedding.T / tau  # (B, B)
    not_self = ~torch.eye(b, dtype=torch.bool, device=embedding.device)  # (B, B)
    positive = (labels[:, None] == labels[None, :]) & not_self  # (B, B)
    has_pos = positive.any(dim=1)  # (B,)
    # rows without a positive (or with B = 1, without any other sample) get finite dummy logits so that
    # logsumexp and its gradient stay finite; those rows are masked out of the mean below
    safe = has_pos[:, None]  # (B, 1)
    log_num = torch.logsumexp(torch.where(safe, sim.masked_fill(~positive, float("-inf")), 0.0), dim=1)  # (B,)
    log_den = torch.logsumexp(torch.where(safe, sim.masked_fill(~not_self, float("-inf")), 0.0), dim=1)  # (B,)
    per_anchor = torch.where(has_pos, log_den - log_num, torch.zeros_like(log_num))  # (B,)
    return per_anchor.sum() / has_pos.sum().clamp(min=1)


def total_loss(logits: torch.Tensor, embedding: torch.Tensor, labels: torch.Tensor, cer_lambda: float,
               cer_tau: float, label_smoothing: float = 0.0, partner_labels: torch.Tensor | None = None,
               share: float = 1.0) -> LossTerms:
    """L_total = L_cls + lambda * L_C (eq. 14); with cer_lambda = 0 the contrastive term is still reported.

    For a mixup batch (:func:`perception.train.mixup_batch`) L_cls is ``share * CE(labels) + (1 - share) *
    CE(partner_labels)``; L_C reads ``labels``, the label of the larger share.

    Args:
        logits: (B, K) class scores.
        embedding: (B, E) l2-normalised embeddings.
        labels: (B,) class indices.
        cer_lambda: weight lambda of the CER term.
        cer_tau: CER temperature tau.
        label_smoothing: smoothing of the cross-entropy's targets (0: plain L_cls as in the paper).
        partner_labels: (B,) labels of the strokes blended in by mixup, or ``None`` (no mixup).
        share: weight of ``labels`` in the blend, in [0, 1].
    """
    ce = F.cross_entropy(logits, labels, label_smoothing=label_smoothing)
    if partner_labels is not None and share < 1.0:
        ce = share * ce + (1.0 - share) * F.cross_entropy(logits, partner_labels, label_smoothing=label_smoothing)
    contrastive = cross_instance_contrastive_loss(embedding, labels, cer_tau)
    total = ce + cer_lambda * contrastive if cer_lambda > 0 else ce
    return LossTerms(total=total, ce=ce, contrastive=contrastive.detach() if cer_lambda <= 0 else contrastive)


def unimodal_cross_entropy(unimodal_logits: torch.Tensor, labels: torch.Tensor, present: torch.Tensor
                           ) -> torch.Tensor:
    """Mean cross-entropy of the per-modality auxiliary heads over the present (stroke, modality) pairs.

    Args:
        unimodal_logits: (B, M, K) class scores of each modality's head.
        labels: (B,) class indices.
        present: (B, M) bool, False for a missing modality (left out of the mean).

    Returns:
        Scalar loss; 0 (still differentiable) when no modality is present.
    """
    b, m, k = unimodal_logits.shape
    per_pair = F.cross_entropy(unimodal_logits.reshape(b * m, k), labels.repeat_interleave(m),
                               reduction="none").view(b, m)  # (B, M)
    weight = present.to(per_pair.dtype)  # (B, M)
    return (per_pair * weight).sum() / weight.sum().clamp(min=1.0)
