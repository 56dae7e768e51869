"""Natural vibration modes of an articulated body with elastic joints (Kry et al. 2007, §3.1).

Linearised about a rest pose θ₀ with joint springs of stiffness K, the body's small free
vibrations solve the generalised symmetric eigenproblem

    K u = ω² M u,        M = M(θ₀) (the mass matrix),  f = ω / 2π Hz,

whose eigenvectors, scaled so that Uᵀ M U = I (M-orthonormal), are the mode shapes.
Directions without stiffness (ω = 0) are the rigid modes.

The chart. A ball joint's velocity coordinates are its child-frame angular velocity ω,
not the derivative of its rotation vector ν (ω = J_r(ν) ν̇, :mod:`tflearn.physics.configspace`).
Two charts about θ₀ are offered (``ModalOptions.chart``):

* ``"tangent"`` (default): x = θ ⊖ θ₀ (:func:`tflearn.physics.configspace.difference`: per ball
  joint log(R(θ₀)ᵀ R(θ)), child frame; per hinge θ − θ₀). The springs store
  V = ½ xᵀ K x — the torque τ = K (θ_set ⊖ θ) of a PD controller — and, since ẋ = v at
  x = 0, the mass matrix is M(θ₀) itself.
* ``"rotvec"``: x = ν − ν₀ in the rotation vectors themselves, V = ½ xᵀ K x (the
  stiffness of a torque field χ = −K(ν − η), :mod:`tflearn.model.fields`). Then v = T x̂ with
  T = diag(J_r(ν₀) per ball joint, 1 per hinge) and the mass matrix is Tᵀ M(θ₀) T.

The frequencies are a property of the mechanics, not of the chart: the same springs
written in the other chart (K_rotvec = Tᵀ K_tangent T) give the same frequencies, and the
shapes map by u_tangent = T u_rotvec (tests/test_modes.py checks both). The two charts
differ only in what a given matrix K means, and agree at θ₀ = 0 (T = I).

Constraints (the paper's "modes in the null space of G"). A constraint is a point of a
link held fixed in the world or held together with a point of another link (a loop
closure), optionally with the two frames' orientations held too (``weld``). Its velocity
rows are G v = 0 with G built from :func:`tflearn.physics.dynamics.point_jacobian` (linear rows
J_a − J_b; angular rows too for a weld). A constraint may carry a spring ``stiffness`` k
on the relative rotation of its two links (the closing joint's own spring): to first
order that rotation is Ω v with Ω the angular rows of J_a − J_b, so K gains k ΩᵀΩ.
The admissible directions are the null space N of G from its SVD (G = U S Vᵀ, N = the
columns of V past the numerical rank), v = N ẋ, and the eigenproblem is projected:
Nᵀ K N y = ω² Nᵀ M N y, u = N y (so G u = 0 and uᵀ M u = 1 exactly as before).

A floating base (``ModalOptions.floating``) prepends six coordinates, the linear and
angular velocity of the root frame (world-aligned, at the world origin), to the joints'.
Its mass matrix is assembled from the links' kinetic energies,
M = Σ_links Jᵢᵀ diag(mᵢ I₃, Rᵢ Iᵢ Rᵢᵀ) Jᵢ with Jᵢ the floating Jacobian of link i's centre of
mass (its joint block equals :func:`tflearn.physics.dynamics.mass_matrix`), and the base has no
springs, so the six rigid-body motions come out as rigid modes, as in the paper's
tables (modes 0–5). Gravity is not part of K: as in the paper, the modes are those of
the joint springs alone.
"""
from __future__ import annotations

import fnmatch
from dataclasses import dataclass, field
from typing import Literal, Optional, Sequence

import numpy as np
import scipy.linalg
import torch

from ..errors import InputError
from ..physics import dynamics
from ..physics.body import Body
from ..physics.configspace import right_jacobian

CHARTS = ("tangent", "rotvec")
N_BASE = 6          # floating-base coordinates: linear then angular velocity of the root


class ModalError(InputError):
    """A bad modal-analysis input (stiffness, pose, constraint, mass matrix)."""


