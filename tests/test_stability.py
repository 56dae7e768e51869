"""The local error growth rate (tflearn.fit.stability) against closed-form linearisations."""
import math

import torch

from tflearn.fit.stability import growth, jacobians, program_growth, program_jacobians
from tflearn.fit.targets import prepare
from tflearn.model.fields import FieldBasis
from tflearn.model.weights import MotionWeights
from tflearn.motions.motion import Motion
from tflearn.motions.torso import BaseMotion, Bases
from tflearn.physics import body as tb
from tflearn.physics import dynamics

F64 = torch.float64


def held(body, q, duration=1.0, samples=51, name="held"):
    """A motion resting at posture q."""
    t = torch.linspace(0, duration, samples, dtype=F64)
    qs = q.expand(samples, -1).clone()
    return Motion(name, t, qs, torch.zeros_like(qs), body=body)


def one_field(eta, k, zeta=0.0, a=1.0, duration=1.0):
    """One isotropic field K = k I at η, step weight a over ``duration``."""
    n = eta.shape[-1]
    basis = FieldBasis(eta[None], k * torch.eye(n, dtype=F64)[None], kind="scalar", damping=zeta)
    weights = MotionWeights(torch.tensor([[a]], dtype=F64), torch.zeros(1, 1, dtype=F64),
                            torch.tensor([duration], dtype=F64))
    return basis, weights


def spring_damper_spectrum(M, stiffness, damping):
    """Eigenvalues of δν̈ = −M⁻¹(S δν + C δν̇) for S = stiffness·I, C = damping·I."""
    n = M.shape[-1]
    Minv = torch.linalg.inv(M)
    A = torch.cat([torch.cat([torch.zeros(n, n, dtype=F64), torch.eye(n, dtype=F64)], 1),
                   torch.cat([-stiffness * Minv, -damping * Minv], 1)])
    return torch.linalg.eigvals(A)


def assert_same_spectrum(got, want, tol):
    got = sorted(got.tolist(), key=lambda z: (round(z.real, 6), z.imag))
    want = sorted(want.tolist(), key=lambda z: (round(z.real, 6), z.imag))
    assert len(got) == len(want)
    assert max(abs(g - w) for g, w in zip(got, want)) < tol


def test_hinge_chain_at_a_field_centre_is_a_spring_damper():
    """A planar chain held at a field's centre (no gravity): A has the spectrum of
    M δν̈ = −w k δν − (c + w k ζ) δν̇, w = a ψ(t/λ) the field's activation at each sample."""
    body = tb.chain(3, "hinge", damping=0.05)
    eta = torch.tensor([0.4, -0.7, 0.3], dtype=F64)
    k, zeta = 2.0, 0.1
    basis, weights = one_field(eta, k, zeta, a=3.0)
    tg = prepare(body, [held(body, eta)])
    A = jacobians(body, basis, weights, tg)
    M = dynamics.mass_matrix(body, eta)
    w = weights.activation(tg.t[0])[:, 0, 0]
    for i in (0, 10, 25, 50):
        want = spring_damper_spectrum(M, w[i] * k, body.damping + w[i] * k * zeta)
        assert_same_spectrum(torch.linalg.eigvals(A[0, i]), want, 1e-6)
    g = growth(body, basis, weights, tg)
    assert (g.rate[0, 1:] < 0).all()       # damped: errors decay once the field is on
    assert abs(float(g.rate[0, 0])) < 1e-9 and abs(float(g.efolds[0])) < 1e-9   # w(0) = 0: free


