"""Field damping (impedance, thesis §4.5.2): χ_i(ν, v) = −K_i (ν − η_i + ζ v) g_i(ν).

The field's value against a hand-written formula and its gradients by gradcheck; ζ = 0
is the thesis' field exactly; on a hinge chain under constant activations the fields'
conservative part has the potential −Σ a_i g_i(ν), so the mechanical energy falls by
exactly the damping work; the torque fit recovers a damped generating field; the basis
file round-trips ζ and older formats load with ζ = 0; the search scores damped
candidates exactly as the weight solve does.
"""
from __future__ import annotations

import json
import math

import pytest
import torch
from torch.autograd import gradcheck
from torch.func import functional_call

from tflearn import config
from tflearn.data import gestures
from tflearn.fit import search, targets, torque
from tflearn.io import basis as bio
from tflearn.model.fields import FieldBasis
from tflearn.model.program import FieldProgram, model_from_state, model_state
from tflearn.model.weights import MotionWeights
from tflearn.physics import dynamics
from tflearn.physics.body import chain
from tflearn.simulation.simulate import SimOptions, simulate

DT = torch.float64


def _full_basis(M=3, n=4, damping=0.4, seed=0):
    g = torch.Generator().manual_seed(seed)
    L = torch.randn(M, n, n, generator=g, dtype=DT).tril() + 2 * torch.eye(n, dtype=DT)
    return FieldBasis(torch.randn(M, n, generator=g, dtype=DT), L @ L.transpose(-1, -2),
                      kind="full", damping=damping)


def test_damped_field_equals_its_formula():
    basis = _full_basis()
    g = torch.Generator().manual_seed(1)
    q, v = torch.randn(5, 4, generator=g, dtype=DT), torch.randn(5, 4, generator=g, dtype=DT)
    chi = basis(q, v)
    assert chi.shape == (5, 3, 4)
    K, eta = basis.K().detach(), basis.eta.detach()
    for s in range(5):
        for i in range(3):
            d = q[s] - eta[i]
            want = -K[i] @ (d + 0.4 * v[s]) * math.exp(-0.5 * float(d @ K[i] @ d))
            assert torch.allclose(chi[s, i], want, rtol=1e-13, atol=1e-15)
    # power of the damping part: −ζ g vᵀKv ≤ 0 for every field
    damp = chi - basis(q)
    assert bool(((damp * v[:, None]).sum(-1) <= 0).all())


def test_zero_damping_is_the_thesis_field():
    basis = _full_basis(damping=0.0)
    q, v = torch.randn(6, 4, dtype=DT), torch.randn(6, 4, dtype=DT)
    assert torch.equal(basis(q, v), basis(q))
    damped = basis.like(basis.eta.detach(), basis.K().detach())
    assert damped.damping == 0.0
    assert not torch.equal(_full_basis(damping=0.1)(q, v), _full_basis(damping=0.1)(q))


def test_damped_field_gradcheck():
    basis = _full_basis(M=2, n=3, damping=0.3)
    q = torch.randn(4, 3, dtype=DT, requires_grad=True)
    v = torch.randn(4, 3, dtype=DT, requires_grad=True)
    params = {k: p.detach().clone().requires_grad_() for k, p in basis.named_parameters()}

    def f(q, v, eta, raw):
        return functional_call(basis, {"eta": eta, "stiffness.raw": raw}, (q, v))
    assert gradcheck(f, (q, v, params["eta"], params["stiffness.raw"]))


def test_bad_damping_refused():
    with pytest.raises(ValueError, match="damping ratio"):
        FieldBasis.empty(3, damping=-0.1)
    with pytest.raises(ValueError, match="damping ratio"):
        FieldBasis.empty(3, damping=math.inf)
    with pytest.raises(config.ConfigError, match="field_damping"):
        config.load(None, ["model.field_damping=-1"])


def test_state_round_trip_keeps_damping():
    basis = _full_basis(damping=0.25)
    weights = MotionWeights.zeros(3, torch.tensor([1.0], dtype=DT))
    b2, _ = model_from_state(model_state(basis, weights))
    assert b2.damping == 0.25
    state = model_state(basis, weights)
    del state["damping"]                          # a checkpoint from before field damping
    assert model_from_state(state)[0].damping == 0.0


