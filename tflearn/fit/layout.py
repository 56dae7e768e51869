"""A spanning layout of fields for motions no field made (recorded, keyframed).

Greedy growth (:mod:`tflearn.fit.search`) adds the one field that best explains what is
left, and stops when the next one gains little. On recorded motion that ends after one
or two fields whose torques point along one or two directions, while a 7-dof arm's
torques turn through all seven. A basis whose fields *positively span* joint space
everywhere along the paths needs no search: M fields at the vertices of a polytope of
radius r around the motions' mean posture ν̄,

    η_i = ν̄ + r u_i,        K_i = κ diag(m̄_1 … m̄_n),

with unit directions u_i that positively span ℝⁿ (``SHAPES``: ``cross``, u = ±e_k,
M = 2n; ``simplex``, the n + 1 vertices of a regular simplex, the fewest that can).
Two convergent shapes keep every centre inside joint space instead, each field pulling
one joint: :func:`pairs_basis` (2n) and :func:`joints_basis` (b + 1 per joint of b
coordinates; within a budget of fields, a pair per coordinate on the joints of most
anisotropic inertia).
Where a field's Gaussian is ≈ 1 it is the spring K(η_i − ν), and the fields' sum is

    Σ_i w_i K(η_i − ν) = K [ W (ν̄ − ν) + r Σ_i w_i u_i ],     W = Σ_i w_i ≥ 0:

the second term points any way, but the first, a co-contraction stiffness W pulling
towards ν̄, comes with it. Every torque at ν is a non-negative combination of the fields
exactly when ν lies inside their centres' hull, ν̄ + r·conv(u) (the origin must lie inside
the hull of the vectors η_i − ν): for ``cross`` the ℓ1 ball ‖ν − ν̄‖₁ < r — not the box
|ν − ν̄|∞ < r — and for ``simplex`` the simplex, whose inscribed ball has radius r/n.
:func:`reach` is the radius a posture needs (the polytope's gauge). Near the boundary W
must grow without bound; well inside it, r ≫ reach, W (ν̄ − ν) is small beside what the
weights must drive, so a larger radius fits the torques better (measured on 14 recorded
windows: docs/mocap.md), and any co-activation beyond it adds stiffness and ζK damping
about the path, the feedback that open-loop torque matching lacks. The weights — step,
pulse and P sub-movement windows per field — come from one exact NNLS solve, and
multiple shooting then fits them to the paths.

m̄ is the mean joint-space inertia along the motions
(:func:`~tflearn.fit.targets.mean_inertia`), so κ is a squared frequency (1/s²) and a
unit activation drives every coordinate at the same rate: the light wrist is not made a
thousand times stiffer than the shoulder (which turns the simulation stiff), and each
field's Gaussian is widest where the inertia is smallest.
"""
from __future__ import annotations

import itertools
import math
import warnings
from typing import Optional

import torch

from ..model.fields import FieldBasis
from ..physics.body import Body
from .targets import Targets, mean_inertia


def _cross(n: int) -> tuple:
    """±e_k (2n×n) and the ℓ1 ball's 2ⁿ facets s/1, s ∈ {±1}ⁿ."""
    eye = torch.eye(n, dtype=torch.float64)
    facets = torch.tensor(list(itertools.product((1.0, -1.0), repeat=n)), dtype=torch.float64)
    return torch.cat([eye, -eye]), facets


def _simplex(n: int) -> tuple:
    """The n + 1 unit vertices u_i of a regular simplex ((n+1)×n: the columns of the
    Helmert basis of 1⊥ ⊂ ℝⁿ⁺¹, scaled to unit length; Σ u_i = 0, u_i·u_j = −1/n) and
    its facets: the one opposite u_i is u_i·x = −1/n, i.e. (−n u_i)·x ≤ 1."""
    H = torch.zeros(n, n + 1, dtype=torch.float64)
    for k in range(1, n + 1):
        H[k - 1, :k] = 1.0
        H[k - 1, k] = -float(k)
        H[k - 1] /= math.sqrt(k * (k + 1))
    u = H.T / math.sqrt(n / (n + 1))
    return u, -n * u