@dataclass(frozen=True)
class Constraint:
    """A point ``point`` (3,) of link ``link`` held fixed in the world (``other`` None) or
    held together with ``other_point`` of link ``other`` (a loop closure); ``weld`` also
    holds the orientation (6 rows instead of 3); ``stiffness`` (N·m/rad) is a spring on
    the links' relative rotation about their rest orientation. Links are named as in
    the body."""

    link: str
    point: tuple = (0.0, 0.0, 0.0)
    other: Optional[str] = None
    other_point: tuple = (0.0, 0.0, 0.0)
    weld: bool = False
    stiffness: float = 0.0

    @classmethod
    def from_config(cls, spec: dict, where: str = "constraints") -> Constraint:
        """``{link, point?, to?, to_point?, weld?, stiffness?}`` → Constraint."""
        known = {"link", "point", "to", "to_point", "weld", "stiffness"}
        if not isinstance(spec, dict) or "link" not in spec or set(spec) - known:
            raise ModalError(f"{where}: a constraint is a mapping with 'link' and optionally "
                             f"{sorted(known - {'link'})}, got {spec!r}")
        return cls(link=spec["link"], point=tuple(map(float, spec.get("point", (0, 0, 0)))),
                   other=spec.get("to"),
                   other_point=tuple(map(float, spec.get("to_point", (0, 0, 0)))),
                   weld=bool(spec.get("weld", False)),
                   stiffness=float(spec.get("stiffness", 0.0)))


@dataclass(frozen=True)
class ModalOptions:
    """chart: ``"tangent"`` or ``"rotvec"`` (see the module); floating: add a free base;
    rigid_tol: a mode is rigid when ω² ≤ rigid_tol · max ω² (and its frequency is then
    reported as 0); rank_tol: singular values of G below rank_tol · max are null;
    closure_tol: the largest gap (m) a constraint may have at the rest pose."""

    chart: Literal["tangent", "rotvec"] = "tangent"
    floating: bool = False
    rigid_tol: float = 1e-9
    rank_tol: float = 1e-10
    closure_tol: float = 1e-6


@dataclass(frozen=True)
class Modes:
    """The result of :func:`analyse`.

    Attributes:
        frequencies: Hz (n,), lowest first; 0 for rigid modes.
        eigenvalues: ω² (n,) as computed (tiny or slightly negative for rigid modes).
        shapes: mode shapes as columns (nx × n) in the chart's coordinates x
            ([6 base coordinates if floating] + nv joint coordinates), M-orthonormal:
            shapesᵀ M shapes = I; n = nx − rank(G).
        rigid: (n,) bool, True where ω² ≤ rigid_tol · max ω².
        M, K: the unprojected mass and stiffness matrices (nx × nx) in the chart, K with
            the constraints' springs.
        G: the constraint Jacobian (c × nx), c = 0 without constraints.
        q0: the rest pose (nv); body, options: as given.
    """

    frequencies: np.ndarray
    eigenvalues: np.ndarray
    shapes: np.ndarray
    rigid: np.ndarray
    M: np.ndarray
    K: np.ndarray
    G: np.ndarray
    q0: np.ndarray
    body: Body = field(repr=False)
    options: ModalOptions = ModalOptions()

    @property
    def n_rigid(self) -> int:
        return int(self.rigid.sum())

    @property
    def joint_shapes(self) -> np.ndarray:
        """The shapes' joint coordinates (nv × n), without the floating base's six."""
        return self.shapes[N_BASE:] if self.options.floating else self.shapes


# ------------------------------------------------------------------------------ stiffness

def joint_names(body: Body) -> list:
    """Names of the moving joints (a joint is named by the link it moves)."""
    return [link.name for link in body.links if link.dof]


