"""TouchFormer (AAAI 2026), read top to bottom like section 3 of the paper.

1. Temporal Conv1D per modality (kernel k_m) to a common width d, plus positional embedding PE(T_m, d).
2. Modality-Adaptive Gating (MAG, sec. 3.1): g_m = sigmoid(W2 ReLU(W1 X_m + b1) + b2) on the masked mean of
   the modality's features; modalities with g_m < gate_th are dropped; alpha_m = softmax over the kept gates;
   Z_m = alpha_m * (X_m + PE).
3. Inter-modal Transformer (sec. 3.2): for every (target a, source b) pair, cross-attention
   Y_{a<-b} = alpha_b * softmax(Q_a K_b^T / sqrt(d_k)) V_b; residual Z~_a = Z_a + sum_b Y_{a<-b} (eq. 9
   writes Z^[0]_a + Y_{a<-b} for one source b; the three sources' outputs are summed here).
4. Intra-modal Transformer: self-attention layers within each modality.
5. Masked mean pooling; fused feature Z = concat_m(alpha_m * pooled_m) (eq. 12); a classifier head and an
   l2-normalised embedding head (for the CER loss, :mod:`perception.losses`).

Choices the paper leaves open, made here:

- W1, W2 of the gate are shared by the four modalities (the paper's equations carry no index m); each
  modality's own Conv1D makes its features distinguishable to the gate. Sharing also keeps a modality that
  was gated off for every sample from losing its gradient for good.
- Missing modalities (stream ``None``) are excluded from the softmax exactly like gated-off ones: alpha = 0.
- If every present modality of a sample falls below gate_th, the present modality with the largest gate is
  kept (alpha = 1), so the model always predicts from something. A sample with no modality at all gets
  all-zero alphas and the classifier sees only its bias.
- ``use_mag=False`` is the ablation "transformer fusion only": alpha = 1 / (number of present modalities).
- A modality dropped by the threshold gets no gradient through its alpha; ``gate_straight_through=True``
  (off by default) passes one as if it had been kept, without changing what the model computes.
- ``stem_dilations`` (empty by default, the paper's single Conv1D) adds residual dilated Conv1D layers after
  step 1's Conv1D, as MTCNN's encoders have; an option for comparing per-sensor encoders, not the paper's.
- ``unimodal_lambda`` (0 by default, not the paper's) adds a training-only head per modality on its own pooled
  feature (step 5's, or with ``unimodal_at="embedding"`` step 1's, before any other sensor is mixed in) and
  their cross-entropy to the loss; the prediction does not use them (:meth:`TouchFormer.forward`).
- Eqs. 1-2 apply W1 to X_m (T_m x d) and yield one g_m; where the time axis is pooled is not said. By default
  the gate takes the masked mean of X_m; ``gate_pool="hidden"`` pools H_m after the ReLU instead.
- ``gate_temperature`` divides the gates before eq. 3's softmax: 0.2 by default instead of the paper's implicit
  1 (``perception.train.DEVIATIONS``); ``touchformer_soft`` keeps 1.
- The paper names no classifier head after eq. 12; ours is linear. ``head_mlp=True`` (off by default) puts
  MulT's residual two-layer MLP (Tsai et al., 2019, which section 3.2 follows) between eq. 12 and both heads.
- Eq. 4 gates the features, Z_m = alpha_m (X_m + PE); eqs. 5-6 define Z^[0]_m = Conv1D(X_m) + PE without
  the weight, and eq. 9's residual starts from Z^[0]. The paper does not say where eq. 4's Z_m goes. Here
  eq. 4 is applied to the Conv1D output, Z_m = alpha_m Z^[0]_m, and feeds the cross-attention (whose
  pre-LayerNorm undoes the scale on Q, K and V) and, by default (``residual_base="gated"``), the residual
  too. So alpha_m weighs a sensor's own stream there, each source's cross-attention output (eq. 8) and the
  pooled feature (eq. 12). ``residual_base="plain"`` starts the residual from Z^[0] as eq. 9 writes it.
- ``time_bias=True`` (off by default, not the paper's) adds -s_h |t_a - t_b| to the logits of each
  cross-attention head h, with t the centre time of each frame on the stroke's clock in seconds
  (``frame_clock_s``, from the front ends' hops: :func:`perception.features.frame_clock_s`) and s_h >= 0 a
  learned slope per head and pair, started at :data:`TIME_BIAS_INIT_SLOPES_PER_S`. The sinusoidal PE counts
  frames, and the four sensors' frames have different rates (21.5, 10, 10 and 7.8 per second), so frame i of
  the sound and frame i of the friction are not the same instant; this gives every pair one clock to attend
  by. On synthetic strokes whose class is only the timing of one sensor's event against another's
  (``robotdemo bench timing``, :mod:`perception.timing_control`), the model without it fits its training
  strokes and tests at chance; with it, it learns the task (docs/touchformer-findings.md, session 47).
- ``inter_modal=False`` (on by default, the paper's) leaves step 3 out: no cross-attention is built and each
  sensor's stream goes from step 2 straight to its own intra-modal Transformer, so the sensors meet only in
  eq. 12's concatenation. A diagnostic below the ablation's lowest rung ("fusion only"): what the paper's
  inter-modal fusion adds on given strokes.
- Padding: every attention masks padded keys; a query row whose keys are all padded (a missing modality)
  attends to its first step instead, which is harmless because that output is scaled by alpha = 0 or pooled
  with weight 0. Conv1D sees zeros at padded steps, identical to its own zero padding, so outputs at real
  steps do not depend on the amount of padding.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar, NamedTuple, Sequence

import torch
import torch.nn as nn
import torch.nn.functional as F

from perception.features import FeatureBatch
from perception.streams import MODALITIES

N_MOD = len(MODALITIES)
GATE_POOLS = ("input", "hidden")
TIME_BIAS_INIT_SLOPES_PER_S = (0.0, 2.0, 8.0, 32.0)
"""``time_bias``: the slopes s_h [1/s] the cross-attention heads start from, cycled over the heads: one head
blind to time, the others attending within about 0.5, 0.1 and 0.03 s of the target frame's instant."""
RESIDUAL_BASES = ("gated", "plain")
UNIMODAL_AT = ("pooled", "embedding")