def test_any_program_linearises_to_its_own_spectrum():
    """A program that is no field, a circulatory spring τ = −(k I + S) ν − c ν̇ with S
    skew-symmetric, on a chain held at ν = 0 (no gravity): A has the spectrum of
    M δν̈ = −(k I + S) δν − (c + c_joint) δν̇: decaying for a small S, growing
    (flutter) for a large one with little damping."""
    body = tb.chain(2, "hinge", damping=0.05)
    q = torch.zeros(2, dtype=F64)
    tg = prepare(body, [held(body, q)])
    M = dynamics.mass_matrix(body, q)
    for s_, c in ((0.3, 0.5), (40.0, 0.01)):
        K = torch.tensor([[2.0, s_], [-s_, 2.0]], dtype=F64)

        def program(t, nu, v, K=K, c=c):
            return -nu @ K.T - c * v
        lam = torch.linalg.eigvals(program_jacobians(body, program, tg)[0, 10])
        Minv = torch.linalg.inv(M)
        want = torch.linalg.eigvals(torch.cat([
            torch.cat([torch.zeros(2, 2, dtype=F64), torch.eye(2, dtype=F64)], 1),
            torch.cat([-Minv @ K, -(c + body.damping) * Minv], 1)]))
        assert_same_spectrum(lam, want, 1e-6)
        assert (float(lam.real.max()) > 0.1) == (s_ > 1)      # flutter only for the large S
        assert (float(lam.real.max()) < 0) == (s_ < 1)
        g = program_growth(body, program, tg)
        assert torch.allclose(g.peak, lam.real.max().expand(1), atol=1e-6)   # held: λ constant
        assert abs(float(g.efolds[0]) - max(float(lam.real.max()), 0.0) * 1.0) < 1e-6


def test_arm_at_rest_in_a_field_has_the_spring_damper_spectrum():
    """The arm (two ball joints: quaternions reduced to their tangent spaces) at a field's
    centre ν = 0: the same closed-form spectrum, 14 eigenvalues, none of them the
    quaternions' structural zeros."""
    body = tb.arm(gravity=(0.0, 0.0, 0.0), damping=0.02)
    eta = torch.zeros(7, dtype=F64)
    basis, weights = one_field(eta, 4.0, 0.05, a=2.0)
    tg = prepare(body, [held(body, eta)])
    A = jacobians(body, basis, weights, tg)
    assert A.shape == (1, 51, 14, 14)
    M = dynamics.mass_matrix(body, eta)
    w = float(weights.activation(tg.t[0, 30])[0, 0])
    want = spring_damper_spectrum(M, w * 4.0, body.damping + w * 4.0 * 0.05)
    assert_same_spectrum(torch.linalg.eigvals(A[0, 30]), want, 1e-5)
    assert float(growth(body, basis, weights, tg).rate[0, 30]) < -1e-3


def test_a_field_met_beyond_its_inflection_pushes_errors_apart():
    """One hinge at distance d from the centre with k d² > 1: the field's slope
    −k g (1 − k d²) is a negative stiffness, λ = √(w k g (k d² − 1) / I)."""
    body = tb.chain(1, "hinge")
    k, d = 3.0, 0.9
    basis, weights = one_field(torch.zeros(1, dtype=F64), k, a=2.0)
    q = torch.tensor([d], dtype=F64)
    tg = prepare(body, [held(body, q)])
    g = growth(body, basis, weights, tg)
    inertia = float(dynamics.mass_matrix(body, q)[0, 0])
    w = weights.activation(tg.t[0])[:, 0, 0]
    slope = w * k * math.exp(-0.5 * k * d * d) * (k * d * d - 1)
    want = (slope / inertia).sqrt()
    assert torch.allclose(g.rate[0], want, atol=1e-6, rtol=1e-6)
    efolds = float(((want[1:] + want[:-1]) / 2 * tg.t[0].diff()).sum())   # trapezoid of λ
    assert abs(float(g.efolds[0]) - efolds) < 1e-6
    assert abs(float(g.peak[0]) - float(want.max())) < 1e-6


