"""tflearn.physics.dynamics against Pinocchio, plus identities, batching and gradients."""
from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest
import torch
from torch.autograd import gradcheck

from tflearn.physics import body as tb
from tflearn.physics import dynamics as D
from tflearn.physics.configspace import integrate, rotvec_to_rotmat

from conftest import (
    ARM_OFFSETS,
    BODY_NAMES,
    DT,
    GRAVITY,
    full_symmetric,
    make_body,
    max_rel_err,
    q_to_pin,
    random_coords,
    to_pin,
)

N_STATES = 20
TOL = 1e-9

CASES = [(name, g) for name in BODY_NAMES for g in ("nograv", "grav")]


def _case(name, g, rng):
    body = make_body(name, GRAVITY if g == "grav" else (0.0, 0.0, 0.0))
    q = random_coords(body, rng, N_STATES)
    v = 2.0 * rng.normal(size=q.shape)
    a = 2.0 * rng.normal(size=q.shape)
    tau = 5.0 * rng.normal(size=q.shape)
    return body, q, v, a, tau


def _t(x):
    return torch.as_tensor(x, dtype=DT)


@pytest.mark.parametrize("name,g", CASES)
def test_against_pinocchio(name, g, rng):
    body, q, v, a, tau = _case(name, g, rng)
    assert any(body.gravity) == (g == "grav")
    model = to_pin(body)
    data = model.createData()
    # One batched call per function (N_STATES×nv), compared state by state.
    tq, tv, ta, ttau = map(_t, (q, v, a, tau))
    out = {
        "rnea": D.rnea(body, tq, tv, ta).numpy(),
        "M": D.mass_matrix(body, tq).numpy(),
        "h": D.bias_forces(body, tq, tv).numpy(),
        "g": D.bias_forces(body, tq, torch.zeros_like(tv)).numpy(),
        "fd": D.forward_dynamics(body, tq, tv, ttau).numpy(),
        "x": D.forward_kinematics(body, tq).numpy(),
        "T": D.kinetic_energy(body, tq, tv).numpy(),
        "V": D.potential_energy(body, tq).numpy(),
    }
    Rw, _ = D.forward_kinematics_rot(body, D.joint_rotations(body, tq), tq)
    errs = {k: 0.0 for k in list(out) + ["R", "tip", "V_direct"]}
    tip_point = np.array(body.tip_point)
    for k in range(N_STATES):
        qp = q_to_pin(body, q[k])
        ref = {
            "rnea": pin.rnea(model, data, qp, v[k], a[k]),
            "M": full_symmetric(pin.crba(model, data, qp)),
            "h": pin.nonLinearEffects(model, data, qp, v[k]),
            "g": pin.computeGeneralizedGravity(model, data, qp),
            "fd": pin.aba(model, data, qp, v[k], tau[k]),
            "T": pin.computeKineticEnergy(model, data, qp, v[k]),
            "V": pin.computePotentialEnergy(model, data, qp),
        }
        for key, val in ref.items():
            errs[key] = max(errs[key], max_rel_err(out[key][k], val))
        pin.forwardKinematics(model, data, qp)
        origins = np.array([data.oMi[j].translation for j in range(1, model.njoints)])
        errs["x"] = max(errs["x"], max_rel_err(out["x"][k, :-1], origins))
        M_tip = data.oMi[body.tip_link + 1]
        tip = M_tip.translation + M_tip.rotation @ tip_point
        errs["tip"] = max(errs["tip"], max_rel_err(out["x"][k, -1], tip))
        rots = np.stack([data.oMi[j].rotation for j in range(1, model.njoints)])
        errs["R"] = max(errs["R"], max_rel_err(torch.stack([R[k] for R in Rw]).numpy(), rots))
        # V = −Σ m g·x_com with the centres of mass placed by Pinocchio's oMi.
        V = -sum(l.mass * np.dot(body.gravity, data.oMi[i + 1].act(np.array(l.com)))
                 for i, l in enumerate(body.links))
        errs["V_direct"] = max(errs["V_direct"], max_rel_err(out["V"][k], V))
    if g == "nograv":
        assert np.abs(out["g"]).max() == 0.0 and np.abs(out["V"]).max() == 0.0
    else:
        assert np.abs(out["g"]).max() > 1.0  # gravity really acts
    bad = {k: e for k, e in errs.items() if not e <= TOL}
    assert not bad, f"{name}/{g}: errors above {TOL}: {bad}"


