"""Baselines of the paper's comparison (LSTM, MTCNN) and the registry of every trainable model.

Both baselines take the same :class:`perception.features.FeatureBatch` and return the same
:class:`perception.touchformer.ModelOutput` as TouchFormer, with gates = presence (1 or 0) and alphas uniform
over present modalities, so training and evaluation code treat all models alike.

- LSTM (Ji et al. 2015 style): each modality's sequence is linearly resampled to ``n_steps`` steps over its
  valid part, missing modalities are zero-filled and flagged by an indicator channel, all concatenated per
  step and fed to a (bi)LSTM.
- MTCNN (Wei et al., IEEE TII 2022; no public code, rebuilt from its description): per modality, a stack of
  dilated temporal convolutions over the energy-spectrum front end (the log band energies / MFCCs and taxel
  window statistics of :mod:`perception.features`), masked mean+max sequence pooling, then the modalities
  fused by concatenation with their presence flags and an MLP head.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn as nn
import torch.nn.functional as F

from perception.features import FeatureBatch
from perception.streams import MODALITIES
from perception.touchformer import (ModelOutput, ResidualDilatedConvs, TouchFormer, TouchFormerConfig,
                                    TouchFormerFusionConfig, TouchFormerMagConfig, TouchFormerSoftGateConfig,
                                    masked_max, masked_mean, uniform_weights)

N_MOD = len(MODALITIES)


def resample_valid(x: torch.Tensor, valid: torch.Tensor, n_steps: int) -> torch.Tensor:
    """Linearly resample each sequence's valid prefix to ``n_steps`` steps.

    Args:
        x: (B, T, C) padded sequences (padding at the end).
        valid: (B, T) bool, True on real steps.
        n_steps: output length.

    Returns:
        (B, n_steps, C); all zeros for rows without valid steps.
    """
    b, t, c = x.shape
    length = valid.sum(dim=1).to(x.dtype)  # (B,)
    centres = (torch.arange(n_steps, device=x.device, dtype=x.dtype) + 0.5) / n_steps  # (S,)
    pos = (centres[None, :] * length[:, None] - 0.5).clamp(min=0.0)  # (B, S)
    pos = torch.minimum(pos, (length[:, None] - 1.0).clamp(min=0.0))  # (B, S)
    lo = pos.floor().long().clamp(max=t - 1)  # (B, S)
    hi = (lo + 1).clamp(max=t - 1)  # (B, S)
    hi = torch.minimum(hi, (length[:, None] - 1.0).clamp(min=0.0).long())  # (B, S)
    w = (pos - lo.to(x.dtype)).unsqueeze(-1)  # (B, S, 1)
    x_lo = torch.gather(x, 1, lo.unsqueeze(-1).expand(b, n_steps, c))  # (B, S, C)
    x_hi = torch.gather(x, 1, hi.unsqueeze(-1).expand(b, n_steps, c))  # (B, S, C)
    out = (1.0 - w) * x_lo + w * x_hi  # (B, S, C)
    return out * (length > 0).to(x.dtype)[:, None, None]  # (B, S, C)


def _uniform_output(logits: torch.Tensor, embedding: torch.Tensor, present: torch.Tensor) -> ModelOutput:
    return ModelOutput(logits=logits, embedding=F.normalize(embedding, dim=-1), gates=present.float(),
                       alphas=uniform_weights(present))


# ----------------------------------------------------------------------------------------------------------
# LSTM


@dataclass(frozen=True)
class LSTMConfig:
    """LSTM baseline hyper-parameters.

    Attributes:
        in_dims: feature channels C_m per modality, :data:`MODALITIES` order.
        n_classes: number of classes K.
        n_steps: common number of steps every modality is resampled to.
        hidden: LSTM hidden size per direction.
        n_layers: stacked LSTM layers.
        bidirectional: bidirectional LSTM.
        dropout: dropout before the heads (and between LSTM layers).
        emb_dim: embedding size E.
        cer_lambda: CER weight (0: cross-entropy only, as in the paper's baseline).
        cer_tau: CER temperature.
    """

    in_dims: tuple[int, ...]
    n_classes: int
    n_steps: int = 32
    hidden: int = 64
    n_layers: int = 1
    bidirectional: bool = True
    dropout: float = 0.1
    emb_dim: int = 64
    cer_lambda: float = 0.0
    cer_tau: float = 0.2


class LSTMClassifier(nn.Module):
    """Recurrent net over the concatenated, resampled per-modality features plus presence indicators."""

    def __init__(self, config: LSTMConfig) -> None:
        super().__init__()
        self.config = config
        c = config
        self.lstm = nn.LSTM(sum(c.in_dims) + N_MOD, c.hidden, num_layers=c.n_layers, batch_first=True,
                            bidirectional=c.bidirectional, dropout=c.dropout if c.n_layers > 1 else 0.0)
        width = c.hidden * (2 if c.bidirectional else 1)
        self.drop = nn.Dropout(c.dropout)
        self.classifier = nn.Linear(width, c.n_classes)
        self.embedding_head = nn.Linear(width, c.emb_dim)

    def forward(self, batch: FeatureBatch) -> ModelOutput:
        c = self.config
        present = batch.present_matrix()  # (B, M)
        steps = []
        for i, m in enumerate(MODALITIES):
            xm = resample_valid(batch.x[m], ~batch.padding[m], c.n_steps)  # (B, S, C_m), 0 if missing
            steps.append(xm * present[:, i, None, None])
        flags = present.float()[:, None, :].expand(-1, c.n_steps, -1)  # (B, S, M) indicator channels
        seq = torch.cat(steps + [flags], dim=-1)  # (B, S, sum C + M)
        out, _ = self.lstm(seq)  # (B, S, width)
        h = self.drop(out.mean(dim=1))  # (B, width)
        return _uniform_output(self.classifier(h), self.embedding_head(h), present)


# ----------------------------------------------------------------------------------------------------------
# MTCNN


@dataclass(frozen=True)
class MTCNNConfig:
    """MTCNN-style baseline hyper-parameters.

    Attributes:
        in_dims: feature channels C_m per modality, :data:`MODALITIES` order.
        n_classes: number of classes K.
        channels: conv channels per modality.
        dilations: dilation of each temporal conv layer.
        kernel_size: temporal kernel (odd).
        dropout: dropout before the heads.
        emb_dim: embedding size E.
        cer_lambda: CER weight (0: cross-entropy only).
        cer_tau: CER temperature.
        max_pool: pool each sensor by its masked mean and maximum (True) or by its mean alone, as TouchFormer
            does (False; an option for comparing the two).
        step_norm: a LayerNorm over the channels of every step of each sensor's encoder output before the
            pooling, as TouchFormer's final LayerNorm does (an option for comparing the two; off by default).
        mlp_head: the fused vector passes a hidden layer of 2 x channels (ReLU, dropout) before the heads (True,
            the default); False puts the heads on the fused vector itself (after dropout), as TouchFormer's
            linear head does (an option for comparing the two).
    """

    in_dims: tuple[int, ...]
    n_classes: int
    channels: int = 32
    dilations: tuple[int, ...] = (1, 2, 4)
    kernel_size: int = 3
    dropout: float = 0.1
    emb_dim: int = 64
    cer_lambda: float = 0.0
    cer_tau: float = 0.2
    max_pool: bool = True
    step_norm: bool = False
    mlp_head: bool = True

    def __post_init__(self) -> None:
        if self.kernel_size % 2 == 0:
            raise ValueError(f"kernel_size must be odd, got {self.kernel_size}")


class DilatedTemporalEncoder(nn.Module):
    """1x1 input projection, then residual dilated Conv1D layers; padded steps kept at zero."""

    def __init__(self, in_dim: int, channels: int, dilations: tuple[int, ...], kernel_size: int) -> None:
        super().__init__()
        self.inp = nn.Conv1d(in_dim, channels, 1)
        self.residual = ResidualDilatedConvs(channels, dilations, kernel_size)

    def forward(self, x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        mask = valid.unsqueeze(1).to(x.dtype)  # (B, 1, T)
        h = self.inp(x.transpose(1, 2)) * mask  # (B, ch, T)
        return self.residual(h, mask).transpose(1, 2)  # (B, T, ch)


class MTCNNClassifier(nn.Module):
    """Per-modality dilated temporal CNNs, masked mean+max pooling (mean alone with ``max_pool=False``),
    concatenation fusion, MLP head (linear with ``mlp_head=False``)."""

    def __init__(self, config: MTCNNConfig) -> None:
        super().__init__()
        self.config = config
        c = config
        self.encoders = nn.ModuleDict({m: DilatedTemporalEncoder(c.in_dims[i], c.channels, c.dilations,
                                                                 c.kernel_size) for i, m in enumerate(MODALITIES)})
        self.step_norm = nn.ModuleDict({m: nn.LayerNorm(c.channels) if c.step_norm else nn.Identity()
                                        for m in MODALITIES})
        width = N_MOD * (2 if c.max_pool else 1) * c.channels + N_MOD
        if c.mlp_head:
            self.fuse = nn.Sequential(nn.Linear(width, 2 * c.channels), nn.ReLU(), nn.Dropout(c.dropout))
            width = 2 * c.channels
        else:
            self.fuse = nn.Sequential(nn.Dropout(c.dropout))
        self.classifier = nn.Linear(width, c.n_classes)
        self.embedding_head = nn.Linear(width, c.emb_dim)

    def forward(self, batch: FeatureBatch) -> ModelOutput:
        present = batch.present_matrix()  # (B, M)
        pooled = []
        for i, m in enumerate(MODALITIES):
            valid = ~batch.padding[m]  # (B, T)
            h = self.step_norm[m](self.encoders[m](batch.x[m], valid))  # (B, T, ch)
            parts = [masked_mean(h, valid)] + ([masked_max(h, valid)] if self.config.max_pool else [])  # (B, ch) each
            pooled.append(torch.cat(parts, dim=1) * present[:, i, None])  # (B, 2 ch) or (B, ch)
        h = self.fuse(torch.cat(pooled + [present.float()], dim=1))  # (B, 2 ch)
        return _uniform_output(self.classifier(h), self.embedding_head(h), present)


# ----------------------------------------------------------------------------------------------------------
# registry

MODEL_REGISTRY: dict[str, tuple[type, type[nn.Module]]] = {
    "touchformer": (TouchFormerConfig, TouchFormer),  # MAG + fusion, trained with CER
    "touchformer_mag": (TouchFormerMagConfig, TouchFormer),  # ablation: MAG + fusion, no CER
    "touchformer_fusion": (TouchFormerFusionConfig, TouchFormer),  # ablation: fusion only
    "touchformer_soft": (TouchFormerSoftGateConfig, TouchFormer),  # variant: MAG weights, no threshold, CER
    "lstm": (LSTMConfig, LSTMClassifier),
    "mtcnn": (MTCNNConfig, MTCNNClassifier),
}
"""Model name -> (config class, model class). Every config has ``in_dims``, ``n_classes``, ``cer_lambda``
and ``cer_tau``; every model's ``forward(batch)`` returns a :class:`ModelOutput`."""


def build_model(name: str, in_dims: tuple[int, ...], n_classes: int, **overrides: Any) -> tuple[Any, nn.Module]:
    """Build a registered model.

    Args:
        name: a key of :data:`MODEL_REGISTRY`.
        in_dims: feature channels per modality (``tuple(feature_dims(cfg).values())``).
        n_classes: number of classes.
        **overrides: other config fields.

    Returns:
        (config, model).

    Raises:
        KeyError: unknown model name (the message lists the known ones).
        ValueError: an override that is not a field of the model's config, or values that the config or the
            model's layers reject.
    """
    if name not in MODEL_REGISTRY:
        raise KeyError(f"unknown model {name!r}; known: {sorted(MODEL_REGISTRY)}")
    config_cls, model_cls = MODEL_REGISTRY[name]
    fields = {f.name for f in dataclasses.fields(config_cls)} - {"in_dims", "n_classes"}
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise ValueError(f"{name}: unknown model option(s) {unknown}; known: {sorted(fields)}")
    try:
        config = config_cls(in_dims=tuple(in_dims), n_classes=n_classes, **overrides)
        return config, model_cls(config)
    except (TypeError, RuntimeError) as exc:  # a value of the wrong type or size for the model's layers
        raise ValueError(f"{name}: model options {overrides} do not make a model: {exc}") from None
