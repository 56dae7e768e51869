"""Compiled (numba) loops of the rigid-body algorithms and of the simulator's state, for
evaluations that need no gradient: one call per batch instead of hundreds of small
tensor operations.

:func:`tflearn.dynamics.forward_dynamics_rot` and ``rnea_rot`` hand their recursions to
:func:`aba` and :func:`rnea`, and :func:`tflearn.configspace.unpack` and
``position_rate`` the simulator's state to :func:`read_state` and :func:`position_rate`,
when no input needs a gradient and the tensors are float64 on the CPU (:func:`applies`);
with a gradient, on another device or dtype, they run their own torch code (the two
agree to 1e-12, tests/test_kernels.py). The maths is the same, per sample b, with the
parent → link motion transform X_i = [[E, 0], [−E [r]×, E]] (E = (R0 R_joint)ᵀ, r the
joint origin) applied by its blocks rather than as a 6×6 matrix:

    V_i = X_i V_p + S_i q̇_i,   c_i = V_i ×ₘ S_i q̇_i,   Iᴬ_i = I_i,   pᴬ_i = V_i ×* I_i V_i;
    leaves → root: U = Iᴬ_i S_i, D = S_iᵀ U, u = τ_i − S_iᵀ pᴬ_i,
                   Iᵃ = Iᴬ_i − U D⁻¹ Uᵀ, pᵃ = pᴬ_i + Iᵃ c_i + U D⁻¹ u,
                   Iᴬ_p += X_iᵀ Iᵃ X_i, pᴬ_p += X_iᵀ pᵃ;
    root → leaves: a' = X_i A_p + c_i, q̈_i = D⁻¹ (u − Uᵀ a'), A_i = a' + S_i q̈_i,

from V_0, A_0 (B×6: the root's parent). S_i is stored padded to 6 columns with its
joint's dof d_i; D (d×d, symmetric positive definite) is inverted by Cholesky, and a D
that is not positive definite gives NaN accelerations (the state blew up).

Compiled once per machine and kept in numba's on-disk cache (``cache=True``): the first
call in a fresh checkout takes several seconds, later processes load it.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
import torch
from numba import njit

from .body import Body


def applies(*xs) -> bool:
    """Whether the compiled loops apply to these arguments (tensors among them): float64
    on the CPU, no gradient to carry."""
    xs = [x for x in xs if isinstance(x, torch.Tensor)]
    return (xs[0].dtype == torch.float64 and xs[0].device.type == "cpu"
            and not (torch.is_grad_enabled() and any(x.requires_grad for x in xs)))


def as_numpy(x: torch.Tensor) -> np.ndarray:
    """A C-contiguous float64 numpy view (or copy) of a CPU tensor."""
    return np.ascontiguousarray((x.detach() if x.requires_grad else x).numpy())


_KIND = {"fixed": 0, "hinge": 1, "ball": 2, "free": 3}


@lru_cache(maxsize=64)
def link_tables(body: Body) -> tuple:
    """Per link: joint kind (0 fixed, 1 hinge, 2 ball, 3 free), index among the rotation
    joints (ball, free; −1 for none), first coordinate, dof and parent (int64 arrays)."""
    kind = np.array([_KIND[link.joint] for link in body.links], dtype=np.int64)
    rot = np.where(kind >= 2, np.cumsum(kind >= 2) - 1, -1).astype(np.int64)
    dof = np.array([link.dof for link in body.links], dtype=np.int64)
    offset = np.concatenate([[0], np.cumsum(dof)[:-1]]).astype(np.int64)
    parent = np.array([link.parent for link in body.links], dtype=np.int64)
    return kind, rot, offset, dof, parent


#: LLVM may contract and reorder floating-point arithmetic, but not assume away NaN/Inf
#: (a blown-up state must still come out non-finite).
_FAST = {"contract", "reassoc", "nsz", "arcp"}


@njit(cache=True, fastmath=_FAST)
def _cholesky_inverse(D, d, out, L, Linv):
    """out[:d, :d] = D[:d, :d]⁻¹ (SPD, by Cholesky; L, Linv: 6×6 scratch); NaN where D is
    not positive definite."""
    for j in range(d):
        s = D[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            out[:d, :d] = np.nan
            return
        L[j, j] = np.sqrt(s)
        for i in range(j + 1, d):
            s = D[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / L[j, j]
    for j in range(d):
        Linv[j, j] = 1.0 / L[j, j]
        for i in range(j + 1, d):
            s = 0.0
            for k in range(j, i):
                s -= L[i, k] * Linv[k, j]
            Linv[i, j] = s / L[i, i]
    for i in range(d):
        for j in range(d):
            s = 0.0
            for k in range(max(i, j), d):
                s += Linv[k, i] * Linv[k, j]
            out[i, j] = s


@njit(cache=True, fastmath=_FAST)
def _cross_motion(V, s, out):
    """out = V ×ₘ s = (ω × s_ω, ω × s_v + v × s_ω) for V = (ω, v)."""
    w0, w1, w2, v0, v1, v2 = V[0], V[1], V[2], V[3], V[4], V[5]
    out[0] = w1 * s[2] - w2 * s[1]
    out[1] = w2 * s[0] - w0 * s[2]
    out[2] = w0 * s[1] - w1 * s[0]
    out[3] = w1 * s[5] - w2 * s[4] + v1 * s[2] - v2 * s[1]
    out[4] = w2 * s[3] - w0 * s[5] + v2 * s[0] - v0 * s[2]
    out[5] = w0 * s[4] - w1 * s[3] + v0 * s[1] - v1 * s[0]


@njit(cache=True, fastmath=_FAST)
def _cross_force(V, P, out):
    """out = V ×* P = (ω × n + v × f, ω × f) for V = (ω, v), P = (n, f)."""
    w0, w1, w2, v0, v1, v2 = V[0], V[1], V[2], V[3], V[4], V[5]
    out[0] = w1 * P[2] - w2 * P[1] + v1 * P[5] - v2 * P[4]
    out[1] = w2 * P[0] - w0 * P[2] + v2 * P[3] - v0 * P[5]
    out[2] = w0 * P[1] - w1 * P[0] + v0 * P[4] - v1 * P[3]
    out[3] = w1 * P[5] - w2 * P[4]
    out[4] = w2 * P[3] - w0 * P[5]
    out[5] = w0 * P[4] - w1 * P[3]


@njit(cache=True, fastmath=_FAST)
def _frame(i, b, kind, rot, R0, origin, axis, R, q, offset, E, r, Rj):
    """Link i's E = (R0 R_joint)ᵀ and origin r in its parent (the motion transform
    X = [[E, 0], [−E [r]×, E]]) at sample b (Rj: 3×3 scratch)."""
    o = offset[i]
    if kind[i] == 1:                                    # hinge: Rodrigues on the angle
        a = axis[i]
        sn, cs = np.sin(q[b, o]), 1.0 - np.cos(q[b, o])
        for m in range(3):
            for n in range(3):
                K2 = a[m] * a[n] - (1.0 if m == n else 0.0)
                Rj[m, n] = (1.0 if m == n else 0.0) + cs * K2
        Rj[0, 1] -= sn * a[2]
        Rj[0, 2] += sn * a[1]
        Rj[1, 0] += sn * a[2]
        Rj[1, 2] -= sn * a[0]
        Rj[2, 0] -= sn * a[1]
        Rj[2, 1] += sn * a[0]
    elif kind[i] >= 2:                                  # ball, free: the rotation given
        Rj[:, :] = R[b, rot[i]]
    else:
        for m in range(3):
            for n in range(3):
                Rj[m, n] = 1.0 if m == n else 0.0
    for m in range(3):
        r[m] = origin[i, m]
        for n in range(3):
            acc = 0.0
            for k in range(3):
                acc += R0[i, n, k] * Rj[k, m]
            E[m, n] = acc                               # (R0 Rj)ᵀ
    if kind[i] == 3:                                    # free: the origin moves, r + R0 t
        for m in range(3):
            for k in range(3):
                r[m] += R0[i, m, k] * q[b, o + 3 + k]


@njit(cache=True, fastmath=_FAST)
def _motion(E, r, x, out):
    """out = X x for a motion vector x = (ω, v): (E ω, E (v − r × ω))."""
    w0 = x[3] - (r[1] * x[2] - r[2] * x[1])
    w1 = x[4] - (r[2] * x[0] - r[0] * x[2])
    w2 = x[5] - (r[0] * x[1] - r[1] * x[0])
    for m in range(3):
        out[m] = E[m, 0] * x[0] + E[m, 1] * x[1] + E[m, 2] * x[2]
        out[3 + m] = E[m, 0] * w0 + E[m, 1] * w1 + E[m, 2] * w2


@njit(cache=True, fastmath=_FAST)
def _force_back(E, r, f, out):
    """out += Xᵀ f for a force f = (n, f): (Eᵀ n + r × Eᵀ f, Eᵀ f)."""
    g0 = E[0, 0] * f[3] + E[1, 0] * f[4] + E[2, 0] * f[5]
    g1 = E[0, 1] * f[3] + E[1, 1] * f[4] + E[2, 1] * f[5]
    g2 = E[0, 2] * f[3] + E[1, 2] * f[4] + E[2, 2] * f[5]
    out[0] += E[0, 0] * f[0] + E[1, 0] * f[1] + E[2, 0] * f[2] + r[1] * g2 - r[2] * g1
    out[1] += E[0, 1] * f[0] + E[1, 1] * f[1] + E[2, 1] * f[2] + r[2] * g0 - r[0] * g2
    out[2] += E[0, 2] * f[0] + E[1, 2] * f[1] + E[2, 2] * f[2] + r[0] * g1 - r[1] * g0
    out[3] += g0
    out[4] += g1
    out[5] += g2


@njit(cache=True, fastmath=_FAST)
def _inertia_back(E, r, Ia, out, W, Z):
    """out += Xᵀ Iᵃ X (6×6) by blocks: with Iᵃ = [[A, B], [Bᵀ, C]] turned into the parent's
    axes, A' = Eᵀ A E (B', C' alike), and [r]× = Rx,
        Xᵀ Iᵃ X = [[A' − B'Rx − (B'Rx)ᵀ − Rx C' Rx, B' + Rx C'], [(B' + Rx C')ᵀ, C']]
    (W, Z: 3×3 scratch)."""
    for blk in range(3):                          # A, B, C → A', B', C' into out's blocks
        ro, co = (0, 0) if blk == 0 else ((0, 3) if blk == 1 else (3, 3))
        for m in range(3):                        # W = M E
            for n in range(3):
                W[m, n] = (Ia[ro + m, co] * E[0, n] + Ia[ro + m, co + 1] * E[1, n]
                           + Ia[ro + m, co + 2] * E[2, n])
        for m in range(3):                        # Z = Eᵀ W
            for n in range(3):
                Z[m, n] = E[0, m] * W[0, n] + E[1, m] * W[1, n] + E[2, m] * W[2, n]
        if blk == 0:
            for m in range(3):
                for n in range(3):
                    out[m, n] += Z[m, n]
        elif blk == 1:                            # B' (and a copy in W)
            for m in range(3):
                for n in range(3):
                    out[m, 3 + n] += Z[m, n]
                    out[3 + n, m] += Z[m, n]
                    W[m, n] = Z[m, n]
            for m in range(3):                    # −B'Rx − (B'Rx)ᵀ into the top-left block
                t0 = W[m, 1] * r[2] - W[m, 2] * r[1]     # (B' Rx)[m, 0]
                t1 = W[m, 2] * r[0] - W[m, 0] * r[2]
                t2 = W[m, 0] * r[1] - W[m, 1] * r[0]
                out[m, 0] -= t0
                out[0, m] -= t0
                out[m, 1] -= t1
                out[1, m] -= t1
                out[m, 2] -= t2
                out[2, m] -= t2
        else:
            for m in range(3):
                for n in range(3):
                    out[3 + m, 3 + n] += Z[m, n]
            for n in range(3):                    # W = Rx C'
                W[0, n] = r[1] * Z[2, n] - r[2] * Z[1, n]
                W[1, n] = r[2] * Z[0, n] - r[0] * Z[2, n]
                W[2, n] = r[0] * Z[1, n] - r[1] * Z[0, n]
            for m in range(3):
                for n in range(3):
                    out[m, 3 + n] += W[m, n]
                    out[3 + n, m] += W[m, n]
            for m in range(3):                    # − (Rx C') Rx
                out[m, 0] -= W[m, 1] * r[2] - W[m, 2] * r[1]
                out[m, 1] -= W[m, 2] * r[0] - W[m, 0] * r[2]
                out[m, 2] -= W[m, 0] * r[1] - W[m, 1] * r[0]


@njit(cache=True, fastmath=_FAST)
def aba(kind, rot, R0, origin, axis, S, dof, offset, parent, inertia, R, q, V0, A0, v, tau, qdd):
    """The articulated-body algorithm (module docstring) for every sample b. Per link i:
    kind (0 fixed, 1 hinge, 2 ball, 3 free), rot (its index in R, −1 for none), R0
    (L×3×3) and origin (L×3) of the joint, axis (L×3, hinges), S (L×6×6, the first
    dof[i] columns used), dof, offset (first coordinate), parent (−1 for the root),
    inertia (L×6×6, spatial, about the link origin); R (B×nr×3×3) the rotation joints'
    rotations, q, v, tau (B×nv), V0, A0 (B×6, or 1×6 for all samples) → qdd (B×nv),
    written in place."""
    # The outward velocity pass is written out here and in :func:`rnea`: as a shared
    # function taking these arrays it cost 0.7 µs more per sample (1.4 → 2.1 µs at 10⁴).
    B, L = q.shape[0], kind.shape[0]
    E = np.zeros((L, 3, 3))
    r = np.zeros((L, 3))
    V = np.zeros((L, 6))
    c = np.zeros((L, 6))
    IA = np.zeros((L, 6, 6))
    pA = np.zeros((L, 6))
    U = np.zeros((L, 6, 6))
    KU = np.zeros((L, 6, 6))                            # D⁻¹ Uᵀ (d×6)
    Dinv = np.zeros((L, 6, 6))
    u = np.zeros((L, 6))
    A = np.zeros((L, 6))
    s = np.zeros(6)
    x = np.zeros(6)
    IV = np.zeros(6)
    pa = np.zeros(6)
    Du = np.zeros(6)
    D = np.zeros((6, 6))
    Rj = np.zeros((3, 3))
    Lc = np.zeros((6, 6))
    Lci = np.zeros((6, 6))
    for b in range(B):
        V0b, A0b = V0[b if V0.shape[0] > 1 else 0], A0[b if A0.shape[0] > 1 else 0]
        for i in range(L):
            _frame(i, b, kind, rot, R0, origin, axis, R, q, offset, E[i], r[i], Rj)
            for m in range(6):
                acc = 0.0
                for k in range(dof[i]):
                    acc += S[i, m, k] * v[b, offset[i] + k]
                s[m] = acc
            _motion(E[i], r[i], V0b if parent[i] < 0 else V[parent[i]], V[i])
            for m in range(6):
                V[i, m] += s[m]
            _cross_motion(V[i], s, c[i])
            for m in range(6):
                acc = 0.0
                for k in range(6):
                    IA[i, m, k] = inertia[i, m, k]
                    acc += inertia[i, m, k] * V[i, k]
                IV[m] = acc
            _cross_force(V[i], IV, pA[i])
        for i in range(L - 1, -1, -1):
            d, o, p = dof[i], offset[i], parent[i]
            for m in range(6):
                acc = pA[i, m]
                for k in range(6):
                    acc += IA[i, m, k] * c[i, k]
                pa[m] = acc
            if d > 0 and kind[i] >= 2:                   # S = the first d unit columns
                for m in range(6):
                    for k in range(d):
                        U[i, m, k] = IA[i, m, k]
                for m in range(d):
                    for k in range(d):
                        D[m, k] = IA[i, m, k]
                    u[i, m] = tau[b, o + m] - pA[i, m]
            elif d > 0:
                for m in range(6):
                    for k in range(d):
                        acc = 0.0
                        for n in range(6):
                            acc += IA[i, m, n] * S[i, n, k]
                        U[i, m, k] = acc
                for m in range(d):
                    for k in range(d):
                        acc = 0.0
                        for n in range(6):
                            acc += S[i, n, m] * U[i, n, k]
                        D[m, k] = acc
                    acc = tau[b, o + m]
                    for n in range(6):
                        acc -= S[i, n, m] * pA[i, n]
                    u[i, m] = acc
            if d > 0:
                _cholesky_inverse(D, d, Dinv[i], Lc, Lci)
                for m in range(d):
                    for k in range(6):
                        acc = 0.0
                        for n in range(d):
                            acc += Dinv[i, m, n] * U[i, k, n]
                        KU[i, m, k] = acc
                for m in range(d):                        # Du = D⁻¹ u − D⁻¹Uᵀ c
                    acc = 0.0
                    for n in range(d):
                        acc += Dinv[i, m, n] * u[i, n]
                    for n in range(6):
                        acc -= KU[i, m, n] * c[i, n]
                    Du[m] = acc
                for m in range(6):
                    for k in range(6):
                        acc = 0.0
                        for n in range(d):
                            acc += U[i, m, n] * KU[i, n, k]
                        IA[i, m, k] -= acc               # Iᵃ = Iᴬ − U D⁻¹ Uᵀ
                    acc = 0.0
                    for n in range(d):
                        acc += U[i, m, n] * Du[n]
                    pa[m] += acc
            if p >= 0:
                _inertia_back(E[i], r[i], IA[i], IA[p], Rj, Lc)
                _force_back(E[i], r[i], pa, pA[p])
        for i in range(L):
            d, o, p = dof[i], offset[i], parent[i]
            _motion(E[i], r[i], A0b if p < 0 else A[p], x)
            for m in range(6):
                x[m] += c[i, m]
            for m in range(d):
                acc = 0.0
                for n in range(d):
                    acc += Dinv[i, m, n] * u[i, n]
                for n in range(6):
                    acc -= KU[i, m, n] * x[n]
                qdd[b, o + m] = acc
            for m in range(6):
                acc = x[m]
                for k in range(d):
                    acc += S[i, m, k] * qdd[b, o + k]
                A[i, m] = acc


@njit(cache=True, fastmath=_FAST)
def rnea(kind, rot, R0, origin, axis, S, dof, offset, parent, inertia, R, q, V0, A0, v, a, tau):
    """Recursive Newton–Euler inverse dynamics for every sample b (the arguments of
    :func:`aba`, with accelerations a in place of torques; tau (B×nv) written in place):

        V_i = X_i V_p + S_i q̇_i,  A_i = X_i A_p + S_i q̈_i + V_i ×ₘ S_i q̇_i,
        F_i = I_i A_i + V_i ×* I_i V_i;   leaves → root: τ_i = S_iᵀ F_i, F_p += X_iᵀ F_i."""
    B, L = q.shape[0], kind.shape[0]
    E = np.zeros((L, 3, 3))
    r = np.zeros((L, 3))
    V = np.zeros((L, 6))
    A = np.zeros((L, 6))
    F = np.zeros((L, 6))
    s = np.zeros(6)
    x = np.zeros(6)
    IV = np.zeros(6)
    Rj = np.zeros((3, 3))
    for b in range(B):
        V0b, A0b = V0[b if V0.shape[0] > 1 else 0], A0[b if A0.shape[0] > 1 else 0]
        for i in range(L):
            d, o, p = dof[i], offset[i], parent[i]
            _frame(i, b, kind, rot, R0, origin, axis, R, q, offset, E[i], r[i], Rj)
            for m in range(6):
                acc = 0.0
                for k in range(dof[i]):
                    acc += S[i, m, k] * v[b, offset[i] + k]
                s[m] = acc
            _motion(E[i], r[i], V0b if parent[i] < 0 else V[parent[i]], V[i])
            for m in range(6):
                V[i, m] += s[m]
            _motion(E[i], r[i], A0b if p < 0 else A[p], A[i])
            _cross_motion(V[i], s, x)
            for m in range(6):
                acc = x[m]
                for k in range(d):
                    acc += S[i, m, k] * a[b, o + k]
                A[i, m] += acc
            for m in range(6):
                acc = 0.0
                acc2 = 0.0
                for k in range(6):
                    acc += inertia[i, m, k] * V[i, k]
                    acc2 += inertia[i, m, k] * A[i, k]
                IV[m] = acc
                F[i, m] = acc2
            _cross_force(V[i], IV, x)
            for m in range(6):
                F[i, m] += x[m]
        for i in range(L - 1, -1, -1):
            d, o, p = dof[i], offset[i], parent[i]
            for k in range(d):
                acc = 0.0
                for m in range(6):
                    acc += S[i, m, k] * F[i, m]
                tau[b, o + k] = acc
            if p >= 0:
                _force_back(E[i], r[i], F[i], F[p])


# ------------------------------------------------------------- the simulator's state

@njit(cache=True, fastmath=_FAST)
def read_state(y, quat, other, coords_order, coords, quats, R):
    """:func:`tflearn.configspace.unpack` for every sample b of the state y (B×D): each
    rotation joint's quaternion (entries ``quat``, nr×4 indices into y) normalised into
    ``quats`` (B×nr×4), its rotation matrix into R (B×nr×3×3) and its principal rotation
    vector, with the other position entries (``other``), put in coordinate order
    (``coords_order``) into ``coords`` (B×nv) — the formulas of
    :func:`tflearn.configspace.quat_to_rotvec` and :func:`~tflearn.configspace.quat_to_rotmat`."""
    B, nr = y.shape[0], quat.shape[0]
    flat = np.empty(3 * nr + other.shape[0])
    for b in range(B):
        for j in range(nr):
            x, yy, z, w = y[b, quat[j, 0]], y[b, quat[j, 1]], y[b, quat[j, 2]], y[b, quat[j, 3]]
            n = np.sqrt(x * x + yy * yy + z * z + w * w)
            x, yy, z, w = x / n, yy / n, z / n, w / n
            quats[b, j, 0], quats[b, j, 1], quats[b, j, 2], quats[b, j, 3] = x, yy, z, w
            R[b, j, 0, 0] = x * x - yy * yy - z * z + w * w
            R[b, j, 0, 1] = 2 * (x * yy - z * w)
            R[b, j, 0, 2] = 2 * (x * z + yy * w)
            R[b, j, 1, 0] = 2 * (x * yy + z * w)
            R[b, j, 1, 1] = -x * x + yy * yy - z * z + w * w
            R[b, j, 1, 2] = 2 * (yy * z - x * w)
            R[b, j, 2, 0] = 2 * (x * z - yy * w)
            R[b, j, 2, 1] = 2 * (yy * z + x * w)
            R[b, j, 2, 2] = -x * x - yy * yy + z * z + w * w
            if not w > 0:                                  # the shortest arc: w > 0
                x, yy, z, w = -x, -yy, -z, -w
            u = np.sqrt(x * x + yy * yy + z * z)
            if u < 1e-3 * w:                               # atan(r)/r by its series
                r2 = (u / w) ** 2
                f = (2 / w) * (1 - r2 / 3 + r2 * r2 / 5 - r2 ** 3 / 7)
            else:
                f = 2 * np.arctan2(u, w) / u
            flat[3 * j], flat[3 * j + 1], flat[3 * j + 2] = f * x, f * yy, f * z
        for k in range(other.shape[0]):
            flat[3 * nr + k] = y[b, other[k]]
        for k in range(coords_order.shape[0]):
            coords[b, k] = flat[coords_order[k]]


@njit(cache=True, fastmath=_FAST)
def position_rate(kind, rot, offset, dof, R, quats, v, position_order, out):
    """:func:`tflearn.configspace.position_rate` for every sample b: q̇ = ½ q ⊗ (ω, 0) per
    rotation joint (ω its first three velocities), θ̇ = v per hinge, ṫ = R u per free
    joint (u its last three), put in the state's order (``position_order``) into ``out``
    (B×n_position); the per-link tables of :func:`aba`."""
    B, nr, L = v.shape[0], quats.shape[1], kind.shape[0]
    flat = np.empty(position_order.shape[0])
    for b in range(B):
        k = 4 * nr
        for i in range(L):
            o = offset[i]
            if kind[i] >= 2:
                j = rot[i]
                x, yy, z, w = quats[b, j, 0], quats[b, j, 1], quats[b, j, 2], quats[b, j, 3]
                w0, w1, w2 = v[b, o], v[b, o + 1], v[b, o + 2]
                flat[4 * j] = 0.5 * (w * w0 + yy * w2 - z * w1)
                flat[4 * j + 1] = 0.5 * (w * w1 + z * w0 - x * w2)
                flat[4 * j + 2] = 0.5 * (w * w2 + x * w1 - yy * w0)
                flat[4 * j + 3] = -0.5 * (x * w0 + yy * w1 + z * w2)
                if kind[i] == 3:
                    for m in range(3):
                        flat[k + m] = (R[b, j, m, 0] * v[b, o + 3] + R[b, j, m, 1] * v[b, o + 4]
                                       + R[b, j, m, 2] * v[b, o + 5])
                    k += 3
            else:
                for m in range(dof[i]):
                    flat[k + m] = v[b, o + m]
                k += dof[i]
        for m in range(position_order.shape[0]):
            out[b, m] = flat[position_order[m]]