@dataclass(frozen=True)
class TouchFormerConfig:
    """TouchFormer hyper-parameters.

    Attributes:
        in_dims: feature channels C_m per modality, :data:`MODALITIES` order (see ``features.feature_dims``).
        n_classes: number of classes K.
        d_model: common width d.
        n_heads: attention heads (d_model must be divisible by it).
        n_layers: intra-modal self-attention layers per modality.
        kernel_sizes: Conv1D kernel k_m per modality (odd).
        gate_hidden: hidden width of the MAG gate MLP.
        gate_th: MAG threshold; a modality with g_m < gate_th is dropped.
        gate_temperature: alpha = softmax(g / gate_temperature) over kept modalities. Eq. 3 has none (1), which
            keeps alphas near uniform: gates lie in [0, 1], so of four modalities none can weigh less than
            0.11. 0.2 by default, a recorded deviation (``perception.train.DEVIATIONS["gate_temperature"]``):
            with the threshold, it scored 2.7 points higher on SSMC validation and 4.1 on USMC.
        use_mag: MAG on; False gives uniform alphas over present modalities (ablation "fusion only").
        emb_dim: embedding size E of the l2-normalised embedding head.
        dropout: dropout in the MLPs (the intra-modal blocks' and ``head_mlp``'s) and on the fused feature Z
            before the heads.
        attn_dropout: dropout on the attention weights themselves. 0 by default: on CPU it forces PyTorch's
            attention onto its unfused path, and drawing the masks took 27 % of a training step at our
            sequence lengths (measured with torch.profiler, batch 32).
        emb_dropout: dropout on the conv embeddings (authors' code: 0.25).
        cer_lambda: weight lambda of the CER loss in L_cls + lambda L_C (0 turns CER off).
        cer_tau: CER temperature tau.
        gate_straight_through: training only: gradients reach a gate that fell below gate_th as if its
            modality had been kept (:func:`mag_weights`); what the model computes is unchanged. Off by default
            (the paper does not say how a dropped gate learns).
        stem_dilations: after the Conv1D of step 1, residual dilated Conv1D layers (kernel 3) of width d with
            these dilations, as MTCNN's encoders have (:class:`ResidualDilatedConvs`). Empty (the paper's
            single Conv1D) by default.
        max_pool: step 5 pools each modality by its masked mean and its maximum (as MTCNN does), concatenated,
            instead of the mean alone (eq. 12's pooling, the default).
        gate_pool: where MAG pools X_m (T x d) over time to one gate g_m, which the paper leaves open:
            "input" (default) takes the masked mean of X_m and applies eqs. 1-2 to it; "hidden" applies eq. 1
            to every step, H_m = ReLU(W1 X_m + b1), and eq. 2 to the masked mean of H_m. The ReLU before the
            mean lets the gate see the energy of zero-mean noise, which the mean of X_m averages away.
        head_mlp: between eq. 12's fused feature Z and the heads, MulT's residual MLP
            Z + W2 dropout(ReLU(W1 Z)) of width 4 d (8 d with ``max_pool``), so the heads can combine one
            sensor's pooled features with another's non-linearly, as MTCNN's MLP head does. Off by default
            (a linear head on Z; the paper names none).
        final_norm: the LayerNorm that ends the intra-modal Transformer of step 4 (MulT's and nanoGPT's; the
            paper names none). It rescales every step's d features to zero mean and unit variance before the
            pooling; False (the default) leaves them as the blocks made them, as MTCNN's encoders do. Off since
            session 22, on validation (``perception.train.DEVIATIONS["final_norm"]``); a config saved before
            the field existed had it on (:data:`SAVED_BEFORE`).
        residual_base: what eq. 9's residual adds the cross-attention outputs to. "gated" (the default):
            eq. 4's Z_m = alpha_m (X_m + PE), taken on the Conv1D output; "plain": eq. 6's Z^[0]_m = X_m + PE,
            without the weight, as eq. 9 writes it (the module docstring, "Choices the paper leaves open").
        unimodal_lambda: weight of an auxiliary training loss, not the paper's: a linear head per modality on
            its own pooled step-5 feature (before alpha) predicts the class, and the mean cross-entropy of those
            heads over the present modalities is added to eq. 14's loss with this weight (deep supervision of
            each sensor's branch, against one sensor's gradient drowning the others'). The heads are used in
            training only; the model's prediction is unchanged. 0 (the default) builds no heads.
        unimodal_at: what the heads of ``unimodal_lambda`` read: "pooled" (default), step 5's pooled feature,
            which the cross-attention of step 3 has already mixed with the other sensors; "embedding", the
            masked mean of step 1's Conv1D output X_m (after ``stem_dilations``), the sensor's own evidence alone.
        time_bias: add -s_h |t_a - t_b| to each cross-attention head's logits, t the frames' centre times in
            seconds (``frame_clock_s``) and s_h a learned slope per head and pair (module docstring). Off by
            default (the paper's cross-attention sees the PE only).
        inter_modal: step 3's inter-modal cross-attention (the paper's). False builds none, and each sensor's
            gated stream Z_m (``residual_base`` "gated"; Z^[0]_m with "plain") goes straight to step 4, so the
            sensors meet only in eq. 12's concatenation: a diagnostic of what the fusion adds, not the paper's.
        frame_clock_s: per modality (:data:`MODALITIES` order), (hop between frames, centre of the first frame)
            in seconds, :func:`perception.features.frame_clock_s` of the front ends; needed by ``time_bias``
            (training fills it in), empty otherwise.
    """

    SAVED_BEFORE: ClassVar[dict[str, Any]] = {"final_norm": True}
    """Fields added after configs were first saved whose value in such a saved config is not the default:
    a checkpoint or run written before ``final_norm`` existed has the closing LayerNorm."""

    IDENTITY_OMITS: ClassVar[dict[str, Any]] = {"unimodal_lambda": 0.0, "unimodal_at": "pooled", "time_bias": False,
                                                "frame_clock_s": (), "inter_modal": True}
    """Fields added after the evaluation's runs were stored, with the value that does what those runs did: a run
    identity (:func:`perception.train.run_identity`) leaves such a field out at that value, so the stored runs
    stay the runs the current code would train."""

    in_dims: tuple[int, ...]
    n_classes: int
    d_model: int = 64
    n_heads: int = 4
    n_layers: int = 2
    kernel_sizes: tuple[int, ...] = (5, 3, 3, 3)
    gate_hidden: int = 32
    gate_th: float = 0.1
    gate_temperature: float = 0.2
    use_mag: bool = True
    emb_dim: int = 64
    dropout: float = 0.1
    attn_dropout: float = 0.0
    emb_dropout: float = 0.25
    cer_lambda: float = 0.1
    cer_tau: float = 0.2
    gate_straight_through: bool = False
    stem_dilations: tuple[int, ...] = ()
    max_pool: bool = False
    gate_pool: str = "input"
    head_mlp: bool = False
    final_norm: bool = False
    residual_base: str = "gated"
    unimodal_lambda: float = 0.0
    unimodal_at: str = "pooled"
    time_bias: bool = False
    inter_modal: bool = True
    frame_clock_s: tuple[tuple[float, float], ...] = ()

    def __post_init__(self) -> None:
        if len(self.in_dims) != N_MOD or len(self.kernel_sizes) != N_MOD:
            raise ValueError(f"in_dims and kernel_sizes need {N_MOD} entries ({MODALITIES})")
        for name in ("d_model", "n_heads", "gate_hidden", "emb_dim", "n_classes"):
            if not (isinstance(getattr(self, name), int) and getattr(self, name) >= 1):
                raise ValueError(f"{name} must be a whole number >= 1, got {getattr(self, name)!r}")
        if not (isinstance(self.n_layers, int) and self.n_layers >= 0):
            raise ValueError(f"n_layers must be a whole number >= 0, got {self.n_layers!r}")
        for name in ("dropout", "attn_dropout", "emb_dropout"):
            if not (isinstance(getattr(self, name), (int, float)) and 0.0 <= getattr(self, name) < 1.0):
                raise ValueError(f"{name} must lie in [0, 1), got {getattr(self, name)!r}")
        if self.d_model % self.n_heads != 0:
            raise ValueError(f"d_model {self.d_model} is not divisible by n_heads {self.n_heads}")
        if any(k % 2 == 0 for k in self.kernel_sizes):
            raise ValueError(f"kernel sizes must be odd, got {self.kernel_sizes}")
        if not 0.0 <= self.gate_th < 1.0:
            raise ValueError(f"gate_th must lie in [0, 1), got {self.gate_th}")
        if self.gate_temperature <= 0:
            raise ValueError(f"gate_temperature must be positive, got {self.gate_temperature}")
        if any(d < 1 for d in self.stem_dilations):
            raise ValueError(f"stem_dilations must be positive, got {self.stem_dilations}")
        if self.gate_pool not in GATE_POOLS:
            raise ValueError(f"gate_pool must be one of {GATE_POOLS}, got {self.gate_pool!r}")
        if not (isinstance(self.unimodal_lambda, (int, float)) and self.unimodal_lambda >= 0):
            raise ValueError(f"unimodal_lambda must be a number >= 0, got {self.unimodal_lambda!r}")
        if self.unimodal_at not in UNIMODAL_AT:
            raise ValueError(f"unimodal_at must be one of {UNIMODAL_AT}, got {self.unimodal_at!r}")
        if self.residual_base not in RESIDUAL_BASES:
            raise ValueError(f"residual_base must be one of {RESIDUAL_BASES}, got {self.residual_base!r}")
        if self.time_bias and not self.inter_modal:
            raise ValueError("time_bias acts on the inter-modal cross-attention, which inter_modal=False leaves out")
        if self.time_bias and not (len(self.frame_clock_s) == N_MOD and all(
                len(c) == 2 and c[0] > 0 and math.isfinite(c[0]) and math.isfinite(c[1]) for c in self.frame_clock_s)):
            raise ValueError(f"time_bias needs frame_clock_s: {N_MOD} (hop_s > 0, first frame centre_s) pairs, "
                             f"got {self.frame_clock_s!r}")


