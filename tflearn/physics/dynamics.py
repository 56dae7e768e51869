"""Batched, differentiable rigid-body algorithms on a :class:`~tflearn.physics.body.Body`.

Every function accepts any leading batch shape ``...`` and works in the input's dtype
(float64 throughout tflearn). Coordinates ``q`` (...×nv) are rotation vectors for ball
joints, angles for hinges and (rotation vector, translation) for free joints; velocities
``v``, accelerations ``a`` and torques ``tau`` (...×nv) follow the layout described in
:mod:`tflearn.physics.body`.

Spatial quantities are 6-vectors (angular, linear) in each link's frame (Featherstone's
body-frame formulation), moved between frames by 6×6 motion transforms X (forces by
Xᵀ); internally the batch is flattened to one dimension so that every product is a
single ``bmm`` or ``mm``. Algorithms:

* :func:`rnea` — inverse dynamics τ = M(q) a + h(q, v) (recursive Newton–Euler),
* :func:`mass_matrix` — M(q) by the composite-rigid-body algorithm,
* :func:`bias_forces` — h(q, v) = τ(q, v, 0) (Coriolis, centrifugal, gravity),
* :func:`forward_dynamics` — a = M⁻¹(τ − h) by the articulated-body algorithm, O(links),
* :func:`forward_kinematics` — world rotations and joint positions, hand tip last,
* :func:`point_jacobian` — the world-aligned Jacobian of a point on a link (for
  external forces: τ = Jᵀ (f, m)); :func:`points_kinematics_rot` for many points at once,
* :func:`kinetic_energy`, :func:`potential_energy`.

The ``*_rot`` variants take the joints' own rotations (a list with one ...×3×3 matrix per
link, ``None`` for hinges and fixed joints, from which the hinge angle is read in ``q``)
so that :mod:`tflearn.simulation.simulate` can drive them from quaternions.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
import torch
import torch.nn.functional as F

from . import kernels
from .body import Body
from .configspace import hat, joint_rotations, rotvec_to_rotmat


@lru_cache(maxsize=64)
def _constants(body: Body, dtype: torch.dtype, device: torch.device) -> dict:
    """Per-link constant tensors: joint origins, zero orientations, axes, inertias, and
    for the spatial recursions each link's 6×6 spatial inertia about its origin, its
    motion subspace S (6×dof) and the tables of its motion transform (:func:`_transforms`)."""
    def t(x):
        return torch.as_tensor(x, dtype=dtype, device=device)
    C = {"origin": [t(l.origin) for l in body.links],
         "R0": [rotvec_to_rotmat(t(l.offset)) for l in body.links],
         "axis": [t(l.axis) for l in body.links],
         "mass": [float(l.mass) for l in body.links],
         "com": [t(l.com) for l in body.links],
         "Ic": [t(l.inertia) for l in body.links],
         "gravity": t(body.gravity),
         "tip": t(body.tip_point)}
    C["hat_axis"] = [hat(a) for a in C["axis"]]
    C["inertia6"] = [_spatial_inertia(m, c, I) for m, c, I in zip(C["mass"], C["com"], C["Ic"])]
    C["S"] = [_motion_subspace(l.joint, a) for l, a in zip(body.links, C["axis"])]
    C["X"] = [_transform_table(l.joint, R0, hat(r), K)
              for l, R0, r, K in zip(body.links, C["R0"], C["origin"], C["hat_axis"])]
    return C


def _spatial_inertia(m: float, c: torch.Tensor, Ic: torch.Tensor) -> torch.Tensor:
    """I = [[Ic + m [c]×[c]×ᵀ, m [c]×], [m [c]×ᵀ, m 1]] (6×6): a link's spatial inertia
    about its frame origin, for (angular, linear) motion vectors."""
    H = hat(c)
    eye = torch.eye(3, dtype=c.dtype, device=c.device)
    return torch.cat([torch.cat([Ic + m * H @ H.T, m * H], -1),
                      torch.cat([m * H.T, m * eye], -1)], -2)


def _motion_subspace(joint: str, axis: torch.Tensor) -> torch.Tensor:
    """S (6×dof): the spatial velocity (ω, v) of the child frame per unit joint rate —
    [1; 0] for a ball joint, [a; 0] for a hinge, 1₆ for a free joint (ω, u), none fixed."""
    eye = torch.eye(6, dtype=axis.dtype, device=axis.device)
    if joint == "ball":
        return eye[:, :3]
    if joint == "hinge":
        return torch.cat([axis, torch.zeros_like(axis)])[:, None]
    if joint == "free":
        return eye
    return eye[:, :0]


def _transform(R0: torch.Tensor, H: torch.Tensor, Rj: torch.Tensor) -> torch.Tensor:
    """X = [[E, 0], [−E H, E]] (...×6×6), E = (R0 Rj)ᵀ: the spatial motion transform from a
    parent to a link whose frame is R0 Rj relative to it, at origin r ([r]× = H); linear
    in the joint rotation Rj."""
    E = (R0 @ Rj).transpose(-1, -2)
    return torch.cat([torch.cat([E, torch.zeros_like(E)], -1), torch.cat([-E @ H, E], -1)], -2)


def _transform_table(joint: str, R0, H, K):
    """What :func:`_transforms` needs to build a link's X with few operations: for a
    ball joint the 9×36 matrix W with vec(X) = vec(Rj) W (X is linear in Rj); for a
    hinge (Rj = 1 + sin θ K + (1 − cos θ) K²) the three 6×6 terms of
    X = X₀ + sin θ X_s + (1 − cos θ) X_c; for a fixed joint X itself; none for a free
    joint, whose origin moves with its coordinates."""
    eye = torch.eye(3, dtype=R0.dtype, device=R0.device)
    if joint == "free":
        return None
    if joint == "ball":
        units = torch.eye(9, dtype=R0.dtype, device=R0.device).reshape(9, 3, 3)
        return _transform(R0, H, units).reshape(9, 36)
    if joint == "hinge":
        return tuple(_transform(R0, H, M) for M in (eye, K, K @ K))
    return _transform(R0, H, eye)


def _bmv(X: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """X x for B matrices (B×k×m) and vectors (B×m)."""
    return torch.bmm(X, x.unsqueeze(-1)).squeeze(-1)


def _bmtv(X: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Xᵀ x (B×m) for B×k×m matrices and B×k vectors."""
    return torch.bmm(x.unsqueeze(1), X).squeeze(1)


