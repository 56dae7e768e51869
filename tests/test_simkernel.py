"""tflearn.simulation.simkernel: the compiled simulator (field program, dynamics and per-member
Dormand–Prince in one loop) against the torch path it replaces (tflearn.simulation.ode.odeint_each
driving tflearn.simulation.simulate.ArmODE, which tests/test_ode.py holds to closed forms and
torchdiffeq): the same paths, step counts, evaluation counts and failures, on every test
body, for every kind of program it takes; and when each path is taken."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from tflearn.data import gestures
from tflearn.model.fields import FieldBasis
from tflearn.model.program import FieldProgram
from tflearn.model.weights import MotionWeights
from tflearn.physics.body import arm
from tflearn.physics.configspace import pack
from tflearn.simulation import simkernel
from tflearn.simulation.simulate import SimOptions, simulate

from conftest import BODY_NAMES, DT, GRAVITY, free_tree, make_body, random_states

EACH = SimOptions(batch="each")


def _both(monkeypatch, body, program, q0, v0, t, options=EACH, **kw):
    """(compiled, torch) trajectories of one simulation; the compiled path must be taken."""
    calls = []
    real = simkernel.integrate
    monkeypatch.setattr(simkernel, "integrate", lambda *a, **k: calls.append(1) or real(*a, **k))
    with torch.no_grad():
        fast = simulate(body, program, q0, v0, t, options, **kw)
        assert calls, "the compiled simulator was not used"
        monkeypatch.setattr(simkernel, "applies", lambda *a: False)
        slow = simulate(body, program, q0, v0, t, options, **kw)
    return fast, slow


def _same(fast, slow, tol=1e-9):
    assert fast.q.shape == slow.q.shape and fast.failure == slow.failure
    pairs = [(fast.q, slow.q), (fast.v, slow.v)] + ([(fast.work, slow.work)] if fast.work is not None else [])
    for a, b in pairs:
        assert torch.equal(torch.isnan(a), torch.isnan(b))
        ok = ~torch.isnan(b)
        assert ((a[ok] - b[ok]).abs() / (1 + b[ok].abs())).max() < tol


def _random_program(body, N, M, P, rng, damping=0.1, index=None, start=None):
    """M diagonal-stiffness fields around the origin and random step, pulse and window
    weights and timings for N motions."""
    n = body.nv
    g = torch.Generator().manual_seed(int(rng.integers(1 << 30)))
    rand = lambda *s: torch.rand(*s, generator=g, dtype=DT)
    basis = FieldBasis(0.6 * (2 * rand(M, n) - 1), torch.diag_embed(0.5 + 2 * rand(M, n)),
                       damping=damping)
    lam = 0.4 + rand(N)
    weights = MotionWeights(2 * rand(N, M), 2 * rand(N, M), lam, step_onset=0.2 * rand(N, M),
                            step_duration=lam[:, None] * (0.5 + rand(N, M)),
                            pulse_onset=0.1 * rand(N, M), pulse_duration=0.3 + rand(N, M),
                            c=rand(N, M, P), window_onset=0.3 * rand(N, P),
                            window_duration=0.2 + 0.4 * rand(N, P))
    return FieldProgram(basis, weights, index=index, start=start)


@pytest.mark.parametrize("name,g", [(n, g) for n in BODY_NAMES for g in ((0.0, 0.0, 0.0), GRAVITY)])
def test_equals_the_torch_path_on_every_body(name, g, rng, monkeypatch):
    """Field damping, body damping, P = 2 windows, an index and motion start times."""
    body = make_body(name, g).with_(damping=0.05)
    program = _random_program(body, 4, 3, 2, rng, index=[3, 1, 2],
                              start=torch.tensor([0.0, 0.1, 0.05, 0.2], dtype=DT))
    q0 = torch.as_tensor(0.4 * random_states(body, rng, 3), dtype=DT)
    v0 = torch.as_tensor(rng.normal(size=q0.shape), dtype=DT)
    t = torch.linspace(0, 0.5, 11, dtype=DT)
    fast, slow = _both(monkeypatch, body, program, q0, v0, t)
    _same(fast, slow)
    assert fast.failure == [None] * 3 and (fast.q[:, -1] - q0).abs().max() > 1e-2


@pytest.mark.parametrize("where", [0, 3])
def test_free_joints_and_a_batch_of_copies(where, rng, monkeypatch):
    """A free joint (root or inner) and a batch (2×N) of the program's motions."""
    body = free_tree(where, GRAVITY)
    program = _random_program(body, 2, 2, 1, rng, damping=0.0)
    q0 = torch.as_tensor(0.3 * random_states(body, rng, 4), dtype=DT).reshape(2, 2, -1)
    t = torch.linspace(0, 0.3, 7, dtype=DT)
    fast, slow = _both(monkeypatch, body, program, q0, torch.zeros_like(q0), t)
    assert fast.q.shape == (2, 2, 7, body.nv)
    _same(fast, slow)


