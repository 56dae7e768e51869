"""A moving base (the torso): RNEA and forward dynamics against Pinocchio with a
free-flyer root whose motion is prescribed, the default path unchanged, and simulation
on a moving base against the equivalence principle."""
from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
import torch

from tflearn import dynamics as D

from conftest import DT, GRAVITY, make_body, q_to_pin, random_coords, to_pin

N = 8


def _base_case(rng):
    """Random free-flyer states: pose (x, R), spatial velocity (v, ω) and spatial
    acceleration (v̇, ω̇) in the base frame (Pinocchio's local convention)."""
    R = [pin.exp3(rng.normal(size=3)) for _ in range(N)]
    x, v, w, dv, dw = (rng.normal(size=(N, 3)) for _ in range(5))
    return R, x, v, w, dv, dw


@pytest.mark.parametrize("name", ["arm_offsets", "tree"])
def test_moving_base_against_pinocchio(name, rng):
    """Arm joint torques τ = RNEA(q, v, a; base) and accelerations with a prescribed
    base motion equal Pinocchio's free-flyer model: the arm rows of rnea(q, v, a) with
    the base's (v, ω, v̇, ω̇), and M_arm⁻¹(τ − those rows at a = 0). tflearn's base
    input is (ω, ω̇, v̇ + ω × v) and gravity Rᵀ g."""
    body = make_body(name, GRAVITY)
    model = to_pin(body, free_flyer=True)
    data = model.createData()
    q = random_coords(body, rng, N)
    qd, qdd, tau = (2.0 * rng.normal(size=q.shape) for _ in range(3))
    R, x, v, w, dv, dw = _base_case(rng)
    ref_tau, ref_acc = [], []
    for k in range(N):
        qp = np.concatenate([x[k], pin.Quaternion(R[k]).coeffs(), q_to_pin(body, q[k])])
        vp = np.concatenate([v[k], w[k], qd[k]])
        ref_tau.append(pin.rnea(model, data, qp, vp, np.concatenate([dv[k], dw[k], qdd[k]]))[6:])
        h = pin.rnea(model, data, qp, vp, np.concatenate([dv[k], dw[k], np.zeros(body.nv)]))[6:]
        M = pin.crba(model, data, qp)[6:, 6:]
        M = np.triu(M) + np.triu(M, 1).T
        ref_acc.append(np.linalg.solve(M, tau[k] - h))
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=DT)
    g = t([Rk.T @ np.array(GRAVITY) for Rk in R])
    base = (t(w), t(dw), t(dv + np.cross(w, v)))
    got = D.rnea(body, t(q), t(qd), t(qdd), gravity=g, base=base)
    np.testing.assert_allclose(got.numpy(), np.array(ref_tau), rtol=1e-10, atol=1e-10)
    acc = D.forward_dynamics(body, t(q), t(qd), t(tau), gravity=g, base=base)
    np.testing.assert_allclose(acc.numpy(), np.array(ref_acc), rtol=1e-9, atol=1e-9)


def test_resting_base_is_the_default(rng):
    """A base at rest, (0, 0, 0), gives exactly the fixed-base results."""
    body = make_body("arm_offsets", GRAVITY)
    q, v, a = (torch.as_tensor(x, dtype=DT) for x in
               (random_coords(body, rng, 4), rng.normal(size=(4, 7)), rng.normal(size=(4, 7))))
    zero = torch.zeros(4, 3, dtype=DT)
    assert torch.equal(D.rnea(body, q, v, a, base=(zero, zero, zero)), D.rnea(body, q, v, a))
    assert torch.equal(D.forward_dynamics(body, q, v, a, base=(zero, zero, zero)),
                       D.forward_dynamics(body, q, v, a))


def _sim(body, program, base=None, T=0.3):
    from tflearn.simulate import SimOptions, simulate
    t = torch.linspace(0, T, 9, dtype=DT)
    q0 = torch.tensor([0.3, -0.2, 0.1, -0.8, 0.2, 0.1, -0.3], dtype=DT)
    return simulate(body, program, q0, torch.zeros(7, dtype=DT), t,
                    SimOptions(rtol=1e-9, atol=1e-11), base=base)


def test_base_motion_derivatives():
    """The spline of a base turning about a fixed axis at ω(t) = ω0 + α t and moving on
    x(t) = ½ a t² gives ω, ω̇ and the acceleration in the base frame."""
    from tflearn.torso import BaseMotion
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    t = np.linspace(0, 1, 201)
    ang = 0.5 * t + 0.5 * 1.5 * t ** 2
    R = np.array([pin.exp3(a * axis) for a in ang])
    acc = np.array([0.3, -1.0, 2.0])
    base = BaseMotion(t, R, 0.5 * t[:, None] ** 2 * acc)
    Rt, w, dw, a = base(0.37)
    np.testing.assert_allclose(Rt.numpy(), pin.exp3((0.5 * 0.37 + 0.75 * 0.37 ** 2) * axis), atol=1e-9)
    np.testing.assert_allclose(w.numpy(), (0.5 + 1.5 * 0.37) * axis, atol=1e-7)
    np.testing.assert_allclose(dw.numpy(), 1.5 * axis, atol=1e-5)
    np.testing.assert_allclose(a.numpy(), Rt.numpy().T @ acc, atol=1e-7)


def test_simulation_on_a_moving_base():
    """Equivalence principle: a base accelerating at a (no gravity) moves the arm as a
    fixed base under gravity −a; a base held turned by R under gravity g as a fixed one
    under Rᵀ g. And gravity fed forward holds the arm still under gravity."""
    from tflearn.body import arm
    from tflearn.simulate import zero_program
    from tflearn.torso import BaseMotion, gravity_feedforward
    t = np.linspace(0, 0.5, 51)
    a = np.array([1.0, -2.0, 4.0])
    free = _sim(arm(), zero_program, BaseMotion(t, np.broadcast_to(np.eye(3), (51, 3, 3)),
                                                0.5 * t[:, None] ** 2 * a))
    fixed = _sim(arm(gravity=list(-a)), zero_program)
    assert float((free.q - fixed.q).abs().max()) < 1e-8
    assert float((free.q[-1] - free.q[0]).abs().max()) > 0.05            # it did move
    Rb = pin.exp3(np.array([0.4, -0.3, 0.9]))
    turned = _sim(arm(gravity=list(GRAVITY)), zero_program, BaseMotion(t, np.broadcast_to(Rb, (51, 3, 3)),
                                                                      np.zeros((51, 3))))
    fixed = _sim(arm(gravity=list(Rb.T @ np.array(GRAVITY))), zero_program)
    assert float((turned.q - fixed.q).abs().max()) < 1e-8
    body = arm(gravity=list(GRAVITY))
    held = _sim(body, gravity_feedforward(body, zero_program))
    assert float((held.q - held.q[0]).abs().max()) < 1e-8
