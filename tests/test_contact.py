"""Ground contact (tflearn.physics.contact): resting depth of the spring law, the sliding
distance of regularised Coulomb friction, and contact torques against Pinocchio."""
from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest
import torch

from tflearn.physics import body as tb
from tflearn.physics import contact as C
from tflearn.physics import dynamics as D
from tflearn.simulation.simulate import SimOptions, simulate, zero_program

from conftest import DT, GRAVITY, q_to_pin, to_pin, v_to_pin

A, B, H, MASS = 0.1, 0.05, 0.025, 1.0     # the block's half sizes (m) and mass (kg)
CORNERS = torch.tensor([[sx * A, sy * B, -H] for sx in (-1, 1) for sy in (-1, 1)], dtype=DT)


def block() -> tb.Body:
    """A 0.2 × 0.1 × 0.05 m, 1 kg box on a free joint, gravity on."""
    inertia = np.diag([B * B + H * H, A * A + H * H, A * A + B * B]) * MASS / 3
    link = tb.Link(name="block", parent=-1, joint="free", origin=(0.0, 0.0, 0.0), mass=MASS,
                   com=(0.0, 0.0, 0.0), inertia=tuple(map(tuple, inertia)))
    return tb.Body(links=(link,), gravity=GRAVITY, name="block")


def _run(ground, z0, vx0, duration, samples=41):
    body = block()
    prog = C.with_ground(body, zero_program, ground, [0] * 4, CORNERS)
    q0 = torch.tensor([0, 0, 0, 0, 0, z0], dtype=DT)
    v0 = torch.tensor([0, 0, 0, vx0, 0, 0], dtype=DT)
    t = torch.linspace(0.0, duration, samples, dtype=DT)
    return simulate(body, prog, q0, v0, t, SimOptions(rtol=1e-8, atol=1e-10))


def test_dropped_block_rests_at_the_spring_depth():
    """Dropped from 2 cm, the block comes to rest sunk by m g/(4 k) (to 0.1%)."""
    ground = C.Ground(stiffness=1e4, damping=100.0, friction=0.5)
    traj = _run(ground, H + 0.02, 0.0, 1.0)
    depth = -(traj.q[-1, 5] - H)
    expected = MASS * 9.81 / (4 * ground.stiffness)
    assert abs(float(depth) / expected - 1) < 1e-3
    assert float(traj.v[-1].abs().max()) < 1e-4
    assert float(traj.q[:, 5].min()) < H            # it hit the ground before settling


def test_sliding_block_stops_at_the_coulomb_distance():
    """From 1 m/s with μ = 0.5 it stops after the regularised law's distance (0.5%), within
    the regularisation's error (v_s = 0.01 m/s: +0.03%) of u²/(2 μ g)."""
    ground = C.Ground(stiffness=1e4, damping=100.0, friction=0.5, slip=0.01)
    u0, g, vs = 1.0, 9.81, ground.slip
    depth = MASS * g / (4 * ground.stiffness)
    traj = _run(ground, H - depth, u0, 0.4)
    dist = float(traj.q[-1, 3])
    coulomb = u0 * u0 / (2 * ground.friction * g)
    regular = (u0 * math.sqrt(u0 * u0 + vs * vs) + vs * vs * math.asinh(u0 / vs)) / (
        2 * ground.friction * g)
    assert abs(regular / coulomb - 1) < 1e-3
    assert abs(dist / regular - 1) < 5e-3
    assert float(traj.v[-1, 3].abs()) < 1e-3        # stopped


def test_contact_torques_are_pinocchio_external_forces(rng):
    """τ = Σ Jᵀ f equals what Pinocchio's RNEA subtracts for the same point forces, for a
    tree on a free base with two contact points below the ground."""
    from test_free_joint import free_tree
    body = free_tree(0, GRAVITY)
    model, P = to_pin(body), v_to_pin(body)
    data = model.createData()
    links, points = [2, 4], torch.tensor([[0.01, 0.02, -0.1], [0.0, -0.03, 0.05]], dtype=DT)
    ground = C.Ground(stiffness=500.0, damping=3.0, friction=0.7, slip=0.05, height=5.0)
    q = torch.as_tensor(rng.normal(size=body.nv), dtype=DT)
    v = torch.as_tensor(rng.normal(size=body.nv), dtype=DT)
    tau = C.contact_torques(body, q, v, links, points, ground).numpy()
    p, J = D.points_kinematics_rot(body, D.joint_rotations(body, q), q, links, points)
    f = C.contact_forces(p, (J[..., :3, :] @ v[:, None])[..., 0], ground).numpy()
    assert (f[:, 2] > 0).all() and (np.abs(f[:, :2]).sum(-1) > 0).all()
    qp, zero = q_to_pin(body, q.numpy()), np.zeros(body.nv)
    pin.forwardKinematics(model, data, qp)
    fext = [pin.Force.Zero() for _ in range(model.njoints)]
    for k, link in enumerate(links):
        oMi = data.oMi[link + 1]
        Rt = oMi.rotation.T
        fext[link + 1] = fext[link + 1] + pin.Force(
            Rt @ f[k], Rt @ np.cross(p[k].numpy() - oMi.translation, f[k]))
    ref = (pin.rnea(model, data, qp, zero, zero)
           - pin.rnea(model, data, qp, zero, zero, pin.StdVec_Force(fext)))
    assert np.abs(tau[P] - ref).max() < 1e-9 * max(1.0, np.abs(ref).max())


def test_bad_ground_parameters():
    with pytest.raises(ValueError, match="ground.friction"):
        C.Ground(friction=-1.0)
    with pytest.raises(ValueError, match="ground.slip"):
        C.Ground(slip=0.0)