def _mv(E, x):
    """E x for matrices (...×k×m, broadcast) and vectors (...×m)."""
    return (E @ x.unsqueeze(-1)).squeeze(-1)


def _inertia_to_parent(X: torch.Tensor, inertia: torch.Tensor) -> torch.Tensor:
    """Xᵀ I X (B×6×6): a spatial inertia in a link's frame seen from its parent's."""
    return X.transpose(-1, -2) @ inertia @ X


def _crm(V: torch.Tensor, s: torch.Tensor, linear: bool = False) -> torch.Tensor:
    """V ×ₘ s = (ω × s_ω, ω × s_v + v × s_ω): the spatial cross product of two motion
    vectors (B×6 each, V = (ω, v)); ``linear`` False when s_v = 0."""
    B = V.shape[0]
    out = torch.cross(V.view(B, 2, 3), s[:, None, :3].expand(B, 2, 3), dim=-1).reshape(B, 6)
    if linear:
        out = out + F.pad(torch.cross(V[:, :3], s[:, 3:], dim=-1), (3, 0))
    return out


def _crf(V: torch.Tensor, P: torch.Tensor) -> torch.Tensor:
    """V ×* P = (ω × n + v × f, ω × f): a motion vector V = (ω, v) acting on a force
    vector P = (n, f) (B×6 each)."""
    B = V.shape[0]
    out = torch.cross(V[:, None, :3].expand(B, 2, 3), P.view(B, 2, 3), dim=-1).reshape(B, 6)
    return out + F.pad(torch.cross(V[:, 3:], P[:, 3:], dim=-1), (0, 3))


def _spd_inverse(D: torch.Tensor) -> torch.Tensor:
    """D⁻¹ for symmetric positive definite B×k×k matrices: 1/D for k = 1, the adjugate
    over the determinant for k = 3 (cofactor rows r₁×r₂, r₂×r₀, r₀×r₁), Cholesky
    otherwise (a LinAlgError where D is not positive definite)."""
    k = D.shape[-1]
    if k == 1:
        return 1.0 / D
    if k == 3:
        cof = torch.cross(D.roll(-1, dims=-2), D.roll(1, dims=-2), dim=-1)
        return cof / (D[:, :1, :] * cof[:, :1, :]).sum(-1, keepdim=True)
    return torch.cholesky_inverse(torch.linalg.cholesky(D))


