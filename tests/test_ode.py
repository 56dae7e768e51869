"""tflearn.simulation.ode: Dormand–Prince with a step size per batch member, on problems with closed
forms, against torchdiffeq's dopri5, and through :func:`tflearn.simulation.simulate.simulate`."""
import math

import pytest
import torch
from torchdiffeq import odeint

from tflearn.data import gestures
from tflearn.model.program import FieldProgram
from tflearn.physics.body import arm
from tflearn.physics.configspace import pack
from tflearn.simulation.ode import odeint_each
from tflearn.simulation.simulate import ArmODE, SimOptions, SimulationFailed, simulate

T = torch.linspace(0, 2, 41, dtype=torch.float64)


def oscillators(omega):
    """ẍ = −ω² x per member: y = (x, ẋ), x(0) = 1, so x = cos ωt."""
    w2 = torch.as_tensor(omega, dtype=torch.float64) ** 2

    def f(t, y, live=None):
        assert t.shape == y.shape[:-1]                 # a time per member
        assert live is None or live.shape == t.shape
        return torch.stack([y[..., 1], -w2 * y[..., 0]], dim=-1)
    y0 = torch.zeros(len(omega), 2, dtype=torch.float64)
    y0[:, 0] = 1
    return f, y0


def test_matches_the_closed_form_at_every_sample():
    f, y0 = oscillators([1.0, 5.0, 40.0])
    sol = odeint_each(f, y0, T, rtol=1e-9, atol=1e-11)
    exact = torch.cos(T[:, None] * torch.tensor([1.0, 5.0, 40.0], dtype=torch.float64))
    assert sol.failure.tolist() == [0, 0, 0]
    assert (sol.ys[..., 0] - exact).abs().max() < 1e-7
    # the faster a member turns, the more steps it takes, each for itself
    assert sol.steps[0] < sol.steps[1] < sol.steps[2]


def test_a_member_is_stepped_as_if_alone():
    f, y0 = oscillators([1.0, 40.0])
    both = odeint_each(f, y0, T)
    for j in range(2):
        g, y = oscillators([[1.0, 40.0][j]])
        alone = odeint_each(g, y, T)
        assert torch.equal(alone.ys[:, 0], both.ys[:, j])
        assert alone.steps[0] == both.steps[j]


def test_a_group_is_stepped_as_one_system():
    """Members in one group share every step and one error norm over all their entries:
    the group (ω = 1, 5) equals one member holding both oscillators (D = 4), its steps
    between those its members take alone; a member in a group of its own is as alone."""
    f, y0 = oscillators([1.0, 40.0, 5.0])
    grouped = odeint_each(f, y0, T, groups=torch.tensor([7, 3, 7]))
    g, y = oscillators([1.0, 5.0])

    def joint(t, x, live=None):                         # the pair as one 4-entry member
        return g(t.expand(2), x.reshape(-1, 2, 2)[0]).reshape(1, 4)
    one = odeint_each(joint, y.reshape(1, 4), T)
    assert torch.allclose(grouped.ys[:, [0, 2]].reshape(len(T), 4), one.ys[:, 0], rtol=0, atol=1e-14)
    assert grouped.steps[0] == grouped.steps[2] == one.steps[0]
    assert grouped.evals[0] == grouped.evals[2]
    alone = odeint_each(*oscillators([40.0]), T)
    assert torch.equal(grouped.ys[:, 1], alone.ys[:, 0])
    apart = odeint_each(f, y0, T)
    assert apart.steps[0] < grouped.steps[0] <= apart.steps[2]


def test_the_right_hand_side_is_told_which_members_are_live():
    """ω = 1 finishes long before ω = 40: from then on live is False for it alone, and
    the calls after it finished are the right-hand sides ω = 40 takes beyond ω = 1's."""
    f, y0 = oscillators([1.0, 40.0])
    seen = []
    sol = odeint_each(lambda t, y, live: seen.append(live) or f(t, y), y0, T)
    after = [s for s in seen if s is not None]
    assert after and all(s.tolist() == [False, True] for s in after)
    assert len(after) == sol.evals[1] - sol.evals[0] > 0


