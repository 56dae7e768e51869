"""Impedance about the path: weights whose fields also hold the limb on it.

Torque matching (:mod:`.torque`) asks the fields' sum for the inverse-dynamics torque
T_j(t) at each posture of the path and nothing about what it does off the path. Many
programs give that torque; the one wanted is the one that *holds* the limb there, whose
field sum pulls a limb pushed off the path back onto it. To first order about the path,

    F_j(ν_t + e, v_t) ≈ F_j(ν_t, v_t) + J_j(t) e,     J_j(t) = Σ_c x_c s_c(t) ∂χ_{i(c)}/∂ν,

(s_c the column's time profile: step ψ, pulse φ or window), so −J_j is the stiffness the
fields add about the path; it is linear in the weights, like the torque. This module asks
for a stiffness target as well,

    −J_j(t) ≈ ω² M(ν_t),

a closed loop whose every coordinate has natural frequency ω about the path (M the
joint-space inertia): the squared residual Σ_t w_t ‖δ (J_j(t) + ω² M(ν_t))‖²_F / S_j, with
δ (rad) the deviation at which a stiffness error counts as much as a torque error, is
added to the relative torque cost C_j and one NNLS solves both. Where the torque leaves
the weights free (opposing fields whose torques cancel along the path) the solve takes
the co-contraction that gives this stiffness; with the fields' damping ratio ζ the same
weights give damping ζ K about the path.

The field Jacobian has a closed form. With d = ν − η, u = K(d + ζ v) and g = exp(−½ dᵀKd),
χ = −u g and ∂g/∂ν = −g K d, so

    ∂χ/∂ν = −g (K − u (K d)ᵀ)         (n×n per field):

a field is convergent (−∂χ/∂ν positive definite, at rest) where dᵀKd < 1, inside the
inflection of its Gaussian, and pushes the limb away from the path beyond it. Fields far
from the limb (a spanning layout's, :mod:`.layout`) are mostly beyond it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from ..model.fields import FieldBasis
from ..model.weights import MotionWeights
from ..physics import dynamics
from ..physics.body import Body
from . import torque
from .nnls import nnls, warn_unconverged
from .targets import Targets, chunks

__all__ = ["Impedance", "field_jacobians", "stiffness_design", "free_share", "stiffness_equations",
           "solve_weights", "path_stiffness", "equilibria"]


@dataclass(frozen=True)
class Impedance:
    """The stiffness asked of the fields about the path: natural frequency ``frequency``
    ω (rad/s; 0: torques only) and the deviation ``deviation`` δ (rad) at which a
    stiffness error weighs as much as a torque error; ``sparsity`` λ ≥ 0 (0: off) first
    adds λ Σ_c √A_cc x_c to the cost (A its normal matrix: an ℓ1 term on the scaled
    weights, which sets the least useful to 0), then solves again without it on the weights
    that term left non-zero (so that the kept ones are not shrunk)."""

    frequency: float = 0.0
    deviation: float = 0.1
    sparsity: float = 0.0


def field_jacobians(basis: FieldBasis, q: torch.Tensor, v: Optional[torch.Tensor] = None) -> torch.Tensor:
    """∂χ_i/∂ν at (q, v) (...×n each) for every field: (...×M×n×n), row k the derivative of
    torque coordinate k (module docstring; the damping term ζ K v included when v is given)."""
    K = basis.K()                                                   # M×n×n
    d = q.unsqueeze(-2) - basis.eta                                 # ...×M×n
    Kd = torch.einsum("mij,...mj->...mi", K, d)
    g = torch.exp(-0.5 * (d * Kd).sum(-1))[..., None, None]
    u = Kd if v is None or not basis.damping else Kd + basis.damping * torch.einsum(
        "mij,...j->...mi", K, v)
    return -g * (K - u.unsqueeze(-1) * Kd.unsqueeze(-2))


def stiffness_design(basis: FieldBasis, weights: MotionWeights, tg: Targets) -> torch.Tensor:
    """D (N×T×n×n×X): J_j(t) = D_j(t) x_j, the Jacobian of the field sum in the weights'
    columns (:func:`~.torque.design`'s order: steps, pulses, windows field by field)."""
    J = field_jacobians(basis, tg.q, tg.v).permute(0, 1, 3, 4, 2)     # N×T×n×n×M
    return torque.profile_columns(J, weights, tg.t)


def stiffness_equations(body: Body, basis: FieldBasis, weights: MotionWeights, tg: Targets,
                        impedance: Impedance) -> tuple:
    """(G_s N×X×X, h_s N×X): the stiffness residual's normal equations, to add to the
    torque cost's (G, h) — the residual is ‖A x + B‖² = const − 2 h_sᵀx + xᵀG_s x with
    A = δ s ⊙ D, B = δ s ⊙ ω²M, s = √(w_t / S_j), G_s = AᵀA, h_s = −AᵀB. Rows of torque
    coordinate k weighted by the cost's ω_k, as the torque residuals are, and by the
    share f_k of its stiffness that the fields leave free (:func:`free_share`)."""
    D = stiffness_design(basis, weights, tg)
    target = impedance.frequency ** 2 * dynamics.mass_matrix(body, tg.q)      # N×T×n×n
    scale = (tg.wt / tg.torque_scale()[:, None]).sqrt() * impedance.deviation  # N×T
    rows = scale[:, :, None, None] * free_share(body, basis)[:, None]
    if tg.coord_weight is not None:
        rows = rows * tg.coord_weight.sqrt()[:, None, :, None]
    A = (rows.unsqueeze(-1) * D).reshape(tg.N, -1, D.shape[-1])
    B = (rows * target).reshape(tg.N, -1)
    At = A.transpose(-1, -2)
    return At @ A, -(At @ B.unsqueeze(-1)).squeeze(-1)


@torch.no_grad()
def free_share(body: Body, basis: FieldBasis) -> torch.Tensor:
    """f (n): the share of each coordinate's stiffness that its joint's fields can set
    apart from its torque, by which the stiffness residual's rows are weighted (δ f_k).
    A joint of b coordinates pulled by m ≥ b + 1 fields of its own has m − b
    co-activations its torque leaves free, and f = min(1, (m − b)/b) on its coordinates:
    1 for a pair per coordinate, where each coordinate's stiffness has its own
    co-activation, and 1/b for a joint simplex, whose one co-activation must serve b
    coordinates' stiffness as the weights also give their torques. A field is the
    joint's own where its centre differs on that joint only from the posture most
    centres share, coordinate by coordinate (the convergent layouts of :mod:`.layout`,
    alone or beside learned fields). f = 1 on a joint with no such fields (any other
    basis, where δ alone weighs the residual)."""
    eta = basis.eta.detach()
    moved = (eta - eta.mode(0).values).abs() > 1e-12                              # M×n
    joints = [body.slice(i) for i in range(len(body.links))]
    touched = torch.stack([moved[:, c].any(-1) for c in joints], -1)             # M×joints
    alone = touched.sum(-1) == 1
    share = torch.ones(body.nv, dtype=torch.float64)
    for i, c in enumerate(joints):
        own, b = int((touched[:, i] & alone).sum()), c.stop - c.start
        if own > b:
            share[c] = min(1.0, (own - b) / b)
    return share


@torch.no_grad()
def solve_weights(body: Body, basis: FieldBasis, weights: MotionWeights, tg: Targets,
                  impedance: Impedance, ridge: float = 0.0) -> torch.Tensor:
    """Every motion's (a, b, c) by one NNLS on C_j plus the stiffness residual (module
    docstring; ``ridge`` as :func:`~.torque.solve_weights`'); returns the torque costs C_j
    (N) of the weights found. With ``impedance.frequency`` and ``.sparsity`` 0 this is
    :func:`~.torque.solve_weights`."""
    if not impedance.frequency and not impedance.sparsity:
        return torque.solve_weights(basis, weights, tg, ridge=ridge)
    X = weights.a_raw.shape[1] * (2 + weights.P)
    costs, keys = torch.empty(tg.N, dtype=torch.float64), ("a_raw", "b_raw", "c_raw")
    for idx in chunks(tg, X * tg.tau.shape[-1]):
        sub, part = weights.select_motions(idx), tg.select(idx, trim=True)
        G, h = torque.normal_equations(basis, sub, part)
        A, b = G, h
        if impedance.frequency:
            Gs, hs = stiffness_equations(body, basis, sub, part, impedance)
            A, b = G + Gs, h + hs
        x = _solve(torque.with_ridge(A, ridge), b, impedance.sparsity, part.names)
        sub.set_vector(x)
        costs[idx] = torque.quadratic_cost(G, h, x)
        weights.set_flat(keys, sub.flat(keys), idx)
    return costs


def _solve(A: torch.Tensor, b: torch.Tensor, sparsity: float, names: list) -> torch.Tensor:
    """argmin_{x ≥ 0} xᵀAx − 2bᵀx (N×X), with ``sparsity`` (:class:`Impedance`) first
    choosing the non-zero weights."""
    if sparsity:
        sol = nnls(A, b - sparsity * torch.diagonal(A, dim1=-2, dim2=-1).sqrt())
        warn_unconverged(sol, names, "impedance.solve_weights (sparsity)")
        on = sol.x > 0
        both = on.unsqueeze(-1) & on.unsqueeze(-2)
        A = torch.where(both, A, torch.zeros_like(A)) + torch.diag_embed((~on).to(A.dtype))
        b = torch.where(on, b, -torch.ones_like(b))
    sol = nnls(A, b)
    warn_unconverged(sol, names, "impedance.solve_weights")
    return sol.x


@torch.no_grad()
def path_stiffness(body: Body, basis: FieldBasis, weights: MotionWeights, tg: Targets) -> torch.Tensor:
    """The stiffness the fields give about each motion's path, as a natural frequency:
    per motion (N), the median over its samples of √λ_min(M⁻¹ K_s) (rad/s; 0 where the
    sum pushes off the path), K_s = −sym J_j(t) the symmetric part of the Jacobian. Each
    motion on the fields it has a weight on only (every run's metrics have it: its cost
    follows those fields, not M)."""
    out = torch.zeros(tg.N, dtype=torch.float64)
    used = weights.used()
    for j in range(tg.N):
        part, fields = tg.select([j], trim=True), used[j].nonzero().flatten().tolist()
        if not fields:
            continue
        own = weights.select_motions([j]).select_fields(fields)
        J = (stiffness_design(basis.select(fields), own, part) * own.vector()[0]).sum(-1)[0]
        Ks = -0.5 * (J + J.transpose(-1, -2))
        L = torch.linalg.cholesky(dynamics.mass_matrix(body, part.q[0]))
        Linv = torch.linalg.inv(L)
        lam = torch.linalg.eigvalsh(Linv @ Ks @ Linv.transpose(-1, -2))[..., 0]
        out[j] = lam[part.mask[0]].clamp_min(0).sqrt().median()
    return out


@torch.no_grad()
def equilibria(basis: FieldBasis, weights: MotionWeights, tg: Targets, iterations: int = 50,
               tol: float = 1e-9, max_step: float = 0.25) -> tuple:
    """The equilibrium trajectory: at each sample the posture ν*(t) at which the fields'
    sum at rest vanishes, Σ_i w_i(t) χ_i(ν*, 0) = 0 (w_i(t) the motion's activations), the
    posture the program pulls the limb towards at that instant. From the path's own
    posture ν_t: Newton's steps ν ← ν − J(ν)⁻¹ F(ν), J = Σ_i w_i ∂χ_i/∂ν
    (:func:`field_jacobians`), where the sum is convergent there (−J positive definite),
    else a step along the force, F / Σ_i w_i ‖K_i‖ (downhill on the fields' potential
    −Σ w_i g_i: beyond a Gaussian's inflection Newton would climb away to the spurious
    zero at infinity); each step at most ``max_step`` rad. Returns (ν* N×T×n,
    found N×T bool: ‖F(ν*)‖ ≤ tol · Σ_i w_i ‖K_i‖ and −J(ν*) positive definite, a stable
    equilibrium; False where no field is active)."""
    w = weights.activation_at(tg.t.transpose(0, 1)).transpose(0, 1).detach()    # N×T×M
    K = basis.K().detach()
    scale = (w * torch.linalg.matrix_norm(K, ord=2)).sum(-1)                     # N×T

    def at_rest(nu):
        """(F N×T×n, J N×T×n×n, −J positive definite N×T) of the sum at rest at ν."""
        F = (w.unsqueeze(-1) * basis(nu).detach()).sum(-2)
        J = (w[..., None, None] * field_jacobians(basis, nu).detach()).sum(-3)
        return F, J, torch.linalg.eigvalsh(-0.5 * (J + J.transpose(-1, -2)))[..., 0] > 0

    nu = tg.q.clone()
    for _ in range(iterations):
        F, J, convergent = at_rest(nu)
        newton = torch.linalg.lstsq(J, -F.unsqueeze(-1)).solution.squeeze(-1)
        step = torch.where(convergent.unsqueeze(-1), newton, F / scale.clamp_min(1e-300).unsqueeze(-1))
        size = step.norm(dim=-1, keepdim=True)
        nu = nu + step * (max_step / size).clamp(max=1.0)
        if bool((size < 1e-13).all()):
            break
    F, _, stable = at_rest(nu)
    found = (F.norm(dim=-1) <= tol * scale) & stable & (scale > 0) & tg.mask
    return nu, found
