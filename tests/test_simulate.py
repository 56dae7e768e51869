"""tflearn.simulation.simulate: conservation laws, the work–energy identity, quaternion state and
gradients.

Accuracy note. torchdiffeq's ``dopri8`` returns the states at the requested times from a
4th-order dense-output interpolant, not from its 8th-order steps: at rtol = atol = 1e-12
that interpolant alone puts ~1e-7 into the state and ~2e-8 into the kinetic energy of the
free arm. ``options={"step_t": t}`` makes the solver step onto every sample time, so the
returned values are step-end values and the drift drops to the integration error
(figures measured at the settings used below are quoted in each test).
"""
from __future__ import annotations

import math

import pytest
import torch
from torch.autograd import gradcheck
from torch.func import functional_call
from torchdiffeq import odeint

from tflearn.model.fields import FieldBasis
from tflearn.model.program import FieldProgram
from tflearn.model.weights import MotionWeights
from tflearn.physics import body as tb
from tflearn.physics import configspace as C
from tflearn.physics import dynamics as D
from tflearn.simulation import simulate as S

from conftest import ARM_OFFSETS, DT, GRAVITY, wrap_angle


def tight(t, tol):
    """dopri8 at rtol = atol = tol, stepping onto every sample time (see module note)."""
    return S.SimOptions(method="dopri8", rtol=tol, atol=tol, solver_options={"step_t": t[1:]})


def energy(body, traj):
    T = D.kinetic_energy(body, traj.q, traj.v)
    V = D.potential_energy(body, traj.q)
    return T, V


def free_arm(**kw):
    return tb.arm(offsets=ARM_OFFSETS, **kw)


# ------------------------------------------------------------------------- energy

def test_kinetic_energy_conserved_without_gravity(gen):
    # Measured: max relative drift 6.0e-14 over 3 s (dopri8, rtol = atol = 1e-12,
    # step_t = t, q0, v0 ~ randn, batch of 2; 2992 right-hand-side evaluations).
    # Without step_t the same run drifts 2.0e-8, failing the bar: that is the
    # interpolant (see the module note), not the integration.
    body = free_arm()
    assert body.gravity == (0.0, 0.0, 0.0) and body.damping == 0.0
    q0 = torch.randn(2, 7, dtype=DT, generator=gen)
    v0 = torch.randn(2, 7, dtype=DT, generator=gen)
    t = torch.linspace(0.0, 3.0, 31, dtype=DT)
    traj = S.simulate(body, S.zero_program, q0, v0, t, tight(t, 1e-12))
    assert traj.q.shape == (2, 31, 7) and traj.v.shape == (2, 31, 7) and traj.work is None
    assert torch.equal(traj.v[:, 0], v0)
    assert float((traj.v - v0[:, None]).abs().max()) > 0.5  # the velocities really change
    T, _ = energy(body, traj)
    drift = ((T - T[:, :1]).abs() / T[:, :1]).max()
    assert float(drift) <= 1e-8


def test_total_energy_conserved_with_gravity(gen):
    # Measured: max |E(t) − E(0)| / max_t max(T, |V − V(0)|) = 4.0e-13 over 1 s
    # (dopri8, rtol = atol = 1e-11, step_t = t, q0, v0 ~ randn, batch of 2; 1900
    # evaluations; V swings by 3.9 J and 1.5 J).
    body = free_arm(gravity=list(GRAVITY))
    q0 = torch.randn(2, 7, dtype=DT, generator=gen)
    v0 = torch.randn(2, 7, dtype=DT, generator=gen)
    t = torch.linspace(0.0, 1.0, 11, dtype=DT)
    traj = S.simulate(body, S.zero_program, q0, v0, t, tight(t, 1e-11))
    T, V = energy(body, traj)
    E = T + V
    exchanged = (V - V[:, :1]).abs().amax(-1)
    assert float(exchanged.min()) > 1.0  # gravity really moves the arm
    scale = torch.maximum(T.abs().amax(-1), exchanged)
    drift = ((E - E[:, :1]).abs().amax(-1) / scale).max()
    assert float(drift) <= 1e-8


def _field_program(gen, N, M, n=7, scale=0.3):
    eta = 0.5 * torch.randn(M, n, dtype=DT, generator=gen)
    K = torch.diag_embed(0.5 + 1.5 * torch.rand(M, n, dtype=DT, generator=gen))
    basis = FieldBasis(eta, K, kind="block", blocks=[3, 1, 3])
    a = scale * (0.5 + torch.rand(N, M, dtype=DT, generator=gen))
    b = scale * (0.5 + torch.rand(N, M, dtype=DT, generator=gen))
    weights = MotionWeights(a, b, duration=torch.full((N,), 0.8, dtype=DT),
                              pulse_onset=0.1 * torch.rand(N, M, dtype=DT, generator=gen))
    return FieldProgram(basis, weights)