def test_the_simulators_right_hand_side_on_live_rows_equals_its_whole_batch():
    body = arm()
    basis, weights, _ = gestures.library_model(body=body)
    torch.manual_seed(1)
    q = 0.5 * torch.randn(3, weights.N, body.nv, dtype=torch.float64)
    y = pack(body, q, torch.randn_like(q))
    t = torch.rand(3, weights.N, dtype=torch.float64)
    f = ArmODE(body, FieldProgram(basis, weights), track_work=False, strict=False)
    live = torch.rand(3, weights.N) < 0.5
    whole, rows = f(t, y), f(t, y, live)
    assert torch.equal(rows[live], whole[live]) and not rows[~live].any()


def test_agrees_with_torchdiffeq_dopri5_on_one_member():
    f, y0 = oscillators([7.0])
    ours = odeint_each(f, y0, T, rtol=1e-7, atol=1e-9).ys
    ref = odeint(lambda t, y: f(t.expand(y.shape[:-1]), y), y0, T, method="dopri5", rtol=1e-7, atol=1e-9)
    assert (ours - ref).abs().max() < 1e-6
    assert (ours[..., 0] - torch.cos(7 * T)[:, None]).abs().max() < 1e-5


def test_a_failing_member_stops_alone():
    """ẏ = y² from y = 1 blows up at t = 1; ẏ = −y beside it goes on undisturbed; a third
    member past the budget stops with code 1."""
    def f(t, y, live):
        return torch.stack([y[:, 0] ** 2, -y[:, 1]], dim=-1)
    y0 = torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=torch.float64)
    sol = odeint_each(f, y0, T)
    assert sol.failure[0] in (2, 3) and sol.failure[1] == 0
    assert torch.isnan(sol.ys[-1, 0]).all() and not torch.isnan(sol.ys[:, 0][T < 0.9]).any()
    assert (sol.ys[:, 1, 1] - torch.exp(-T)).abs().max() < 1e-7
    g, y = oscillators([1.0, 300.0])
    capped = odeint_each(g, y, T, max_evals=600)
    assert capped.failure.tolist() == [0, 1] and capped.evals[1] > 600 >= capped.evals[0]


def test_gradients_through_the_steps():
    rate = torch.tensor([0.7, 2.0], dtype=torch.float64, requires_grad=True)
    y0 = torch.tensor([[1.0], [0.5]], dtype=torch.float64, requires_grad=True)

    def run(r, y):
        return odeint_each(lambda t, x, live: -r[:, None] * x, y, T[:9], rtol=1e-10, atol=1e-12).ys
    assert torch.autograd.gradcheck(run, (rate, y0))
    # and the value of the gradient: d/dr y0 e^{−rt} = −t y0 e^{−rt}
    (g,) = torch.autograd.grad(run(rate, y0)[-1].sum(), rate)
    t = T[8]
    assert torch.allclose(g, -t * y0.detach()[:, 0] * torch.exp(-rate.detach() * t), atol=1e-9)


@pytest.fixture(scope="module")
def library():
    body = arm()
    basis, weights, _ = gestures.library_model(body=body)
    return body, basis, weights


def test_gradients_through_the_live_rows_of_the_simulator(library):
    """Two gestures whose steps differ, so that the dynamics run on the live row alone
    for a while: gradcheck of (a mix of) each end state through those steps, with respect
    to a scale of each member's torques."""
    body, basis, weights = library
    program = FieldProgram(basis, weights, index=[2, 4])
    t = torch.linspace(0, 0.12, 4, dtype=torch.float64)
    y0 = pack(body, *(torch.zeros(2, body.nv, dtype=torch.float64),) * 2)

    def run(s):
        f = ArmODE(body, lambda t, q, v: s[:, None] * program(t, q, v), strict=False)
        return odeint_each(f, y0, t, rtol=1e-10, atol=1e-10)
    s = torch.tensor([1.0, 1.3], dtype=torch.float64, requires_grad=True)
    steps = run(s).steps
    assert steps[0] != steps[1]
    mix = torch.linspace(-1, 1, y0.shape[-1], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda s: run(s).ys[-1] @ mix, (s,))