def test_inverted_pendulum_on_a_base_accelerating_upward():
    """A hinge pendulum held upside down, its base accelerating upward at a: it falls as
    e^{λt}, λ = √(m l_c (g + a) / I) — the moving base is in the linearisation; padding
    of a shorter second motion is NaN and leaves the first's numbers alone."""
    body = tb.chain(1, "hinge", gravity=(0.0, 0.0, -9.81))
    link = body.links[0]
    up = torch.tensor([math.pi], dtype=F64)
    accel = 4.0
    ts = torch.linspace(0, 2.0, 41, dtype=F64)
    x = torch.zeros(41, 3, dtype=F64)
    x[:, 2] = 0.5 * accel * ts ** 2
    base = BaseMotion(ts.numpy(), torch.eye(3, dtype=F64).expand(41, 3, 3).numpy(), x.numpy())
    motions = [held(body, up, name="long"), held(body, up, 0.5, 26, name="short")]
    tg = prepare(body, motions, base=Bases.of([base, base]))
    basis, weights = one_field(torch.zeros(1, dtype=F64), 1.0, a=0.0)
    weights = weights.select_motions([0, 0])
    g = growth(body, basis, weights, tg)
    inertia = float(dynamics.mass_matrix(body, up)[0, 0])
    lam = math.sqrt(link.mass * link.length / 2 * (9.81 + accel) / inertia)
    assert torch.allclose(g.rate[0], torch.full((51,), lam, dtype=F64), rtol=1e-6)
    assert abs(float(g.efolds[0]) - lam * 1.0) < 1e-6
    assert torch.isnan(g.rate[1, 26:]).all() and abs(float(g.efolds[1]) - lam * 0.5) < 1e-6


def test_motions_taken_a_chunk_at_a_time_give_the_same_rates(monkeypatch):
    """Growth over chunks of motions (memory bounded) equals growth over all at once."""
    from tflearn.fit import targets
    body = tb.chain(2, "hinge", damping=0.02)
    eta = torch.tensor([0.2, -0.4], dtype=F64)
    basis, weights = one_field(eta, 5.0, a=1.5)
    motions = [held(body, eta + 0.3 * i, 0.5 + 0.25 * i, 21 + 5 * i, name=f"m{i}") for i in range(3)]
    tg = prepare(body, motions)
    weights = weights.select_motions([0, 0, 0])
    whole = growth(body, basis, weights, tg)
    monkeypatch.setattr(targets, "CHUNK_BYTES", 1)
    parts = growth(body, basis, weights, tg)
    assert torch.equal(whole.rate.isnan(), parts.rate.isnan())
    assert torch.allclose(whole.rate.nan_to_num(), parts.rate.nan_to_num(), rtol=0, atol=1e-12)
    assert torch.equal(whole.efolds, parts.efolds) and float(whole.efolds.max()) > 0


def test_each_motion_is_linearised_on_the_fields_it_uses(monkeypatch):
    """Two motions, each on its own field (and a third field that neither uses), one held
    at its field's centre and one past its field's inflection: each motion's program
    holds its own field alone (:func:`own_fields`), in one chunk or one motion per chunk,
    and the rates are those of the whole basis (errors damped in the first, pushed apart
    in the second)."""
    from tflearn.fit import stability, targets
    from tflearn.model.program import FieldProgram
    body = tb.chain(2, "hinge", damping=0.02)
    eta = torch.tensor([[0.2, -0.4], [-0.3, 0.5], [1.5, 1.5]], dtype=F64)
    k = torch.tensor([5.0, 12.0, 3.0], dtype=F64)[:, None, None]
    basis = FieldBasis(eta, k * torch.eye(2, dtype=F64), kind="scalar")
    a = torch.tensor([[1.5, 0.0, 0.0], [0.0, 1.5, 0.0]], dtype=F64)
    weights = MotionWeights(a, torch.zeros_like(a), torch.tensor([1.0, 1.0], dtype=F64))
    off = eta[1] + torch.tensor([0.6, 0.0], dtype=F64)           # past the inflection, 1/√12
    tg = prepare(body, [held(body, eta[0], name="m0"), held(body, off, name="m1")])
    full = program_growth(body, FieldProgram(basis, weights), tg)
    assert float(full.rate[0, 25:].max()) < 0 < float(full.rate[1, 25:].min())   # the step on
    built = []
    monkeypatch.setattr(stability, "FieldProgram",
                        lambda b, w: built.append(b.eta.tolist()) or FieldProgram(b, w))
    for size, chunked in ((None, [[[eta[0].tolist()], [eta[1].tolist()]]]),
                          (1, [[[eta[0].tolist()]], [[eta[1].tolist()]]])):
        built.clear()
        if size:
            monkeypatch.setattr(targets, "CHUNK_BYTES", size)
        own = growth(body, basis, weights, tg)
        assert built == chunked
        assert torch.allclose(own.rate, full.rate, rtol=0, atol=1e-12)


