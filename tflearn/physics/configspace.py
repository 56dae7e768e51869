"""Configuration-space maths of a body: rotations, charts, packing and differences.

Coordinates ν (...×nv) stack, per joint in link order, a ball joint's rotation vector v
(R = exp([v]×), principal when |v| ≤ π), a hinge's angle θ, nothing for a fixed joint
(:mod:`tflearn.physics.body`). Here, in one place:

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
  of :mod:`tflearn.physics.body`; not Pinocchio's SE(3) log).
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import roma
import torch

from . import kernels, kernels_state
from .body import Body

TAYLOR_THETA2 = 0.25  # below θ² = 0.25 the J_r coefficients use their Taylor series


def rotvec_to_rotmat(v: torch.Tensor) -> torch.Tensor:
    """R = exp([v]×) (...×3 → ...×3×3), exact and smooth at v = 0 (via a unit quaternion)."""
    return quat_to_rotmat(roma.rotvec_to_unitquat(v))


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


# ----------------------------------------------- unit quaternions (XYZW) by constant tables

def _rotmat_of_outer(M: torch.Tensor) -> torch.Tensor:
    """R (9) from M = q qᵀ (4×4), q = (x, y, z, w): R is quadratic in q."""
    (xx, xy, xz, xw), (_, yy, yz, yw), (_, _, zz, zw), (_, _, _, ww) = M
    return torch.stack([xx - yy - zz + ww, 2 * (xy - zw), 2 * (xz + yw),
                        2 * (xy + zw), -xx + yy - zz + ww, 2 * (yz - xw),
                        2 * (xz - yw), 2 * (yz + xw), -xx - yy + zz + ww])


def _rate_of_outer(M: torch.Tensor) -> torch.Tensor:
    """q ⊗ (ω, 0) (4) from M = q ωᵀ (4×3): (w ω + v × ω, −v·ω) for q = (v, w)."""
    return torch.stack([M[3, 0] + M[1, 2] - M[2, 1], M[3, 1] + M[2, 0] - M[0, 2],
                        M[3, 2] + M[0, 1] - M[1, 0], -(M[0, 0] + M[1, 1] + M[2, 2])])


@lru_cache(maxsize=8)
def _quat_tables(dtype: torch.dtype, device: torch.device) -> tuple:
    """(Q 16×9, P 12×4): vec(R(q)) = vec(q qᵀ) Q and q ⊗ (ω, 0) = vec(q ωᵀ) P, so that
    each is one outer product and one matrix product however many joints are batched."""
    def table(f, shape):
        units = torch.eye(shape[0] * shape[1], dtype=torch.float64)
        return torch.stack([f(u.reshape(shape)) for u in units]).to(dtype=dtype, device=device)
    return table(_rotmat_of_outer, (4, 4)), table(_rate_of_outer, (4, 3))


def quat_to_rotmat(quat: torch.Tensor) -> torch.Tensor:
    """R(q) (...×4 → ...×3×3) of unit quaternions (XYZW, as roma)."""
    Q = _quat_tables(quat.dtype, quat.device)[0]
    outer = quat.unsqueeze(-1) * quat.unsqueeze(-2)
    return (outer.flatten(-2) @ Q).unflatten(-1, (3, 3))


def quat_rate(quat: torch.Tensor, omega: torch.Tensor) -> torch.Tensor:
    """q̇ = ½ q ⊗ (ω, 0) (...×4) for a child-frame angular velocity ω (...×3)."""
    P = _quat_tables(quat.dtype, quat.device)[1]
    return 0.5 * ((quat.unsqueeze(-1) * omega.unsqueeze(-2)).flatten(-2) @ P)


def quat_to_rotvec(quat: torch.Tensor) -> torch.Tensor:
    """The principal rotation vector (|v| ≤ π) of unit quaternions (...×4 → ...×3):
    with the sign making w > 0 (as roma's shortest arc), v = 2 atan2(|u|, w) u/|u| for
    q = (u, w); below |u| = 1e-3 w by the series of atan(r)/r, r = |u|/w, so that values
    and derivatives stay exact at the identity."""
    quat = torch.where(quat[..., 3:] > 0, quat, -quat)
    u, w = quat[..., :3], quat[..., 3:]
    n = u.norm(dim=-1, keepdim=True)
    small = n < 1e-3 * w
    n_safe = torch.where(small, torch.ones_like(n), n)
    w_safe = torch.where(small, w, torch.ones_like(w))
    r2 = (n / w_safe) ** 2
    series = (2 / w_safe) * (1 - r2 / 3 + r2 * r2 / 5 - r2 ** 3 / 7)
    return u * torch.where(small, series, 2 * torch.atan2(n_safe, w) / n_safe)


# ------------------------------------------------------------------ the simulator's state

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


@lru_cache(maxsize=64)
def _layout(body: Body, device: torch.device) -> dict:
    """Where each part of the state y lives, for :func:`unpack` and :func:`position_rate`:
    the rotation joints (ball, free) in link order (``rot``), their quaternions' entries
    in y (nr×4) and angular rates in v (nr×3; equally their rotation vectors in ν); the
    other position entries (hinge angles, free translations) in y; and two permutations:
    [rotation vectors (3 nr), other entries] → coordinate order, and [quaternion rates
    (4 nr), other rates] → y's order."""
    rot, quat, rate, other, coords, position = [], [], [], [], [], []
    k = 0
    for i, link in enumerate(body.links):
        start = body.slice(i).start
        if link.joint in ("ball", "free"):
            j = len(rot)
            coords += [("rot", 3 * j + d) for d in range(3)]
            position += [("rot", 4 * j + d) for d in range(4)]
            rot.append(i)
            quat.append(list(range(k, k + 4)))
            rate.append(list(range(start, start + 3)))
            k += 4
        n_other = 3 if link.joint == "free" else (0 if link.joint == "ball" else link.dof)
        for d in range(n_other):
            coords.append(("other", len(other)))
            position.append(("other", len(other)))
            other.append(k + d)
        k += n_other

    def tensor(x, shape=(-1,)):
        return torch.tensor(x, dtype=torch.long, device=device).reshape(shape)

    def order(src, width):
        return tensor([m if kind == "rot" else width * len(rot) + m for kind, m in src])
    out = {"rot": rot, "n_pos": k, "quat": tensor(quat, (len(rot), 4)),
           "rate": tensor(rate, (len(rot), 3)), "other": tensor(other),
           "coords": order(coords, 3), "position": order(position, 4)}
    out["numpy"] = {key: np.ascontiguousarray(out[key].cpu().numpy().astype(np.int64))
                    for key in ("quat", "other", "coords", "position")}   # for tflearn.physics.kernels
    return out


def state_tangent_basis(body: Body, y: torch.Tensor) -> torch.Tensor:
    """Orthonormal columns (...×D×(D − nr)) spanning the space of states y (...×D) less
    each quaternion's own direction: unit columns for the entries that are not
    quaternions (hinge angles, translations, velocities), in y's order, then for each
    rotation joint q ⊗ (e_k, 0), k = 1, 2, 3 (orthonormal and ⊥ q for a unit q)."""
    L = _layout(body, y.device)
    D = y.shape[-1]
    quat = L["quat"].reshape(-1, 4)
    keep = sorted(set(range(D)) - set(quat.flatten().tolist()))
    B = y.new_zeros(y.shape[:-1] + (D, D - quat.shape[0]))
    B[..., keep, torch.arange(len(keep))] = 1.0
    col = len(keep)
    for rows in quat:
        q = y[..., rows]
        q = q / q.norm(dim=-1, keepdim=True)
        for k in range(3):
            e = q.new_zeros(4)
            e[k] = 1.0
            B[..., rows, col] = roma.quat_product(q, e.expand_as(q))
            col += 1
    return B


def _unpack_compiled(body: Body, L: dict, y: torch.Tensor):
    """:func:`unpack` by :func:`tflearn.physics.kernels_state.read_state` (no gradient, float64 CPU)."""
    batch, nr = y.shape[:-1], L["quat"].shape[0]
    flat = kernels.as_numpy(y.reshape(-1, y.shape[-1]))
    B = flat.shape[0]
    coords, quats, R = np.empty((B, body.nv)), np.empty((B, nr, 4)), np.empty((B, nr, 3, 3))
    N = L["numpy"]
    kernels_state.read_state(flat, N["quat"], N["other"], N["coords"], coords, quats, R)
    R = torch.from_numpy(R).reshape(batch + (nr, 3, 3))
    return (_per_link(body, L, R), torch.from_numpy(coords).reshape(batch + (body.nv,)),
            torch.from_numpy(quats).reshape(batch + (nr, 4)), y[..., L["n_pos"]:])


def _per_link(body: Body, L: dict, x: torch.Tensor) -> list:
    """A list with one matrix per link from x (...×nr×3×3, the rotation joints' in link
    order), None for links without a rotation joint."""
    out = [None] * len(body.links)
    for j, i in enumerate(L["rot"]):
        out[i] = x[..., j, :, :]
    return out


def joint_rotations(body: Body, q: torch.Tensor) -> list:
    """The joints' own rotations exp([v]×) (ball, free) or None (hinge, fixed); q (...×nv).
    All rotation joints are converted in one batched call."""
    L = _layout(body, q.device)
    return _per_link(body, L, rotvec_to_rotmat(q[..., L["rate"]]))


def unpack(body: Body, y: torch.Tensor):
    """State y → (joint rotations, ν principal coordinates, unit quaternions, v).

    Rotations (...×3×3) are a list with one entry per link, None for hinges and fixed
    joints; the quaternions (...×nr×4) are those of the rotation joints (ball, free) in
    link order, normalised as they are read. A free joint's coordinates are its principal
    rotation vector and its translation."""
    L = _layout(body, y.device)
    if kernels.applies(y):
        return _unpack_compiled(body, L, y)
    quats = y[..., L["quat"]]
    quats = quats / quats.norm(dim=-1, keepdim=True)
    coords = torch.cat([quat_to_rotvec(quats).flatten(-2), y[..., L["other"]]], -1)
    return (_per_link(body, L, quat_to_rotmat(quats)), coords[..., L["coords"]], quats,
            y[..., L["n_pos"]:])


def position_rate(body: Body, rots: list, quats: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """The position block of ẏ (...×n_position) from :func:`unpack`'s rotations and
    quaternions and the velocities v: q̇ = ½ q ⊗ (ω, 0) per rotation joint (ω its
    child-frame angular velocity), θ̇ = v per hinge, ṫ = R u per free joint."""
    L = _layout(body, v.device)
    if kernels.applies(quats, v, *rots) and v.shape[:-1] == quats.shape[:-2]:
        B, nr = v[..., 0].numel(), quats.shape[-2]
        kind, rot, offset, _ = kernels.link_tables(body)
        R = [r for r in rots if r is not None]             # read for free joints only
        R = (kernels.as_numpy(torch.stack(R, -3).reshape(B, nr, 3, 3)) if (kind == 3).any()
             else np.zeros((1, 0, 3, 3)))
        out = np.empty((B, L["position"].numel()))
        kernels_state.position_rate(kind, rot, offset, R, kernels.as_numpy(quats.reshape(B, nr, 4)),
                                    kernels.as_numpy(v.reshape(B, -1)), L["numpy"]["position"], out)
        return torch.from_numpy(out).reshape(v.shape[:-1] + out.shape[-1:])
    rates = [quat_rate(quats, v[..., L["rate"]]).flatten(-2)]
    for i, link in enumerate(body.links):
        vi = v[..., body.slice(i)]
        if link.joint == "free":
            rates.append((rots[i] @ vi[..., 3:, None]).squeeze(-1))
        elif link.joint != "ball" and link.dof:
            rates.append(vi)
    return torch.cat(rates, -1)[..., L["position"]]