def test_simulate_each_member_alone_equals_in_batch(library):
    """The gestures in one batch of per-member steps: each path exactly as simulated alone,
    and within the tolerance of torchdiffeq's shared steps."""
    body, basis, weights = library
    t = torch.arange(0, 151, dtype=torch.float64) / 100
    q0 = torch.zeros(weights.N, body.nv, dtype=torch.float64)
    each = SimOptions(batch="each")
    with torch.no_grad():
        batch = simulate(body, FieldProgram(basis, weights), q0, q0, t, each)
        shared = simulate(body, FieldProgram(basis, weights), q0, q0, t)
        for j in (0, 3):
            alone = simulate(body, FieldProgram(basis, weights, index=[j]), q0[j:j + 1], q0[j:j + 1], t, each)
            assert torch.equal(alone.q[0], batch.q[j])
    assert batch.failure == [None] * weights.N
    assert (batch.q - shared.q).abs().max() < 1e-5


def test_simulate_each_reports_failures_as_data(library):
    body, basis, weights = library
    hard = weights.select_motions([0, 1])
    with torch.no_grad():
        hard.a_raw[1] = 1e6                       # a motion driven a million times harder
    t = torch.arange(0, 101, dtype=torch.float64) / 100
    q0 = torch.zeros(2, body.nv, dtype=torch.float64)
    opts = SimOptions(batch="each", max_evals=3000)
    with torch.no_grad():
        tr = simulate(body, FieldProgram(basis, hard), q0, q0, t, opts, throw=False)
        with pytest.raises(SimulationFailed, match="batch member 1"):
            simulate(body, FieldProgram(basis, hard), q0, q0, t, opts)
    assert tr.failure[0] is None and "budget" in tr.failure[1]
    assert torch.isfinite(tr.q[0]).all() and torch.isnan(tr.q[1, -1]).all()


@pytest.mark.parametrize("bad", [dict(method="bosh3"), dict(adjoint=True), dict(batch="every")])
def test_options_refused(bad):
    with pytest.raises(ValueError, match="batch"):
        SimOptions(**{"batch": "each", **bad})


def test_throw_false_needs_each(library):
    body, basis, weights = library
    q0 = torch.zeros(weights.N, body.nv, dtype=torch.float64)
    with pytest.raises(ValueError, match="throw=False"):
        simulate(body, FieldProgram(basis, weights), q0, q0, T, throw=False)


def test_field_program_time_per_member(library):
    body, basis, weights = library
    q = torch.randn(3, body.nv, dtype=torch.float64) * 0.3
    prog = FieldProgram(basis, weights, index=[4, 0, 2])
    t = torch.tensor([0.3, 1.1, 0.7], dtype=torch.float64)
    got = prog(t, q)
    for i in range(3):
        assert torch.allclose(got[i], prog(t[i], q)[i], atol=0, rtol=1e-15)
    assert not math.isnan(float(got.sum()))


def test_score_models_equals_each_model_scored_alone(library):
    """Three models (the library without one of its fields each) scored in one batch of
    3·N members: every Scores exactly as score() gives that model alone."""
    from tflearn import metrics
    from tflearn.fit.targets import prepare
    body, basis, weights = library
    motions = [m for m, _ in gestures.generate(body, gestures=[gestures.GESTURES[g] for g in
                                                               ("come_here", "tuck")])]
    tg = prepare(body, motions)
    own = weights.select_motions([list(gestures.GESTURES).index(n) for n in ("come_here", "tuck")])
    models = [(basis.select(keep), own.select_fields(keep))
              for keep in ([1, 2, 3, 4, 5, 6], [0, 2, 3, 4, 5, 6], list(range(7)))]
    opts = SimOptions(rtol=1e-6, atol=1e-8, batch="each")
    together = metrics.score_models(body, models, tg, opts)
    for (b, w), s in zip(models, together):
        alone = metrics.score(body, b, w, tg, opts)
        assert s.rmse == alone.rmse and s.tip == alone.tip and s.failure == alone.failure
    assert together[2].rmse[0] < 1e-3 < together[0].rmse[0]      # field 0 drives come_here
    with pytest.raises(ValueError, match="batch='each'"):
        metrics.score_models(body, models, tg, SimOptions())
