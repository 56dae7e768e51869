"""Batched, differentiable rigid-body algorithms on a :class:`~tflearn.body.Body`.

Every function accepts any leading batch shape ``...`` and works in the input's dtype
(float64 throughout tflearn). Coordinates ``q`` (...×nv) are rotation vectors for ball
joints, angles for hinges and (rotation vector, translation) for free joints; velocities
``v``, accelerations ``a`` and torques ``tau`` (...×nv) follow the layout described in
:mod:`tflearn.body`.

Spatial quantities are kept as (angular, linear) pairs of 3-vectors in each link's frame
(Featherstone's body-frame formulation). Algorithms:

* :func:`rnea` — inverse dynamics τ = M(q) a + h(q, v) (recursive Newton–Euler),
* :func:`mass_matrix` — M(q), from RNEA columns with v = 0 and no gravity,
* :func:`bias_forces` — h(q, v) = τ(q, v, 0) (Coriolis, centrifugal, gravity),
* :func:`forward_dynamics` — a = M⁻¹(τ − h) by a Cholesky solve,
* :func:`forward_kinematics` — world rotations and joint positions, hand tip last,
* :func:`point_jacobian` — the world-aligned Jacobian of a point on a link (for
  external forces: τ = Jᵀ (f, m)); :func:`points_kinematics_rot` for many points at once,
* :func:`kinetic_energy`, :func:`potential_energy`.

The ``*_rot`` variants take the joints' own rotations (a list with one ...×3×3 matrix per
link, ``None`` for hinges and fixed joints, from which the hinge angle is read in ``q``)
so that :mod:`tflearn.simulate` can drive them from quaternions.
"""
from __future__ import annotations

from functools import lru_cache

import torch

from .body import Body
from .configspace import rotvec_to_rotmat


@lru_cache(maxsize=64)
def _constants(body: Body, dtype: torch.dtype, device: torch.device) -> dict:
    """Per-link constant tensors: joint origins, zero orientations, axes, inertias."""
    def t(x):
        return torch.as_tensor(x, dtype=dtype, device=device)
    return {
        "origin": [t(l.origin) for l in body.links],
        "R0": [rotvec_to_rotmat(t(l.offset)) for l in body.links],
        "axis": [t(l.axis) for l in body.links],
        "mass": [float(l.mass) for l in body.links],
        "com": [t(l.com) for l in body.links],
        "Ic": [t(l.inertia) for l in body.links],
        "gravity": t(body.gravity),
        "tip": t(body.tip_point),
    }


