"""The 6-DOF free joint: dynamics against Pinocchio's free flyer, the simulator's state,
and a free-floating body conserving energy and momentum."""
from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
import torch

from tflearn.physics import dynamics as D
from tflearn.physics.configspace import difference, integrate, pack, unpack
from tflearn.simulation.simulate import SimOptions, simulate, zero_program

from conftest import (
    DT,
    GRAVITY,
    free_tree,
    full_symmetric,
    max_rel_err,
    q_to_pin,
    random_states,
    to_pin,
    v_to_pin,
)

TOL = 1e-9




@pytest.mark.parametrize("where,gravity", [(0, (0.0, 0.0, 0.0)), (0, GRAVITY), (3, GRAVITY)])
def test_free_joint_against_pinocchio(where, gravity, rng):
    body = free_tree(where, gravity)
    model, P = to_pin(body), v_to_pin(body)
    data = model.createData()
    n = 8
    q = random_states(body, rng, n)
    v, a, tau = (2.0 * rng.normal(size=q.shape) for _ in range(3))
    t = lambda x: torch.as_tensor(x, dtype=DT)
    tq, tv, ta, ttau = map(t, (q, v, a, tau))
    ours = {"rnea": D.rnea(body, tq, tv, ta).numpy()[:, P],
            "M": D.mass_matrix(body, tq).numpy()[:, P][:, :, P],
            "fd": D.forward_dynamics(body, tq, tv, ttau).numpy()[:, P],
            "x": D.forward_kinematics(body, tq).numpy()[:, :-1],
            "T": D.kinetic_energy(body, tq, tv).numpy(),
            "V": D.potential_energy(body, tq).numpy()}
    errs = dict.fromkeys(ours, 0.0)
    for k in range(n):
        qp = q_to_pin(body, q[k])
        vp, ap, taup = v[k][P], a[k][P], tau[k][P]
        pin.forwardKinematics(model, data, qp)
        ref = {"rnea": pin.rnea(model, data, qp, vp, ap),
               "M": full_symmetric(pin.crba(model, data, qp)),
               "fd": pin.aba(model, data, qp, vp, taup),
               "x": np.stack([data.oMi[j + 1].translation for j in range(len(body.links))]),
               "T": pin.computeKineticEnergy(model, data, qp, vp),
               "V": pin.computePotentialEnergy(model, data, qp)}
        for key in errs:
            errs[key] = max(errs[key], max_rel_err(ours[key][k], ref[key]))
    assert max(errs.values()) < TOL, errs


def test_free_joint_point_jacobian_is_the_point_velocity(rng):
    """J v is the derivative of a point's position along the exact free motion
    R(s) = R exp([s ω]×), t(s) = t + s R u (and each other joint moved likewise)."""
    body = free_tree(0)
    q = torch.as_tensor(random_states(body, rng, 4), dtype=DT)
    v = torch.as_tensor(rng.normal(size=q.shape), dtype=DT)
    point, link, h = (0.05, -0.02, 0.1), 4, 1e-6

    def moved(s):                 # q ⊕ s v: ṫ = R u for the free joint at s = 0
        return integrate(body, q, s * v)

    def point_at(qq):
        Rw, x = D.forward_kinematics_rot(body, D.joint_rotations(body, qq), qq)
        return x[..., link, :] + (Rw[link] @ torch.as_tensor(point, dtype=DT))

    fd = (point_at(moved(h)) - point_at(moved(-h))) / (2 * h)
    J = D.point_jacobian(body, q, link, point)
    assert torch.allclose((J[..., :3, :] @ v[..., None])[..., 0], fd, atol=1e-7)


def test_pack_unpack_difference_round_trip(rng):
    body = free_tree(0)
    q = torch.as_tensor(random_states(body, rng, 5), dtype=DT)
    v = torch.as_tensor(rng.normal(size=q.shape), dtype=DT)
    y = pack(body, q, v)
    assert y.shape[-1] == 7 + 1 + 4 + 1 + 4 + body.nv
    assert torch.equal(y[..., 4:7], q[..., 3:6])          # translation after the quaternion
    _, q2, _, v2 = unpack(body, y)
    assert torch.allclose(q2, q, atol=1e-12) and torch.equal(v2, v)
    d = difference(body, q, q2)
    assert d.abs().max() < 1e-12
    step = torch.zeros_like(q)
    step[:, 3:6] = torch.tensor([0.1, -0.2, 0.3], dtype=DT)
    R = D.joint_rotations(body, q)[0]
    assert torch.allclose(difference(body, q, q + step)[:, 3:6],
                          (R.transpose(-1, -2) @ step[:, 3:6, None])[..., 0], atol=1e-14)


def momentum(body, q, v):
    """World linear and angular momentum (about the origin) from the links' centres of
    mass (their point Jacobians) and their inertias turned into the world."""
    rots = D.joint_rotations(body, q)
    coms = torch.tensor([l.com for l in body.links], dtype=DT)
    J = D.points_kinematics_rot(body, rots, q, list(range(len(body.links))), coms)[1]
    Rw, x = D.forward_kinematics_rot(body, rots, q)
    P, L = 0.0, 0.0
    for i, l in enumerate(body.links):
        vel = J[..., i, :, :] @ v[..., None]
        vc, w = vel[..., :3, 0], vel[..., 3:, 0]
        xc = x[..., i, :] + (Rw[i] @ coms[i])
        Iw = Rw[i] @ torch.as_tensor(l.inertia, dtype=DT) @ Rw[i].transpose(-1, -2)
        P = P + l.mass * vc
        L = L + torch.cross(xc, l.mass * vc, dim=-1) + (Iw @ w[..., None])[..., 0]
    return P, L


def test_free_floating_body_conserves_energy_and_momentum(rng):
    """Zero gravity, no torques: T, P and L stay constant while the tree tumbles and
    drifts (dopri5 at rtol 1e-10)."""
    body = free_tree(0)
    q0 = torch.as_tensor(random_states(body, rng, 1)[0], dtype=DT)
    v0 = torch.as_tensor(rng.normal(size=body.nv), dtype=DT)
    t = torch.linspace(0.0, 1.0, 11, dtype=DT)
    traj = simulate(body, zero_program, q0, v0, t, SimOptions(rtol=1e-10, atol=1e-12))
    T = D.kinetic_energy(body, traj.q, traj.v)
    P, L = momentum(body, traj.q, traj.v)
    assert (traj.q[-1, 3:6] - q0[3:6]).norm() > 0.1          # it did move
    assert float((T - T[0]).abs().max() / T[0]) < 1e-8
    assert float((P - P[0]).abs().max() / P[0].norm()) < 1e-8
    assert float((L - L[0]).abs().max() / L[0].norm()) < 1e-8


@pytest.mark.parametrize("where", [0, 3])
def test_integrate_inverts_difference(where, rng):
    """q ⊕ x ⊖ q = x (steps below 1 rad per joint) and q ⊕ (q₂ ⊖ q) = q₂ (as rotations)
    for ball, hinge and free joints."""
    body = free_tree(where)
    q = torch.as_tensor(random_states(body, rng, 6), dtype=DT)
    x = torch.as_tensor(rng.uniform(-0.55, 0.55, size=q.shape), dtype=DT)
    assert torch.allclose(difference(body, q, integrate(body, q, x)), x, atol=1e-12)
    q2 = torch.as_tensor(random_states(body, rng, 6), dtype=DT)
    back = integrate(body, q, difference(body, q, q2))
    assert torch.allclose(difference(body, q2, back), torch.zeros_like(q), atol=1e-12)
