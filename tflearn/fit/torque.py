"""Torque matching (thesis eq. 3.10/3.11) and its solvers.

For motion j with inverse-dynamics torques T_j(t) and fields (η_i, K_i) the model torque
is linear in the motion's weights x_j = (a_j, b_j) ∈ R^{2M}:

    F_j(t) = Φ_j(t) x_j,   Φ_j(t) = [ψ_ji(t) χ_i(ν_j(t)) | φ_ji(t) χ_i(ν_j(t))]   (n×2M)

The cost of a motion is relative to its torque energy S_j = Σ_t w_t ‖T_j(t)‖²:

    C_j = Σ_t w_t ‖T_j(t) − F_j(t)‖² / S_j = 1 − 2 h_jᵀ x_j + x_jᵀ G_j x_j,
    G_j = Σ_t w_t Φᵀ Φ / S_j,   h_j = Σ_t w_t Φᵀ T_j / S_j

(w the trapezoid weights, so Σ_t w_t f(t) ≈ ∫ f dt as in eq. 3.9). With the fields fixed
the exact weights solve a batched NNLS (:func:`solve_weights`); the EM alternation
(:func:`em`) repeats that solve and gradient steps on the fields' centres and stiffnesses
(and phases, if variable) with the weights held — by the envelope theorem this is
gradient descent on the reduced cost min_x C(x, η, K). :func:`joint_descent` is the plain
alternative: gradient descent on fields and weights together.
"""
from __future__ import annotations

from typing import Callable, Optional

import torch

from ..fields import FieldBasis, MotionWeights
from .nnls import nnls
from .targets import Targets


def design(basis: FieldBasis, weights: MotionWeights, tg: Targets) -> torch.Tensor:
    """Φ (N×T×n×2M): the torque of unit step and pulse weights on each field."""
    chi = basis(tg.q)                                   # N×T×M×n
    psi, phi = weights.profiles_per_motion(tg.t)        # N×T×M
    return torch.cat([(psi.unsqueeze(-1) * chi), (phi.unsqueeze(-1) * chi)], dim=-2).transpose(-1, -2)


def normal_equations(basis: FieldBasis, weights: MotionWeights, tg: Targets):
    """(G (N×2M×2M), h (N×2M)) of the relative torque cost."""
    Phi = design(basis, weights, tg)
    ws = (tg.w / tg.torque_scale()[:, None])[..., None, None]
    G = (ws * Phi.transpose(-1, -2) @ Phi).sum(1)
    h = (ws.squeeze(-1) * (Phi.transpose(-1, -2) @ tg.tau.unsqueeze(-1)).squeeze(-1)).sum(1)
    return G, h


def weights_vector(weights: MotionWeights) -> torch.Tensor:
    return torch.cat([weights.a, weights.b], dim=-1)


@torch.no_grad()
def solve_weights(basis: FieldBasis, weights: MotionWeights, tg: Targets) -> torch.Tensor:
    """Set every motion's (a, b) to its exact NNLS optimum; returns the costs C_j (N)."""
    G, h = normal_equations(basis, weights, tg)
    x = nnls(G, h)
    M = basis.M
    weights.a_raw.copy_(x[:, :M])
    weights.b_raw.copy_(x[:, M:])
    return 1 - 2 * (h * x).sum(-1) + (x.unsqueeze(-2) @ G @ x.unsqueeze(-1)).squeeze(-1).squeeze(-1)


def torque_cost(basis: FieldBasis, weights: MotionWeights, tg: Targets) -> torch.Tensor:
    """C_j (N), differentiable in the fields and the weights (eq. 3.10, relative)."""
    F = (design(basis, weights, tg) @ weights_vector(weights).unsqueeze(1).unsqueeze(-1)).squeeze(-1)
    r = ((tg.tau - F) ** 2).sum(-1)
    return (tg.w * r).sum(-1) / tg.torque_scale()


def relative_rms_torque_error(basis, weights, tg: Targets) -> torch.Tensor:
    """sqrt(C_j): RMS torque error relative to the RMS torque, per motion (N)."""
    with torch.no_grad():
        return torque_cost(basis, weights, tg).clamp_min(0).sqrt()


def field_parameters(basis: FieldBasis, weights: MotionWeights, phases: bool) -> list:
    params = [basis.eta, *basis.stiffness.parameters()]
    return params + (weights.phase_parameters() if phases else [])


def em(basis: FieldBasis, weights: MotionWeights, tg: Targets, steps: int = 100,
       lr: float = 0.03, phases: bool = False, tol: float = 0.0,
       callback: Optional[Callable] = None) -> list:
    """EM-style alternation: exact NNLS weights, then an Adam step on (η, K[, phases]).

    Each step solves the weights exactly and moves the fields along the gradient of the
    cost at those weights — by the envelope theorem, the gradient of the reduced cost
    min_x C(x, η, K). Stops after ``steps`` or when the summed cost changes by less than
    ``tol`` (relative) between steps. ``callback(step, costs)`` is called every step.
    Returns the cost history (sum over motions) and leaves the weights at their NNLS
    optimum for the final fields."""
    opt = torch.optim.Adam(field_parameters(basis, weights, phases), lr=lr)
    history, prev = [], None
    for step in range(steps):
        solve_weights(basis, weights, tg)
        opt.zero_grad()
        costs = torque_cost(basis, weights, tg)
        loss = costs.sum()
        loss.backward()
        opt.step()
        weights.project_()
        history.append(float(loss.detach()))
        if callback:
            callback(step, costs.detach())
        if prev is not None and tol and abs(prev - history[-1]) <= tol * max(prev, 1e-12):
            break
        prev = history[-1]
    final = solve_weights(basis, weights, tg)
    history.append(float(final.sum()))
    return history


def joint_descent(basis: FieldBasis, weights: MotionWeights, tg: Targets, steps: int = 100,
                  lr: float = 0.03, phases: bool = False,
                  callback: Optional[Callable] = None) -> list:
    """Plain projected gradient descent (Adam) on fields and weights together."""
    params = field_parameters(basis, weights, phases) + [weights.a_raw, weights.b_raw]
    opt = torch.optim.Adam(params, lr=lr)
    history = []
    for step in range(steps):
        opt.zero_grad()
        costs = torque_cost(basis, weights, tg)
        loss = costs.sum()
        loss.backward()
        opt.step()
        weights.project_()
        history.append(float(loss.detach()))
        if callback:
            callback(step, costs.detach())
    with torch.no_grad():
        history.append(float(torque_cost(basis, weights, tg).sum()))
    return history
