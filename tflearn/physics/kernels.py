"""Compiled (numba) loops of the rigid-body algorithms, for evaluations that need no
gradient: one call per batch instead of hundreds of small tensor operations (those of the
simulator's state are :mod:`tflearn.physics.kernels_state`).

:func:`tflearn.physics.dynamics.forward_dynamics` and ``rnea`` (rotation vectors: the kernel turns
them into rotations, :func:`_rodrigues`) and their ``*_rot`` variants (the rotations given)
hand their recursions to :func:`aba` and :func:`rnea` when no input needs a gradient and the
tensors are float64 on the CPU (:func:`applies`); with a gradient, on another device or
dtype, they run their own torch code (the two agree to 1e-12, tests/test_kernels.py).
The maths is the same, per sample b, with the parent → link motion transform
X_i = [[E, 0], [−E [r]×, E]] (E = (R0 R_joint)ᵀ, r the joint origin) applied by its
blocks rather than as a 6×6 matrix:

    V_i = X_i V_p + S_i q̇_i,   c_i = V_i ×ₘ S_i q̇_i,   Iᴬ_i = I_i,   pᴬ_i = V_i ×* I_i V_i;
    leaves → root: U = Iᴬ_i S_i, D = S_iᵀ U, u = τ_i − S_iᵀ pᴬ_i,
                   Iᵃ = Iᴬ_i − U D⁻¹ Uᵀ, pᵃ = pᴬ_i + Iᵃ c_i + U D⁻¹ u,
                   Iᴬ_p += X_iᵀ Iᵃ X_i, pᴬ_p += X_iᵀ pᵃ;
    root → leaves: a' = X_i A_p + c_i, q̈_i = D⁻¹ (u − Uᵀ a'), A_i = a' + S_i q̈_i,

from V_0, A_0 (B×6: the root's parent). Each joint kind has its own branch, written out
on fixed sizes: a hinge (S = (a, 0)) has a scalar D; a ball joint (S = [1; 0]) has
U = Iᴬ's first three columns and D its top-left 3×3 block (inverted by its adjugate),
so that with Iᴬ = [[D, B], [Bᵀ, C]] only one block of Iᵃ is left,
Iᵃ = [[0, 0], [0, C − Bᵀ D⁻¹ B]], pᵃ = (τ, …), and A_ω = D⁻¹ (u − B a'_v); a free joint
(S = 1₆) has Iᵃ = 0, pᵃ = τ, A = D⁻¹ u (D⁻¹ by Cholesky); a fixed joint passes Iᴬ and
pᴬ on. The root's Iᵃ and pᵃ, having no parent to go to, are not formed. A state that
blew up, or a singular D (:func:`aba` divides as numpy does: no exception), comes out
with non-finite accelerations.

The helpers the loops call are inlined (``inline="always"``) and pass spatial vectors
and transforms as tuples of scalars (kept in registers) rather than through arrays: a
shared function taking many arrays, called as such, cost 0.7 µs more per sample
(reference-counted array structs). Compiled once per machine and kept in numba's
on-disk cache (``cache=True``), in a folder named by a digest of the sources
(:func:`cache_folder`): the first call in a fresh checkout, or after any of them
changed, takes several seconds, later processes load it.
"""
from __future__ import annotations

import hashlib
import os
from functools import lru_cache

import numba
import numpy as np
import torch
from numba import njit

from .body import Body

#: The files (relative to the tflearn package) whose functions numba compiles and caches
#: (:func:`cache_folder`).
CACHE_SOURCES = ("physics/kernels.py", "physics/kernels_state.py", "simulation/simkernel.py")


def cache_folder() -> str:
    """Where numba caches this package's compiled functions: a folder named by a digest
    of :data:`CACHE_SOURCES`, under ``NUMBA_CACHE_DIR`` if that is set, else under this
    package's ``__pycache__``. Numba invalidates a cached function only when its own
    file changes, not when a function it inlines from another file (or a flag defined
    there) does: after kernels.py changed its fast-math flags, tflearn.simulation.simkernel's
    simulator kept running from the cache as compiled with the old ones (the main job's
    stiffnesses 1e-13 from a fresh compile's). A change to any of these files now compiles
    them all afresh. Where that folder cannot be written numba falls back to its own locations."""
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    digest = hashlib.sha256()
    for name in CACHE_SOURCES:
        with open(os.path.join(here, name), "rb") as f:
            digest.update(f.read())
    base = numba.config.CACHE_DIR or os.path.join(here, "__pycache__")
    return os.path.join(base, f"numba-{digest.hexdigest()[:16]}")