def test_special_angles_are_sampled(rng):
    """The state sampler really produces |v| = π exactly, near 0 and exactly 0."""
    body = make_body("arm")
    q = random_coords(body, rng, N_STATES)
    for cols in (slice(0, 3), slice(4, 7)):  # shoulder and wrist
        norms = np.linalg.norm(q[:, cols], axis=-1)
        assert norms[0] == pytest.approx(math.pi, rel=1e-15)
        assert norms[1] == pytest.approx(math.pi - 1e-9, rel=1e-15)
        assert norms[2] == pytest.approx(1e-9, rel=1e-12) and norms[3] == 0.0
        assert norms[4] == math.pi and torch.linalg.vector_norm(_t(q[4, cols])) == math.pi
        assert np.all((norms[5:] > 0) & (norms[5:] <= math.pi))


@pytest.mark.parametrize("name", BODY_NAMES)
def test_rnea_forward_dynamics_round_trip(name, rng):
    body, q, v, a, _ = _case(name, "grav", rng)
    tq, tv, ta = map(_t, (q, v, a))
    tau = D.rnea(body, tq, tv, ta)
    a2 = D.forward_dynamics(body, tq, tv, tau)
    assert float((a2 - ta).abs().max()) <= 1e-10 * max(1.0, float(ta.abs().max()))


@pytest.mark.parametrize("name", BODY_NAMES)
def test_mass_matrix_identities(name, rng):
    body, q, v, _, _ = _case(name, "grav", rng)
    tq, tv = _t(q), _t(v)
    nv = body.nv
    # Columns straight from RNEA (no symmetrisation): M e_k = τ(q, 0, e_k) without gravity.
    eye = torch.eye(nv, dtype=DT)
    cols = torch.stack([D.rnea(body, tq, torch.zeros_like(tv), eye[k].expand_as(tv),
                               gravity=False) for k in range(nv)], dim=-1)
    M = D.mass_matrix(body, tq)
    scale = float(M.abs().max())
    assert float((cols - cols.transpose(-1, -2)).abs().max()) <= 1e-12 * scale
    assert float((M - cols).abs().max()) <= 1e-12 * scale
    assert float(torch.linalg.eigvalsh(M).min()) > 0.0
    # T = ½ vᵀ M v, and h = rnea(q, v, 0) is what makes a = 0.
    T = D.kinetic_energy(body, tq, tv)
    vMv = 0.5 * (tv.unsqueeze(-2) @ M @ tv.unsqueeze(-1))[..., 0, 0]
    assert float((T - vMv).abs().max()) <= 1e-12 * float(T.abs().max())
    h = D.bias_forces(body, tq, tv)
    a0 = D.forward_dynamics(body, tq, tv, h)
    assert float(a0.abs().max()) <= 1e-10


def test_gravity_torque_is_potential_gradient_for_hinges(rng):
    """For a hinge chain the coordinates are plain angles, so g(q) = ∂V/∂q exactly."""
    body = make_body("chain4_hinge", GRAVITY)
    q = _t(random_coords(body, rng, 5)).requires_grad_(True)
    V = D.potential_energy(body, q)
    (dV,) = torch.autograd.grad(V.sum(), q)
    g = D.bias_forces(body, q.detach(), torch.zeros_like(q))
    assert float(g.abs().max()) > 1.0
    assert float((g - dV).abs().max()) <= 1e-12 * float(g.abs().max())


def test_gravity_torque_is_child_frame_potential_derivative(rng):
    """For ball joints g = dV/dε with q = log(exp(v)·exp(ε)): a child-frame perturbation."""
    body = make_body("arm_offsets", GRAVITY)
    q = _t(random_coords(body, rng, 7)[5:])  # two generic states
    rots = D.joint_rotations(body, q)
    eps = torch.zeros_like(q, requires_grad=True)
    pert = []
    for i, link in enumerate(body.links):
        if link.joint == "ball":
            pert.append(rots[i] @ rotvec_to_rotmat(eps[..., body.slice(i)]))
        else:
            pert.append(None)
    qh = q + torch.cat([eps[..., body.slice(i)] * (l.joint == "hinge")
                        for i, l in enumerate(body.links)], dim=-1)
    V = D.potential_energy_rot(body, pert, qh)
    (dV,) = torch.autograd.grad(V.sum(), eps)
    g = D.bias_forces(body, q, torch.zeros_like(q))
    assert float(g.abs().max()) > 1.0
    assert float((g - dV).abs().max()) <= 1e-12 * float(g.abs().max())


