"""Configuration-space maths of a body: rotations, charts, packing and differences.

Coordinates ν (...×nv) stack, per joint in link order, a ball joint's rotation vector v
(R = exp([v]×), principal when |v| ≤ π), a hinge's angle θ, nothing for a fixed joint
(:mod:`tflearn.body`). Here, in one place:

* SO(3) on rotation vectors: :func:`hat`, :func:`rotvec_to_rotmat`, the right Jacobian
  :func:`right_jacobian` with :func:`body_velocity` ω = J_r(v) v̇ and
  :func:`body_acceleration`, the chart's wrapping (:func:`wrap_rotvec`,
  :func:`unwrap_rotvec`) and quaternion sequences (:func:`align_quaternions`);
* the simulator's state y = [unit quaternion (4) per ball joint, θ per hinge, unit
  quaternion (4) and translation t (3) per free joint, v (nv)]
  (:func:`n_position`, :func:`pack`, :func:`unpack`);
* the difference of two configurations (:func:`difference`, Pinocchio's
  ``difference``): per ball joint log(R_aᵀ R_b) in the child frame, per hinge θ_b − θ_a,
  per free joint (log(R_aᵀ R_b), R_aᵀ (t_b − t_a)) (SO(3) × R³, the velocity convention
  of :mod:`tflearn.body`; not Pinocchio's SE(3) log).
"""
from __future__ import annotations

import math

import roma
import torch

from .body import Body

TAYLOR_THETA2 = 0.25  # below θ² = 0.25 the J_r coefficients use their Taylor series


def rotvec_to_rotmat(v: torch.Tensor) -> torch.Tensor:
    """R = exp([v]×) (...×3 → ...×3×3), exact and smooth at v = 0 (via a unit quaternion)."""
    return roma.unitquat_to_rotmat(roma.rotvec_to_unitquat(v))



def hat(v: torch.Tensor) -> torch.Tensor:
    """Skew matrix [v]× (...×3 → ...×3×3), [v]× w = v × w."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(v.shape + (3,))


# Taylor coefficients in s = θ²: a = Σ (−s)ⁿ/(2n+2)!, b = Σ (−s)ⁿ/(2n+3)!, and d/ds.
_A = [(-1) ** n / math.factorial(2 * n + 2) for n in range(8)]
_B = [(-1) ** n / math.factorial(2 * n + 3) for n in range(8)]
_DA = [(n + 1) * c for n, c in enumerate(_A[1:])]
_DB = [(n + 1) * c for n, c in enumerate(_B[1:])]


def _series(coef, s):
    """Σ coef[n] sⁿ by Horner's rule."""
    out = torch.full_like(s, coef[-1])
    for c in reversed(coef[:-1]):
        out = out * s + c
    return out


def _jr_coefficients(s: torch.Tensor):
    """a(s), b(s) and their derivatives da/ds, db/ds at s = θ² (... each).

    a = (1 − cos θ)/θ²,   b = (θ − sin θ)/θ³,
    da/ds = (θ sin θ/2 − (1 − cos θ))/θ⁴,   db/ds = (θ(1 − cos θ) − 3(θ − sin θ))/(2θ⁵),
    with 1 − cos θ = 2 sin²(θ/2). Below s = ``TAYLOR_THETA2`` (θ < 0.5), where the closed
    forms cancel, their Taylor series (8 terms; relative error < 1e-14 everywhere) are
    used; the closed forms are evaluated at a safe θ there so that values and autograd
    derivatives stay finite at v = 0.
    """
    small = s < TAYLOR_THETA2
    th = torch.sqrt(torch.where(small, torch.ones_like(s), s))
    sn, omc = torch.sin(th), 2 * torch.sin(th / 2) ** 2
    closed = (omc / th**2, (th - sn) / th**3, (th * sn / 2 - omc) / th**4,
              (th * omc - 3 * (th - sn)) / (2 * th**5))
    series = (_series(_A, s), _series(_B, s), _series(_DA, s), _series(_DB, s))
    return tuple(torch.where(small, x, y) for x, y in zip(series, closed))


def right_jacobian(v: torch.Tensor) -> torch.Tensor:
    """J_r(v) = I − a [v]× + b [v]×² (...×3 → ...×3×3), so that ω = J_r(v) v̇ is the
    body-frame angular velocity of R = exp([v]×) ([ω]× = Rᵀ Ṙ). J_r(0) = I."""
    a, b, _, _ = _jr_coefficients((v * v).sum(-1))
    K = hat(v)
    eye = torch.eye(3, dtype=v.dtype, device=v.device)
    return eye - a[..., None, None] * K + b[..., None, None] * (K @ K)