def redirect_cache() -> str:
    """Point numba at :func:`cache_folder` for the functions decorated next (numba fixes a
    function's cache location when it is decorated); returns the setting to restore once
    they are, so that other code's numba caches stay where their users put them."""
    previous = numba.config.CACHE_DIR
    numba.config.CACHE_DIR = cache_folder()
    return previous


_NUMBA_CACHE_DIR = redirect_cache()                  # restored at the end of this module


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
    joints (ball, free; −1 for none), first coordinate and parent (int64 arrays)."""
    kind = np.array([_KIND[link.joint] for link in body.links], dtype=np.int64)
    rot = np.where(kind >= 2, np.cumsum(kind >= 2) - 1, -1).astype(np.int64)
    dof = np.array([link.dof for link in body.links], dtype=np.int64)
    offset = np.concatenate([[0], np.cumsum(dof)[:-1]]).astype(np.int64)
    parent = np.array([link.parent for link in body.links], dtype=np.int64)
    return kind, rot, offset, parent


#: LLVM may contract floating-point arithmetic (fused multiply–add), but not reorder it
#: ("reassoc": the code a fresh process compiled and runs then differed from the code it
#: wrote to numba's cache, so a checkout's first run gave other numbers than every later
#: one — a simulation's path in the last bits, a trained stiffness in the third digit;
#: bench/kernel_cache.py checks it) nor assume away NaN/Inf (a blown-up state must still
#: come out non-finite).
_FAST = {"contract", "nsz", "arcp"}


@njit(cache=True, fastmath=_FAST)
def _cholesky_inverse(D, out, L, Linv):
    """out = D⁻¹ for a 6×6 D (SPD, by Cholesky; L, Linv: 6×6 scratch); NaN where D is not
    positive definite."""
    for j in range(6):
        s = D[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            out[:, :] = np.nan
            return
        L[j, j] = np.sqrt(s)
        for i in range(j + 1, 6):
            s = D[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / L[j, j]
    for j in range(6):
        Linv[j, j] = 1.0 / L[j, j]
        for i in range(j + 1, 6):
            s = 0.0
            for k in range(j, i):
                s -= L[i, k] * Linv[k, j]
            Linv[i, j] = s / L[i, i]
    for i in range(6):
        for j in range(6):
            s = 0.0
            for k in range(max(i, j), 6):
                s += Linv[k, i] * Linv[k, j]
            out[i, j] = s


@njit(cache=True, fastmath=_FAST)
def _quat_rotmat(x, y, z, w):
    """R(q) (9 entries, row-major) of a unit quaternion q = (x, y, z, w): the formula of
    :func:`tflearn.physics.configspace.quat_to_rotmat`."""
    return (x * x - y * y - z * z + w * w, 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), -x * x + y * y - z * z + w * w, 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), -x * x - y * y + z * z + w * w)


#: Below this half-angle sinc(h) = sin h / h is taken by its series (roma's threshold).
_SINC_SERIES = 2.0 * np.finfo(np.float64).eps ** (1 / 6)


@njit(cache=True, fastmath=_FAST)
def _rodrigues(x, y, z):
    """exp([v]×) (9 entries, row-major) of a rotation vector v = (x, y, z), through its
    unit quaternion (sinc(h)/2 · v, cos h), h = |v|/2, with sinc(h) = 1 − h²/6 + h⁴/120
    below h = 2ε^⅙: the numerics of :func:`tflearn.physics.configspace.rotvec_to_rotmat` (roma)."""
    h = np.sqrt(x * x + y * y + z * z) / 2
    s = (1 - h * h / 6 + h ** 4 / 120) / 2 if h < _SINC_SERIES else np.sin(h) / h / 2
    return _quat_rotmat(s * x, s * y, s * z, np.cos(h))


@njit(cache=True, fastmath=_FAST, inline="always")
def _frame(i, b, kind, rot, R0, origin, axis, R, q, offset):
    """Link i's E = (R0 J)ᵀ (9 scalars, row-major) and origin r in its parent (3) at sample
    b: the motion transform X_i = [[E, 0], [−E [r]×, E]]. The joint rotation J: a hinge's
    1 + sin θ [a]× + (1 − cos θ)(a aᵀ − 1); a ball or free joint's R[b, rot[i]], or
    exp([ν]×) of its rotation vector in q when R is empty; r + R0 t for a free joint."""
    o, k = offset[i], kind[i]
    if k == 1:
        a0, a1, a2 = axis[i, 0], axis[i, 1], axis[i, 2]
        sn, cs = np.sin(q[b, o]), 1.0 - np.cos(q[b, o])
        J = (1.0 + cs * (a0 * a0 - 1.0), cs * a0 * a1 - sn * a2, cs * a0 * a2 + sn * a1,
             cs * a0 * a1 + sn * a2, 1.0 + cs * (a1 * a1 - 1.0), cs * a1 * a2 - sn * a0,
             cs * a0 * a2 - sn * a1, cs * a1 * a2 + sn * a0, 1.0 + cs * (a2 * a2 - 1.0))
    elif k >= 2 and R.shape[0] == 0:
        J = _rodrigues(q[b, o], q[b, o + 1], q[b, o + 2])
    elif k >= 2:
        j = rot[i]
        J = (R[b, j, 0, 0], R[b, j, 0, 1], R[b, j, 0, 2], R[b, j, 1, 0], R[b, j, 1, 1], R[b, j, 1, 2],
             R[b, j, 2, 0], R[b, j, 2, 1], R[b, j, 2, 2])
    else:
        J = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    j00, j01, j02, j10, j11, j12, j20, j21, j22 = J
    p00, p01, p02 = R0[i, 0, 0], R0[i, 0, 1], R0[i, 0, 2]
    p10, p11, p12 = R0[i, 1, 0], R0[i, 1, 1], R0[i, 1, 2]
    p20, p21, p22 = R0[i, 2, 0], R0[i, 2, 1], R0[i, 2, 2]
    e = (p00 * j00 + p01 * j10 + p02 * j20, p10 * j00 + p11 * j10 + p12 * j20,
         p20 * j00 + p21 * j10 + p22 * j20, p00 * j01 + p01 * j11 + p02 * j21,
         p10 * j01 + p11 * j11 + p12 * j21, p20 * j01 + p21 * j11 + p22 * j21,
         p00 * j02 + p01 * j12 + p02 * j22, p10 * j02 + p11 * j12 + p12 * j22,
         p20 * j02 + p21 * j12 + p22 * j22)
    r0, r1, r2 = origin[i, 0], origin[i, 1], origin[i, 2]
    if k == 3:
        t0, t1, t2 = q[b, o + 3], q[b, o + 4], q[b, o + 5]
        r0 += p00 * t0 + p01 * t1 + p02 * t2
        r1 += p10 * t0 + p11 * t1 + p12 * t2
        r2 += p20 * t0 + p21 * t1 + p22 * t2
    return e, (r0, r1, r2)


@njit(cache=True, fastmath=_FAST, inline="always")
def _store_frame(E, r, i, e, t):
    """E[i] = e (9 scalars, row-major), r[i] = t (3)."""
    E[i, 0, 0], E[i, 0, 1], E[i, 0, 2], E[i, 1, 0], E[i, 1, 1], E[i, 1, 2], \
        E[i, 2, 0], E[i, 2, 1], E[i, 2, 2] = e
    r[i, 0], r[i, 1], r[i, 2] = t


@njit(cache=True, fastmath=_FAST, inline="always")
def _load_frame(E, r, i):
    """(E[i] (9 scalars, row-major), r[i] (3))."""
    return ((E[i, 0, 0], E[i, 0, 1], E[i, 0, 2], E[i, 1, 0], E[i, 1, 1], E[i, 1, 2],
             E[i, 2, 0], E[i, 2, 1], E[i, 2, 2]), (r[i, 0], r[i, 1], r[i, 2]))


@njit(cache=True, fastmath=_FAST, inline="always")
def _row(x, j):
    """x[j] as 6 scalars."""
    return x[j, 0], x[j, 1], x[j, 2], x[j, 3], x[j, 4], x[j, 5]


@njit(cache=True, fastmath=_FAST, inline="always")
def _put(x, j, y):
    """x[j] = y (6 scalars)."""
    x[j, 0], x[j, 1], x[j, 2], x[j, 3], x[j, 4], x[j, 5] = y


@njit(cache=True, fastmath=_FAST, inline="always")
def _add(x, y):
    """x + y (6 scalars each)."""
    return x[0] + y[0], x[1] + y[1], x[2] + y[2], x[3] + y[3], x[4] + y[4], x[5] + y[5]


@njit(cache=True, fastmath=_FAST, inline="always")
def _motion(e, t, x):
    """X x for X = [[E, 0], [−E [r]×, E]] (e = E, t = r) and a motion x = (ω, v):
    (E ω, E (v − r × ω))."""
    e00, e01, e02, e10, e11, e12, e20, e21, e22 = e
    r0, r1, r2 = t
    x0, x1, x2, x3, x4, x5 = x
    w0, w1, w2 = x3 - (r1 * x2 - r2 * x1), x4 - (r2 * x0 - r0 * x2), x5 - (r0 * x1 - r1 * x0)
    return (e00 * x0 + e01 * x1 + e02 * x2, e10 * x0 + e11 * x1 + e12 * x2,
            e20 * x0 + e21 * x1 + e22 * x2, e00 * w0 + e01 * w1 + e02 * w2,
            e10 * w0 + e11 * w1 + e12 * w2, e20 * w0 + e21 * w1 + e22 * w2)


@njit(cache=True, fastmath=_FAST, inline="always")
def _force_back(e, t, f):
    """Xᵀ f for a force f = (n, f): (Eᵀ n + r × Eᵀ f, Eᵀ f)."""
    e00, e01, e02, e10, e11, e12, e20, e21, e22 = e
    r0, r1, r2 = t
    n0, n1, n2, f0, f1, f2 = f
    g0 = e00 * f0 + e10 * f1 + e20 * f2
    g1 = e01 * f0 + e11 * f1 + e21 * f2
    g2 = e02 * f0 + e12 * f1 + e22 * f2
    return (e00 * n0 + e10 * n1 + e20 * n2 + r1 * g2 - r2 * g1,
            e01 * n0 + e11 * n1 + e21 * n2 + r2 * g0 - r0 * g2,
            e02 * n0 + e12 * n1 + e22 * n2 + r0 * g1 - r1 * g0, g0, g1, g2)


@njit(cache=True, fastmath=_FAST, inline="always")
def _joint_motion(i, b, kind, axis, offset, v):
    """S_i v_i (6 scalars) for the rates v at sample b: (a θ̇, 0) for a hinge, (ω, 0) for a
    ball joint, (ω, u) for a free joint, 0 for a fixed one."""
    o, k = offset[i], kind[i]
    if k == 1:
        return axis[i, 0] * v[b, o], axis[i, 1] * v[b, o], axis[i, 2] * v[b, o], 0.0, 0.0, 0.0
    if k == 2:
        return v[b, o], v[b, o + 1], v[b, o + 2], 0.0, 0.0, 0.0
    if k == 3:
        return v[b, o], v[b, o + 1], v[b, o + 2], v[b, o + 3], v[b, o + 4], v[b, o + 5]
    return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0


@njit(cache=True, fastmath=_FAST, inline="always")
def _cross_motion(V, s):
    """V ×ₘ s = (ω × s_ω, ω × s_v + v × s_ω) for motions V = (ω, v) and s."""
    w0, w1, w2, v0, v1, v2 = V
    s0, s1, s2, s3, s4, s5 = s
    return (w1 * s2 - w2 * s1, w2 * s0 - w0 * s2, w0 * s1 - w1 * s0,
            w1 * s5 - w2 * s4 + v1 * s2 - v2 * s1, w2 * s3 - w0 * s5 + v2 * s0 - v0 * s2,
            w0 * s4 - w1 * s3 + v0 * s1 - v1 * s0)


@njit(cache=True, fastmath=_FAST, inline="always")
def _cross_force(V, P):
    """V ×* P = (ω × n + v × f, ω × f) for a motion V = (ω, v) and a force P = (n, f)."""
    w0, w1, w2, v0, v1, v2 = V
    n0, n1, n2, f0, f1, f2 = P
    return (w1 * n2 - w2 * n1 + v1 * f2 - v2 * f1, w2 * n0 - w0 * n2 + v2 * f0 - v0 * f2,
            w0 * n1 - w1 * n0 + v0 * f1 - v1 * f0, w1 * f2 - w2 * f1, w2 * f0 - w0 * f2,
            w0 * f1 - w1 * f0)


@njit(cache=True, fastmath=_FAST, inline="always")
def _rigid_times(inertia, i, x):
    """I x (6 scalars) for a rigid body's spatial inertia I = inertia[i] =
    [[Ī, m [c]×], [m [c]×ᵀ, m 1]] and a motion x = (ω, v): (Ī ω + h × v, m v − h × ω),
    h = m c read off I's upper-right block."""
    m, h0, h1, h2 = inertia[i, 3, 3], inertia[i, 2, 4], inertia[i, 0, 5], inertia[i, 1, 3]
    w0, w1, w2, v0, v1, v2 = x
    return (inertia[i, 0, 0] * w0 + inertia[i, 0, 1] * w1 + inertia[i, 0, 2] * w2 + h1 * v2 - h2 * v1,
            inertia[i, 1, 0] * w0 + inertia[i, 1, 1] * w1 + inertia[i, 1, 2] * w2 + h2 * v0 - h0 * v2,
            inertia[i, 2, 0] * w0 + inertia[i, 2, 1] * w1 + inertia[i, 2, 2] * w2 + h0 * v1 - h1 * v0,
            m * v0 - (h1 * w2 - h2 * w1), m * v1 - (h2 * w0 - h0 * w2), m * v2 - (h0 * w1 - h1 * w0))


