"""Sharpness-aware minimisation (SAM; Foret et al., ICLR 2021), as a two-pass step around any optimizer.

SAM minimises the worst loss within an l2 ball of radius rho around the weights: the first backward pass gives
the gradient g at w, the weights move to the ascent point w + e, e = rho g / ||g||, a second backward pass
gives the gradient there, and the optimizer steps from w with that gradient. Chen et al. (ICLR 2022, "When
vision transformers outperform ResNets without pre-training or strong data augmentations") found it lifts
transformers trained on small data far more than convolutional networks, by leading them out of sharp minima.

Written here rather than taken from a package: PyTorch has no SAM, and the step is these two functions around
the training loop's own optimizer, clipping and EMA.
"""

from __future__ import annotations

from typing import Sequence

import torch


def ascend(params: Sequence[torch.nn.Parameter], rho: float) -> list[torch.Tensor | None]:
    """Move every parameter with a gradient to SAM's ascent point, p += rho g / ||g|| (the norm over all of
    them), and return each one's step (None where it had no gradient) for :func:`descend_back`.

    A zero gradient (nothing to ascend along) moves nothing.
    """
    grads = [None if p.grad is None else p.grad.detach() for p in params]
    present = [g for g in grads if g is not None]
    if not present:
        return [None] * len(grads)
    norm = torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in present]))
    scale = rho / norm.clamp(min=1e-12)
    steps: list[torch.Tensor | None] = []
    with torch.no_grad():
        for p, g in zip(params, grads):
            if g is None:
                steps.append(None)
                continue
            e = g * scale
            p.add_(e)
            steps.append(e)
    return steps


def descend_back(params: Sequence[torch.nn.Parameter], steps: Sequence[torch.Tensor | None]) -> None:
    """Undo :func:`ascend`: every parameter back to where it was, its gradient (the one taken at the ascent
    point) kept for the optimizer."""
    with torch.no_grad():
        for p, e in zip(params, steps):
            if e is not None:
                p.sub_(e)
