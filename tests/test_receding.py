"""Receding-horizon path matching (tflearn.fit.receding).

On test_shooting's two-hinge chain (motion "twice": two known fields switched on in two
windows): a piece started on the motion's own simulation continues that simulation, so
the pieces the fit advances through are one simulation; ``ShootingOptions.windows``
moves those windows' weights and nothing else; window weights perturbed by up to 40 %
are recovered window by window; a fit whose result simulates further from the path than
its start gives the start back; a batch of pieces that fails is simulated piece by
piece; ``solver.shooting.receding`` sends a run's longer motions there; a whole recorded
clip is one simulation.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch
from test_shooting import TIGHT, _truth

from tflearn import synthesis
from tflearn.fit import receding, shooting, targets
from tflearn.fit.path import path_loss
from tflearn.model.program import FieldProgram
from tflearn.motions.motion import Motion
from tflearn.physics.body import chain
from tflearn.simulation.simulate import SimOptions, simulate

DT = torch.float64
SIM = SimOptions(rtol=1e-9, atol=1e-11, max_evals=50_000)


@pytest.fixture(scope="module")
def twice():
    """(body, basis, generating weights, targets) of the motion "twice" alone: 1.0 s at
    50 Hz, two windows (onsets 0 and 0.45 s)."""
    body = chain(2, "hinge")
    basis, weights = _truth()
    for p in basis.parameters():
        p.requires_grad_(False)
    weights = weights.select_motions([1])
    t = torch.arange(51, dtype=DT) / 50
    q0 = torch.zeros(1, 2, dtype=DT)
    with torch.no_grad():
        tr = simulate(body, FieldProgram(basis, weights), q0, q0, t,
                      SimOptions(method="dopri8", rtol=1e-12, atol=1e-12, solver_options={"step_t": t[1:]}))
    return body, basis, weights, targets.prepare(body, [Motion("twice", t, tr.q[0], tr.v[0], body=body)])


def test_a_piece_started_on_the_simulation_continues_it(twice):
    body, basis, weights, tg = twice
    with torch.no_grad():
        q, v = targets.simulate_targets(body, basis, weights, tg, TIGHT)
        k0, k1 = 20, 45
        piece = receding.pieces(tg, [0], [k0], [k1], q[:, k0], v[:, k0])
        assert piece.t[0, 0] == 0 and piece.t[0, -1] == pytest.approx(float(tg.t[0, k1] - tg.t[0, k0]))
        assert float(piece.w.sum()) == pytest.approx(float(piece.duration[0]))
        assert torch.equal(piece.q[0, 1:], tg.q[0, k0 + 1:k1 + 1])      # the target after its start
        qp, vp = targets.simulate_targets(body, basis, receding._shifted(weights, [0], tg.t[0, k0:k0 + 1]),
                                          piece, TIGHT)
    assert torch.allclose(qp[0], q[0, k0:k1 + 1], atol=1e-8)
    assert torch.allclose(vp[0], v[0, k0:k1 + 1], atol=1e-7)


def test_windows_move_those_windows_weights_only(twice):
    body, basis, weights, tg = twice
    w = weights.select_motions([0])
    with torch.no_grad():
        w.a_raw.fill_(0.5)
        w.c_raw.mul_(1.3)
    before = {k: getattr(w, k).detach().clone() for k in ("a_raw", "b_raw", "c_raw", "window_onset")}
    opts = shooting.ShootingOptions(horizon=10.0, iterations=2, windows=(1,))
    shooting.shooting_match(body, basis, w, tg, options=opts, sim=SIM)
    assert torch.equal(w.a_raw, before["a_raw"]) and torch.equal(w.b_raw, before["b_raw"])
    assert torch.equal(w.c_raw[..., 0], before["c_raw"][..., 0])
    assert torch.equal(w.window_onset, before["window_onset"])
    assert not torch.equal(w.c_raw[..., 1], before["c_raw"][..., 1])


def test_window_weights_are_recovered_window_by_window(twice):
    """From window weights perturbed by up to 40 %, the fit gives back the generating
    ones (4 and 3 on the two fields that drive the motion, 0 on the others) and its
    path, simulated once from the start."""
    body, basis, weights, tg = twice
    w = weights.select_motions([0])
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        w.c_raw.mul_(1 + 0.4 * (2 * torch.rand(w.c_raw.shape, generator=g, dtype=DT) - 1))
    with torch.no_grad():
        start = float(path_loss(body, *targets.simulate_targets(body, basis, w, tg, SIM), tg)[0])
    steps = []
    opts = shooting.ShootingOptions(receding=0.0, iterations=8)
    res = receding.receding_match(body, basis, w, tg, options=opts, sim=SIM,
                                  callback=lambda k, cost: steps.append(k))
    assert steps == [0, 1] and not res.failures
    assert torch.allclose(w.c, weights.c, atol=1e-4)
    assert res.loss[0] < 1e-8 < start


@pytest.mark.slow
def test_windows_out_of_order_are_fitted_in_order_of_onset_and_kept_in_theirs(twice):
    """Window widths that differ put a later window's onset before an earlier one's
    (``submovement_windows`` at a few windows a second): the windows given in reverse
    order are fitted as in order of onset, and come back in the order given."""
    body, basis, weights, tg = twice
    opts = shooting.ShootingOptions(receding=0.0, iterations=8)
    ordered, backwards = weights.select_motions([0]), weights.select_motions([0])
    with torch.no_grad():
        for w in (ordered, backwards):
            w.c_raw.mul_(1.3)
        for key in ("window_onset", "window_duration"):
            getattr(backwards, key).copy_(getattr(backwards, key).flip(1))
        backwards.c_raw.copy_(backwards.c_raw.flip(2))
    onsets = backwards.window_onset.clone()
    receding.receding_match(body, basis, ordered, tg, options=opts, sim=SIM)
    receding.receding_match(body, basis, backwards, tg, options=opts, sim=SIM)
    assert torch.equal(backwards.window_onset, onsets)
    assert torch.allclose(backwards.c.flip(2), ordered.c, atol=1e-12)
    assert torch.allclose(ordered.c, weights.c, atol=1e-4)


def test_a_fit_that_ends_further_from_the_path_gives_its_start_back(twice, monkeypatch):
    """Each piece fitted well but the whole simulated worse than at the start (a fit
    made to move window 0's weights away): the starting weights come back."""
    body, basis, weights, tg = twice
    w = weights.select_motions([0])
    real = shooting.shooting_match

    def away(body, basis, sub, piece, options, sim):
        res = real(body, basis, sub, piece, options=options, sim=sim)
        with torch.no_grad():
            sub.c_raw[..., 0].mul_(2.0)
        return res
    monkeypatch.setattr(receding.shooting, "shooting_match", away)
    opts = shooting.ShootingOptions(receding=0.0)
    res = receding.receding_match(body, basis, w, tg, options=opts, sim=SIM)
    assert torch.equal(w.c, weights.c) and res.loss[0] < 1e-8


@pytest.mark.slow
def test_a_batch_of_pieces_that_fails_is_simulated_piece_by_piece(twice, monkeypatch):
    """Two motions whose pieces cannot be simulated together (a simulation of more than
    one motion made to fail) are each fitted as they would be alone."""
    body, basis, weights, tg = twice
    real = receding.simulate_targets

    def alone(body, basis, w, tg, sim):
        if tg.N > 1:
            raise receding.SimulationFailed("budget", "made to fail")
        return real(body, basis, w, tg, sim)
    monkeypatch.setattr(receding, "simulate_targets", alone)
    w = weights.select_motions([0, 0])
    with torch.no_grad():
        w.c_raw.mul_(torch.tensor([1.3, 0.8], dtype=DT)[:, None, None])
    res = receding.receding_match(body, basis, w, tg.select([0, 0]),
                                  options=shooting.ShootingOptions(receding=0.0, iterations=8), sim=SIM)
    assert not res.failures and max(res.loss) < 1e-8
    assert torch.allclose(w.c, weights.c.expand(2, -1, -1), atol=1e-4)


@pytest.mark.parametrize("receding, method", [(None, "shooting"), (1.0, "shooting"), (0.5, "receding"),
                                              (0.0, "receding")])
def test_motions_longer_than_receding_are_fitted_there(twice, monkeypatch, receding, method):
    """``solver.shooting.receding`` (s): the 1 s motion goes window by window when it
    is longer than that, else to the growing horizons."""
    body, basis, weights, tg = twice
    seen = []
    for name in ("shooting_match", "receding_match"):
        monkeypatch.setattr(synthesis, name, lambda *a, name=name, **k: seen.append((name, k["motions"])) or
                            shooting.ShootingResult(loss=[0.0]))
    opts = dataclasses.replace(shooting.ShootingOptions(), receding=receding)
    record = synthesis.shoot(body, basis, weights.select_motions([0]), tg, [0], opts, SIM)
    assert seen == [(f"{method}_match", [0])] and record == {"twice": {"loss": 0.0, "failure": None}}


def test_shoot_tells_which_window_it_is_on(twice):
    body, basis, weights, tg = twice
    told = []
    opts = dataclasses.replace(shooting.ShootingOptions(iterations=2), receding=0.0)
    synthesis.shoot(body, basis, weights.select_motions([0]), tg, [0], opts, SIM, progress=told.append)
    assert told == ["window 1/2", "window 2/2"]


@pytest.mark.slow
def test_a_whole_recorded_clip_is_one_simulation(mocap, tmp_path):
    """A whole recorded clip (the bye, 3.7 s, imported at 50 Hz on a fixed chest) under
    configs/convergent.yaml with windows that follow its length (8 a second: 30): the
    NNLS weights alone leave it 0.057 rad / 14.7 cm off (measured); fitted window by
    window it is reproduced as one simulation from its first frame to its last, within
    the recorded-motion bar (measured with the preset's γ = 100 in a run of three clips:
    0.0295 rad / 2.48 cm)."""
    from tflearn import train
    from tflearn.config import load
    preset = Path(__file__).parents[1] / "configs" / "convergent.yaml"
    cfg = load(preset, [f"data={mocap / 'dataset-1_bye_normal_001.bvh'}", f"out={tmp_path / 'run'}",
                        "bvh.rate=50", "model.window_rate=8", "success.rmse=0.05", "success.tip=0.03"])
    metrics = train.run(cfg)
    row, = metrics["motions"].values()
    assert metrics["history"]["shooting"] is not None
    assert row["success"] and row["rmse"] <= 0.05 and row["tip"] <= 0.03
