"""Batched non-negative least squares on normal equations.

Solves, for every batch element independently,

    x* = argmin_{x ≥ 0} ½ xᵀ G x − hᵀ x         (G = AᵀA, h = Aᵀy: min ‖A x − y‖², x ≥ 0)

by the Lawson–Hanson active-set method, run in lock step over the batch with masks.
G (...×k×k) symmetric positive semi-definite, h (...×k) → x (...×k). Not differentiable
(the exact solve is a fixed point; gradients of a cost at x* with respect to other
parameters need no derivative of x*, by the envelope theorem).

Convergence is data, not an exception (:class:`NNLSResult`): a batch element has
converged when, as the iteration ends, x ≥ 0 is the unconstrained minimiser on its
passive set P (the inner loop finished) and the KKT conditions hold off it,

    w = h − G x ≤ tol · max|h|   on every index not in P

(w is the negative gradient; NaN counts as a violation). ``throw=True`` raises
:class:`NNLSError` instead of returning unconverged elements.

A column whose squared norm G_ii is below 10¹⁰ times the dtype's smallest normal
number (2·10⁻²⁹⁸ in float64) takes no weight: its products with any weight underflow
to subnormal numbers, whose few bits made the passive solve NaN (a field whose Gaussian
is 10⁻¹⁵⁵ on a motion's path; it cannot drive that motion with any finite weight).
"""
from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import NamedTuple

import torch


class NNLSResult(NamedTuple):
    """The solve: x (...×k, ≥ 0), converged (... bool, per batch element) and the number
    of outer (Lawson–Hanson) iterations run."""

    x: torch.Tensor
    converged: torch.Tensor
    iterations: int


class NNLSError(ArithmeticError):
    """:func:`nnls` with ``throw=True`` left some batch elements unconverged."""


class NNLSWarning(RuntimeWarning):
    """Some NNLS solves did not converge (see :func:`warn_unconverged`)."""


def packed(mask: torch.Tensor) -> tuple:
    """(cols, pad), both B×W: each row's indices where ``mask`` (B×k bools) holds, in
    order, first, W the most any row has (at least 1); ``pad`` marks the filling."""
    W = max(int(mask.sum(-1).max()), 1)
    cols = torch.argsort((~mask).to(torch.int8), dim=-1, stable=True)[:, :W]
    return cols, ~torch.gather(mask, -1, cols)


def take(G: torch.Tensor, h: torch.Tensor, cols: torch.Tensor, pad: torch.Tensor) -> tuple:
    """(G[b, cols_b][:, cols_b], h[b, cols_b]) for each row b (B×W×W, B×W), 0 in the
    rows, columns and entries of the padding (:func:`packed`)."""
    W = cols.shape[-1]
    rows = torch.gather(G, -2, cols.unsqueeze(-1).expand(-1, -1, G.shape[-1]))
    Gp = torch.gather(rows, -1, cols.unsqueeze(-2).expand(-1, W, -1))
    return (torch.where(pad.unsqueeze(-1) | pad.unsqueeze(-2), 0.0, Gp),
            torch.where(pad, 0.0, torch.gather(h, -1, cols)))


def _solve_passive(G: torch.Tensor, h: torch.Tensor, P: torch.Tensor, ridge: float) -> torch.Tensor:
    """Unconstrained minimiser restricted to the passive set P (zeros elsewhere), solved
    on each element's passive indices only (:func:`packed`): O(|P|³), not O(k³)."""
    cols, pad = packed(P)
    Gp, hp = take(G, h, cols, pad)
    eye = torch.eye(Gp.shape[-1], dtype=G.dtype, device=G.device)
    scale = torch.diagonal(G, dim1=-2, dim2=-1).abs().amax(-1, keepdim=True).clamp_min(1e-300)
    on = (~pad).to(G.dtype)
    A = Gp + eye * pad.to(G.dtype).unsqueeze(-1) + ridge * scale.unsqueeze(-1) * eye * on.unsqueeze(-1)
    z = torch.linalg.solve(A, hp.unsqueeze(-1)).squeeze(-1) * on
    # One step of iterative refinement against the unregularised system removes the
    # ridge's bias (≈ cond(G)·ridge relative).
    r = (hp - (Gp @ z.unsqueeze(-1)).squeeze(-1)) * on
    z = (z + torch.linalg.solve(A, r.unsqueeze(-1)).squeeze(-1)) * on
    return torch.zeros_like(h).scatter_(-1, cols, z)


