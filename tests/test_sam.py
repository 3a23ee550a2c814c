"""Sharpness-aware minimisation's two-pass step (perception.sam)."""

from __future__ import annotations

import pytest
import torch

from perception import sam


def _quadratic_grads(params, curvatures):
    """Gradients of sum_i 0.5 c_i |p_i|^2 at the parameters' current values."""
    for p in params:
        p.grad = None
    loss = sum(0.5 * c * (p ** 2).sum() for p, c in zip(params, curvatures))
    loss.backward()


def test_ascent_moves_every_weight_jointly_by_rho_up_the_gradient_and_back():
    torch.manual_seed(0)
    params = [torch.nn.Parameter(torch.randn(3, 2)), torch.nn.Parameter(torch.randn(5)),
              torch.nn.Parameter(torch.randn(4))]
    params[2].requires_grad_(False)  # a frozen weight: no gradient, never moved
    start = [p.detach().clone() for p in params]
    _quadratic_grads(params[:2], (1.0, 10.0))
    g = [p.grad.clone() for p in params[:2]]
    rho = 0.05
    steps = sam.ascend(params, rho)
    moved = torch.cat([(p.detach() - s).flatten() for p, s in zip(params[:2], start)])
    assert torch.linalg.vector_norm(moved) == pytest.approx(rho, rel=1e-5)  # one ball over all weights
    grad = torch.cat([x.flatten() for x in g])
    assert torch.allclose(moved, rho * grad / torch.linalg.vector_norm(grad), atol=1e-7)  # along the gradient
    assert steps[2] is None and torch.equal(params[2].detach(), start[2])

    _quadratic_grads(params[:2], (1.0, 10.0))  # the gradient at the ascent point
    at_ascent = [p.grad.clone() for p in params[:2]]
    sam.descend_back(params, steps)
    for p, s in zip(params, start):
        assert torch.allclose(p.detach(), s, atol=1e-7)  # back where it was
    assert all(torch.equal(p.grad, a) for p, a in zip(params[:2], at_ascent))  # the ascent's gradient is kept
    # on the steeper quadratic the ascent point's gradient is larger: SAM pushes harder against sharp directions
    assert (at_ascent[1].norm() / g[1].norm()) > (at_ascent[0].norm() / g[0].norm())


def test_a_zero_gradient_moves_nothing():
    p = torch.nn.Parameter(torch.ones(3))
    p.grad = torch.zeros(3)
    steps = sam.ascend([p], 0.1)
    assert torch.equal(p.detach(), torch.ones(3)) and torch.isfinite(steps[0]).all()
    assert sam.ascend([torch.nn.Parameter(torch.ones(2))], 0.1) == [None]  # no gradient at all