@dataclass(frozen=True)
class TouchFormerMagConfig(TouchFormerConfig):
    """Ablation "+MAG": gating on, CER loss off."""

    cer_lambda: float = 0.0


@dataclass(frozen=True)
class TouchFormerFusionConfig(TouchFormerConfig):
    """Ablation "transformer fusion only": no MAG (uniform alphas), no CER."""

    use_mag: bool = False
    cer_lambda: float = 0.0


@dataclass(frozen=True)
class TouchFormerSoftGateConfig(TouchFormerConfig):
    """Variant "MAG without its threshold": ``gate_th = 0``, so no modality is dropped and the gates only set
    the softmax weights; CER on. Not in the paper: on our data the threshold dropped sensors on training and
    test strokes alike, and this variant scored 2-4 points higher on SSMC and USMC validation and 8 on
    fine-grained than TouchFormer at temperature 1 (the report before session 18's;
    docs/touchformer-findings.md). Its softmax keeps eq. 3's temperature 1, the setting it was chosen at
    (``gate_temperature`` 0.2 was measured only on the thresholded TouchFormer). It keeps the closing LayerNorm for
    the same reason: without it, it lost 1.0 points on USMC validation and 2.9 on fine-grained (``final_norm``)."""

    gate_th: float = 0.0
    gate_temperature: float = 1.0
    final_norm: bool = True