def _flatten(rots: list, *xs: torch.Tensor):
    """Broadcast joint rotations (...×3×3) and vectors (...×k) to their common batch
    shape and flatten it: (batch shape, rotations B×3×3, vectors B×k)."""
    rots, *xs = _broadcast(rots, *xs)
    return (xs[0].shape[:-1], [None if R is None else R.reshape(-1, 3, 3) for R in rots],
            *(x.reshape(-1, x.shape[-1]) for x in xs))


def _broadcast(rots: list, *xs: torch.Tensor):
    """Expand joint rotations and vectors (...×k) to their common batch shape."""
    batch = torch.broadcast_shapes(*(x.shape[:-1] for x in xs),
                                   *(R.shape[:-2] for R in rots if R is not None))
    rots = [None if R is None else R.expand(batch + (3, 3)) for R in rots]
    return (rots, *(x.expand(batch + x.shape[-1:]) for x in xs))


def _per_sample(x, batch, B: int) -> torch.Tensor:
    """A 3-vector (3 or ...×3, broadcast to ``batch``) as B×3."""
    return x.expand(batch + (3,)).reshape(B, 3)


def _relative_rotations(body: Body, rots: list, q: torch.Tensor) -> list:
    """R_i = R0_i · R_joint,i: each link frame relative to its parent (...×3×3); a hinge's
    by Rodrigues, R_joint = 1 + sin θ [a]× + (1 − cos θ)[a]×²."""
    C = _constants(body, q.dtype, q.device)
    out = []
    for i, link in enumerate(body.links):
        R0 = C["R0"][i]
        if link.joint in ("ball", "free"):
            out.append(R0 @ rots[i])
        elif link.joint == "hinge":
            th, K = q[..., body.slice(i)][..., None], C["hat_axis"][i]
            out.append(R0 + R0 @ (torch.sin(th) * K + (1 - torch.cos(th)) * (K @ K)))
        else:
            out.append(R0.expand(q.shape[:-1] + (3, 3)))
    return out


def _joint_origin(body: Body, i: int, q: torch.Tensor) -> torch.Tensor:
    """Link i's origin in its parent's frame: the joint origin r, or r + R0 t for a free
    joint (3, or ...×3 for a free joint)."""
    C = _constants(body, q.dtype, q.device)
    if body.links[i].joint != "free":
        return C["origin"][i]
    return C["origin"][i] + _mv(C["R0"][i], q[..., body.slice(i)][..., 3:])


def _transforms(body: Body, rots: list, q: torch.Tensor) -> list:
    """Spatial motion transforms parent → link i (B×6×6) on (angular, linear) vectors,
        X_i = [[E, 0], [−E [r]×, E]],   E = R_iᵀ, r the joint origin in the parent
    (ω_i = E ω_p, v_i = E(v_p + ω_p × r)); a force (n, f) goes back to the parent as
    X_iᵀ. Built from the tables of :func:`_transform_table`; a free joint's by
    :func:`_transform` at its moving origin r + R0 t. rots (B×3×3), q (B×nv)."""
    C = _constants(body, q.dtype, q.device)
    B, out = q.shape[0], []
    for i, link in enumerate(body.links):
        T = C["X"][i]
        if link.joint == "ball":
            X = (rots[i].reshape(B, 9) @ T).view(B, 6, 6)
        elif link.joint == "free":
            X = _transform(C["R0"][i], hat(_joint_origin(body, i, q)), rots[i])
        elif link.joint == "hinge":
            th = q[:, body.slice(i), None]
            X = T[0] + torch.sin(th) * T[1] + (1 - torch.cos(th)) * T[2]
        else:
            X = T.expand(B, 6, 6)
        out.append(X)
    return out