# ----------------------------------------------------------------------- energy balance

def _energy_run(zeta: float):
    """A 3-link hinge chain held by two fields with constant weights (a step of 10 ms
    already done at t = 0.01 s), from a spread posture: ν, v on a fine grid."""
    body = chain(3)
    basis = FieldBasis(torch.tensor([[0.6, -0.4, 0.3], [-0.5, 0.2, 0.7]], dtype=DT),
                       torch.stack([torch.diag(torch.tensor(k, dtype=DT))
                                    for k in ([1.5, 0.8, 2.0], [0.7, 1.2, 0.9])]),
                       kind="diag", damping=zeta)
    a = torch.tensor([[0.8, 0.5]], dtype=DT)
    weights = MotionWeights(a, torch.zeros_like(a), torch.tensor([3.0], dtype=DT),
                            step_duration=torch.full_like(a, 0.01))
    t = torch.linspace(0.01, 3.0, 3001, dtype=DT)
    q0 = torch.tensor([[-0.9, 1.1, -0.6]], dtype=DT)
    v0 = torch.tensor([[0.5, -1.0, 0.8]], dtype=DT)
    with torch.no_grad():
        tr = simulate(body, FieldProgram(basis, weights), q0, v0, t,
                      SimOptions(method="dopri8", rtol=1e-11, atol=1e-12), track_work=True)
    return body, basis, a[0], tr


def _mechanical_energy(body, basis, a, q, v):
    """T(q, v) − Σ_i a_i g_i(ν): kinetic energy plus the fields' potential (hinges: ν = q,
    and χ_i = ∇ g_i, so Σ a_i χ_i = −∇(−Σ a_i g_i))."""
    d = q.unsqueeze(-2) - basis.eta.detach()
    g = torch.exp(-0.5 * (d * (basis.K().detach() * d.unsqueeze(-2)).sum(-1)).sum(-1))
    return dynamics.kinetic_energy(body, q, v) - (a * g).sum(-1)


@pytest.mark.slow
def test_field_damping_dissipates_exactly_its_work():
    """E(t) − E(0) equals the damping work W_D = ∫ Σ_i a_i (−ζ g_i vᵀ K_i v) dt (trapezoid
    on 3,001 samples) to 1e-6 of the energy lost, E never rises, and ζ = 0 conserves E to
    1e-6 of the largest kinetic energy (the solver's error: measured 1.3e-7 J against a
    peak kinetic energy of 0.86 J; the damped run loses 0.90 J)."""
    body, basis, a, tr = _energy_run(0.4)
    q, v = tr.q[0], tr.v[0]
    E = _mechanical_energy(body, basis, a, q, v)
    with torch.no_grad():
        damp = (a[:, None] * (basis(q, v) - basis(q))).sum(-2)             # T×n
    power = (damp * v).sum(-1)
    W = torch.cumulative_trapezoid(power, tr.t)
    lost = float(E[0] - E[-1])
    assert lost > 0.05
    assert float((E[1:] - E[:-1]).max()) <= 1e-9
    assert torch.allclose(E[1:] - E[0], W, atol=1e-6 * lost, rtol=0)
    # the program's own work (track_work) is the conservative part's plus the damping's
    kinetic = dynamics.kinetic_energy(body, q, v)
    assert torch.allclose(tr.work[0], kinetic - kinetic[0], atol=1e-8)
    body, basis, a, tr = _energy_run(0.0)
    E = _mechanical_energy(body, basis, a, tr.q[0], tr.v[0])
    peak = float(dynamics.kinetic_energy(body, tr.q[0], tr.v[0]).max())
    assert float((E - E[0]).abs().max()) <= 1e-6 * peak


# ----------------------------------------------------------------------- torque fit

@pytest.fixture(scope="module")
def damped_come_here():
    """come_here's field (k = 1, a = 3) with ζ = 0.5, simulated from rest at 100 Hz."""
    (m, lb), = gestures.generate(gestures=[gestures.GESTURES["come_here"]])
    basis = lb.basis.like(lb.basis.eta.detach(), lb.basis.K().detach())
    basis.damping = 0.5
    with torch.no_grad():
        tr = simulate(lb.body, FieldProgram(basis, lb.weights), lb.q0, lb.qd0, m.t,
                      SimOptions(method="dopri8", rtol=1e-10, atol=1e-10,
                                 solver_options={"step_t": m.t[1:]}))
    from tflearn.motions.motion import Motion
    motion = Motion("damped", m.t, tr.q[0], tr.v[0])
    return lb, basis, motion, targets.prepare(lb.body, [motion])