def test_work_equals_energy_gain(gen):
    # Measured: max |ΔE(t) − W(t)| / max_t |W(t)| = 1.0e-10 over 1 s (dopri8,
    # rtol = atol = 1e-10, step_t = t, 2 motions × 3 fields, with gravity; work scales
    # 0.13 J and 0.33 J; 3265 evaluations). At 1e-11 it is 8.8e-12 for twice the time.
    body = free_arm(gravity=list(GRAVITY))
    program = _field_program(gen, N=2, M=3)
    q0 = 0.5 * torch.randn(2, 7, dtype=DT, generator=gen)
    v0 = 0.5 * torch.randn(2, 7, dtype=DT, generator=gen)
    t = torch.linspace(0.0, 1.0, 11, dtype=DT)
    with torch.no_grad():
        traj = S.simulate(body, program, q0, v0, t, tight(t, 1e-10), track_work=True)
    assert traj.work.shape == (2, 11) and float(traj.work[:, 0].abs().max()) == 0.0
    T, V = energy(body, traj)
    gain = (T + V) - (T + V)[:, :1]
    work_scale = traj.work.abs().amax(-1)
    assert float(work_scale.min()) > 0.05  # the program does real work
    err = ((gain - traj.work).abs().amax(-1) / work_scale).max()
    assert float(err) <= 1e-8


def test_damping_dissipates_energy(gen):
    # A damped body under no torque is the undamped body under the program τ = −c v; the
    # work of that program is the energy change, and it is negative and decreasing.
    # Measured: |ΔE − W| / max |W| = 6.4e-14, states agree to 1.1e-11 (dopri8, 1e-10).
    # c is kept small: damping on the hand's tiny spin inertia (2e-4 kg m²) makes the
    # equations stiff (time constant I/c), and an explicit solver then crawls.
    c = 0.05
    body = free_arm(gravity=list(GRAVITY))
    q0 = torch.randn(2, 7, dtype=DT, generator=gen)
    v0 = torch.randn(2, 7, dtype=DT, generator=gen)
    t = torch.linspace(0.0, 0.5, 11, dtype=DT)
    damped = S.simulate(body.with_(damping=c), S.zero_program, q0, v0, t, tight(t, 1e-10))
    driven = S.simulate(body, lambda t, q, v: -c * v, q0, v0, t, tight(t, 1e-10),
                        track_work=True)
    assert float((damped.q - driven.q).abs().max()) <= 1e-8
    assert float((damped.v - driven.v).abs().max()) <= 1e-8
    T, V = energy(body, damped)
    E = T + V
    dE = E[:, 1:] - E[:, :-1]
    assert bool((dE < 0).all())  # strictly decreasing at every sample
    dW = driven.work[:, 1:] - driven.work[:, :-1]
    assert bool((dW < 0).all())
    scale = driven.work.abs().amax(-1, keepdim=True)
    assert float(((E - E[:, :1] - driven.work).abs() / scale).max()) <= 1e-8


# -------------------------------------------------------------------- orientation

def _quat_slices(body):
    out, k = [], 0
    for link in body.links:
        if link.joint == "ball":
            out.append(slice(k, k + 4))
            k += 4
        else:
            k += link.dof
    assert k == C.n_position(body)
    return out


def test_raw_quaternion_norms_stay_one(gen):
    # Measured: max ||quat| − 1| = 9.5e-13 over 1.5 s (dopri8, rtol = atol = 1e-10,
    # step_t = t, v0 ~ 2 randn, no gravity).
    body = free_arm()
    q0 = torch.randn(2, 7, dtype=DT, generator=gen)
    v0 = 2.0 * torch.randn(2, 7, dtype=DT, generator=gen)
    t = torch.linspace(0.0, 1.5, 16, dtype=DT)
    y0 = C.pack(body, q0, v0)
    assert y0.shape == (2, C.n_position(body) + 7)
    opts = tight(t, 1e-10)
    ys = odeint(S.ArmODE(body, S.zero_program), y0, t, method=opts.method, rtol=opts.rtol,
                atol=opts.atol, options=opts.solver_options)
    norms = torch.stack([ys[..., s].norm(dim=-1) for s in _quat_slices(body)])
    assert float((norms - 1).abs().max()) <= 1e-9
    # The quaternions really travel (they would also stay unit if nothing moved).
    quats0 = torch.stack([y0[..., s] for s in _quat_slices(body)])
    assert float((torch.stack([ys[-1, ..., s] for s in _quat_slices(body)]) - quats0).abs().max()) > 0.5
    # unpack reads them as rotation matrices in SO(3) and principal vectors |v| ≤ π.
    rots, coords, _, _ = C.unpack(body, ys)
    for R in (rots[0], rots[2]):
        eye = torch.eye(3, dtype=DT)
        assert float((R.transpose(-1, -2) @ R - eye).abs().max()) <= 1e-13
    for cols in (slice(0, 3), slice(4, 7)):
        assert float(coords[..., cols].norm(dim=-1).max()) <= math.pi + 1e-12