def _root_motion(B: int, g: torch.Tensor, base):
    """The root's parent: spatial velocity V_0 (None for a fixed base: zero) and
    acceleration A_0 (B×6), (0, −g) for a fixed base, (ω_b, 0) and (ω̇_b, a_b − g) for a
    moving one; g and the base terms B×3."""
    if base is None:
        return None, F.pad(-g, (3, 0))
    w, dw, a = base
    return F.pad(w, (0, 3)), torch.cat([dw, a - g], -1)


def _gravity(body: Body, q: torch.Tensor, gravity) -> torch.Tensor:
    """g (3 or ...×3): True → the body's, False → zero, or the tensor given."""
    if isinstance(gravity, torch.Tensor):
        return gravity
    g = _constants(body, q.dtype, q.device)["gravity"]
    return g if gravity else torch.zeros_like(g)


def _prepare(body: Body, rots: list, q, x, y, gravity, base):
    """Flatten the batch and build what both recursions start from: (batch shape, X
    (list of B×6×6), q̇ (B×nv), the second vector (B×nv), V_0, A_0)."""
    batch, rots, q, x, y = _flatten(rots, q, x, y)
    B = q.shape[0]
    g = _per_sample(_gravity(body, q, gravity), batch, B)
    if base is not None:
        base = tuple(_per_sample(b, batch, B) for b in base)
    return (batch, _transforms(body, rots, q), x, y) + _root_motion(B, g, base)


def _velocities(body: Body, X: list, v: torch.Tensor, V0):
    """V_i = X_i V_p + S_i q̇_i and the joint motion s_i = S_i q̇_i (B×6 each)."""
    C = _constants(body, v.dtype, v.device)
    V, s = [], []
    for i, link in enumerate(body.links):
        s.append(v[:, body.slice(i)] @ C["S"][i].T)
        Vp = V0 if link.parent < 0 else V[link.parent]
        V.append(s[i] if Vp is None else _bmv(X[i], Vp) + s[i])
    return V, s


def rnea_rot(body: Body, rots: list, q: torch.Tensor, v: torch.Tensor, a: torch.Tensor,
             gravity=True, base=None) -> torch.Tensor:
    """Recursive Newton–Euler inverse dynamics, τ = M(q)a + C(q,v)v + g(q).

    Spatial (angular, linear) vectors in each link's frame (Featherstone), X_i the
    parent → link transform (:func:`_transforms`), S_i the motion subspace
    (ω = S q̇; for a free joint (ω, u)), I_i the spatial inertia about the link origin:
        V_i = X_i V_p + S_i q̇_i,      A_i = X_i A_p + S_i q̈_i + V_i ×ₘ S_i q̇_i,
        F_i = I_i A_i + V_i ×* I_i V_i,
    backwards τ_i = S_iᵀ F_i and F_p += X_iᵀ F_i. The root's parent has V_0 = 0,
    A_0 = (0, −g) (``gravity``: True for the body's g, False for none, or a ...×3 tensor
    of per-batch gravity vectors). A moving base (``base`` = (ω_b, ω̇_b, a_b), ...×3 each,
    in the base frame: its angular velocity, angular acceleration and the classical
    acceleration of its origin) enters as V_0 = (ω_b, 0), A_0 = (ω̇_b, a_b − g): the
    torques seen in the inertial frame moving with the base origin's velocity at that
    instant (Galilean invariance). Without a gradient to carry, on float64 CPU tensors,
    the recursions run compiled (:func:`tflearn.physics.kernels.rnea`).
    """
    if kernels.applies(*rots, q, v, a, gravity, *(base or ())):
        return _compiled_call("rnea", body, rots, q, v, a, gravity, base)
    C = _constants(body, q.dtype, q.device)
    batch, X, v, a, V0, A0 = _prepare(body, rots, q, v, a, gravity, base)
    V, s = _velocities(body, X, v, V0)
    Fs, A = [], []
    for i, link in enumerate(body.links):
        Ap = A0 if link.parent < 0 else A[link.parent]
        A.append(_bmv(X[i], Ap) + a[:, body.slice(i)] @ C["S"][i].T
                 + _crm(V[i], s[i], link.joint == "free"))
        I6 = C["inertia6"][i]                      # symmetric: I x = x I
        Fs.append(A[i] @ I6 + _crf(V[i], V[i] @ I6))
    tau = [None] * len(body.links)
    for i in reversed(range(len(body.links))):
        tau[i] = Fs[i] @ C["S"][i]
        p = body.links[i].parent
        if p >= 0:
            Fs[p] = Fs[p] + _bmtv(X[i], Fs[i])
    return torch.cat(tau, dim=-1).reshape(batch + (body.nv,))


