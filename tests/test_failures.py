"""Failures as results: one failure type for a simulation that cannot go on, scored per
motion (a batch in which one motion fails still scores the others, each on its own
time grid), and divergence (NaN/Inf in a cost, a loss, a gradient or a state) that
rejects the step, names the motion and never reaches basis.json."""
from __future__ import annotations

import math

import pytest
import torch

from tflearn import metrics
from tflearn.data import gestures
from tflearn.fit import path as path_fit
from tflearn.fit import stability, targets, torque
from tflearn.fit.torque import DivergenceWarning
from tflearn.model.program import FieldProgram
from tflearn.motions.motion import Motion
from tflearn.simulation import simulate as S

DT = torch.float64
OPTS = S.SimOptions(rtol=1e-7, atol=1e-9, max_evals=20000)


@pytest.fixture(scope="module")
def pair():
    """come_here (3 s) and tuck, with their generating model in one basis."""
    chosen = [gestures.GESTURES["come_here"], gestures.GESTURES["tuck"]]
    pairs = gestures.generate(gestures=chosen)
    basis, weights, _ = gestures.library_model(chosen)
    motions = [m for m, _ in pairs]
    return pairs[0][1].body, basis, weights, targets.prepare(pairs[0][1].body, motions)


def test_simulation_failed_is_its_own_type():
    """Not a RuntimeError: ``except RuntimeError`` never hides it, nor it torch's errors."""
    assert not issubclass(S.SimulationFailed, RuntimeError)
    err = S.SimulationFailed("budget", "more than 5 right-hand-side evaluations")
    assert err.reason == "budget" and "budget" in str(err)


def _arm_run(program, options=S.SimOptions()):
    body = gestures.arm()
    t = torch.linspace(0, 0.5, 11, dtype=DT)
    z = torch.zeros(1, 7, dtype=DT)
    return S.simulate(body, program, z, z, t, options)


def test_nonfinite_state_fails_with_its_reason():
    def program(t, q, v):
        return torch.full_like(v, float("nan")) if float(t) > 0.2 else torch.zeros_like(v)
    with pytest.raises(S.SimulationFailed, match="NaN or Inf") as err:
        _arm_run(program)
    assert err.value.reason == "nonfinite"


def test_singular_mass_matrix_fails_with_its_reason(monkeypatch):
    def singular(*args, **kw):
        raise torch.linalg.LinAlgError("not positive-definite")
    monkeypatch.setattr(S.dynamics, "forward_dynamics_rot", singular)
    with pytest.raises(S.SimulationFailed) as err:
        _arm_run(S.zero_program)
    assert err.value.reason == "singular"


def test_integrator_giving_up_fails_with_its_reason(monkeypatch):
    """torchdiffeq signals an underflowing step with an AssertionError (which vanishes
    under ``python -O``); simulate turns it into SimulationFailed("solver")."""
    def gives_up(*args, **kw):
        raise AssertionError("underflow in dt 0.0")
    monkeypatch.setattr(S, "odeint", gives_up)
    with pytest.raises(S.SimulationFailed, match="underflow") as err:
        _arm_run(S.zero_program)
    assert err.value.reason == "solver"


def test_budget_fails_with_its_reason():
    with pytest.raises(S.SimulationFailed) as err:
        _arm_run(lambda t, q, v: 50 * torch.sin(40 * q), S.SimOptions(max_evals=30))
    assert err.value.reason == "budget"


def test_select_simulates_on_its_own_grid(pair):
    """A sub-selection's grid ends with its own longest motion, not the batch's."""
    body, _, _, tg = pair
    come_here = Motion("come_here", tg.t[0], tg.q[0], tg.v[0])
    half = Motion("half", tg.t[1, :151], tg.q[1, :151], tg.v[1, :151])
    tg = targets.prepare(body, [come_here, half])
    short = 1
    one = tg.select([short])
    assert float(one.grid[-1]) == pytest.approx(float(tg.duration[short]))
    assert float(tg.grid[-1]) > float(one.grid[-1])
    assert torch.equal(one.grid[one.index[0]], one.t[0])


@pytest.mark.parametrize("batch", [pytest.param("shared", marks=pytest.mark.slow), "each"])
def test_one_failing_motion_leaves_the_others_scored(pair, batch):
    """tuck's weights ×10⁴ make its simulation run past the budget (5000 right-hand
    sides; come_here needs about 1600); come_here is still scored, exactly as it scores
    alone, and only tuck is reported failed — with a batch stepped together (simulated
    again motion by motion) and with each motion stepped alone in it (one simulation)."""
    body, basis, weights, tg = pair
    wild = weights.select_motions([0, 1])
    with torch.no_grad():
        wild.a_raw[1] *= 1e4
    opts = S.SimOptions(rtol=1e-7, atol=1e-9, max_evals=5000, batch=batch)
    calls = S.calls
    s = metrics.score(body, basis, wild, tg, opts)
    assert S.calls - calls == (3 if batch == "shared" else 1)
    alone = metrics.score(body, basis, weights.select_motions([0]), tg.select([0]), opts)
    assert s.failure[0] is None and "budget" in s.failure[1]
    assert s.rmse[0] == alone.rmse[0] and s.tip[0] == alone.tip[0]
    assert s.rmse[0] < 1e-3 and s.rmse[1] == float("inf")
    assert s.succeeded(0.03, 0.02) == [True, False]
    summary = metrics.summarize(s, s.succeeded(0.03, 0.02), tg, basis.M, 0.0,
                                stability.growth(body, basis, wild, tg), torch.zeros(2),
                                metrics.numbers(wild, tg, body.nv))
    assert "failure" in summary["motions"]["tuck"] and "failure" not in summary["motions"]["come_here"]
    # the growth along the target path needs no simulation: the failed motion has it too
    assert math.isfinite(summary["motions"]["tuck"]["growth_rate"])