def _negative_gradient(G: torch.Tensor, h: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """w = h − G x (B×k)."""
    return h - (G @ x.unsqueeze(-1)).squeeze(-1)


def _step_back(x, z, P, need, tol):
    """Move the elements in ``need`` (B) from x towards z as far as x stays ≥ 0,
    x + α (z − x) with α = min over {i ∈ P: z_i ≤ 0} of x_i / (x_i − z_i), and drop
    from P the indices that reach 0 (≤ tol · max|x|). Returns (x, P)."""
    bad = P & (z <= 0)
    ratio = torch.where(bad, x / (x - z).clamp_min(1e-300), torch.full_like(x, torch.inf))
    alpha = ratio.amin(-1, keepdim=True).clamp(0, 1)
    x = torch.where(need.unsqueeze(-1), x + alpha * (z - x), x)
    drop = need.unsqueeze(-1) & P & (x <= tol * x.abs().amax(-1, keepdim=True).clamp_min(1e-300))
    return torch.where(drop, torch.zeros_like(x), x), P & ~drop


def _inner(G, h, x, P, active, tol, ridge):
    """Lawson–Hanson inner loop for the elements in ``active`` (B): solve on P, step back
    while the solution has a non-positive passive entry (at most k + 1 times). Returns
    (x, P, stuck), stuck (B) the elements still stepping back when the loop ended."""
    for _ in range(G.shape[-1] + 1):
        z = _solve_passive(G, h, P, ridge)
        need = (P & (z <= 0)).any(-1) & active
        x = torch.where((active & ~need).unsqueeze(-1), z, x)
        active = need
        if not bool(active.any()):
            break
        x, P = _step_back(x, z, P, need, tol)
    return x, P, active


@torch.no_grad()
def nnls(G: torch.Tensor, h: torch.Tensor, tol: float = 1e-12, max_iter: int | None = None,
         ridge: float = 1e-12, throw: bool = False) -> NNLSResult:
    """Exact NNLS by Lawson–Hanson on (G, h) (see the module docstring): at most
    ``max_iter`` outer iterations (default 3k + 10), each freeing the index of largest
    w = h − G x > tol · max|h|. Returns :class:`NNLSResult` (x ...×k, converged ...);
    ``throw=True`` raises :class:`NNLSError` if any element did not converge."""
    batch, k = h.shape[:-1], h.shape[-1]
    G = G.expand(batch + (k, k)).reshape(-1, k, k)
    h = h.reshape(-1, k)
    x = torch.zeros_like(h)
    P = torch.zeros(h.shape, dtype=torch.bool, device=h.device)
    settled = torch.ones(h.shape[0], dtype=torch.bool, device=h.device)
    bound = tol * (h.abs().amax(-1, keepdim=True) + 1e-300)
    usable = torch.diagonal(G, dim1=-2, dim2=-1) > 1e10 * torch.finfo(G.dtype).tiny
    max_iter = max_iter or 3 * k + 10
    iterations = 0
    while iterations < max_iter:
        w = _negative_gradient(G, h, x)
        cand = (~P) & (w > bound) & usable
        active = cand.any(-1)
        if not bool(active.any()):
            break
        j = torch.where(cand, w, -torch.inf).argmax(-1)
        P = P | (torch.nn.functional.one_hot(j, k).bool() & active.unsqueeze(-1))
        x, P, stuck = _inner(G, h, x, P, active, tol, ridge)
        settled = torch.where(active, ~stuck, settled)
        iterations += 1
    kkt = (P | (_negative_gradient(G, h, x) <= bound) | ~usable).all(-1) & (x >= 0).all(-1)
    result = NNLSResult(x.clamp_min(0).reshape(batch + (k,)), (settled & kkt).reshape(batch),
                        iterations)
    if throw and not bool(result.converged.all()):
        bad = int((~result.converged).sum())
        raise NNLSError(f"NNLS did not converge for {bad} of {result.converged.numel()} "
                        f"problem(s) after {iterations} iteration(s) (max_iter={max_iter})")
    return result


def nnls_lstsq(A: torch.Tensor, y: torch.Tensor, **kw) -> NNLSResult:
    """min ‖A x − y‖² s.t. x ≥ 0 for A (...×m×k), y (...×m): :func:`nnls` on G = AᵀA,
    h = Aᵀy (keywords passed on)."""
    G = A.transpose(-1, -2) @ A
    h = (A.transpose(-1, -2) @ y.unsqueeze(-1)).squeeze(-1)
    return nnls(G, h, **kw)


def warn_unconverged(result: NNLSResult, names: Sequence[str], where: str) -> None:
    """One :class:`NNLSWarning` from ``where`` naming the batch elements (``names``, in
    flattened batch order) whose solve did not converge; nothing if all converged."""
    failed = [n for n, ok in zip(names, result.converged.reshape(-1).tolist()) if not ok]
    if failed:
        warnings.warn(f"{where}: NNLS did not converge for {', '.join(map(str, failed))} "
                      f"after {result.iterations} iteration(s)", NNLSWarning, stacklevel=3)