# ------------------------------------------------------------------------- batching

def test_batch_shapes_match_loop(rng):
    body = make_body("arm_offsets", GRAVITY)
    q = _t(random_coords(body, rng, 6)).reshape(2, 3, 7)
    v = _t(rng.normal(size=(2, 3, 7)))
    a = _t(rng.normal(size=(2, 3, 7)))
    funcs = {
        "rnea": lambda q, v, a: D.rnea(body, q, v, a),
        "M": lambda q, v, a: D.mass_matrix(body, q),
        "h": lambda q, v, a: D.bias_forces(body, q, v),
        "fd": lambda q, v, a: D.forward_dynamics(body, q, v, a),
        "x": lambda q, v, a: D.forward_kinematics(body, q),
        "tip": lambda q, v, a: D.tip_position(body, q),
        "T": lambda q, v, a: D.kinetic_energy(body, q, v),
        "V": lambda q, v, a: D.potential_energy(body, q),
    }
    shapes = {"rnea": (2, 3, 7), "M": (2, 3, 7, 7), "h": (2, 3, 7), "fd": (2, 3, 7),
              "x": (2, 3, 4, 3), "tip": (2, 3, 3), "T": (2, 3), "V": (2, 3)}
    for key, f in funcs.items():
        batched = f(q, v, a)
        assert batched.shape == shapes[key], key
        looped = torch.stack([torch.stack([f(q[i, j], v[i, j], a[i, j]) for j in range(3)])
                              for i in range(2)])
        assert float((batched - looped).abs().max()) <= 1e-12 * max(1.0, float(looped.abs().max())), key


def test_broadcasting_unbatched_velocity(rng):
    """q (2×3×nv) with v, a (nv) broadcast like any torch op."""
    body = make_body("arm_offsets", GRAVITY)
    q = _t(random_coords(body, rng, 6)).reshape(2, 3, 7)
    v, a = _t(rng.normal(size=7)), _t(rng.normal(size=7))
    tau = D.rnea(body, q, v, a)
    assert tau.shape == (2, 3, 7)
    ref = D.rnea(body, q, v.expand(2, 3, 7), a.expand(2, 3, 7))
    assert torch.equal(tau, ref)
    acc = D.forward_dynamics(body, q, v, tau)
    assert float((acc - a).abs().max()) <= 1e-10


def test_float32_in_float32_out(rng):
    body = make_body("arm_offsets", GRAVITY)
    q = _t(random_coords(body, rng, 6)[4:])
    v, a = _t(rng.normal(size=(2, 7))), _t(rng.normal(size=(2, 7)))
    f32 = [x.float() for x in (q, v, a)]
    pairs = [
        (D.rnea(body, *f32), D.rnea(body, q, v, a)),
        (D.mass_matrix(body, f32[0]), D.mass_matrix(body, q)),
        (D.forward_dynamics(body, *f32), D.forward_dynamics(body, q, v, a)),
        (D.forward_kinematics(body, f32[0]), D.forward_kinematics(body, q)),
        (D.kinetic_energy(body, f32[0], f32[1]), D.kinetic_energy(body, q, v)),
        (D.potential_energy(body, f32[0]), D.potential_energy(body, q)),
    ]
    for lo, hi in pairs:
        assert lo.dtype == torch.float32
        assert hi.dtype == torch.float64
        assert float((lo.double() - hi).abs().max()) <= 1e-4 * max(1.0, float(hi.abs().max()))


# ------------------------------------------------------------------------ gradients

def _grad_inputs(rng, body):
    q = random_coords(body, rng, 6)[[3, 5]]  # state 3: every ball joint exactly zero
    q[1, :3] = 0.0                            # and a generic state with zero shoulder
    assert np.all(q[:, :3] == 0.0) and np.any(q[1, 4:] != 0.0)
    q = _t(q).requires_grad_(True)
    v = _t(rng.normal(size=(2, body.nv))).requires_grad_(True)
    a = _t(rng.normal(size=(2, body.nv))).requires_grad_(True)
    return q, v, a


@pytest.fixture
def grad_body():
    return tb.arm(gravity=list(GRAVITY), offsets=ARM_OFFSETS)


def test_gradcheck_rnea(grad_body, rng):
    q, v, a = _grad_inputs(rng, grad_body)
    assert gradcheck(lambda q, v, a: D.rnea(grad_body, q, v, a), (q, v, a))