@njit(cache=True, fastmath=_FAST, inline="always")
def _rotate(E, i, M, j, ro, co, W, Z, z):
    """Z[z] = Eᵀ N E for the 3×3 block N = M[j, ro:ro+3, co:co+3] (W: 3×3 scratch)."""
    for m in range(3):
        for n in range(3):
            W[m, n] = M[j, ro + m, co] * E[i, 0, n] + M[j, ro + m, co + 1] * E[i, 1, n] \
                + M[j, ro + m, co + 2] * E[i, 2, n]
    for m in range(3):
        for n in range(3):
            Z[z, m, n] = E[i, 0, m] * W[0, n] + E[i, 1, m] * W[1, n] + E[i, 2, m] * W[2, n]


@njit(cache=True, fastmath=_FAST, inline="always")
def _inertia_shift(r, i, Z, full, out, p, W):
    """out[p] += [[A − B Rx − (B Rx)ᵀ − Rx C Rx, B + Rx C], [(B + Rx C)ᵀ, C]], Rx = [r_i]×,
    for the blocks A, B, C = Z[0], Z[1], Z[2] (A = B = 0 unless ``full``): with X_i by its
    blocks, X_iᵀ [[A, B], [Bᵀ, C]] X_i for blocks already turned into the parent's axes
    (Eᵀ A E, …) (W: 3×3 scratch)."""
    r0, r1, r2 = r[i, 0], r[i, 1], r[i, 2]
    for n in range(3):                            # W = Rx C
        W[0, n] = r1 * Z[2, 2, n] - r2 * Z[2, 1, n]
        W[1, n] = r2 * Z[2, 0, n] - r0 * Z[2, 2, n]
        W[2, n] = r0 * Z[2, 1, n] - r1 * Z[2, 0, n]
    for m in range(3):
        t0 = W[m, 1] * r2 - W[m, 2] * r1          # (Rx C Rx)[m, :]
        t1 = W[m, 2] * r0 - W[m, 0] * r2
        t2 = W[m, 0] * r1 - W[m, 1] * r0
        if full:
            t0 += Z[1, m, 1] * r2 - Z[1, m, 2] * r1 - Z[0, m, 0]
            t1 += Z[1, m, 2] * r0 - Z[1, m, 0] * r2 - Z[0, m, 1]
            t2 += Z[1, m, 0] * r1 - Z[1, m, 1] * r0 - Z[0, m, 2]
            for n in range(3):
                W[m, n] += Z[1, m, n]             # B + Rx C
            out[p, 0, m] -= Z[1, m, 1] * r2 - Z[1, m, 2] * r1     # − (B Rx)ᵀ
            out[p, 1, m] -= Z[1, m, 2] * r0 - Z[1, m, 0] * r2
            out[p, 2, m] -= Z[1, m, 0] * r1 - Z[1, m, 1] * r0
        out[p, m, 0] -= t0
        out[p, m, 1] -= t1
        out[p, m, 2] -= t2
    for m in range(3):
        for n in range(3):
            out[p, m, 3 + n] += W[m, n]
            out[p, 3 + n, m] += W[m, n]
            out[p, 3 + m, 3 + n] += Z[2, m, n]


