"""Batched non-negative least squares on normal equations.

Solves, for every batch element independently,

    x* = argmin_{x ≥ 0} ½ xᵀ G x − hᵀ x         (G = AᵀA, h = Aᵀy: min ‖A x − y‖², x ≥ 0)

by the Lawson–Hanson active-set method, run in lock step over the batch with masks.
G (...×k×k) symmetric positive semi-definite, h (...×k) → x (...×k). Not differentiable
(the exact solve is a fixed point; gradients of a cost at x* with respect to other
parameters need no derivative of x*, by the envelope theorem).
"""
from __future__ import annotations

import torch


def _solve_passive(G: torch.Tensor, h: torch.Tensor, P: torch.Tensor, ridge: float) -> torch.Tensor:
    """Unconstrained minimiser restricted to the passive set P (zeros elsewhere)."""
    Pf = P.to(G.dtype)
    mask = Pf.unsqueeze(-1) * Pf.unsqueeze(-2)
    eye = torch.eye(G.shape[-1], dtype=G.dtype, device=G.device)
    scale = torch.diagonal(G, dim1=-2, dim2=-1).abs().amax(-1, keepdim=True).clamp_min(1e-300)
    Gp = G * mask + eye * (1 - Pf).unsqueeze(-1) + ridge * scale.unsqueeze(-1) * eye * Pf.unsqueeze(-1)
    z = torch.linalg.solve(Gp, (h * Pf).unsqueeze(-1)).squeeze(-1) * Pf
    # One step of iterative refinement against the unregularised system removes the
    # ridge's bias (≈ cond(G)·ridge relative).
    r = (h - (G @ z.unsqueeze(-1)).squeeze(-1)) * Pf
    return (z + torch.linalg.solve(Gp, r.unsqueeze(-1)).squeeze(-1)) * Pf


@torch.no_grad()
def nnls(G: torch.Tensor, h: torch.Tensor, tol: float = 1e-12, max_iter: int | None = None,
         ridge: float = 1e-12) -> torch.Tensor:
    """Exact NNLS by Lawson–Hanson on (G, h); see the module docstring. Returns x (...×k)."""
    batch, k = h.shape[:-1], h.shape[-1]
    G = G.expand(batch + (k, k)).reshape(-1, k, k)
    h = h.reshape(-1, k)
    B = h.shape[0]
    x = torch.zeros_like(h)
    P = torch.zeros(B, k, dtype=torch.bool, device=h.device)
    scale = (h.abs().amax(-1, keepdim=True) + 1e-300)
    max_iter = max_iter or 3 * k + 10
    for _ in range(max_iter):
        w = h - (G @ x.unsqueeze(-1)).squeeze(-1)
        cand = (~P) & (w > tol * scale)
        active = cand.any(-1)
        if not bool(active.any()):
            break
        j = torch.where(cand, w, torch.full_like(w, -torch.inf)).argmax(-1)
        P = P | (torch.nn.functional.one_hot(j, k).bool() & active.unsqueeze(-1))
        for _inner in range(k + 1):
            z = _solve_passive(G, h, P, ridge)
            bad = P & (z <= 0)
            need = bad.any(-1) & active
            if not bool(need.any()):
                x = torch.where(active.unsqueeze(-1), z, x)
                break
            ratio = torch.where(bad, x / (x - z).clamp_min(1e-300), torch.full_like(x, torch.inf))
            alpha = ratio.amin(-1, keepdim=True).clamp(0, 1)
            x_new = x + alpha * (z - x)
            x = torch.where(need.unsqueeze(-1), x_new, torch.where(active.unsqueeze(-1), z, x))
            drop = need.unsqueeze(-1) & P & (x <= tol * x.abs().amax(-1, keepdim=True).clamp_min(1e-300))
            P = P & ~drop
            x = torch.where(drop, torch.zeros_like(x), x)
            active = active & need
    return x.clamp_min(0).reshape(batch + (k,))


def nnls_lstsq(A: torch.Tensor, y: torch.Tensor, **kw) -> torch.Tensor:
    """min ‖A x − y‖² s.t. x ≥ 0 for A (...×m×k), y (...×m)."""
    G = A.transpose(-1, -2) @ A
    h = (A.transpose(-1, -2) @ y.unsqueeze(-1)).squeeze(-1)
    return nnls(G, h, **kw)