def test_own_fields_pad_with_zero_weights():
    """Motion 0 on fields 2 and 0, motion 1 on field 1 alone: packed in field order, W = 2,
    motion 1's second slot a padding with a, b, c = 0 (its field's timing kept)."""
    from tflearn.fit.stability import own_fields
    eta = torch.arange(6, dtype=F64).reshape(3, 2)
    basis = FieldBasis(eta, torch.eye(2, dtype=F64).expand(3, 2, 2).clone(), kind="scalar")
    a = torch.tensor([[1.0, 0.0, 2.0], [0.0, 0.0, 0.0]], dtype=F64)
    b = torch.tensor([[0.0, 0.0, 0.0], [0.0, 3.0, 0.0]], dtype=F64)
    weights = MotionWeights(a, b, torch.tensor([1.0, 2.0], dtype=F64))
    fields, w = own_fields(basis, weights)
    assert fields.eta.tolist() == [[eta[0].tolist(), eta[2].tolist()], [eta[1].tolist(), eta[0].tolist()]]
    assert w.a.tolist() == [[1.0, 2.0], [0.0, 0.0]] and w.b.tolist() == [[0.0, 0.0], [3.0, 0.0]]
    assert torch.equal(w.step_duration, weights.step_duration[:, :2])


def test_elimination_refuses_a_removal_that_adds_error_growth(tmp_path):
    """``solver.reduce.growth``: a trial that keeps every motion it touches reproduced is
    still refused when it adds more than that many e-folds of error growth to one of them
    (computed once per trial, kept with it); without the option only simulation decides."""
    from tflearn import config, train
    from tflearn.fit import stability
    from tflearn.metrics import Scores
    from tflearn.train.stages import reduce
    from tflearn.train.state import Reference
    body = tb.from_config(config.load(None, []).body)
    eta = torch.zeros(7, dtype=F64)
    wild = torch.full((7,), 0.6, dtype=F64)
    tg = prepare(body, [held(body, eta, name="calm"), held(body, wild, name="wild")])
    basis, weights = one_field(eta, 4.0, a=2.0)
    weights = weights.select_motions([0, 0])
    efolds = stability.growth(body, basis, weights, tg).efolds.tolist()
    assert efolds[0] < 1e-6 and efolds[1] > 2.0          # at the centre / beyond the inflection
    reproduced = (Scores([0.0] * 2, [0.0] * 2, [0.0] * 2, tg.q, [None] * 2), [True, True])
    state = train.RunState(config={}, stage="reduce", rng=torch.zeros(1), reference=Reference(
        rmse=[0.01] * 2, tip=[0.01] * 2, ok=[True] * 2, efolds=[0.0, 0.0]))
    ctx = train.new_context(config.load(None, [f"out={tmp_path}", "solver.reduce.growth=1.0",
                                                "solver.method=pipeline"]), tg)
    trial = reduce.Trial(0, "refit", check=reproduced, motions=[0, 1], model=(basis, weights))
    assert not reduce.accepts(ctx, state, trial, tg)
    assert trial.efolds == efolds
    state.reference.efolds[1] = efolds[1] - 0.9          # within one e-fold of the reference
    assert reduce.accepts(ctx, state, trial, tg)
    state.reference.efolds[1] = 0.0
    plain = train.new_context(config.load(None, [f"out={tmp_path}", "solver.method=pipeline"]), tg)
    assert reduce.accepts(plain, state, reduce.Trial(0, "refit", check=reproduced, motions=[0, 1],
                                                     model=(basis, weights)), tg)