@njit(cache=True, fastmath=_FAST, error_model="numpy")
def aba(kind, rot, R0, origin, axis, offset, parent, inertia, R, q, V0, A0, v, tau, qdd):
    """The articulated-body algorithm (module docstring) for every sample b. Per link i:
    kind (0 fixed, 1 hinge, 2 ball, 3 free), rot (its index in R, −1 for none), R0
    (L×3×3) and origin (L×3) of the joint, axis (L×3, hinges), offset (first
    coordinate), parent (−1 for the root; parents before children), inertia (L×6×6, the
    rigid body's spatial inertia about the link origin, :func:`_rigid_times`); R
    (B×nr×3×3) the rotation joints' rotations, or empty (0×0×3×3) to take them from the
    rotation vectors in q; q, v, tau (B×nv), V0, A0 (B×6, or 1×6 for all samples) → qdd
    (B×nv), written in place."""
    B, L = q.shape[0], kind.shape[0]
    E = np.empty((L, 3, 3))
    r = np.empty((L, 3))
    V = np.empty((L, 6))
    c = np.empty((L, 6))
    A = np.empty((L, 6))
    IA = np.empty((L, 6, 6))
    pA = np.empty((L, 6))
    U = np.empty((L, 6))                                # hinge: Iᴬ S
    Dinv = np.empty((L, 6, 6))                          # hinge: 1 × 1, ball: 3 × 3, free: 6 × 6
    u = np.empty((L, 6))
    Ia = np.empty((1, 6, 6))                            # a hinge's Iᵃ
    W = np.empty((6, 6))
    Z = np.empty((3, 6, 6))
    for b in range(B):
        bv, ba = b if V0.shape[0] > 1 else 0, b if A0.shape[0] > 1 else 0
        for i in range(L):
            p = parent[i]
            e, t = _frame(i, b, kind, rot, R0, origin, axis, R, q, offset)
            _store_frame(E, r, i, e, t)
            s = _joint_motion(i, b, kind, axis, offset, v)
            Vi = _add(_motion(e, t, _row(V0, bv) if p < 0 else _row(V, p)), s)
            _put(V, i, Vi)
            _put(c, i, _cross_motion(Vi, s))
            _put(pA, i, _cross_force(Vi, _rigid_times(inertia, i, Vi)))
            for m in range(6):
                for n in range(6):
                    IA[i, m, n] = inertia[i, m, n]
        for i in range(L - 1, -1, -1):
            k, o, p = kind[i], offset[i], parent[i]
            if k == 2:
                pa = _ball_back(i, b, o, p, E, r, c, IA, pA, Dinv, u, tau, W, Z)
            elif k == 1:
                pa = _hinge_back(i, b, o, p, axis, E, r, c, IA, pA, U, Dinv, u, tau, Ia, W, Z)
            elif k == 3:                                # Iᵃ = 0, pᵃ = τ
                _cholesky_inverse(IA[i], Dinv[i], W, Z[0])
                for m in range(6):
                    u[i, m] = tau[b, o + m] - pA[i, m]
                pa = tau[b, o], tau[b, o + 1], tau[b, o + 2], tau[b, o + 3], tau[b, o + 4], tau[b, o + 5]
            else:                                       # fixed: Iᵃ = Iᴬ, pᵃ = pᴬ
                if p >= 0:
                    _rotate(E, i, IA, i, 0, 0, W, Z, 0)
                    _rotate(E, i, IA, i, 0, 3, W, Z, 1)
                    _rotate(E, i, IA, i, 3, 3, W, Z, 2)
                    _inertia_shift(r, i, Z, True, IA, p, W)
                pa = _row(pA, i)
            if p >= 0:
                e, t = _load_frame(E, r, i)
                _put(pA, p, _add(_row(pA, p), _force_back(e, t, pa)))
        for i in range(L):
            k, o, p = kind[i], offset[i], parent[i]
            e, t = _load_frame(E, r, i)
            a0, a1, a2, a3, a4, a5 = _add(_motion(e, t, _row(A0, ba) if p < 0 else _row(A, p)), _row(c, i))
            if k == 2:                          # A_ω = D⁻¹ (u − B a'_v), q̈ = A_ω − a'_ω
                y0 = u[i, 0] - (IA[i, 0, 3] * a3 + IA[i, 0, 4] * a4 + IA[i, 0, 5] * a5)
                y1 = u[i, 1] - (IA[i, 1, 3] * a3 + IA[i, 1, 4] * a4 + IA[i, 1, 5] * a5)
                y2 = u[i, 2] - (IA[i, 2, 3] * a3 + IA[i, 2, 4] * a4 + IA[i, 2, 5] * a5)
                x0 = Dinv[i, 0, 0] * y0 + Dinv[i, 0, 1] * y1 + Dinv[i, 0, 2] * y2
                x1 = Dinv[i, 1, 0] * y0 + Dinv[i, 1, 1] * y1 + Dinv[i, 1, 2] * y2
                x2 = Dinv[i, 2, 0] * y0 + Dinv[i, 2, 1] * y1 + Dinv[i, 2, 2] * y2
                qdd[b, o], qdd[b, o + 1], qdd[b, o + 2] = x0 - a0, x1 - a1, x2 - a2
                a0, a1, a2 = x0, x1, x2
            elif k == 1:                        # q̈ = (u − Uᵀ a') / D, A = a' + S q̈
                x = (u[i, 0] - (U[i, 0] * a0 + U[i, 1] * a1 + U[i, 2] * a2 + U[i, 3] * a3
                                + U[i, 4] * a4 + U[i, 5] * a5)) * Dinv[i, 0, 0]
                qdd[b, o] = x
                a0, a1, a2 = a0 + axis[i, 0] * x, a1 + axis[i, 1] * x, a2 + axis[i, 2] * x
            elif k == 3:                        # A = D⁻¹ u, q̈ = A − a'
                a = (a0, a1, a2, a3, a4, a5)
                for m in range(6):
                    x = 0.0
                    for n in range(6):
                        x += Dinv[i, m, n] * u[i, n]
                    qdd[b, o + m] = x - a[m]
                    A[i, m] = x
                a0, a1, a2, a3, a4, a5 = _row(A, i)
            _put(A, i, (a0, a1, a2, a3, a4, a5))