def _pairs(n: int) -> tuple:
    """±e_k (2n×n), one antagonist pair per coordinate, and the box ‖x‖∞ ≤ 1's 2n facets
    ±e_k: with :data:`PAIR_COUPLING` each field pulls one coordinate only, so every
    torque is theirs inside the box, not only inside the ℓ1 ball of ``cross``."""
    eye = torch.eye(n, dtype=torch.float64)
    u = torch.cat([eye, -eye])
    return u, u


#: Layout shapes: name → n → (unit directions u (M×n), facets A (F×n) of conv(u) = {x: A x ≤ 1}).
SHAPES = {"cross": _cross, "simplex": _simplex, "pairs": _pairs}

#: A ``pairs`` field's stiffness on the coordinates it does not pull, relative to its own.
PAIR_COUPLING = 4e-3

#: The largest |η| of a joint's block that a convergent (``pairs``) centre may have: a
#: rotation vector's angle or a hinge's angle below π, a posture the joint can hold.
JOINT_LIMIT = 0.95 * math.pi


def _inertia(body: Body, tg: Targets) -> torch.Tensor:
    """m̄ (n): the mean joint-space inertia over every real sample of the motions."""
    samples = tg.mask.sum(-1, keepdim=True).to(tg.q.dtype)                    # N×1
    return (mean_inertia(body, tg) * samples).sum(0) / samples.sum()


def _range(tg: Targets) -> tuple:
    """(largest, smallest) value of each coordinate over the motions' real samples (n each)."""
    real = tg.mask.unsqueeze(-1)
    return torch.where(real, tg.q, -math.inf).amax((0, 1)), torch.where(real, tg.q, math.inf).amin((0, 1))


def reach(shape: str, x: torch.Tensor) -> torch.Tensor:
    """The radius r that a displacement x = ν − ν̄ (...×n) needs to lie in the layout's
    hull r·conv(u): the gauge max(0, maxⱼ Aⱼ·x) (``cross``: ‖x‖₁; ``simplex``:
    max_i −n u_i·x). Every torque is a non-negative combination of the fields at ν
    where it is below r (module docstring)."""
    _, facets = SHAPES[shape](x.shape[-1])
    return (x @ facets.T).amax(-1).clamp_min(0)


def spanning_basis(body: Body, tg: Targets, template: FieldBasis, radius: float,
                   stiffness: float, shape: str, fields: Optional[int] = None) -> FieldBasis:
    """The fields of ``SHAPES[shape]`` like ``template`` (its kind must hold a diagonal K:
    not ``scalar``; its damping ratio is kept) at ν̄ + ``radius`` u_i, K = ``stiffness`` ·
    diag(m̄), ν̄ and m̄ the mean posture and mean inertia over every real sample of the
    motions in ``tg`` (module docstring). Warns when a motion leaves the hull of the
    centres (:func:`reach` ≥ ``radius``), where the fields no longer push every way."""
    if shape == "joints":
        return joints_basis(body, tg, template, radius, stiffness, fields)
    if template.kind == "scalar":
        raise ValueError("spanning_basis: the layout's stiffness is per coordinate; "
                         "it needs model.stiffness diag, block or full, not scalar")
    if shape == "pairs":
        return pairs_basis(body, tg, template, radius, stiffness)
    if shape not in SHAPES:
        raise ValueError(f"spanning_basis: unknown shape {shape!r}; one of {sorted(SHAPES)}")
    real = tg.mask.unsqueeze(-1).to(tg.q.dtype)
    centre = (tg.q * real).sum((0, 1)) / real.sum((0, 1))                      # n
    inertia = _inertia(body, tg)                                              # n
    far = (reach(shape, tg.q - centre) * tg.mask).amax(-1)                   # N
    if float(far.max()) >= radius:
        j = int(far.argmax())
        warnings.warn(f"layout: motion {tg.names[j]} leaves the {shape} of the fields' centres "
                      f"(it needs a radius of {float(far[j]):.2f} rad about the motions' mean "
                      f"posture, the layout has {radius:g}), where they cannot push every way: "
                      f"raise solver.layout.radius", stacklevel=2)
    u, _ = SHAPES[shape](centre.shape[0])
    n = centre.shape[0]
    K = (stiffness * torch.diag(inertia)).expand(len(u), n, n).clone()
    return template.like(centre + radius * u, K)