def mass_matrix_rot(body: Body, rots: list, q: torch.Tensor) -> torch.Tensor:
    """M(q) (...×nv×nv) by the composite-rigid-body algorithm (CRBA):
        I^c_i = I_i + Σ_children X_cᵀ I^c_c X_c   (leaves → root),
        M_ii = S_iᵀ I^c_i S_i,   and for each ancestor j of i, with F carried up by
        F ← X_kᵀ F from F = I^c_i S_i:   M_ji = S_jᵀ F = M_ijᵀ;
    blocks of joints on different branches are zero."""
    C = _constants(body, q.dtype, q.device)
    batch, rots, q = _flatten(rots, q)
    X = _transforms(body, rots, q)
    links = body.links
    Ic = list(C["inertia6"])
    for i in reversed(range(len(links))):
        if links[i].parent >= 0:
            Ic[links[i].parent] = Ic[links[i].parent] + _inertia_to_parent(X[i], Ic[i])
    blocks = {}
    for i in range(len(links)):
        S = C["S"][i]
        F = (Ic[i] @ S).expand(q.shape[:1] + S.shape)
        blocks[i, i] = S.T @ F
        j = i
        while links[j].parent >= 0:
            F = X[j].transpose(-1, -2) @ F
            j = links[j].parent
            blocks[j, i] = C["S"][j].T @ F
            blocks[i, j] = blocks[j, i].transpose(-1, -2)
    idx = range(len(links))
    M = torch.cat([torch.cat([blocks.get((r, c), q.new_zeros(q.shape[:1] + (links[r].dof, links[c].dof)))
                              for c in idx], -1) for r in idx], -2)
    return (0.5 * (M + M.transpose(-1, -2))).reshape(batch + (body.nv, body.nv))


def forward_dynamics_rot(body: Body, rots: list, q: torch.Tensor, v: torch.Tensor,
                         tau: torch.Tensor, gravity=None, base=None) -> torch.Tensor:
    """a = M(q)⁻¹ (τ − h(q, v)) by the articulated-body algorithm (ABA), O(links).

    With V_i, s_i = S_i q̇_i as in :func:`rnea_rot`, c_i = V_i ×ₘ s_i:
        leaves → root: Iᴬ_i = I_i + Σ_children X_cᵀ Iᵃ_c X_c,
                       pᴬ_i = V_i ×* I_i V_i + Σ_children X_cᵀ pᵃ_c,
                       U_i = Iᴬ_i S_i,  D_i = S_iᵀ U_i,  u_i = τ_i − S_iᵀ pᴬ_i,
                       Iᵃ_i = Iᴬ_i − U_i D_i⁻¹ U_iᵀ,  pᵃ_i = pᴬ_i + Iᵃ_i c_i + U_i D_i⁻¹ u_i;
        root → leaves: a'_i = X_i A_p + c_i,  q̈_i = D_i⁻¹ (u_i − U_iᵀ a'_i),
                       A_i = a'_i + S_i q̈_i,
    from A_0 = (0, −g) (``gravity``: ...×3, default the body's) or a moving ``base``
    (see :func:`rnea_rot`). D_i (SPD) is inverted in closed form (:func:`_spd_inverse`);
    a state that blew up gives non-finite accelerations. Without a gradient to carry, on
    float64 CPU tensors, the recursions run compiled (:func:`tflearn.physics.kernels.aba`).
    """
    if kernels.applies(*rots, q, v, tau, gravity, *(base or ())):
        return _compiled_call("aba", body, rots, q, v, tau, True if gravity is None else gravity, base)
    C = _constants(body, q.dtype, q.device)
    batch, X, v, tau, V0, A0 = _prepare(body, rots, q, v, tau,
                                        True if gravity is None else gravity, base)
    V, s = _velocities(body, X, v, V0)
    n = len(body.links)
    c = [_crm(V[i], s[i], body.links[i].joint == "free") for i in range(n)]
    IA = list(C["inertia6"])                             # 6×6 until a child adds to it
    pA = [_crf(V[i], V[i] @ IA[i]) for i in range(n)]
    K = [None] * n                                       # (D⁻¹ Uᵀ, D⁻¹ u) per link
    for i in reversed(range(n)):
        S, Ia = C["S"][i], IA[i]
        pa = pA[i] + (c[i] @ Ia if Ia.ndim == 2 else _bmv(Ia, c[i]))
        if S.shape[-1]:
            U = (Ia @ S).expand(X[i].shape[:1] + S.shape)
            Dinv = _spd_inverse(U.transpose(-1, -2) @ S)
            K[i] = (Dinv @ U.transpose(-1, -2), _bmv(Dinv, tau[:, body.slice(i)] - pA[i] @ S))
            Ia = Ia - U @ K[i][0]
            pa = pa + _bmv(U, K[i][1] - _bmv(K[i][0], c[i]))
        p = body.links[i].parent
        if p >= 0:
            IA[p] = IA[p] + _inertia_to_parent(X[i], Ia)
            pA[p] = pA[p] + _bmtv(X[i], pa)
    A, qdd = [], []
    for i, link in enumerate(body.links):
        a = _bmv(X[i], A0 if link.parent < 0 else A[link.parent]) + c[i]
        if K[i] is not None:
            qdd.append(K[i][1] - _bmv(K[i][0], a))
            a = a + qdd[-1] @ C["S"][i].T
        A.append(a)
    return torch.cat(qdd, dim=-1).reshape(batch + (body.nv,))