@njit(cache=True, fastmath=_FAST, inline="always")
def _ball_back(i, b, o, p, E, r, c, IA, pA, Dinv, u, tau, W, Z):
    """A ball joint's step leaves → root: S = [1; 0], so with Iᴬ = [[D, B], [Bᵀ, C]],
    U = [D; Bᵀ], Iᵃ = [[0, 0], [0, C − Bᵀ D⁻¹ B]] (added to the parent's Iᴬ here) and
    pᵃ = (τ, pᴬ_f + Iᵃ_C c_v + Bᵀ D⁻¹ u) (returned); D⁻¹ (symmetric, by its adjugate)
    and u = τ − pᴬ_n kept for the pass root → leaves."""
    d00, d01, d02 = IA[i, 0, 0], IA[i, 0, 1], IA[i, 0, 2]
    d11, d12, d22 = IA[i, 1, 1], IA[i, 1, 2], IA[i, 2, 2]
    a00, a01, a02 = d11 * d22 - d12 * d12, d02 * d12 - d01 * d22, d01 * d12 - d02 * d11
    a11, a12, a22 = d00 * d22 - d02 * d02, d01 * d02 - d00 * d12, d00 * d11 - d01 * d01
    f = 1.0 / (d00 * a00 + d01 * a01 + d02 * a02)
    Dinv[i, 0, 0], Dinv[i, 1, 1], Dinv[i, 2, 2] = f * a00, f * a11, f * a22
    Dinv[i, 0, 1] = Dinv[i, 1, 0] = f * a01
    Dinv[i, 0, 2] = Dinv[i, 2, 0] = f * a02
    Dinv[i, 1, 2] = Dinv[i, 2, 1] = f * a12
    for m in range(3):
        u[i, m] = tau[b, o + m] - pA[i, m]
    if p < 0:
        return _row(pA, i)                      # the root's: not used
    for m in range(3):                          # W = [D⁻¹ B | D⁻¹ u]
        for n in range(3):
            W[m, n] = Dinv[i, m, 0] * IA[i, 0, 3 + n] + Dinv[i, m, 1] * IA[i, 1, 3 + n] \
                + Dinv[i, m, 2] * IA[i, 2, 3 + n]
        W[m, 3] = Dinv[i, m, 0] * u[i, 0] + Dinv[i, m, 1] * u[i, 1] + Dinv[i, m, 2] * u[i, 2]
    for m in range(3):                          # Iᵃ_C = C − Bᵀ D⁻¹ B into Z[0, 3:, 3:]
        for n in range(3):
            Z[0, 3 + m, 3 + n] = IA[i, 3 + m, 3 + n] - (IA[i, 0, 3 + m] * W[0, n] + IA[i, 1, 3 + m] * W[1, n]
                                                        + IA[i, 2, 3 + m] * W[2, n])
    for m in range(3):                          # pᵃ_f into W[3]
        W[3, m] = pA[i, 3 + m] + IA[i, 0, 3 + m] * W[0, 3] + IA[i, 1, 3 + m] * W[1, 3] \
            + IA[i, 2, 3 + m] * W[2, 3] + Z[0, 3 + m, 3] * c[i, 3] + Z[0, 3 + m, 4] * c[i, 4] \
            + Z[0, 3 + m, 5] * c[i, 5]
    _rotate(E, i, Z, 0, 3, 3, W, Z, 2)
    _inertia_shift(r, i, Z, False, IA, p, W)
    return tau[b, o], tau[b, o + 1], tau[b, o + 2], W[3, 0], W[3, 1], W[3, 2]