@pytest.mark.slow
def test_until_failure_stops_simulating_at_the_first_failed_motion(pair):
    """``score(..., until_failure=True)``, for a judge that refuses any failure: the batch
    fails, tuck (first, weights ×10⁴) fails alone, and come_here after it is not
    simulated — one simulation fewer than without the flag, come_here reported failed
    with the reason; the verdict "some motion failed" is the same."""
    body, basis, weights, tg = pair
    wild = weights.select_motions([1, 0])
    with torch.no_grad():
        wild.a_raw[0] *= 1e4
    swapped = tg.select([1, 0])
    opts = S.SimOptions(rtol=1e-7, atol=1e-9, max_evals=5000)
    calls = S.calls
    full = metrics.score(body, basis, wild, swapped, opts)
    assert S.calls - calls == 3 and full.failure[1] is None
    calls = S.calls
    short = metrics.score(body, basis, wild, swapped, opts, until_failure=True)
    assert S.calls - calls == 2
    assert "budget" in short.failure[0] and short.failure[1] == "not simulated: tuck failed first"
    assert short.rmse == [float("inf")] * 2 and bool(short.q_sim[1].isnan().all())
    assert short.succeeded(0.03, 0.02) == [False, False]


def test_path_step_rejects_a_diverged_point_naming_the_motion(pair):
    """After a good step, weights that went NaN: the step is rejected with a
    DivergenceWarning naming the motions, the parameters go back to the best point and
    the learning rate halves."""
    body, basis, weights, tg = pair
    one, w = tg.select([0]), weights.select_motions([0])
    kw = dict(options=S.SimOptions(rtol=1e-5, atol=1e-7, max_evals=20000))
    first = path_fit.path_step(body, basis, w, one, lr=1e-3, **kw)
    assert first.failure is None and first.best is not None
    best_a = first.best["model"]["weights"]["a_raw"].clone()
    with torch.no_grad():
        w.a_raw.fill_(float("nan"))
    with pytest.warns(DivergenceWarning, match="come_here"):
        res = path_fit.path_step(body, basis, w, one, lr=1e-3, best=first.best,
                                 optimizer_state=first.optimizer, **kw)
    assert res.failure is not None and res.lr == 5e-4 and res.loss == float("inf")
    assert torch.equal(w.a_raw.detach(), best_a)
    assert torch.isfinite(w.a_raw).all()


@pytest.mark.slow
def test_path_step_on_some_motions_leaves_the_others_untouched(pair):
    """``motions=[1], fields=False`` (the path stage's ``solver.path.motions:
    unreproduced``): the loss and the step are motion 1's alone, as if it were the only
    motion, while motion 0 — not simulated — and the fields keep every value bit for bit."""
    body, basis, weights, tg = pair
    kw = dict(options=S.SimOptions(rtol=1e-5, atol=1e-7, max_evals=20000), fields=False)
    both, alone = weights.select_motions([0, 1]), weights.select_motions([1])
    with torch.no_grad():
        for w in (both, alone):
            w.a_raw.mul_(1.1)
    before = {k: v.clone() for k, v in both.state_dict().items()}
    eta, raw = basis.eta.detach().clone(), basis.stiffness.raw.detach().clone()
    calls = S.calls
    res = path_fit.path_step(body, basis, both, tg, lr=1e-3, motions=[1], **kw)
    assert S.calls - calls == 1                                   # one simulation: motion 1's
    ref = path_fit.path_step(body, basis, alone, tg.select([1]), lr=1e-3, **kw)
    assert res.failure is None and res.loss == pytest.approx(ref.loss, rel=1e-12) and res.loss > 1e-6
    assert torch.allclose(both.a_raw[1], alone.a_raw[0], rtol=1e-12, atol=0)
    assert not torch.equal(both.a_raw[1], before["a_raw"][1])    # motion 1 moved
    for key, value in before.items():
        assert torch.equal(getattr(both, key)[0], value[0]), key   # motion 0 did not
    assert torch.equal(basis.eta, eta) and torch.equal(basis.stiffness.raw, raw)