class ModelOutput(NamedTuple):
    """What every material classifier returns.

    Attributes:
        logits: (B, K) class scores.
        embedding: (B, E) l2-normalised embedding.
        gates: (B, 4) MAG gate g_m in [0, 1] (0 for a missing modality), :data:`MODALITIES` order.
        alphas: (B, 4) modality weights alpha_m; 0 for dropped and missing modalities; rows sum to 1.
    """

    logits: torch.Tensor
    embedding: torch.Tensor
    gates: torch.Tensor
    alphas: torch.Tensor


# ----------------------------------------------------------------------------------------------------------
# helpers


def sinusoidal_pe(length: int, d: int, device: torch.device, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Sinusoidal positional embedding PE(T, d) (Vaswani et al.), returns (T, d) in ``dtype`` (computed in
    float32)."""
    pos = torch.arange(length, device=device, dtype=torch.float32)[:, None]  # (T, 1)
    freq = torch.exp(torch.arange(0, d, 2, device=device, dtype=torch.float32) * (-math.log(10_000.0) / d))
    pe = torch.zeros(length, d, device=device)  # (T, d)
    pe[:, 0::2] = torch.sin(pos * freq)
    pe[:, 1::2] = torch.cos(pos * freq[: d // 2])
    return pe.to(dtype)


def masked_mean(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Mean over valid time steps; 0 where a row has none. x (B, T, d), valid (B, T) -> (B, d)."""
    w = valid.to(x.dtype).unsqueeze(-1)  # (B, T, 1)
    return (x * w).sum(dim=1) / w.sum(dim=1).clamp(min=1.0)  # (B, d)


def mag_weights(gates: torch.Tensor, present: torch.Tensor, gate_th: float, temperature: float = 1.0,
                straight_through: bool = False) -> torch.Tensor:
    """MAG modality weights: softmax of the gates over kept modalities.

    Args:
        gates: (B, M) gates g_m in [0, 1].
        present: (B, M) bool, False for missing modalities.
        gate_th: modalities with g_m < gate_th are dropped.
        temperature: softmax temperature (1 in the paper).
        straight_through: the returned values are unchanged, but gradients flow as if no modality were
            dropped (softmax over all present gates), so a gate that fell below gate_th still learns whether
            its modality would have helped (a straight-through estimator for the hard threshold).

    Returns:
        (B, M) alphas: 0 for dropped/missing modalities, the rest sum to 1. If every present modality is
        below the threshold, the present one with the largest gate is kept; with none present, all 0.
    """
    hard = _thresholded_weights(gates, present, gate_th, temperature)  # (B, M)
    if not straight_through:
        return hard
    soft = _thresholded_weights(gates, present, 0.0, temperature)  # (B, M), nothing dropped
    return hard + (soft - soft.detach())


def _thresholded_weights(gates: torch.Tensor, present: torch.Tensor, gate_th: float, temperature: float
                         ) -> torch.Tensor:
    """:func:`mag_weights` without the straight-through option."""
    kept = present & (gates >= gate_th)  # (B, M)
    best = gates.masked_fill(~present, -1.0).argmax(dim=1)  # (B,)
    fallback = F.one_hot(best, gates.shape[1]).bool() & present  # (B, M)
    kept = torch.where(kept.any(dim=1, keepdim=True), kept, fallback)  # (B, M)
    logits = (gates / temperature).masked_fill(~kept, float("-inf"))  # (B, M)
    alphas = torch.softmax(logits.masked_fill(~kept.any(dim=1, keepdim=True), 0.0), dim=1)  # (B, M)
    return alphas * kept  # (B, M)


def frame_times_s(config: TouchFormerConfig, lengths: dict[str, int], device: torch.device
                  ) -> dict[str, torch.Tensor] | None:
    """Centre time [s] of every frame of each modality on the stroke's clock, ``config.frame_clock_s``:
    modality -> (T_m,) float32. None without ``time_bias``."""
    if not config.time_bias:
        return None
    return {m: config.frame_clock_s[i][1] + config.frame_clock_s[i][0]
            * torch.arange(lengths[m], device=device, dtype=torch.float32) for i, m in enumerate(MODALITIES)}


def masked_max(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Maximum over valid time steps; 0 where a row has none. x (B, T, d), valid (B, T) -> (B, d)."""
    peak = x.masked_fill(~valid.unsqueeze(-1), float("-inf")).amax(dim=1)  # (B, d)
    return torch.where(valid.any(dim=1, keepdim=True), peak, torch.zeros_like(peak))  # (B, d)


def uniform_weights(present: torch.Tensor) -> torch.Tensor:
    """Uniform weights over present modalities: (B, M) bool -> (B, M) float, rows sum to 1 (or 0)."""
    p = present.float()  # (B, M)
    return p / p.sum(dim=1, keepdim=True).clamp(min=1.0)


# ----------------------------------------------------------------------------------------------------------
# building blocks


class ResidualDilatedConvs(nn.Module):
    """Residual dilated Conv1D layers h <- h + ReLU(conv_d(h)) with 'same' padding; padded steps kept at 0."""

    def __init__(self, channels: int, dilations: tuple[int, ...], kernel_size: int = 3) -> None:
        super().__init__()
        self.convs = nn.ModuleList([nn.Conv1d(channels, channels, kernel_size, dilation=d,
                                              padding=d * (kernel_size // 2)) for d in dilations])

    def forward(self, h: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """h (B, ch, T) zero at padded steps, mask (B, 1, T) -> (B, ch, T)."""
        for conv in self.convs:
            h = (h + F.relu(conv(h))) * mask  # (B, ch, T)
        return h


class ModalityEmbedding(nn.Module):
    """Temporal Conv1D (kernel k_m, 'same' padding) from C_m feature channels to width d, then the optional
    residual dilated layers (``TouchFormerConfig.stem_dilations``)."""

    def __init__(self, in_dim: int, d_model: int, kernel_size: int, dilations: tuple[int, ...] = ()) -> None:
        super().__init__()
        self.conv = nn.Conv1d(in_dim, d_model, kernel_size, padding=kernel_size // 2)
        self.dilated = ResidualDilatedConvs(d_model, dilations) if dilations else None

    def forward(self, x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        mask = valid.unsqueeze(1).to(x.dtype)  # (B, 1, T)
        x = x * valid.unsqueeze(-1)  # (B, T, C) zeros at padding == the conv's own zero padding
        h = self.conv(x.transpose(1, 2)) * mask  # (B, d, T)
        if self.dilated is not None:
            h = self.dilated(h, mask)  # (B, d, T)
        return h.transpose(1, 2)  # (B, T, d)


class ModalityGate(nn.Module):
    """MAG gate g = sigmoid(W2 ReLU(W1 X + b1) + b2) of one modality's features X (B, T, d), pooled over time
    before W1 (``pool="input"``) or before W2 (``pool="hidden"``), see ``TouchFormerConfig.gate_pool``."""

    def __init__(self, d_model: int, hidden: int, pool: str = "input") -> None:
        super().__init__()
        self.fc1 = nn.Linear(d_model, hidden)
        self.fc2 = nn.Linear(hidden, 1)
        self.pool = pool

    def forward(self, xs: Sequence[torch.Tensor], valids: Sequence[torch.Tensor]) -> torch.Tensor:
        """The M modalities' features xs[m] (B, T_m, d) with their valid steps valids[m] (B, T_m) -> (B, M)."""
        if self.pool == "hidden":
            h = torch.stack([masked_mean(F.relu(self.fc1(x)), v) for x, v in zip(xs, valids)], dim=1)  # (B, M, h)
        else:
            h = F.relu(self.fc1(torch.stack([masked_mean(x, v) for x, v in zip(xs, valids)], dim=1)))  # (B, M, h)
        return torch.sigmoid(self.fc2(h)).squeeze(-1)  # (B, M)


class Attention(nn.Module):
    """Multi-head attention of queries q onto keys/values kv with padded keys masked."""

    def __init__(self, d_model: int, n_heads: int, dropout: float) -> None:
        super().__init__()
        self.n_heads = n_heads
        self.q = nn.Linear(d_model, d_model)
        self.kv = nn.Linear(d_model, 2 * d_model)
        self.proj = nn.Linear(d_model, d_model)
        self.dropout = dropout

    def forward(self, q: torch.Tensor, kv: torch.Tensor, kv_valid: torch.Tensor,
                bias: torch.Tensor | None = None) -> torch.Tensor:
        """q (B, Tq, d) onto kv (B, Tk, d) with kv_valid (B, Tk); ``bias`` (h, Tq, Tk), if given, is added to
        every head's logits (``time_bias``). Returns (B, Tq, d)."""
        b, tq, d = q.shape
        tk = kv.shape[1]
        h = self.n_heads
        # a row without any valid key attends to its first step (its output is discarded downstream)
        kv_valid = kv_valid.clone()  # (B, Tk)
        kv_valid[:, 0] |= ~kv_valid.any(dim=1)
        qh = self.q(q).view(b, tq, h, d // h).transpose(1, 2)  # (B, h, Tq, d/h)
        k, v = self.kv(kv).split(d, dim=-1)  # (B, Tk, d) each
        kh = k.view(b, tk, h, d // h).transpose(1, 2)  # (B, h, Tk, d/h)
        vh = v.view(b, tk, h, d // h).transpose(1, 2)  # (B, h, Tk, d/h)
        mask = kv_valid[:, None, None, :]  # (B, 1, 1, Tk) True = attend
        if bias is not None:  # additive logits, -inf at padded keys
            mask = bias.to(q.dtype)[None].masked_fill(~mask, float("-inf"))  # (B, h, Tq, Tk)
        y = F.scaled_dot_product_attention(qh, kh, vh, attn_mask=mask,
                                           dropout_p=self.dropout if self.training else 0.0)  # (B, h, Tq, d/h)
        y = y.transpose(1, 2).reshape(b, tq, d)  # (B, Tq, d)
        return self.proj(y)  # (B, Tq, d)


class MLP(nn.Module):
    def __init__(self, d_model: int, dropout: float) -> None:
        super().__init__()
        self.fc = nn.Linear(d_model, 4 * d_model)
        self.proj = nn.Linear(4 * d_model, d_model)
        self.drop = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.drop(self.proj(F.gelu(self.fc(x))))  # (B, T, d)


class CrossModalAttention(nn.Module):
    """Y^_{a<-b} = softmax(Q_a K_b^T / sqrt(d_k)) V_b with pre-LayerNorm on target and source (MulT)."""

    def __init__(self, d_model: int, n_heads: int, dropout: float, time_bias: bool = False) -> None:
        super().__init__()
        self.ln_target = nn.LayerNorm(d_model)
        self.ln_source = nn.LayerNorm(d_model)
        self.attn = Attention(d_model, n_heads, dropout)
        self.time_slope = (nn.Parameter(torch.tensor([TIME_BIAS_INIT_SLOPES_PER_S[i % len(TIME_BIAS_INIT_SLOPES_PER_S)]
                                                      for i in range(n_heads)]))
                           if time_bias else None)  # (h,) s_h [1/s], used as |s_h|

    def forward(self, target: torch.Tensor, source: torch.Tensor, source_valid: torch.Tensor,
                time_gap_s: torch.Tensor | None = None) -> torch.Tensor:
        """target (B, Ta, d) attends to source (B, Tb, d); ``time_gap_s`` (Ta, Tb) = |t_a - t_b| in seconds,
        needed with ``time_bias``."""
        bias = None
        if self.time_slope is not None:
            if time_gap_s is None:
                raise ValueError("a time-biased cross-attention needs the frames' time gaps")
            bias = -self.time_slope.abs()[:, None, None] * time_gap_s[None]  # (h, Ta, Tb)
        return self.attn(self.ln_target(target), self.ln_source(source), source_valid, bias)  # (B, Ta, d)


class SelfAttentionBlock(nn.Module):
    """Pre-norm Transformer encoder layer (nanoGPT Block, non-causal, padded keys masked)."""

    def __init__(self, d_model: int, n_heads: int, dropout: float, attn_dropout: float = 0.0) -> None:
        super().__init__()
        self.ln_1 = nn.LayerNorm(d_model)
        self.attn = Attention(d_model, n_heads, attn_dropout)
        self.ln_2 = nn.LayerNorm(d_model)
        self.mlp = MLP(d_model, dropout)

    def forward(self, x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        h = self.ln_1(x)  # (B, T, d)
        x = x + self.attn(h, h, valid)  # (B, T, d)
        return x + self.mlp(self.ln_2(x))  # (B, T, d)


class IntraModalTransformer(nn.Module):
    """n_layers self-attention blocks within one modality, then a final LayerNorm (none with
    ``final_norm=False``)."""

    def __init__(self, d_model: int, n_heads: int, n_layers: int, dropout: float, attn_dropout: float = 0.0,
                 final_norm: bool = True) -> None:
        super().__init__()
        self.blocks = nn.ModuleList([SelfAttentionBlock(d_model, n_heads, dropout, attn_dropout)
                                     for _ in range(n_layers)])
        self.ln_f = nn.LayerNorm(d_model) if final_norm else nn.Identity()

    def forward(self, x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        for block in self.blocks:
            x = block(x, valid)  # (B, T, d)
        return self.ln_f(x)  # (B, T, d)


# ----------------------------------------------------------------------------------------------------------
# the model


class TouchFormer(nn.Module):
    """MAG + inter/intra-modal Transformer fusion over four asynchronous feature sequences."""

    def __init__(self, config: TouchFormerConfig) -> None:
        super().__init__()
        self.config = config
        c = config
        self.embed = nn.ModuleDict({m: ModalityEmbedding(c.in_dims[i], c.d_model, c.kernel_sizes[i],
                                                      c.stem_dilations)
                                    for i, m in enumerate(MODALITIES)})
        self.emb_drop = nn.Dropout(c.emb_dropout)
        self.gate = ModalityGate(c.d_model, c.gate_hidden, c.gate_pool)
        self.cross = nn.ModuleDict({f"{tgt}_from_{src}": CrossModalAttention(c.d_model, c.n_heads, c.attn_dropout,
                                                                             c.time_bias)
                                    for tgt in MODALITIES for src in MODALITIES if src != tgt and c.inter_modal})
        self.intra = nn.ModuleDict({m: IntraModalTransformer(c.d_model, c.n_heads, c.n_layers, c.dropout,
                                                             c.attn_dropout, c.final_norm)
                                    for m in MODALITIES})
        self.head_drop = nn.Dropout(c.dropout)
        width = N_MOD * c.d_model * (2 if c.max_pool else 1)
        self.head_mlp = (nn.Sequential(nn.Linear(width, width), nn.ReLU(), nn.Dropout(c.dropout),
                                       nn.Linear(width, width)) if c.head_mlp else None)
        self.classifier = nn.Linear(width, c.n_classes)
        self.embedding_head = nn.Linear(width, c.emb_dim)
        head_in = c.d_model if c.unimodal_at == "embedding" else width // N_MOD
        self.unimodal_heads = (nn.ModuleDict({m: nn.Linear(head_in, c.n_classes) for m in MODALITIES})
                               if c.unimodal_lambda > 0 else None)

    def forward(self, batch: FeatureBatch) -> ModelOutput:
        return self.forward_with_unimodal(batch)[0]

    def forward_with_unimodal(self, batch: FeatureBatch) -> tuple[ModelOutput, torch.Tensor | None]:
        """:meth:`forward` and the (B, M, K) class scores of the per-modality auxiliary heads
        (``TouchFormerConfig.unimodal_lambda``; None without them), which only the training loss reads."""
        c = self.config
        valid = {m: ~batch.padding[m] for m in MODALITIES}  # (B, T_m) each
        present = batch.present_matrix()  # (B, M)

        # 1. temporal convolution to width d
        x_hat = {m: self.embed[m](batch.x[m], valid[m]) for m in MODALITIES}  # (B, T_m, d) each

        # 2. modality-adaptive gating
        gates = self.gate([x_hat[m] for m in MODALITIES], [valid[m] for m in MODALITIES]) * present  # (B, M), 0 missing
        if c.use_mag:
            alphas = mag_weights(gates, present, c.gate_th, c.gate_temperature,
                                 straight_through=c.gate_straight_through and self.training)  # (B, M)
        else:
            alphas = uniform_weights(present).to(gates.dtype)  # (B, M)
        a = {m: alphas[:, i, None, None] for i, m in enumerate(MODALITIES)}  # (B, 1, 1) each
        plain, z0 = {}, {}
        for m in MODALITIES:
            pe = sinusoidal_pe(x_hat[m].shape[1], c.d_model, x_hat[m].device, x_hat[m].dtype)  # (T_m, d)
            plain[m] = self.emb_drop(x_hat[m] + pe)  # (B, T_m, d), eq. 6's Z^[0]
            z0[m] = a[m] * plain[m]  # (B, T_m, d), eq. 4's Z_m
        base = z0 if c.residual_base == "gated" else plain

        # 3. inter-modal cross-attention, each source's output scaled by its alpha, plus residual
        times = frame_times_s(c, {m: x_hat[m].shape[1] for m in MODALITIES}, x_hat[MODALITIES[0]].device)
        z_tilde = {}
        for tgt in MODALITIES:
            y = base[tgt]  # (B, T_tgt, d)
            for src in MODALITIES:
                if src != tgt and c.inter_modal:
                    gap = None if times is None else (times[tgt][:, None] - times[src][None, :]).abs()  # (T_tgt, T_src)
                    y = y + a[src] * self.cross[f"{tgt}_from_{src}"](z0[tgt], z0[src], valid[src], gap)  # (B, T_tgt, d)
            z_tilde[tgt] = y

        # 4. intra-modal self-attention
        z_intra = {m: self.intra[m](z_tilde[m], valid[m]) for m in MODALITIES}  # (B, T_m, d) each

        # 5. pooling, alpha-weighted concat (eq. 12), heads
        own = {m: self._pool(z_intra[m], valid[m]) for m in MODALITIES}  # (B, d) each, (B, 2 d) with max_pool
        pooled = torch.cat([a[m].squeeze(-1) * own[m] for m in MODALITIES], dim=1)  # (B, M d), (B, 2 M d)
        h = self.head_drop(pooled)  # (B, width)
        if self.head_mlp is not None:
            h = h + self.head_mlp(h)  # (B, width), MulT's residual projection
        logits = self.classifier(h)  # (B, K)
        embedding = F.normalize(self.embedding_head(h), dim=-1)  # (B, E)
        unimodal = None
        if self.unimodal_heads is not None:
            read = ({m: masked_mean(x_hat[m], valid[m]) for m in MODALITIES} if c.unimodal_at == "embedding"
                    else own)  # (B, d) or (B, width / M) each
            unimodal = torch.stack([self.unimodal_heads[m](read[m]) for m in MODALITIES], dim=1)  # (B, M, K)
        return ModelOutput(logits=logits, embedding=embedding, gates=gates, alphas=alphas), unimodal

    def _pool(self, z: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """Step 5's pooling of one modality: (B, T, d) -> (B, d), or (B, 2 d) with ``max_pool``."""
        mean = masked_mean(z, valid)  # (B, d)
        return torch.cat([mean, masked_max(z, valid)], dim=1) if self.config.max_pool else mean