@njit(cache=True, fastmath=_FAST, inline="always")
def _hinge_back(i, b, o, p, axis, E, r, c, IA, pA, U, Dinv, u, tau, Ia, W, Z):
    """A hinge's step leaves → root: S = (a, 0), U = Iᴬ S, D = aᵀ U_n (scalar),
    u = τ − aᵀ pᴬ_n, Iᵃ = Iᴬ − U Uᵀ / D (added to the parent's Iᴬ here),
    pᵃ = pᴬ + Iᵃ c + U u / D (returned)."""
    a0, a1, a2 = axis[i, 0], axis[i, 1], axis[i, 2]
    for m in range(6):
        U[i, m] = IA[i, m, 0] * a0 + IA[i, m, 1] * a1 + IA[i, m, 2] * a2
    dinv = 1.0 / (a0 * U[i, 0] + a1 * U[i, 1] + a2 * U[i, 2])
    Dinv[i, 0, 0] = dinv
    u[i, 0] = tau[b, o] - (a0 * pA[i, 0] + a1 * pA[i, 1] + a2 * pA[i, 2])
    if p < 0:
        return _row(pA, i)                      # the root's: not used
    for m in range(6):
        for n in range(6):
            Ia[0, m, n] = IA[i, m, n] - U[i, m] * U[i, n] * dinv
    for m in range(6):                          # pᵃ into W[3]
        x = pA[i, m] + U[i, m] * u[i, 0] * dinv
        for n in range(6):
            x += Ia[0, m, n] * c[i, n]
        W[3, m] = x
    _rotate(E, i, Ia, 0, 0, 0, W, Z, 0)
    _rotate(E, i, Ia, 0, 0, 3, W, Z, 1)
    _rotate(E, i, Ia, 0, 3, 3, W, Z, 2)
    _inertia_shift(r, i, Z, True, IA, p, W)
    return _row(W, 3)