def test_free_spin_wraps_through_pi():
    """One symmetric ball-jointed body spinning about its axis z at rate ω from ν = 0: the
    principal rotation vector is (0, 0, wrap(ωt)), wrap to (−π, π]."""
    omega = 2.7
    body = tb.chain(1, "ball")
    assert body.gravity == (0.0, 0.0, 0.0)
    q0 = torch.zeros(1, 3, dtype=DT)  # exactly the zero rotation
    v0 = torch.tensor([[0.0, 0.0, omega]], dtype=DT)
    t = torch.linspace(0.0, 3.0, 61, dtype=DT)
    traj = S.simulate(body, S.zero_program, q0, v0, t, tight(t, 1e-12))
    # Measured: max error 8e-15 (dopri8, rtol = atol = 1e-12, step_t = t).
    angle = torch.as_tensor(wrap_angle((omega * t).numpy()), dtype=DT)
    expect = torch.zeros(61, 3, dtype=DT)
    expect[:, 2] = angle
    # Samples straddle π (ωt = 3.105 and 3.240 wrap to 3.105 and −3.043) and 2π.
    assert float(angle.max()) > 3.1 and float(angle.min()) < -3.0
    assert float((traj.q[0] - expect).abs().max()) <= 1e-9
    assert float((traj.v[0] - v0).abs().max()) <= 1e-12


def test_gradient_wrt_q0_at_zero_rotation(gen):
    body = free_arm(gravity=list(GRAVITY))
    q0 = torch.zeros(1, 7, dtype=DT)
    v0 = torch.randn(1, 7, dtype=DT, generator=gen)
    wq = torch.randn(3, 7, dtype=DT, generator=gen)
    wv = torch.randn(3, 7, dtype=DT, generator=gen)
    t = torch.tensor([0.0, 0.05, 0.1], dtype=DT)
    kw = S.SimOptions(method="rk4", solver_options={"step_size": 0.01})

    def loss(q0):
        traj = S.simulate(body, S.zero_program, q0, v0, t, kw)
        return (traj.q[0] * wq).sum() + (traj.v[0] * wv).sum()

    x = q0.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(loss(x), x)
    assert torch.isfinite(grad).all()
    h = 1e-6
    fd = torch.stack([(loss(q0 + h * e) - loss(q0 - h * e)) / (2 * h)
                      for e in torch.eye(7, dtype=DT)[:, None]]).reshape(1, 7)
    assert float((grad - fd).abs().max()) <= 1e-6 * float(fd.abs().max())


def test_gradcheck_simulate_wrt_v0_and_field_centre(gen):
    body = free_arm(gravity=list(GRAVITY))
    program = _field_program(gen, N=1, M=2, scale=1.0)
    q0 = 0.5 * torch.randn(1, 7, dtype=DT, generator=gen)
    v0 = torch.randn(1, 7, dtype=DT, generator=gen).requires_grad_(True)
    eta = program.basis.eta.detach().clone().requires_grad_(True)
    t = torch.tensor([0.0, 0.05, 0.1], dtype=DT)

    def run(v0, eta):
        def prog(tt, q, v):
            return functional_call(program, {"basis.eta": eta}, (tt, q, v))
        rk4 = S.SimOptions(method="rk4", solver_options={"step_size": 0.01})
        traj = S.simulate(body, prog, q0, v0, t, rk4)
        return traj.q, traj.v

    # The field centre matters to the result (so the check is not vacuous).
    with torch.no_grad():
        q_a, _ = run(v0, eta)
        q_b, _ = run(v0, eta + 0.1)
    assert float((q_a - q_b).abs().max()) > 1e-4
    assert gradcheck(run, (v0, eta), fast_mode=True)


def test_max_evals_bounds_a_whole_simulation():
    """``max_evals`` counts right-hand-side evaluations over the whole run (torchdiffeq's
    max_num_steps counts steps between two output times only): 2 s of a freely spinning
    arm at rtol 1e-9 needs far more than 60 (dopri5 makes 6 per step), while a budget
    above what it uses lets the same run finish with the same result."""
    body = tb.arm()
    q0 = torch.tensor([[0.3, 0.2, -0.1, -1.0, 0.2, 0.1, 0.0]], dtype=DT)
    v0 = torch.tensor([[2.0, -1.0, 0.5, 3.0, 1.0, -2.0, 0.5]], dtype=DT)
    t = torch.linspace(0, 2, 21, dtype=DT)
    kw = dict(rtol=1e-9, atol=1e-9)
    with pytest.raises(S.SimulationFailed, match="more than 60 right-hand-side evaluations") as err:
        S.simulate(body, S.zero_program, q0, v0, t, S.SimOptions(max_evals=60, **kw))
    assert err.value.reason == "budget"
    free = S.simulate(body, S.zero_program, q0, v0, t, S.SimOptions(max_evals=None, **kw))
    bounded = S.simulate(body, S.zero_program, q0, v0, t, S.SimOptions(max_evals=100000, **kw))
    assert torch.equal(free.q, bounded.q)