@pytest.mark.slow
def test_torque_fit_recovers_a_damped_field(damped_come_here):
    """With the generating field and ζ the NNLS weights are a = 3 (to 1e-4) at the
    spline's own error (cost ≤ 1e-8); the same field without damping cannot fit it."""
    lb, basis, _, tg = damped_come_here
    w = MotionWeights.zeros(1, tg.duration, tg.names)
    cost = float(torque.solve_weights(basis, w, tg)[0])
    assert cost <= 1e-8
    a, b = w.a.detach()[0, 0], w.b.detach()[0, 0]
    assert abs(float(a) - 3.0) <= 1e-4 and float(b) <= 1e-3
    undamped = lb.basis.like(basis.eta.detach(), basis.K().detach())
    assert float(torque.solve_weights(undamped, MotionWeights.zeros(1, tg.duration, tg.names), tg)[0]) > 1e-3


def test_candidate_scores_carry_the_damping(damped_come_here):
    """score_candidates' cost of an isotropic candidate equals solve_weights' cost of a
    damped basis holding it (to 1e-10), and differs from the undamped one."""
    _, basis, _, tg = damped_come_here
    empty = FieldBasis.empty(7, "scalar", [3, 1, 3], damping=0.5)
    w0 = MotionWeights.zeros(0, tg.duration, tg.names)
    centres = torch.stack([basis.eta.detach()[0], basis.eta.detach()[0] + 0.2])
    scores = search.score_candidates(empty, w0, tg, centres, [0.5, 1.0])
    for c in range(2):
        for s, k in enumerate([0.5, 1.0]):
            one = empty.extend(centres[c:c + 1], k * torch.eye(7, dtype=DT)[None])
            want = float(torque.solve_weights(one, MotionWeights.zeros(1, tg.duration, tg.names), tg)[0])
            assert abs(float(scores[c, s]) - want) <= 1e-10
    plain = search.score_candidates(FieldBasis.empty(7, "scalar", [3, 1, 3]), w0, tg, centres, [1.0])
    assert float(plain[0, 0]) > 1e-3 > float(scores[0, 1])


# ----------------------------------------------------------------------- basis file

def test_basis_file_round_trips_damping(damped_come_here, tmp_path):
    lb, basis, _, _ = damped_come_here
    src = bio.LearnedBasis(lb.body, basis, lb.weights, lb.q0, lb.qd0, lb.rate)
    bio.save(src, tmp_path / "basis.json")
    doc = json.loads((tmp_path / "basis.json").read_text())
    assert doc["format"] == "tflearn-basis/3" and doc["field_damping"] == 0.5
    assert bio.load(tmp_path / "basis.json").basis.damping == 0.5
    old = dict(doc, format="tflearn-basis/2")
    del old["field_damping"]
    assert bio.from_dict(old).basis.damping == 0.0
    with pytest.raises(bio.BasisFileError, match="belongs to tflearn-basis/3"):
        bio.from_dict(dict(old, field_damping=0.5))
    for bad, match in (({k: v for k, v in doc.items() if k != "field_damping"}, "field_damping"),
                       (dict(doc, field_damping=-0.2), "non-negative"),
                       (dict(doc, field_damping="x"), "field_damping")):
        (tmp_path / "bad.json").write_text(json.dumps(bad))
        with pytest.raises(bio.BasisFileError, match=match):
            bio.load(tmp_path / "bad.json")


def test_slsqp_refuses_field_damping(tmp_path):
    from tflearn import train
    cfg = config.load(None, ["solver.method=slsqp", "model.fields=2", "model.field_damping=0.2",
                             f"out={tmp_path}"])
    with pytest.raises(config.ConfigError, match="field_damping"):
        train.run(cfg)
    assert not (tmp_path / "checkpoint.pt").exists()