@lru_cache(maxsize=64)
def _kernel_tables(body: Body) -> tuple:
    """The body's constants for :func:`tflearn.physics.kernels.aba`, per link: joint kind, index
    among the rotation joints, R0, origin, axis, first coordinate, parent, spatial inertia."""
    C = _constants(body, torch.float64, torch.device("cpu"))
    kind, rot, offset, parent = kernels.link_tables(body)
    stack = lambda xs: np.ascontiguousarray(np.stack([x.numpy() for x in xs]))
    return (kind, rot, stack(C["R0"]), stack(C["origin"]), stack(C["axis"]), offset, parent,
            stack(C["inertia6"]))


def _compiled_call(name: str, body: Body, rots, q, v, x, gravity, base) -> torch.Tensor:
    """:func:`tflearn.physics.kernels.aba` (x = τ → q̈) or :func:`tflearn.physics.kernels.rnea` (x = q̈ → τ),
    (...×nv); ``rots`` the joint rotations, or None for the kernel to compute them from
    the rotation vectors in q. The arrays go to the kernel as numpy views, with few torch
    operations: a call at batch 1 is then mostly the kernel itself."""
    given = [] if rots is None else rots
    if v.shape == q.shape == x.shape and all(R is None or R.shape[:-2] == q.shape[:-1] for R in given):
        batch = q.shape[:-1]                             # nothing to broadcast (the simulator)
        given = [None if R is None else R.reshape(-1, 3, 3) for R in given]
        q, v, x = (y.reshape(-1, y.shape[-1]) for y in (q, v, x))
    else:
        batch, given, q, v, x = _flatten(given, q, v, x)
    B = q.shape[0]
    if base is None and not isinstance(gravity, torch.Tensor):
        root = _kernel_root(body, bool(gravity))         # the same V_0, A_0 for every sample
    else:
        V0, A0 = _root_motion(B, _per_sample(_gravity(body, q, gravity), batch, B),
                              None if base is None else tuple(_per_sample(b, batch, B) for b in base))
        root = (np.zeros((1, 6)) if V0 is None else kernels.as_numpy(V0), kernels.as_numpy(A0))
    R = [kernels.as_numpy(y) for y in given if y is not None]
    R = np.ascontiguousarray(np.stack(R, 1)) if R else np.zeros((0, 0, 3, 3))
    out = np.empty((B, body.nv))
    q, v, x = (kernels.as_numpy(y) for y in (q, v, x))
    getattr(kernels, name)(*_kernel_tables(body), R, q, *root, v, x, out)
    return torch.from_numpy(out).reshape(batch + (body.nv,))


@lru_cache(maxsize=128)
def _kernel_root(body: Body, gravity: bool) -> tuple:
    """V_0 = 0 and A_0 = (0, −g) (1×6 each) of a fixed base, g the body's or none."""
    g = np.asarray(body.gravity, dtype=np.float64) if gravity else np.zeros(3)
    return np.zeros((1, 6)), np.concatenate([np.zeros(3), -g])[None]