def test_path_step_failing_at_the_start_changes_nothing(pair):
    body, basis, weights, tg = pair
    w = weights.select_motions([0])
    with torch.no_grad():
        w.a_raw.fill_(float("nan"))
    with pytest.warns(DivergenceWarning):
        res = path_fit.path_step(body, basis, w, tg.select([0]), lr=1e-3, options=OPTS)
    assert res.best is None and res.failure


def test_em_rejects_a_nonfinite_trial_step(pair, monkeypatch):
    """An LM trial whose torque cost is NaN is rejected (a warning names the motion) and
    EM carries on from the last good point: its history stays finite and monotone."""
    body, basis, weights, tg = pair
    one = tg.select([0])
    b = basis.select([0])
    with torch.no_grad():
        b.eta.add_(0.05)
    w = weights.select_motions([0]).select_fields([0])
    real = torque.solve_weights
    calls = {"n": 0}

    def flaky(*args, **kw):
        calls["n"] += 1
        costs = real(*args, **kw)
        return torch.full_like(costs, float("nan")) if calls["n"] == 2 else costs
    monkeypatch.setattr(torque, "solve_weights", flaky)
    with pytest.warns(DivergenceWarning, match="come_here"):
        history = torque.em(b, w, one, steps=10)
    assert all(torch.isfinite(torch.tensor(history)))
    assert all(y <= x for x, y in zip(history, history[1:])) and history[-1] < history[0]


def test_program_of_a_scored_batch_is_unchanged(pair):
    """Scoring never changes the model it scores (no in-place writes)."""
    body, basis, weights, tg = pair
    before = [p.detach().clone() for p in FieldProgram(basis, weights).parameters()]
    metrics.score(body, basis, weights, tg, OPTS)
    after = list(FieldProgram(basis, weights).parameters())
    assert all(torch.equal(x, y) for x, y in zip(before, after))


def test_search_never_picks_a_nonfinite_candidate(pair, monkeypatch):
    """Candidate scores that come out NaN are ranked +∞ (never chosen) with a warning
    naming the motions; the search still finds come_here's field."""
    from tflearn.fit import search
    body, basis, weights, tg = pair
    one = tg.select([0])
    real = search.score_candidates

    def some_nan(*args, **kw):
        costs = real(*args, **kw).clone()
        costs[0] = float("nan")              # the first candidate of every chunk
        return costs
    monkeypatch.setattr(search, "score_candidates", some_nan)
    gen = torch.Generator().manual_seed(0)
    with pytest.warns(DivergenceWarning, match="come_here"):
        empty = weights.select_motions([0]).select_fields([])
        centre, k, cost = search.best_candidate(basis.select([]), empty, one, 16, [0.5, 1.0, 2.0], gen)
    assert torch.isfinite(centre).all() and cost < 1.0


class _Log:
    """What a stage tells the run's log, kept: the statuses."""

    def __init__(self):
        self.statuses = []

    def status(self, **values):
        self.statuses.append(values)

    def __getattr__(self, name):
        return lambda *args, **kw: None


@pytest.mark.parametrize("budget", [300, 20000])
def test_path_stage_takes_no_step_where_the_scoring_fails(pair, monkeypatch, budget):
    """The path stage's Adam steps simulate their motions with the gradient's graph
    (hundreds of KB an evaluation). Where a motion's simulation runs out of its budget
    in the scoring (300 evaluations for 3 s), Adam's start would fail after filling that
    graph: the stage records the scoring's failure, naming the motion, and takes no step.
    With the budget the motions need (20,000), the step is taken."""
    from types import SimpleNamespace

    from tflearn import config
    from tflearn.model.program import model_state
    from tflearn.train.stages import path as stage
    from tflearn.train.state import RunState
    body, basis, weights, tg = pair
    w = weights.select_motions([0, 1])
    with torch.no_grad():
        w.a_raw.mul_(1.2)                                  # neither motion reproduced
    cfg = config.load(None, ["solver.shooting.iterations=0", f"solver.path.max_evals={budget}"])
    options = cfg.solver.path.options()

    def check(b, ww, t):
        s = metrics.score(body, b, ww, t, options)
        return s, s.succeeded(cfg.success.rmse, cfg.success.tip)
    steps = []
    monkeypatch.setattr(stage.path_fit, "path_step",
                        lambda *a, **kw: steps.append(1) or path_fit.PathStep(1.0, 1e-3, {}, None))
    log = _Log()
    ctx = SimpleNamespace(cfg=cfg, tg=tg, body=body, options=options, variable_phases=False, log=log,
                          check=check, sequence=("path", "rescue"), tick=lambda state: 0,
                          save=lambda state: None)
    state = RunState(config={}, stage="path", rng=torch.Generator().get_state(),
                     model=model_state(basis, w))
    stage.run(ctx, state)
    if budget == 300:
        assert steps == [] and state.stage == "rescue" and not state.path.needed
        assert "come_here" in state.history.path and "tuck" in state.history.path
        assert "evaluations" in state.history.path
        assert {"advance": 0, "failed": "the simulation fails at the start"} in log.statuses
    else:
        assert steps == [1] and state.stage == "path" and state.path.needed and state.history.path is None