def stiffness_matrix(body: Body, uniform: float = 1.0, scale: Optional[dict] = None,
                     matrix=None) -> np.ndarray:
    """Joint stiffness K (nv × nv, N·m/rad).

    Either ``matrix`` (nv × nv, symmetric positive semi-definite) as it is, or the diagonal
    ``uniform`` · s_j with s_j the product of the factors of ``scale`` (glob pattern on
    joint names → factor, e.g. {"spine*": 10}) whose pattern matches joint j. A pattern
    that matches no joint, a matrix of another size or not symmetric PSD, or a negative
    stiffness raise :class:`ModalError`."""
    nv = body.nv
    if matrix is not None:
        K = np.asarray(matrix, dtype=float)
        if K.shape != (nv, nv):
            raise ModalError(f"stiffness.matrix: expected {nv}×{nv} for body {body.name!r}, "
                             f"got shape {K.shape}")
        if not np.isfinite(K).all() or not np.allclose(K, K.T):
            raise ModalError("stiffness.matrix: must be finite and symmetric")
        if np.linalg.eigvalsh(K).min() < -1e-12 * max(1.0, np.abs(K).max()):
            raise ModalError("stiffness.matrix: must be positive semi-definite")
        return 0.5 * (K + K.T)
    if not uniform >= 0:
        raise ModalError(f"stiffness.uniform: must be non-negative, got {uniform}")
    diag = np.full(nv, float(uniform))
    names = joint_names(body)
    for pattern, factor in (scale or {}).items():
        hits = [n for n in names if fnmatch.fnmatchcase(n, pattern)]
        if not hits:
            raise ModalError(f"stiffness.scale: no joint matches {pattern!r} "
                             f"(joints: {', '.join(names)})")
        if not float(factor) >= 0:
            raise ModalError(f"stiffness.scale[{pattern!r}]: must be non-negative, got {factor}")
        for i, link in enumerate(body.links):
            if link.name in hits:
                diag[body.slice(i)] *= float(factor)
    return np.diag(diag)


def link_index(body: Body, name: str, where: str) -> int:
    """Index of the link called ``name``; :class:`ModalError` naming ``where`` otherwise."""
    for i, link in enumerate(body.links):
        if link.name == name:
            return i
    raise ModalError(f"{where}: no link named {name!r} (links: "
                     f"{', '.join(link.name for link in body.links)})")


def rest_pose(body: Body, pose=None) -> np.ndarray:
    """θ₀ (nv) from ``pose``: None (zeros), a list of nv numbers, or a mapping of link
    name → that joint's coordinates (others zero)."""
    q0 = np.zeros(body.nv)
    if pose is None:
        return q0
    if isinstance(pose, dict):
        for name, value in pose.items():
            i = link_index(body, name, "pose")
            value = np.atleast_1d(np.asarray(value, dtype=float))
            if value.shape != (body.links[i].dof,):
                raise ModalError(f"pose[{name!r}]: expected {body.links[i].dof} numbers, "
                                 f"got {value.size}")
            q0[body.slice(i)] = value
        return q0
    q0 = np.asarray(pose, dtype=float)
    if q0.shape != (body.nv,) or not np.isfinite(q0).all():
        raise ModalError(f"pose: expected {body.nv} finite numbers, got shape {q0.shape}")
    return q0


# ------------------------------------------------------------------------------ matrices

def chart_jacobian(body: Body, q0, floating: bool = False) -> np.ndarray:
    """T (nx × nx): v = T ẋ for the rotation-vector chart at q0 — J_r(ν₀) per ball joint,
    1 per hinge, identity on a floating base's six coordinates."""
    q0 = torch.as_tensor(q0, dtype=torch.float64)
    blocks = [np.eye(N_BASE)] if floating else []
    for i, link in enumerate(body.links):
        if link.joint == "ball":
            blocks.append(right_jacobian(q0[body.slice(i)]).numpy())
        elif link.dof:
            blocks.append(np.eye(link.dof))
    return scipy.linalg.block_diag(*blocks)


def _floating_jacobian(body: Body, q0: torch.Tensor, link: int, point) -> np.ndarray:
    """6 × (6 + nv): (linear, angular) world velocity of a point of a link in terms of the
    root's (linear, angular) velocity at the world origin and the joint velocities."""
    J = dynamics.point_jacobian(body, q0, link, point).numpy()
    Rw, x = dynamics.forward_kinematics_rot(body, dynamics.joint_rotations(body, q0), q0)
    p = (x[link] + Rw[link] @ torch.as_tensor(point, dtype=torch.float64)).numpy()
    base = np.zeros((6, N_BASE))
    base[:3, :3] = np.eye(3)
    base[:3, 3:] = -_hat(p)          # v = v_root + ω_root × p
    base[3:, 3:] = np.eye(3)
    return np.concatenate([base, J], axis=1)


def _hat(p: np.ndarray) -> np.ndarray:
    return np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])


