"""How fast a model's errors grow along its motions' paths (the local error growth rate).

A torque program that matches a motion's torques on its path may still be unstable off
it: a small error then grows until the simulation leaves the path. Linearising the
closed loop ẏ = f(t, y) (the simulator's state y, :mod:`tflearn.simulation.simulate`: quaternions,
hinge angles, velocities; the program's fields, field damping, joint damping and a
moving base included) about the target path y*(t),

    δẏ = A(t) δy,    A(t) = ∂f/∂y (t, y*(t))     (central differences, step ``h``),

and the local growth rate is λ(t) = max Re eig A(t) (1/s): where the frozen-time
linearisation holds, an error grows like e^{λ t}. A stable spring–damper has λ < 0, an
undamped one λ = 0 (its eigenvalues ±iω), a field met beyond its Gaussian's inflection
(negative stiffness) λ = √(−k/I) > 0. Per motion the peak of λ over the samples and the
e-folds Λ = ∫ max(λ, 0) dt (the factor e^Λ an error may grow by over the motion) are
reported.

Quaternions are normalised where they are read, so f does not change along a
quaternion's own direction q: A q = 0, a structural eigenvalue 0 per rotation joint that
says nothing of the motion. In a basis of y made of the tangent directions q ⊗ (e_k, 0)
(k = 1, 2, 3; orthonormal and ⊥ q), the other entries, and the directions q, A is block
triangular with a zero last block, so its other eigenvalues are exactly those of
Bᵀ A B, B (D×(D − nr)) the tangent and other columns: :func:`jacobians` returns that.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ..model.fields import FieldBasis, MotionFields
from ..model.program import FieldProgram
from ..model.weights import MotionWeights
from ..physics.body import Body
from ..physics.configspace import n_position, pack, state_tangent_basis
from ..simulation.simulate import ArmODE
from .nnls import packed
from .targets import Targets, chunks


@dataclass
class Growth:
    """rate (N×T, 1/s; NaN on padding) the local growth rate λ at each sample; peak (N,
    1/s) its largest value over a motion's samples; efolds (N) Λ = ∫ max(λ, 0) dt."""

    rate: torch.Tensor
    peak: torch.Tensor
    efolds: torch.Tensor


def jacobians(body: Body, basis: FieldBasis, weights: MotionWeights, tg: Targets,
              h: float = 1e-6) -> torch.Tensor:
    """:func:`program_jacobians` of the motions' field program."""
    return program_jacobians(body, FieldProgram(basis, weights), tg, h)


@torch.no_grad()
def program_jacobians(body: Body, program, tg: Targets, h: float = 1e-6) -> torch.Tensor:
    """Bᵀ A(t) B, A = ∂f/∂y of the closed loop under ``program(t, ν, v) → τ`` (t: each
    member's own time, 2D×T×N), at every target sample (N×T×D'×D', D' = D − nr the
    state's size less one per quaternion; see the module), A by central differences of
    step ``h`` in each state entry, all in one batch."""
    y = pack(body, tg.q, tg.v).transpose(0, 1)                       # T×N×D
    D = y.shape[-1]
    step = h * torch.eye(D, dtype=y.dtype)                             # D×D
    ys = torch.cat([y + step[:, None, None], y - step[:, None, None]])  # 2D×T×N×D
    t = tg.t.transpose(0, 1).expand(2 * D, -1, -1)                      # 2D×T×N, each motion's own
    base = None
    if tg.base is not None:                                              # each member's piece only
        base = tg.base.at(torch.arange(tg.N).expand(2 * D, tg.t.shape[1], -1), t)
    f = ArmODE(body, program, base=base, strict=False)(t, ys)
    cols = (f[:D] - f[D:]) / (2 * h)                                   # D(column)×T×N×D(row)
    A = cols.permute(2, 1, 3, 0)                                       # N×T×D×D
    B = state_tangent_basis(body, y.transpose(0, 1))                   # N×T×D×D'
    return B.transpose(-1, -2) @ A @ B


def growth(body: Body, basis: FieldBasis, weights: MotionWeights, tg: Targets,
           h: float = 1e-6) -> Growth:
    """The local error growth of every motion under its program (see the module), a
    chunk of motions at a time (:func:`~.targets.chunks`: memory stays bounded), each
    motion's program on the fields it has a weight on only (:func:`own_fields`)."""
    D = n_position(body) + body.nv                                   # the state's size
    rate = torch.full(tg.mask.shape, float("nan"), dtype=tg.q.dtype)
    for idx in chunks(tg, 2 * D * (basis.M + 4)):
        part = tg.select(idx, trim=True)
        program = FieldProgram(*own_fields(basis, weights.select_motions(idx)))
        rate[idx, :part.mask.shape[1]] = _rates(body, program, part, h)
    return _summary(rate, tg)


def own_fields(basis: FieldBasis, weights: MotionWeights) -> tuple:
    """(each motion's fields (:class:`~tflearn.model.fields.MotionFields`, N×W), its weights on
    them): the fields it has a weight on, in order, padded to the most any motion has (W)
    with weights of 0. Its torques are those of the whole basis, whose other fields'
    torques are multiplied by 0, at O(W) cost, not O(M)."""
    cols, pad = packed(weights.used())
    fields = MotionFields(basis.eta.detach()[cols], basis.K().detach()[cols], basis.damping)
    return fields, weights.take_fields(cols, pad)


def program_growth(body: Body, program, tg: Targets, h: float = 1e-6) -> Growth:
    """The local error growth of every motion under ``program(t, ν, v) → τ`` (see
    :func:`program_jacobians`), all motions in one batch (memory grows with them)."""
    return _summary(_rates(body, program, tg, h), tg)


def _rates(body: Body, program, tg: Targets, h: float) -> torch.Tensor:
    """λ (N×T): the largest real part of the closed loop's eigenvalues at every sample."""
    return torch.linalg.eigvals(program_jacobians(body, program, tg, h)).real.amax(-1)


def _summary(rate: torch.Tensor, tg: Targets) -> Growth:
    """:class:`Growth` of the rates λ (N×T) at the samples of ``tg`` (padding: NaN)."""
    rate = rate.masked_fill(~tg.mask, float("nan"))
    peak = rate.nan_to_num(-torch.inf).amax(-1)
    efolds = (rate.clamp_min(0).nan_to_num(0.0) * tg.w).sum(-1)
    return Growth(rate, peak, efolds)
