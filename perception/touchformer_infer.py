"""Inference-only TouchFormer: the same parameters and the same outputs, in a few batched operations.

:class:`perception.touchformer.TouchFormer` follows the paper step by step, one module call per modality and
per (target, source) pair: 12 cross-attentions and 8 self-attention blocks, about 1 000 small tensor
operations per forward. At batch 1 on one CPU thread the cost is the per-operation overhead, not the
arithmetic (``robotdemo bench inference`` compares both paths). :class:`FusedTouchFormer` computes the same
function with the per-pair and per-modality weights stacked:

- the four modalities are padded to one length and stacked, (M, B, T, d), padding masked as before;
- a LayerNorm's affine part is folded into the linear map that follows it:
  (n * g + b) W^T + c = n (W diag g)^T + (W b + c), with n the normalised input;
- the 12 cross-attentions run as one batched matrix product per projection and one attention call;
- the intra-modal blocks run for all four modalities at once, layer by layer.

Eval mode only (no dropout). The outputs equal the reference model's to float rounding
(``tests/test_touchformer_infer.py``).
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from perception.features import FeatureBatch
from perception.streams import MODALITIES
from perception.touchformer import (N_MOD, CrossModalAttention, ModelOutput, TouchFormer, frame_times_s, mag_weights,
                                    masked_max, masked_mean, sinusoidal_pe, uniform_weights)

# (target, source) pairs grouped by target, MODALITIES order: pair p has target PAIR_TARGET[p]
PAIRS = tuple((tgt, src) for tgt in MODALITIES for src in MODALITIES if src != tgt)
PAIR_TARGET = tuple(MODALITIES.index(t) for t, _ in PAIRS)
PAIR_SOURCE = tuple(MODALITIES.index(s) for _, s in PAIRS)


def _fold(ln: nn.LayerNorm, linear: nn.Linear) -> tuple[torch.Tensor, torch.Tensor]:
    """W', c' with linear(ln(x)) = layer_norm(x, no affine) @ W' + c'; W' is (d_in, d_out), c' (d_out,)."""
    w = linear.weight * ln.weight[None, :]  # (d_out, d_in)
    c = linear.weight @ ln.bias + linear.bias  # (d_out,)
    return w.t().contiguous(), c


def _stack_folded(pairs: list[tuple[nn.LayerNorm, nn.Linear]]) -> tuple[torch.Tensor, torch.Tensor]:
    """(P, d_in, d_out) folded weights and (P, 1, d_out) biases of P (LayerNorm, Linear) pairs."""
    folded = [_fold(ln, lin) for ln, lin in pairs]
    return torch.stack([w for w, _ in folded]), torch.stack([c for _, c in folded])[:, None, :]


def _stack_linear(linears: list[nn.Linear]) -> tuple[torch.Tensor, torch.Tensor]:
    """(P, d_in, d_out) weights and (P, 1, d_out) biases of P Linear maps."""
    return (torch.stack([lin.weight.t() for lin in linears]).contiguous(),  # (P, d_in, d_out)
            torch.stack([lin.bias for lin in linears])[:, None, :])  # (P, 1, d_out)


class FusedTouchFormer(nn.Module):
    """A trained :class:`TouchFormer` repacked for fast inference (see the module docstring).

    The weights are copied when it is built: build it again after changing the reference model.
    """

    def __init__(self, model: TouchFormer) -> None:
        super().__init__()
        self.config = c = model.config
        self.reference = model  # front end (convolutions, gate) and heads are used as they are
        norms = [m for m in model.modules() if isinstance(m, nn.LayerNorm)]
        self.eps = norms[0].eps if norms else 1e-5  # the eps all its LayerNorms share
        cross: list[CrossModalAttention] = [model.cross[f"{t}_from_{s}"] for t, s in PAIRS] if c.inter_modal else []
        with torch.no_grad():
            if cross:
                self.q_w, self.q_b = _stack_folded([(m.ln_target, m.attn.q) for m in cross])  # (12, d, d)
                self.kv_w, self.kv_b = _stack_folded([(m.ln_source, m.attn.kv) for m in cross])  # (12, d, 2d)
                self.cp_w, self.cp_b = _stack_linear([m.attn.proj for m in cross])  # (12, d, d)
            self.layers = []
            for layer in range(c.n_layers):
                blocks = [model.intra[m].blocks[layer] for m in MODALITIES]
                qkv = [_stack_folded([(b.ln_1, b.attn.q) for b in blocks]),
                       _stack_folded([(b.ln_1, b.attn.kv) for b in blocks])]
                self.layers.append({
                    "qkv_w": torch.cat([qkv[0][0], qkv[1][0]], dim=2),  # (M, d, 3d)
                    "qkv_b": torch.cat([qkv[0][1], qkv[1][1]], dim=2),  # (M, 1, 3d)
                    "proj": _stack_linear([b.attn.proj for b in blocks]),  # (M, d, d)
                    "fc": _stack_folded([(b.ln_2, b.mlp.fc) for b in blocks]),  # (M, d, 4d)
                    "mlp_proj": _stack_linear([b.mlp.proj for b in blocks]),  # (M, 4d, d)
                })
            if c.final_norm:  # the intra-modal blocks' closing LayerNorm
                self.lnf_w = torch.stack([model.intra[m].ln_f.weight for m in MODALITIES])[:, None, :]  # (M, 1, d)
                self.lnf_b = torch.stack([model.intra[m].ln_f.bias for m in MODALITIES])[:, None, :]  # (M, 1, d)
        self.time_slope = (torch.stack([m.time_slope.detach().abs() for m in cross])  # (12, h) |s_h| [1/s]
                           if c.time_bias else None)
        self.src_index = torch.tensor(PAIR_SOURCE)
        self.tgt_index = torch.tensor(PAIR_TARGET)
        self._pe: dict[int, torch.Tensor] = {}

    def train(self, mode: bool = True) -> "FusedTouchFormer":
        if mode:
            raise RuntimeError("FusedTouchFormer is for inference only; train the reference TouchFormer")
        return super().train(False)

    def _positional(self, length: int) -> torch.Tensor:
        if length not in self._pe:
            self._pe[length] = sinusoidal_pe(length, self.config.d_model, torch.device("cpu"))
        return self._pe[length]  # (T, d)

    def _attend(self, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, key_valid: torch.Tensor,
                bias: torch.Tensor | None = None) -> torch.Tensor:
        """Batched multi-head attention. q, k, v (P, B, T, d); key_valid (P, B, T); ``bias`` (P, h, T, T) added
        to the logits (``time_bias``) -> (P, B, T, d)."""
        p, b, t, d = q.shape
        h = self.config.n_heads
        heads = lambda x: x.reshape(p * b, t, h, d // h).transpose(1, 2)  # noqa: E731  (P B, h, T, d/h)
        mask = key_valid.reshape(p * b, 1, 1, t)  # True = attend
        if bias is not None:
            mask = (bias[:, None].expand(p, b, h, t, t).reshape(p * b, h, t, t).to(q.dtype)
                    .masked_fill(~mask, float("-inf")))  # (P B, h, T, T)
        y = F.scaled_dot_product_attention(heads(q), heads(k), heads(v), attn_mask=mask)  # (P B, h, T, d/h)
        return y.transpose(1, 2).reshape(p, b, t, d)

    def _time_bias(self, t_max: int) -> torch.Tensor | None:
        """``time_bias``: (12, h, T, T) logits -|s_h| |t_target - t_source| of every pair, frames beyond a
        modality's length included (their rows and keys are discarded or masked); None without it."""
        if self.time_slope is None:
            return None
        times = frame_times_s(self.config, {m: t_max for m in MODALITIES}, torch.device("cpu"))
        stacked = torch.stack([times[m] for m in MODALITIES])  # (M, T)
        gap = (stacked[self.tgt_index][:, :, None] - stacked[self.src_index][:, None, :]).abs()  # (12, T, T)
        return -self.time_slope[:, :, None, None] * gap[:, None]  # (12, h, T, T)

    def _cross_attend(self, z0: torch.Tensor, key_valid: torch.Tensor, alphas: torch.Tensor, t_max: int
                      ) -> torch.Tensor:
        """Step 3 without its residual: z0 (M, B, T, d), key masks (M, B, T), alphas (B, M) -> the sum over
        sources of each target's cross-attention outputs, each scaled by its source's alpha, (M, B, T, d)."""
        d, b = self.config.d_model, z0.shape[1]
        n0 = F.layer_norm(z0, (d,), eps=self.eps).reshape(N_MOD, b * t_max, d)  # (M, B T, d)
        q = torch.baddbmm(self.q_b, n0[self.tgt_index], self.q_w)  # (12, B T, d)
        k, v = torch.baddbmm(self.kv_b, n0[self.src_index], self.kv_w).split(d, dim=-1)  # (12, B T, d) each
        shape = (len(PAIRS), b, t_max, d)
        y = self._attend(q.reshape(shape), k.reshape(shape), v.reshape(shape), key_valid[self.src_index],
                         self._time_bias(t_max))
        y = torch.baddbmm(self.cp_b, y.reshape(len(PAIRS), b * t_max, d), self.cp_w).reshape(shape)  # (12, B, T, d)
        y = y * alphas.t()[self.src_index][:, :, None, None]  # scaled by the source's alpha
        return y.reshape(N_MOD, N_MOD - 1, b, t_max, d).sum(dim=1)  # (M, B, T, d)

    @torch.no_grad()
    def forward(self, batch: FeatureBatch) -> ModelOutput:
        c, ref = self.config, self.reference
        d = c.d_model
        valid = {m: ~batch.padding[m] for m in MODALITIES}  # (B, T_m) each
        present = batch.present_matrix()  # (B, M)

        # 1.-2. temporal convolution and gating, as in the reference model
        x_hat = {m: ref.embed[m](batch.x[m], valid[m]) for m in MODALITIES}  # (B, T_m, d) each
        gates = ref.gate([x_hat[m] for m in MODALITIES], [valid[m] for m in MODALITIES]) * present  # (B, M)
        alphas = (mag_weights(gates, present, c.gate_th, c.gate_temperature) if c.use_mag
                  else uniform_weights(present).to(gates.dtype))  # (B, M)

        # stack the modalities at one length T: z0 (M, B, T, d), key masks (M, B, T)
        t_max = max(x.shape[1] for x in x_hat.values())
        b = present.shape[0]
        plain = torch.stack([F.pad(x_hat[m] + self._positional(x_hat[m].shape[1]),
                                   (0, 0, 0, t_max - x_hat[m].shape[1]))
                             for m in MODALITIES])  # (M, B, T, d), Z^[0]_m = X_m + PE
        z0 = plain * alphas.t()[:, :, None, None]  # Z_m = alpha_m (X_m + PE)
        steps_valid = torch.stack([F.pad(valid[m], (0, t_max - valid[m].shape[1])) for m in MODALITIES])  # (M, B, T)
        key_valid = steps_valid.clone()
        key_valid[:, :, 0] |= ~key_valid.any(dim=2)  # a row without valid keys attends to its first step

        # 3. inter-modal cross-attention, all 12 (target, source) pairs at once
        base = z0 if c.residual_base == "gated" else plain  # what the residual adds to (residual_base)
        z = self._cross_attend(z0, key_valid, alphas, t_max) + base if c.inter_modal else base  # (M, B, T, d)

        # 4. intra-modal self-attention, the four modalities at once
        z = z.reshape(N_MOD, b * t_max, d)
        shape = (N_MOD, b, t_max, d)
        for layer in self.layers:
            h = F.layer_norm(z, (d,), eps=self.eps)  # (M, B T, d)
            q, k, v = torch.baddbmm(layer["qkv_b"], h, layer["qkv_w"]).split(d, dim=-1)
            y = self._attend(q.reshape(shape), k.reshape(shape), v.reshape(shape), key_valid)  # (M, B, T, d)
            z = z + torch.baddbmm(layer["proj"][1], y.reshape(N_MOD, b * t_max, d), layer["proj"][0])
            h = F.gelu(torch.baddbmm(layer["fc"][1], F.layer_norm(z, (d,), eps=self.eps), layer["fc"][0]))
            z = z + torch.baddbmm(layer["mlp_proj"][1], h, layer["mlp_proj"][0])  # (M, B T, d)
        if c.final_norm:
            z = F.layer_norm(z, (d,), eps=self.eps) * self.lnf_w + self.lnf_b  # (M, B T, d)

        # 5. pooling, alpha-weighted concat (eq. 12), heads
        z, w = z.reshape(N_MOD * b, t_max, d), steps_valid.reshape(N_MOD * b, t_max)  # (M B, T, d), (M B, T)
        pooled = masked_mean(z, w)  # (M B, d)
        if c.max_pool:
            pooled = torch.cat([pooled, masked_max(z, w)], dim=1)  # (M B, 2 d)
        pooled = (pooled.reshape(N_MOD, b, -1) * alphas.t()[:, :, None]).transpose(0, 1).reshape(b, -1)  # (B, [2] M d)
        if ref.head_mlp is not None:
            pooled = pooled + ref.head_mlp(pooled)  # (B, width), MulT's residual projection
        logits = ref.classifier(pooled)  # (B, K)
        embedding = F.normalize(ref.embedding_head(pooled), dim=-1)  # (B, E)
        return ModelOutput(logits=logits, embedding=embedding, gates=gates, alphas=alphas)


def for_inference(model: nn.Module) -> nn.Module:
    """The fastest equivalent of a trained model for inference: a TouchFormer repacked, any other model as is."""
    model.eval()
    if isinstance(model, TouchFormer):
        return FusedTouchFormer(model).eval()
    return model