def floating_mass_matrix(body: Body, q0) -> np.ndarray:
    """M ((6 + nv) × (6 + nv)) of the body on a free base at pose q0 (see the module)."""
    q0 = torch.as_tensor(q0, dtype=torch.float64)
    Rw, _ = dynamics.forward_kinematics_rot(body, dynamics.joint_rotations(body, q0), q0)
    M = np.zeros((N_BASE + body.nv,) * 2)
    for i, link in enumerate(body.links):
        J = _floating_jacobian(body, q0, i, link.com)
        R = Rw[i].numpy()
        inertia = scipy.linalg.block_diag(link.mass * np.eye(3), R @ np.asarray(link.inertia) @ R.T)
        M += J.T @ inertia @ J
    return 0.5 * (M + M.T)


def _point(body: Body, q0: torch.Tensor, link: int, point) -> np.ndarray:
    Rw, x = dynamics.forward_kinematics_rot(body, dynamics.joint_rotations(body, q0), q0)
    return (x[link] + Rw[link] @ torch.as_tensor(point, dtype=torch.float64)).numpy()


def constraint_jacobian(body: Body, q0, constraints: Sequence[Constraint],
                        floating: bool = False, closure_tol: float = 1e-6):
    """(G, K_c) in velocity coordinates (tangent chart): G (c × nx), per constraint 3
    linear rows (6 with ``weld``), and K_c (nx × nx) = Σ k ΩᵀΩ of the constraints'
    springs. Raises :class:`ModalError` for an unknown link, a negative spring or a
    constraint not met at q0 (points further apart than ``closure_tol``)."""
    q0 = torch.as_tensor(q0, dtype=torch.float64)
    nx = body.nv + (N_BASE if floating else 0)

    def jac(link, point):
        if floating:
            return _floating_jacobian(body, q0, link, point)
        return dynamics.point_jacobian(body, q0, link, point).numpy()

    rows, Kc = [], np.zeros((nx, nx))
    for k, c in enumerate(constraints):
        where = f"constraints[{k}]"
        if not c.stiffness >= 0:
            raise ModalError(f"{where}.stiffness: must be non-negative, got {c.stiffness}")
        a = link_index(body, c.link, f"{where}.link")
        J = jac(a, c.point)
        if c.other is not None:
            b = link_index(body, c.other, f"{where}.to")
            J = J - jac(b, c.other_point)
            gap = np.linalg.norm(_point(body, q0, a, c.point) - _point(body, q0, b, c.other_point))
            if gap > closure_tol:
                raise ModalError(f"{where}: the points are {gap:.4g} m apart at the rest pose "
                                 f"(a loop closure must hold there)")
        rows.append(J if c.weld else J[:3])
        Kc += c.stiffness * J[3:].T @ J[3:]
    return (np.concatenate(rows, axis=0) if rows else np.zeros((0, nx))), Kc


def null_space(G: np.ndarray, rank_tol: float = 1e-10) -> np.ndarray:
    """N (nx × (nx − rank G)): orthonormal basis of G's null space from its SVD."""
    nx = G.shape[1]
    if G.shape[0] == 0:
        return np.eye(nx)
    _, s, Vt = np.linalg.svd(G)
    rank = int((s > rank_tol * max(s.max(), 1e-300)).sum())
    return Vt[rank:].T


# ------------------------------------------------------------------------------ analysis