def test_gradcheck_forward_dynamics(grad_body, rng):
    q, v, tau = _grad_inputs(rng, grad_body)
    assert gradcheck(lambda q, v, tau: D.forward_dynamics(grad_body, q, v, tau), (q, v, tau))


def test_gradcheck_forward_kinematics(grad_body, rng):
    q, _, _ = _grad_inputs(rng, grad_body)
    assert gradcheck(lambda q: D.forward_kinematics(grad_body, q), (q,))


def test_gradient_at_zero_rotation_is_the_small_angle_limit(grad_body):
    """At ν = 0 the tip Jacobian column of the shoulder is ω × (tip − shoulder)."""
    q = torch.zeros(7, dtype=DT, requires_grad=True)
    J = torch.autograd.functional.jacobian(lambda q: D.tip_position(grad_body, q), q)
    assert torch.isfinite(J).all()
    R0 = rotvec_to_rotmat(torch.tensor(ARM_OFFSETS[0], dtype=DT))
    tip = D.tip_position(grad_body, q.detach())
    for k in range(3):
        w = R0[:, k]  # a child-frame unit rate about axis k, seen in the world
        assert torch.allclose(J[:, k], torch.linalg.cross(w, tip), atol=1e-12, rtol=0)


def _pin_joint_of(body, link: int) -> int:
    """Pinocchio joint id carrying a link (a fixed link rides on its parent's joint)."""
    ids, jid = [], 0
    for l in body.links:
        if l.joint != "fixed":
            jid += 1
            ids.append(jid)
        else:
            ids.append(ids[l.parent] if l.parent >= 0 else 0)
    return ids[link]


@pytest.mark.parametrize("name", BODY_NAMES)
def test_point_jacobian_transpose_is_pinocchio_external_force(name, rng):
    """τ = Jᵀ(f, m) for a wrench at a point equals what Pinocchio's RNEA subtracts for that
    external force (given on the carrying joint, in its local frame)."""
    body = make_body(name, GRAVITY)
    model = to_pin(body)
    data = model.createData()
    q = random_coords(body, rng, 8)
    link = len(body.links) - 1
    point = rng.normal(size=3) * 0.1
    J = D.point_jacobian(body, _t(q), link, point).numpy()
    x = D.forward_kinematics_rot(body, D.joint_rotations(body, _t(q)), _t(q))
    Rw, pos = x[0][link].numpy(), x[1][..., link, :].numpy()
    err = 0.0
    for k in range(len(q)):
        f, m = rng.normal(size=3), rng.normal(size=3)
        p = pos[k] + Rw[k] @ point
        qp, zero = q_to_pin(body, q[k]), np.zeros(body.nv)
        pin.forwardKinematics(model, data, qp)
        jid = _pin_joint_of(body, link)
        oMi = data.oMi[jid]
        fext = [pin.Force.Zero() for _ in range(model.njoints)]
        Rt = oMi.rotation.T
        fext[jid] = pin.Force(Rt @ f, Rt @ (m + np.cross(p - oMi.translation, f)))
        ref = (pin.rnea(model, data, qp, zero, zero)
               - pin.rnea(model, data, qp, zero, zero, pin.StdVec_Force(fext)))
        err = max(err, max_rel_err(J[k].T @ np.concatenate([f, m]), ref))
    assert err < TOL


def test_point_jacobian_maps_velocity_to_point_velocity(rng):
    """J v is the time derivative of the point's world position (central differences along
    q(t) = q ⊕ v t, each ball joint turning as R exp([v t]×))."""
    body = make_body("arm_offsets")
    q = _t(random_coords(body, rng, 6)[1:])
    v = _t(rng.normal(size=q.shape))
    point = (0.02, -0.03, -0.1)
    h = 1e-6

    def moved(s):
        return integrate(body, q, s * v)

    def point_at(qq):
        Rw, x = D.forward_kinematics_rot(body, D.joint_rotations(body, qq), qq)
        return x[..., 1, :] + (Rw[1] @ _t(point).expand(x.shape[:-2] + (3,)).unsqueeze(-1)).squeeze(-1)

    fd = (point_at(moved(h)) - point_at(moved(-h))) / (2 * h)
    J = D.point_jacobian(body, q, 1, point)
    assert torch.allclose((J[..., :3, :] @ v.unsqueeze(-1)).squeeze(-1), fd, atol=1e-7)