def hinge_rotmat(axis: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """Rodrigues: R = I + sin θ [a]× + (1 − cos θ)[a]×² for a unit axis a; θ (...) → ...×3×3."""
    return rotvec_to_rotmat(theta[..., None] * axis)


def _mv(E, x):
    return (E @ x.unsqueeze(-1)).squeeze(-1)


def _mtv(E, x):
    return (E.transpose(-1, -2) @ x.unsqueeze(-1)).squeeze(-1)


def _broadcast(rots: list, *xs: torch.Tensor):
    """Expand joint rotations and vectors (...×k) to their common batch shape."""
    batch = torch.broadcast_shapes(*(x.shape[:-1] for x in xs),
                                   *(R.shape[:-2] for R in rots if R is not None))
    rots = [None if R is None else R.expand(batch + (3, 3)) for R in rots]
    return (rots, *(x.expand(batch + x.shape[-1:]) for x in xs))


def joint_rotations(body: Body, q: torch.Tensor) -> list:
    """The joints' own rotations exp([v]×) (ball, free) or None (hinge, fixed); q (...×nv)."""
    return [rotvec_to_rotmat(q[..., body.slice(i)][..., :3]) if l.joint in ("ball", "free")
            else None for i, l in enumerate(body.links)]


def _relative_rotations(body: Body, rots: list, q: torch.Tensor) -> list:
    """R_i = R0_i · R_joint,i: each link frame relative to its parent (...×3×3)."""
    C = _constants(body, q.dtype, q.device)
    out = []
    for i, link in enumerate(body.links):
        R0 = C["R0"][i]
        if link.joint in ("ball", "free"):
            out.append(R0 @ rots[i])
        elif link.joint == "hinge":
            out.append(R0 @ hinge_rotmat(C["axis"][i], q[..., body.slice(i)][..., 0]))
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


def _joint_linear(body: Body, i: int, x: torch.Tensor):
    """The linear part of S_i x (a free joint's u, child frame); None for other joints."""
    return x[..., body.slice(i)][..., 3:] if body.links[i].joint == "free" else None


def _joint_motion(body: Body, i: int, x: torch.Tensor) -> torch.Tensor:
    """S_i x: the angular velocity a joint rate x produces, in the child frame."""
    link = body.links[i]
    xs = x[..., body.slice(i)]
    if link.joint == "ball":
        return xs
    if link.joint == "free":
        return xs[..., :3]
    if link.joint == "hinge":
        return xs * _constants(body, x.dtype, x.device)["axis"][i]
    return torch.zeros(x.shape[:-1] + (3,), dtype=x.dtype, device=x.device)


def rnea_rot(body: Body, rots: list, q: torch.Tensor, v: torch.Tensor, a: torch.Tensor,
             gravity=True, base=None) -> torch.Tensor:
    """Recursive Newton–Euler inverse dynamics, τ = M(q)a + C(q,v)v + g(q).

    Forward pass (link i, parent p, E = R_iᵀ, r the joint origin in the parent):
        ω_i = E ω_p + S q̇,                  v_i = E(v_p + ω_p × r)
        ω̇_i = E ω̇_p + S q̈ + ω_i × S q̇,     v̇_i = E(v̇_p + ω̇_p × r) + v_i × S q̇
    and for a free joint (r = origin + R0 t, joint rate (ω_j, u), acceleration (ω̇_j, u̇))
    also v_i += u and v̇_i += u̇ + ω_i × u (the linear half of the spatial v_i × S q̇);
    with base acceleration (0, −g) (``gravity``: True for the body's g, False for none, or
    a ...×3 tensor of per-batch gravity vectors). A moving base (``base`` = (ω_b, ω̇_b,
    a_b), ...×3 each, in the base frame: its angular velocity, angular acceleration and
    the classical acceleration of its origin) enters at the root as ω_p = ω_b, v_p = 0,
    ω̇_p = ω̇_b, v̇_p = a_b − g: the torques are those seen in the inertial frame moving
    with the base origin's velocity at that instant (Galilean invariance).
    Link wrench (c the centre of mass, Ic its inertia):
        p = m(v + ω×c), L = Ic ω + c×p,  h = m(v̇ + ω̇×c),  n = Ic ω̇ + c×h
        f_i = (n + ω×L + v×p,  h + ω×p)
    Backward pass: τ_i = Sᵀ n_i ((n_i, f_i) for a free joint); parent gets
    (Eᵀn + r×Eᵀf, Eᵀf).
    """
    C = _constants(body, q.dtype, q.device)
    rots, q, v, a = _broadcast(rots, q, v, a)
    zero = torch.zeros(q.shape[:-1] + (3,), dtype=q.dtype, device=q.device)
    Rrel = _relative_rotations(body, rots, q)
    if isinstance(gravity, torch.Tensor):
        g = gravity
    else:
        g = C["gravity"] if gravity else torch.zeros_like(C["gravity"])
    n_links = len(body.links)
    w, vl, dw, dv, E = ([None] * n_links for _ in range(5))
    for i, link in enumerate(body.links):
        E[i] = Rrel[i].transpose(-1, -2)
        r = _joint_origin(body, i, q)
        if link.parent < 0 and base is None:
            wp, vp, dwp, dvp = zero, zero, zero, zero - g
        elif link.parent < 0:
            wp, vp, dwp, dvp = base[0].expand_as(zero), zero, base[1].expand_as(zero), base[2] - g
        else:
            p = link.parent
            wp, vp, dwp, dvp = w[p], vl[p], dw[p], dv[p]
        wj = _joint_motion(body, i, v)
        w[i] = _mv(E[i], wp) + wj
        vl[i] = _mv(E[i], vp + torch.cross(wp, r.expand_as(wp), dim=-1))
        dw[i] = _mv(E[i], dwp) + _joint_motion(body, i, a) + torch.cross(w[i], wj, dim=-1)
        dv[i] = (_mv(E[i], dvp + torch.cross(dwp, r.expand_as(dwp), dim=-1))
                 + torch.cross(vl[i], wj, dim=-1))
        uj = _joint_linear(body, i, v)
        if uj is not None:
            vl[i] = vl[i] + uj
            dv[i] = (dv[i] + _joint_linear(body, i, a) + torch.cross(w[i], uj, dim=-1)
                     + torch.cross(uj, wj, dim=-1))
    n, f = [None] * n_links, [None] * n_links
    for i in range(n_links):
        m, c, Ic = C["mass"][i], C["com"][i].expand_as(w[i]), C["Ic"][i]
        p = m * (vl[i] + torch.cross(w[i], c, dim=-1))
        L = _mv(Ic, w[i]) + torch.cross(c, p, dim=-1)
        h = m * (dv[i] + torch.cross(dw[i], c, dim=-1))
        nn_ = _mv(Ic, dw[i]) + torch.cross(c, h, dim=-1)
        n[i] = nn_ + torch.cross(w[i], L, dim=-1) + torch.cross(vl[i], p, dim=-1)
        f[i] = h + torch.cross(w[i], p, dim=-1)
    tau = [None] * n_links
    for i in reversed(range(n_links)):
        link = body.links[i]
        if link.joint == "ball":
            tau[i] = n[i]
        elif link.joint == "hinge":
            tau[i] = (n[i] * C["axis"][i]).sum(-1, keepdim=True)
        elif link.joint == "free":
            tau[i] = torch.cat([n[i], f[i]], dim=-1)
        if link.parent >= 0:
            fp = _mtv(E[i], f[i])
            r = _joint_origin(body, i, q).expand_as(fp)
            n[link.parent] = n[link.parent] + _mtv(E[i], n[i]) + torch.cross(r, fp, dim=-1)
            f[link.parent] = f[link.parent] + fp
    return torch.cat([t for t in tau if t is not None], dim=-1)


def mass_matrix_rot(body: Body, rots: list, q: torch.Tensor) -> torch.Tensor:
    """M(q) (...×nv×nv): column k is RNEA(q, v=0, a=e_k) without gravity."""
    nv = body.nv
    eye = torch.eye(nv, dtype=q.dtype, device=q.device)
    qe = q.unsqueeze(-2)
    rots_e = [None if R is None else R.unsqueeze(-3) for R in rots]
    cols = rnea_rot(body, rots_e, qe, torch.zeros_like(eye), eye, gravity=False)
    M = cols.transpose(-1, -2)
    return 0.5 * (M + M.transpose(-1, -2))


def forward_dynamics_rot(body: Body, rots: list, q: torch.Tensor, v: torch.Tensor,
                         tau: torch.Tensor, gravity=None, base=None) -> torch.Tensor:
    """a = M(q)⁻¹ (τ − h(q, v)) by Cholesky factorisation (M is symmetric positive definite).

    One batched RNEA pass gives both: nv columns (v = 0, a = e_k, no gravity) for M and
    one (v, a = 0, gravity) for h. ``gravity`` (...×3, default the body's) and a moving
    ``base`` (see :func:`rnea_rot`) enter h only.
    """
    nv = body.nv
    rots, q, v, tau = _broadcast(rots, q, v, tau)
    eye = torch.eye(nv, dtype=q.dtype, device=q.device)
    acc = torch.cat([eye, torch.zeros_like(eye[:1])], dim=0)
    vel = torch.cat([torch.zeros(q.shape[:-1] + (nv, nv), dtype=q.dtype, device=q.device),
                     v.unsqueeze(-2)], dim=-2)
    if gravity is None and base is None:
        g = _constants(body, q.dtype, q.device)["gravity"]
        grav = torch.cat([torch.zeros(nv, 3, dtype=q.dtype, device=q.device), g[None]], dim=0)
    else:
        g = _constants(body, q.dtype, q.device)["gravity"] if gravity is None else gravity
        grav = _last_column(g, nv)
        base = None if base is None else tuple(_last_column(x, nv) for x in base)
    out = rnea_rot(body, [None if R is None else R.unsqueeze(-3) for R in rots],
                   q.unsqueeze(-2), vel, acc, gravity=grav, base=base)
    M = out[..., :nv, :].transpose(-1, -2)
    M = 0.5 * (M + M.transpose(-1, -2))
    h = out[..., nv, :]
    Lc = torch.linalg.cholesky(M)
    return torch.cholesky_solve((tau - h).unsqueeze(-1), Lc).squeeze(-1)


def _last_column(x: torch.Tensor, nv: int) -> torch.Tensor:
    """...×3 → ...×(nv+1)×3: zero for the nv mass-matrix columns, x for the bias column."""
    x = x.unsqueeze(-2)
    return torch.cat([torch.zeros(x.shape[:-2] + (nv, 3), dtype=x.dtype, device=x.device), x], dim=-2)


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
    """Inverse dynamics τ(q, v, a) (...×nv), optionally on a moving base; see :func:`rnea_rot`."""
    return rnea_rot(body, joint_rotations(body, q), q, v, a, gravity, base)


def mass_matrix(body: Body, q):
    """Joint-space inertia matrix M(q) (...×nv×nv), symmetric positive definite."""
    return mass_matrix_rot(body, joint_rotations(body, q), q)


def bias_forces(body: Body, q, v):
    """h(q, v) = C(q, v)v + g(q) (...×nv): the torque that gives zero acceleration."""
    return rnea(body, q, v, torch.zeros_like(v))


def forward_dynamics(body: Body, q, v, tau, gravity=None, base=None):
    """Accelerations a = M⁻¹(τ − h) (...×nv); damping is not included here. ``gravity``
    and ``base``: see :func:`forward_dynamics_rot`."""
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