def analyse(body: Body, q0, K, constraints: Sequence[Constraint] = (),
            options: ModalOptions = ModalOptions()) -> Modes:
    """The modes of ``body`` about rest pose q0 (nv) with joint stiffness K (nv × nv, in
    ``options.chart``) under ``constraints`` (see the module for the maths).

    Raises :class:`ModalError` for a K of the wrong size, a pose of the wrong size, a bad
    constraint, or a singular (projected) mass matrix."""
    if options.chart not in CHARTS:
        raise ModalError(f"chart: must be one of {CHARTS}, got {options.chart!r}")
    nv = body.nv
    q0 = np.asarray(q0, dtype=float)
    if q0.shape != (nv,):
        raise ModalError(f"pose: expected {nv} coordinates, got shape {q0.shape}")
    K = np.asarray(K, dtype=float)
    if K.shape != (nv, nv):
        raise ModalError(f"stiffness: expected {nv}×{nv} for body {body.name!r}, "
                         f"got shape {K.shape}")
    qt = torch.as_tensor(q0)
    if options.floating:
        M = floating_mass_matrix(body, qt)
        K = scipy.linalg.block_diag(np.zeros((N_BASE, N_BASE)), K)
    else:
        M = dynamics.mass_matrix(body, qt).numpy()
    G, Kc = constraint_jacobian(body, qt, constraints, options.floating, options.closure_tol)
    if options.chart == "rotvec":
        T = chart_jacobian(body, q0, options.floating)
        M, G, Kc = T.T @ M @ T, G @ T, T.T @ Kc @ T
    K = K + Kc
    N = null_space(G, options.rank_tol)
    Mr, Kr = N.T @ M @ N, N.T @ K @ N
    _check_mass(Mr, body)
    lam, Y = scipy.linalg.eigh(0.5 * (Kr + Kr.T), 0.5 * (Mr + Mr.T))
    rigid = lam <= options.rigid_tol * max(lam.max(), 0.0) if lam.size else lam.astype(bool)
    freq = np.where(rigid, 0.0, np.sqrt(np.clip(lam, 0.0, None)) / (2 * np.pi))
    return Modes(frequencies=freq, eigenvalues=lam, shapes=N @ Y, rigid=rigid, M=M, K=K,
                 G=G, q0=q0, body=body, options=options)


def _check_mass(M: np.ndarray, body: Body) -> None:
    """M must be positive definite (a link with no inertia about a free axis is not)."""
    w = np.linalg.eigvalsh(M) if M.size else np.ones(1)
    if not w.min() > 1e-12 * max(w.max(), 1e-300):
        raise ModalError(f"body {body.name!r}: the mass matrix is singular at the rest pose "
                         f"(smallest eigenvalue {w.min():.3g}, largest {w.max():.3g}): some "
                         f"coordinate moves no mass or inertia (on a floating base the root "
                         f"link's joint must be fixed)")


def tangent_stiffness(modes: Modes) -> np.ndarray:
    """The joint stiffness (nv × nv) in the tangent chart — the gain of a PD controller
    τ = K_t (θ_set ⊖ θ) with these springs: K itself for the tangent chart, T⁻ᵀ K T⁻¹
    for the rotation-vector chart."""
    K = modes.K[N_BASE:, N_BASE:] if modes.options.floating else modes.K
    if modes.options.chart == "tangent":
        return K
    Tinv = np.linalg.inv(chart_jacobian(modes.body, modes.q0))
    return Tinv.T @ K @ Tinv


# ------------------------------------------------------------------------------ fields

def field_modes(body: Body, eta, K) -> list:
    """The modes of the body about each torque field's centre: near η a field
    χ = −K(ν − η)·exp(…) is the spring −K(ν − η) in rotation vectors, so field i gives
    :func:`analyse` (body, ηᵢ, Kᵢ) in the ``rotvec`` chart; eta (M×nv), K (M×nv×nv)."""
    eta, K = np.asarray(eta, dtype=float), np.asarray(K, dtype=float)
    return [analyse(body, eta[i], K[i], options=ModalOptions(chart="rotvec"))
            for i in range(eta.shape[0])]


def excitation(modes: Modes, q_from) -> np.ndarray:
    """How a release from pose ``q_from`` (nv; fixed base) excites each mode: the shares
    (n, summing to 1) of the spring energy ½ Σₖ ω²ₖ cₖ² of the displacement x = q_from ⊖ θ₀
    (in the modes' chart: ν − ν₀ in rotvec, the child-frame difference in tangent),
    cₖ = uₖᵀ M x (x = Σ cₖ uₖ, the shapes being M-orthonormal). Linear: the picture near
    θ₀ of what the spring, released at ``q_from``, sets vibrating."""
    q_from = torch.as_tensor(np.asarray(q_from, dtype=float))
    q0 = torch.as_tensor(modes.q0)
    if modes.options.chart == "rotvec":
        x = (q_from - q0).numpy()
    else:
        from ..physics.configspace import difference
        x = difference(modes.body, q0, q_from).numpy()
    c = modes.shapes.T @ (modes.M @ x)
    energy = np.clip(modes.eigenvalues, 0.0, None) * c * c
    total = energy.sum()
    return energy / total if total > 0 else energy