@njit(cache=True, fastmath=_FAST)
def rnea(kind, rot, R0, origin, axis, offset, parent, inertia, R, q, V0, A0, v, a, tau):
    """Recursive Newton–Euler inverse dynamics for every sample b (the arguments of
    :func:`aba`, with accelerations a in place of torques; tau (B×nv) written in place):

        V_i = X_i V_p + S_i q̇_i,  A_i = X_i A_p + S_i q̈_i + V_i ×ₘ S_i q̇_i,
        F_i = I_i A_i + V_i ×* I_i V_i;   leaves → root: τ_i = S_iᵀ F_i, F_p += X_iᵀ F_i."""
    B, L = q.shape[0], kind.shape[0]
    E = np.empty((L, 3, 3))
    r = np.empty((L, 3))
    V = np.empty((L, 6))
    A = np.empty((L, 6))
    F = np.empty((L, 6))
    for b in range(B):
        bv, ba = b if V0.shape[0] > 1 else 0, b if A0.shape[0] > 1 else 0
        for i in range(L):
            p = parent[i]
            e, t = _frame(i, b, kind, rot, R0, origin, axis, R, q, offset)
            _store_frame(E, r, i, e, t)
            s = _joint_motion(i, b, kind, axis, offset, v)
            Vi = _add(_motion(e, t, _row(V0, bv) if p < 0 else _row(V, p)), s)
            Ai = _add(_add(_motion(e, t, _row(A0, ba) if p < 0 else _row(A, p)),
                           _joint_motion(i, b, kind, axis, offset, a)), _cross_motion(Vi, s))
            _put(V, i, Vi)
            _put(A, i, Ai)
            _put(F, i, _add(_rigid_times(inertia, i, Ai), _cross_force(Vi, _rigid_times(inertia, i, Vi))))
        for i in range(L - 1, -1, -1):
            k, o, p = kind[i], offset[i], parent[i]
            if k == 1:
                tau[b, o] = axis[i, 0] * F[i, 0] + axis[i, 1] * F[i, 1] + axis[i, 2] * F[i, 2]
            elif k >= 2:
                for m in range(3 if k == 2 else 6):
                    tau[b, o + m] = F[i, m]
            if p >= 0:
                e, t = _load_frame(E, r, i)
                _put(F, p, _add(_row(F, p), _force_back(e, t, _row(F, i))))


numba.config.CACHE_DIR = _NUMBA_CACHE_DIR