def _turning_bases(rng, n, T=41, span=1.0):
    """n random moving bases (tflearn.motions.torso.Bases): each turning about its own axis at a
    varying rate and its origin swinging, sampled T times over ``span`` s."""
    import pinocchio as pin

    from tflearn.motions.torso import BaseMotion, Bases
    t = torch.linspace(0, span, T, dtype=DT).numpy()
    motions = []
    for _ in range(n):
        axis, amp, x0 = rng.normal(size=3), rng.uniform(0.5, 1.5), rng.normal(size=3)
        R = [pin.exp3(amp * (np.sin(3 * s) + s) * axis / np.linalg.norm(axis)) for s in t]
        motions.append(BaseMotion(t, R, 0.2 * np.sin(4 * t[:, None] + x0)))
    return Bases.of(motions)


@pytest.mark.parametrize("name", [pytest.param("arm_offsets", marks=pytest.mark.slow), "tree"])
def test_a_moving_base_per_member(name, rng, monkeypatch):
    """Each member on its own moving base (tflearn.motions.torso.Bases, members taken in another
    order and shifted in time, under gravity): the compiled loop's base polynomials and
    terms equal the torch path's (Bases.terms)."""
    body = make_body(name, GRAVITY).with_(damping=0.05)
    shift = torch.tensor([0.0, 0.1, 0.3], dtype=DT)
    bases = _turning_bases(rng, 2).take(torch.tensor([1, 0, 1]), shift=shift)
    program = _random_program(body, 3, 2, 1, rng)
    q0 = torch.as_tensor(0.4 * random_states(body, rng, 3), dtype=DT)
    t = torch.linspace(0, 0.5, 11, dtype=DT)
    fast, slow = _both(monkeypatch, body, program, q0, torch.zeros_like(q0), t, base=bases)
    _same(fast, slow)
    fixed = simulate(body, program, q0, torch.zeros_like(q0), t, EACH)
    assert float((fast.q[:, -1] - fixed.q[:, -1]).abs().max()) > 1e-2     # the bases matter


def test_the_gesture_library_with_its_work(monkeypatch):
    """The five gestures (P = 0, ζ = 0), the program's work integrated beside them."""
    body = arm()
    basis, weights, _ = gestures.library_model(body=body)
    q0 = torch.zeros(weights.N, body.nv, dtype=DT)
    t = torch.linspace(0, 1.5, 31, dtype=DT)
    fast, slow = _both(monkeypatch, body, FieldProgram(basis, weights), q0, q0, t, track_work=True)
    _same(fast, slow)
    assert fast.work[:, -1].abs().min() > 1e-3


def test_own_field_programs(monkeypatch):
    """gestures.own_fields_program: one group of fields per motion."""
    body = arm()
    gs = list(gestures.GESTURES.values())
    basis, weights, spans = gestures.library_model(gs, body)
    program = gestures.own_fields_program(basis, weights, spans)
    q0 = torch.zeros(len(gs), body.nv, dtype=DT)
    t = torch.linspace(0, 1.0, 21, dtype=DT)
    fast, slow = _both(monkeypatch, body, program, q0, q0, t)
    _same(fast, slow)
    with torch.no_grad():
        whole = simulate(body, FieldProgram(basis, weights), q0, q0, t, EACH)
    assert (whole.q - fast.q).abs().max() < 1e-12


def test_stacked_models(monkeypatch):
    """metrics' stack of K models, with different M, in one batch of K·N members."""
    from tflearn.metrics import _Stacked
    body = arm()
    basis, weights, _ = gestures.library_model(body=body)
    two = [0, 2]
    programs = [FieldProgram(basis, weights), FieldProgram(basis.select(two), weights.select_fields(two))]
    q0 = torch.zeros(2, weights.N, body.nv, dtype=DT)
    t = torch.linspace(0, 0.8, 17, dtype=DT)
    fast, slow = _both(monkeypatch, body, _Stacked(programs), q0, q0, t, throw=False)
    _same(fast, slow)
    assert (fast.q[0] - fast.q[1]).abs().max() > 1e-2