def pairs_basis(body: Body, tg: Targets, template: FieldBasis, radius: float,
                stiffness: float) -> FieldBasis:
    """Convergent antagonist pairs: for each coordinate k two fields at c ± r_k e_k that
    pull that coordinate only (K_i = κ diag(m̄) ⊙ (e_k + :data:`PAIR_COUPLING` (1 − e_k))),
    c the middle of the motions' range of each coordinate, r_k ≤ ``radius`` the largest
    that keeps the centre's joint block within :data:`JOINT_LIMIT` (a posture the joint
    can hold). Every torque at ν is the pairs' where c − r_k⁻ < ν_k < c + r_k⁺ for every
    k; the sum of a pair, w⁺κm̄_k(c + r⁺ − ν_k) + w⁻κm̄_k(c − r⁻ − ν_k), is an
    equilibrium-point controller of coordinate k, its co-activation w⁺ + w⁻ the
    coordinate's stiffness (:mod:`.impedance` chooses it). Warns when a motion leaves the
    box."""
    hi, lo = _range(tg)
    centre, n = 0.5 * (hi + lo), body.nv
    u, _ = _pairs(n)
    r = torch.stack([_within_joints(body, centre, ui, radius) for ui in u])          # 2n
    short = [k for k in range(n) if hi[k] - centre[k] >= r[k] or centre[k] - lo[k] >= r[n + k]]
    if short:
        warnings.warn(f"layout: the motions reach coordinate(s) {short} beyond the pairs' centres "
                      f"(radius {radius:g} rad about the middle of their range, centres held "
                      f"within {JOINT_LIMIT:.2f} rad of each joint's rest), where those fields no "
                      f"longer push every way", stacklevel=3)
    inertia = _inertia(body, tg)
    gain = u.abs() + PAIR_COUPLING * (1 - u.abs())
    return template.like(centre + r[:, None] * u, torch.diag_embed(stiffness * inertia * gain))