def forward_kinematics_rot(body: Body, rots: list, q: torch.Tensor):
    """World rotations (list of ...×3×3) and positions of joint origins plus the tip.

    R_i = R_p R_rel,i, x_i = x_p + R_p r_i (r_i = origin + R0 t for a free joint); the
    tip is x_t + R_t · tip_point.
    Returns (rotations, positions) with positions ...×(n_links+1)×3, tip last.
    """
    C = _constants(body, q.dtype, q.device)
    rots, q = _broadcast(rots, q)
    Rrel = _relative_rotations(body, rots, q)
    Rw, xw = [], []
    for i, link in enumerate(body.links):
        r = _joint_origin(body, i, q)
        if link.parent < 0:
            Rw.append(Rrel[i])
            xw.append(r.expand(q.shape[:-1] + (3,)))
        else:
            p = link.parent
            Rw.append(Rw[p] @ Rrel[i])
            xw.append(xw[p] + _mv(Rw[p], r.expand(q.shape[:-1] + (3,))))
    t = body.tip_link
    tip = xw[t] + _mv(Rw[t], C["tip"].expand(q.shape[:-1] + (3,)))
    return Rw, torch.stack(xw + [tip], dim=-2)


def _ancestors(body: Body, link: int) -> list[int]:
    """Link indices from ``link`` up to the root (``link`` first)."""
    chain = []
    while link >= 0:
        chain.append(link)
        link = body.links[link].parent
    return chain


def point_jacobian_rot(body: Body, rots: list, q: torch.Tensor, link: int,
                       point) -> torch.Tensor:
    """J(q) (...×6×nv) of a point fixed in a link, axes world-aligned, rows (linear, angular)
    — Pinocchio's LOCAL_WORLD_ALIGNED frame Jacobian at that point; one point of
    :func:`points_jacobian_rot`."""
    pt = torch.as_tensor(point, dtype=q.dtype, device=q.device)
    return points_kinematics_rot(body, rots, q, [link], pt[None])[1][..., 0, :, :]


def points_kinematics_rot(body: Body, rots: list, q: torch.Tensor, links, points):
    """(p (...×P×3), J (...×P×6×nv)): the world positions of P points, point k fixed in
    link ``links[k]`` at ``points[k]`` (P×3, link frame), and their Jacobians, axes
    world-aligned, rows (linear, angular); one kinematics pass.

    A unit rate of joint j's coordinate d (j the link or an ancestor; S_d = e_d for a ball
    joint or a free joint's rotation, the axis for a hinge) turns the subtree with world
    angular velocity ω = R_j S_d (R_j the world rotation of link j's frame) about the
    joint origin x_j, so
        J_ang[:, d] = R_j S_d,     J_lin[:, d] = ω × (p − x_j);
    a free joint's translation rate d moves it rigidly: J_lin[:, d] = R_j e_d, J_ang = 0;
    joints that do not carry the link give zero columns. A force f and moment m applied
    at the point act on the joints as τ = Jᵀ (f, m) (the dual of ẋ = J v).
    """
    C = _constants(body, q.dtype, q.device)
    n = len(body.links)
    links = [k % n for k in links]
    Rw, x = forward_kinematics_rot(body, rots, q)
    batch = x.shape[:-2]
    zero = torch.zeros(batch + (3, 3), dtype=q.dtype, device=q.device)
    ang, lin, org, carried = [], [], [], []
    for j, l in enumerate(body.links):
        if l.joint == "fixed":
            continue
        axes = _mv(Rw[j], C["axis"][j]).unsqueeze(-1) if l.joint == "hinge" else Rw[j]
        ang.append(axes)
        lin.append(torch.zeros_like(axes))
        if l.joint == "free":
            ang.append(zero)
            lin.append(Rw[j])
        org.append(x[..., j, :, None].expand(batch + (3, l.dof)))
        carried += [[j in _ancestors(body, k) for k in links]] * l.dof
    A, Lin, O = (torch.cat(z, dim=-1).unsqueeze(-3) for z in (ang, lin, org))   # ...×1×3×nv
    pts = torch.as_tensor(points, dtype=q.dtype, device=q.device)
    Rl = torch.stack([Rw[k] for k in links], dim=-3)                             # ...×P×3×3
    p = x[..., links, :] + _mv(Rl, pts.expand(batch + pts.shape))                # ...×P×3
    arm = (p.unsqueeze(-1) - O).expand(batch + (len(links), 3, body.nv))
    mask = torch.as_tensor(carried, device=q.device).T.unsqueeze(-2)            # P×1×nv
    J_lin = torch.where(mask, torch.cross(A.expand_as(arm), arm, dim=-2) + Lin, 0.0)
    J_ang = torch.where(mask, A, 0.0).expand_as(J_lin)
    return p, torch.cat([J_lin, J_ang], dim=-2)