def body_velocity(v: torch.Tensor, vd: torch.Tensor) -> torch.Tensor:
    """ω = J_r(v) v̇ = v̇ − a v×v̇ + b v×(v×v̇)  (...×3, ...×3 → ...×3)."""
    a, b, _, _ = _jr_coefficients((v * v).sum(-1))
    vxvd = torch.cross(v, vd, dim=-1)
    return vd - a[..., None] * vxvd + b[..., None] * torch.cross(v, vxvd, dim=-1)


def body_acceleration(v: torch.Tensor, vd: torch.Tensor, vdd: torch.Tensor) -> torch.Tensor:
    """ω̇ = J_r(v) v̈ + (d/dt J_r) v̇ (...×3 each → ...×3).

    With K = [v]×, K̇ = [v̇]× and K̇ v̇ = 0:
        (d/dt J_r) v̇ = −ȧ v×v̇ + ḃ v×(v×v̇) + b v̇×(v×v̇),   ȧ = 2 (v·v̇) da/ds, ḃ likewise.
    """
    a, b, da, db = _jr_coefficients((v * v).sum(-1))
    sd = 2 * (v * vd).sum(-1)
    vxvd = torch.cross(v, vd, dim=-1)
    jdot_vd = (-(da * sd)[..., None] * vxvd + (db * sd)[..., None] * torch.cross(v, vxvd, dim=-1)
               + b[..., None] * torch.cross(vd, vxvd, dim=-1))
    return body_velocity(v, vdd) + jdot_vd