def test_failures_match(monkeypatch):
    """A member past its budget and one whose state is not finite stop alone, with the
    same codes, NaN samples and evaluation counts as the torch path."""
    body = arm()
    basis, weights, _ = gestures.library_model(body=body)
    hard = weights.select_motions([0, 1, 2])
    with torch.no_grad():
        hard.a_raw[1] = 1e6
    q0 = torch.zeros(3, body.nv, dtype=DT)
    q0[2, 0] = float("nan")
    t = torch.linspace(0, 1.0, 11, dtype=DT)
    opts = SimOptions(batch="each", max_evals=3000)
    fast, slow = _both(monkeypatch, body, FieldProgram(basis, hard), q0, torch.zeros_like(q0), t,
                       opts, throw=False)
    _same(fast, slow)
    assert fast.failure[0] is None and "budget" in fast.failure[1] and "NaN" in fast.failure[2]
    with torch.no_grad():
        y0 = pack(body, q0, torch.zeros_like(q0))
        sol = simkernel.integrate(body, FieldProgram(basis, hard), y0, t, rtol=1e-7, atol=1e-9,
                                  max_evals=3000)
    assert sol.failure.tolist() == [0, 1, 3] and 3000 < int(sol.evals[1]) <= 3006
    assert int(sol.steps[0]) > 5


def test_groups_share_their_steps(monkeypatch):
    """Members in a group share every step (the copies of multiple shooting): the same
    paths, steps and failures as the torch path, equal steps within a group, and a group
    of identical copies is the member alone; a non-finite member stops its group."""
    body = arm()
    basis, weights, _ = gestures.library_model(body=body)
    program = FieldProgram(basis, weights)
    q0 = torch.zeros(2, weights.N, body.nv, dtype=DT)
    q0[1, :2] = 0.2
    groups = torch.tensor([[0, 0, 1, 1, 2], [3, 4, 5, 5, 2]])
    t = torch.linspace(0, 1.0, 21, dtype=DT)
    fast, slow = _both(monkeypatch, body, program, q0, torch.zeros_like(q0), t, groups=groups)
    _same(fast, slow, tol=1e-12)
    with torch.no_grad():
        y0 = pack(body, q0, torch.zeros_like(q0))
        sol = simkernel.integrate(body, program, y0, t, rtol=1e-7, atol=1e-9, max_evals=None, groups=groups)
        alone = simkernel.integrate(body, program, y0, t, rtol=1e-7, atol=1e-9, max_evals=None)
        assert sol.steps[0, 0] == sol.steps[0, 1] and sol.steps[1, 2] == sol.steps[1, 3]
        assert sol.steps[0, 0] != alone.steps[0, 0] or sol.steps[0, 1] != alone.steps[0, 1]
        assert torch.allclose(sol.ys[:, :, 4], alone.ys[:, :, 4], rtol=0, atol=1e-12)   # copies
        q0[0, 1, 0] = float("nan")
        y0 = pack(body, q0, torch.zeros_like(q0))
        bad = simkernel.integrate(body, program, y0, t, rtol=1e-7, atol=1e-9, max_evals=None, groups=groups)
    assert bad.failure[0].tolist() == [3, 3, 0, 0, 0] and bad.failure[1].tolist() == [0] * 5


def test_taken_only_without_a_gradient(monkeypatch):
    """A program whose parameters need a gradient runs the torch path (and carries it);
    the same under no_grad runs compiled; the shared-step solver never does."""
    body = arm()
    basis, weights, _ = gestures.library_model(body=body)
    q0 = torch.zeros(weights.N, body.nv, dtype=DT)
    t = torch.linspace(0, 0.2, 5, dtype=DT)
    assert not simkernel.applies(FieldProgram(basis, weights), q0)
    tr = simulate(body, FieldProgram(basis, weights), q0, q0, t, EACH)
    assert tr.q.requires_grad
    with torch.no_grad():
        assert simkernel.applies(FieldProgram(basis, weights), q0)
        assert not simkernel.applies(lambda t, q, v: torch.zeros_like(v), q0)
        assert not simkernel.applies(FieldProgram(basis, weights), q0.float())
    monkeypatch.setattr(simkernel, "integrate", lambda *a, **k: pytest.fail("compiled for shared steps"))
    with torch.no_grad():
        simulate(body, FieldProgram(basis, weights), q0, q0, t)