def kinetic_energy_rot(body: Body, rots: list, q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """T = ½ vᵀ M(q) v (...), with M v from one RNEA pass (zero velocity, acceleration v,
    no gravity) instead of a second copy of the velocity recursion."""
    Mv = rnea_rot(body, rots, q, torch.zeros_like(v), v, gravity=False)
    return 0.5 * (v * Mv).sum(-1)


def potential_energy_rot(body: Body, rots: list, q: torch.Tensor) -> torch.Tensor:
    """V = −Σ_i m_i g·x_com,i (...)."""
    C = _constants(body, q.dtype, q.device)
    Rw, x = forward_kinematics_rot(body, rots, q)
    V = 0.0
    for i in range(len(body.links)):
        xc = x[..., i, :] + _mv(Rw[i], C["com"][i].expand_as(x[..., i, :]))
        V = V - C["mass"][i] * (xc * C["gravity"]).sum(-1)
    return V


# Public API on rotation-vector coordinates.

def rnea(body: Body, q, v, a, gravity: bool = True, base=None):
    """Inverse dynamics τ(q, v, a) (...×nv), optionally on a moving base; see :func:`rnea_rot`.
    Compiled, the kernel turns the rotation vectors into rotations itself."""
    if kernels.applies(q, v, a, gravity, *(base or ())):
        return _compiled_call("rnea", body, None, q, v, a, gravity, base)
    return rnea_rot(body, joint_rotations(body, q), q, v, a, gravity, base)


def mass_matrix(body: Body, q):
    """Joint-space inertia matrix M(q) (...×nv×nv), symmetric positive definite."""
    return mass_matrix_rot(body, joint_rotations(body, q), q)


def bias_forces(body: Body, q, v):
    """h(q, v) = C(q, v)v + g(q) (...×nv): the torque that gives zero acceleration."""
    return rnea(body, q, v, torch.zeros_like(v))


def forward_dynamics(body: Body, q, v, tau, gravity=None, base=None):
    """Accelerations a = M⁻¹(τ − h) (...×nv); damping is not included here. ``gravity``
    and ``base``: see :func:`forward_dynamics_rot`. Compiled, the kernel turns the rotation
    vectors into rotations itself."""
    if kernels.applies(q, v, tau, gravity, *(base or ())):
        return _compiled_call("aba", body, None, q, v, tau, True if gravity is None else gravity, base)
    return forward_dynamics_rot(body, joint_rotations(body, q), q, v, tau, gravity, base)


def forward_kinematics(body: Body, q):
    """Positions of the joint origins and the tip, ...×(n_links+1)×3 (tip last)."""
    return forward_kinematics_rot(body, joint_rotations(body, q), q)[1]


def tip_position(body: Body, q):
    """End-effector (hand tip) position ...×3."""
    return forward_kinematics(body, q)[..., -1, :]


def point_jacobian(body: Body, q, link: int, point):
    """World-aligned Jacobian (...×6×nv, rows linear then angular) of ``point`` (3,) in the
    frame of link ``link``; see :func:`point_jacobian_rot`."""
    return point_jacobian_rot(body, joint_rotations(body, q), q, link, point)


def kinetic_energy(body: Body, q, v):
    """½ vᵀ M(q) v (...)."""
    return kinetic_energy_rot(body, joint_rotations(body, q), q, v)


def potential_energy(body: Body, q):
    """Gravitational potential −Σ m g·x_com (...)."""
    return potential_energy_rot(body, joint_rotations(body, q), q)