def joints_basis(body: Body, tg: Targets, template: FieldBasis, radius: float,
                 stiffness: float, fields: Optional[int] = None) -> FieldBasis:
    """Convergent joint simplices: for each joint of b coordinates, b + 1 fields that pull
    that joint only (a hinge's two are :func:`pairs_basis`' pair), M = Σ (b + 1) = n + the
    number of joints (10 for the arm, against 14 pairs). Field i of a joint pulls along
    s_i = S u_i, u_i the unit vertices of a regular simplex in ℝᵇ (Σ u_i = 0) and
    S = diag(√m̄) over the joint's coordinates, with

        K_i = κ s_i s_iᵀ + :data:`PAIR_COUPLING` κ diag(m̄),    η_i = c + r_i n̂_i,   n̂_i = s_i/|s_i|,

    c the middle of the motions' range of each coordinate and r_i ≤ ``radius`` the
    largest that keeps the joint's block of η_i within :data:`JOINT_LIMIT`. Where the
    Gaussians are ≈ 1 field i's torque is κ s_i |s_i| (r_i − n̂_i·(ν − c)): along s_i
    wherever n̂_i·(ν − c) < r_i, so every torque of the joint is the fields' inside the
    polytope {x: n̂_i·x < r_i} (it holds the ball of radius min r_i about c), and with
    every weight positive their stiffness κ S(Σ w_i u_i u_iᵀ)S is positive definite
    and scales with the joint's inertia, as the pairs' does. The basis is of a kind that
    holds a joint's oblique pulls: ``template``'s where it is ``block`` or ``full``, else
    ``block`` (its blocks and damping kept). Warns when a motion leaves a joint's
    polytope.

    ``fields`` F (None: n + the joints) spends what a budget of F fields allows on pairs:
    joints take a pair per coordinate (u = ±e_k, 2b fields, :func:`pairs_basis`' fields
    of that joint) instead of their simplex, in the order of their inertia's anisotropy
    max m̄/min m̄ over the joint (one co-activation holds coordinates of unequal inertia
    worst), while M stays ≤ F (:func:`pairs_per_joint`)."""
    hi, lo = _range(tg)
    centre, n, inertia = 0.5 * (hi + lo), body.nv, _inertia(body, tg)
    paired = pairs_per_joint(body, inertia, fields)
    pulls = []                                                                  # s_i, each n
    for j, (k, b) in enumerate(zip(itertools.accumulate([0] + body.blocks), body.blocks)):
        eye = torch.eye(b, dtype=torch.float64)
        u = torch.cat([eye, -eye]) if b == 1 or paired[j] else _simplex(b)[0]
        s = torch.zeros(len(u), n, dtype=torch.float64)
        s[:, k:k + b] = u * inertia[k:k + b].sqrt()
        pulls.append(s)
    s = torch.cat(pulls)                                                        # M×n
    normal = s / s.norm(dim=-1, keepdim=True)
    r = torch.stack([_within_joints(body, centre, ni, radius) for ni in normal])
    x = torch.where(tg.mask.unsqueeze(-1), tg.q - centre, 0.0)
    out = [i for i in range(len(s)) if float((x @ normal[i]).amax()) >= float(r[i])]
    if out:
        warnings.warn(f"layout: the motions reach beyond the joint simplices' field(s) {out} "
                      f"(radius {radius:g} rad about the middle of their range, centres held "
                      f"within {JOINT_LIMIT:.2f} rad of each joint's rest), where those fields no "
                      f"longer push every way", stacklevel=3)
    K = stiffness * (s[:, :, None] * s[:, None, :] + PAIR_COUPLING * torch.diag(inertia))
    kind = template.kind if template.kind in ("block", "full") else "block"
    return FieldBasis(centre + r[:, None] * normal, K, kind=kind, blocks=template.blocks,
                      damping=template.damping)


def pairs_per_joint(body: Body, inertia: torch.Tensor, fields: Optional[int]) -> list:
    """Which joints of the joint simplices take a pair per coordinate (list of bool, one
    per joint) within a budget of ``fields`` (None: none): the simplices' n + the joints,
    then each joint of b > 1 coordinates, most anisotropic inertia first (max m̄/min m̄
    over its coordinates), paired where its b − 1 more fields keep M ≤ ``fields``.
    Raises ValueError when ``fields`` is below the simplices' count."""
    blocks = body.blocks
    M = sum(b + 1 for b in blocks)
    if fields is not None and fields < M:
        raise ValueError(f"joints_basis: a budget of {fields} fields is below the joint simplices' {M} "
                         f"(n + the number of joints)")
    start = list(itertools.accumulate([0] + blocks))
    spread = [float(inertia[k:k + b].max() / inertia[k:k + b].min()) for k, b in zip(start, blocks)]
    paired = [False] * len(blocks)
    for j in sorted(range(len(blocks)), key=lambda j: -spread[j]):
        if fields is not None and blocks[j] > 1 and M + blocks[j] - 1 <= fields:
            paired[j], M = True, M + blocks[j] - 1
    return paired


def _within_joints(body: Body, centre: torch.Tensor, u: torch.Tensor, radius: float) -> torch.Tensor:
    """The largest r ≤ ``radius`` with every joint block of centre + r u within
    :data:`JOINT_LIMIT` (0 where the centre itself is not): per block, the positive root
    of |c + r u|² = L², r = −c·u + √((c·u)² − |c|² + L²)."""
    r = torch.tensor(float(radius), dtype=torch.float64)
    for i in range(len(body.links)):
        c, w = centre[body.slice(i)], u[body.slice(i)]
        cu, uu = (c * w).sum(), (w * w).sum()
        if uu == 0:
            continue
        disc = (cu ** 2 - uu * ((c * c).sum() - JOINT_LIMIT ** 2)).clamp_min(0)
        r = torch.minimum(r, ((-cu + disc.sqrt()) / uu).clamp_min(0))
    return r