def _nearest_equivalent(v: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """The rotation vector (|v| + 2πk) v̂ equivalent to v that is closest to ref (...×3).

    All vectors on v's axis with length ≡ |v| (mod 2π) give the same rotation; the
    closest to ref along that line has k = round((v̂·ref − |v|)/2π). For v = 0 the axis
    is taken from ref (x̂ when ref = 0 too).
    """
    th = v.norm(dim=-1, keepdim=True)
    rn = ref.norm(dim=-1, keepdim=True)
    ex = torch.zeros_like(v)
    ex[..., 0] = 1.0
    ref_axis = torch.where(rn > 0, ref / torch.where(rn > 0, rn, 1.0), ex)
    axis = torch.where(th > 0, v / torch.where(th > 0, th, 1.0), ref_axis)
    k = torch.round(((axis * ref).sum(-1, keepdim=True) - th) / (2 * math.pi))
    return (th + 2 * math.pi * k) * axis


def unwrap_rotvec(v: torch.Tensor) -> torch.Tensor:
    """Unwrap a sequence of rotation vectors (...×T×3, time on dim −2) so that it is
    continuous across |v| = π.

    The sample of smallest |v| (per sequence) is kept as it is; going forwards and then
    backwards from it, each sample is replaced by its equivalent (|v| + 2πk) v̂ closest to
    its already unwrapped neighbour. Anchoring at the smallest rotation keeps the lift
    away from the chart's singular shell |v| = 2π unless the motion really winds
    (leaves the rest rotation, crosses π and comes back near it).
    """
    T = v.shape[-2]
    anchor = v.norm(dim=-1).argmin(dim=-1, keepdim=True)    # ...×1
    out = list(v.unbind(-2))
    for i in range(1, T):
        out[i] = torch.where(anchor < i, _nearest_equivalent(out[i], out[i - 1]), out[i])
    for i in range(T - 2, -1, -1):
        out[i] = torch.where(anchor > i, _nearest_equivalent(out[i], out[i + 1]), out[i])
    return torch.stack(out, dim=-2)


def wrap_rotvec(v: torch.Tensor) -> torch.Tensor:
    """The principal rotation vector (|v| ≤ π) of the same rotation (...×3)."""
    th = v.norm(dim=-1, keepdim=True)
    phi = th - 2 * math.pi * torch.round(th / (2 * math.pi))
    return torch.where(th > 0, v * (phi / torch.where(th > 0, th, 1.0)), v)


def align_quaternions(quat: torch.Tensor) -> torch.Tensor:
    """Flip signs along a sequence of unit quaternions (...×T×4, time on dim −2) so that
    successive ones have a non-negative dot product (q and −q are the same rotation)."""
    dots = (quat[..., 1:, :] * quat[..., :-1, :]).sum(-1)
    flips = torch.cat([torch.ones_like(dots[..., :1]), torch.where(dots < 0, -1.0, 1.0)], -1)
    return quat * torch.cumprod(flips, dim=-1)[..., None]


POSITION_SIZE = {"ball": 4, "free": 7}   # packed position entries (others: their dof)


def n_position(body: Body) -> int:
    """Size of the packed position block: 4 per ball joint, 1 per hinge, 7 per free joint."""
    return sum(POSITION_SIZE.get(link.joint, link.dof) for link in body.links)



def pack(body: Body, q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Coordinates ν (...×nv) and velocities v (...×nv) → state y (...×(n_position+nv))."""
    batch = torch.broadcast_shapes(q.shape[:-1], v.shape[:-1])
    q, v = q.expand(batch + q.shape[-1:]), v.expand(batch + v.shape[-1:])
    parts = []
    for i, link in enumerate(body.links):
        s = q[..., body.slice(i)]
        if link.joint == "free":
            parts += [roma.rotvec_to_unitquat(s[..., :3]), s[..., 3:]]
        else:
            parts.append(roma.rotvec_to_unitquat(s) if link.joint == "ball" else s)
    return torch.cat(parts + [v], dim=-1)


def unpack(body: Body, y: torch.Tensor):
    """State y → (joint rotations, ν principal coordinates, unit quaternions, v).

    Rotations (...×3×3) and quaternions (...×4) are lists with one entry per link, None
    for hinges and fixed joints; quaternions are normalised as they are read. A free
    joint's coordinates are its principal rotation vector and its translation."""
    rots, coords, quats, k = [], [], [], 0
    for link in body.links:
        if link.joint in ("ball", "free"):
            quat = roma.quat_normalize(y[..., k:k + 4])
            quats.append(quat)
            rots.append(roma.unitquat_to_rotmat(quat))
            coords.append(roma.unitquat_to_rotvec(quat, shortest_arc=True))
            if link.joint == "free":
                coords.append(y[..., k + 4:k + 7])
            k += POSITION_SIZE[link.joint]
        else:
            quats.append(None)
            rots.append(None)
            coords.append(y[..., k:k + link.dof])
            k += link.dof
    return rots, torch.cat(coords, dim=-1), quats, y[..., k:]


def difference(body: Body, q_a: torch.Tensor, q_b: torch.Tensor) -> torch.Tensor:
    """q_b ⊖ q_a (...×nv): log(R_aᵀ R_b) per ball joint (child frame; ν_b − ν_a to first
    order, and well behaved where the principal rotation vector wraps at π), θ_b − θ_a
    per hinge, (log(R_aᵀ R_b), R_aᵀ (t_b − t_a)) per free joint."""
    parts = []
    for i, link in enumerate(body.links):
        s = body.slice(i)
        if link.joint == "ball":
            R = rotvec_to_rotmat(q_a[..., s]).transpose(-1, -2) @ rotvec_to_rotmat(q_b[..., s])
            parts.append(roma.unitquat_to_rotvec(roma.rotmat_to_unitquat(R)))
        elif link.joint == "free":
            Ra = rotvec_to_rotmat(q_a[..., s][..., :3])
            R = Ra.transpose(-1, -2) @ rotvec_to_rotmat(q_b[..., s][..., :3])
            dt = (q_b[..., s][..., 3:] - q_a[..., s][..., 3:]).unsqueeze(-1)
            parts += [roma.unitquat_to_rotvec(roma.rotmat_to_unitquat(R)),
                      (Ra.transpose(-1, -2) @ dt).squeeze(-1)]
        elif link.dof:
            parts.append(q_b[..., s] - q_a[..., s])
    return torch.cat(parts, dim=-1)


def integrate(body: Body, q: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """q ⊕ x (...×nv), the inverse of :func:`difference` (difference(q, q ⊕ x) = x while
    each ball rotation stays below π): log(R(ν) exp([x]×)) per ball joint (x in the child
    frame), θ + x per hinge, (log(R exp([x_ω]×)), t + R x_t) per free joint."""
    parts = []
    for i, link in enumerate(body.links):
        s = body.slice(i)
        if link.joint in ("ball", "free"):
            R = rotvec_to_rotmat(q[..., s][..., :3])
            parts.append(roma.rotmat_to_rotvec(R @ rotvec_to_rotmat(x[..., s][..., :3])))
            if link.joint == "free":
                parts.append(q[..., s][..., 3:] + (R @ x[..., s][..., 3:, None])[..., 0])
        elif link.dof:
            parts.append(q[..., s] + x[..., s])
    return torch.cat(parts, dim=-1)
