"""The spanning field layout (tflearn.fit.layout) and coordinate-weighted torque costs."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from tflearn.config import ConfigError, load
from tflearn.data import gestures
from tflearn.fit import layout, search, targets, torque
from tflearn.fit.nnls import nnls_lstsq
from tflearn.metrics import score
from tflearn.mocap import bvh
from tflearn.mocap import retarget as rt
from tflearn.model.fields import FieldBasis
from tflearn.model.weights import MotionWeights
from tflearn.motions import motion as motion_mod
from tflearn.motions import spline
from tflearn.simulation.simulate import SimOptions

from conftest import DT, full_symmetric, q_to_pin, to_pin


@pytest.fixture(scope="module")
def come_here():
    (m, lb), = gestures.generate(gestures=[gestures.GESTURES["come_here"]])
    return lb.body, m


def test_mean_inertia_is_pinocchios(come_here):
    """m̄ is the mean of Pinocchio's CRBA diagonal over the motion's samples (1e-12)."""
    import pinocchio as pin
    body, m = come_here
    tg = targets.prepare(body, [m])
    model = to_pin(body)
    data = model.createData()
    want = np.mean([np.diag(full_symmetric(pin.crba(model, data, q_to_pin(body, q))))
                    for q in m.q.numpy()], axis=0)
    got = targets.mean_inertia(body, tg)[0].numpy()
    assert np.abs(got - want).max() <= 1e-12 * np.abs(want).max()
    assert got[0] / got[6] > 100                     # the shoulder is far heavier than the wrist


def test_uniform_weights_are_the_thesis_cost(come_here):
    """ω = 1 gives the unweighted costs to rounding; ``inertia`` gives Σ w ω (τ − F)² /
    Σ w ω τ², checked against a direct sum, and is another number."""
    body, m = come_here
    tg = targets.prepare(body, [m])
    assert tg.coord_weight is None
    with pytest.warns(UserWarning, match="come_here leaves the cross"):  # a cost identity: no span needed
        basis = layout.spanning_basis(body, tg, FieldBasis.empty(7, "diag", body.blocks), 2.5, 3.0, "cross")
    w = MotionWeights.zeros(14, tg.duration, tg.names)
    plain = torque.solve_weights(basis, w, tg)
    ones = replace(tg, coord_weight=torch.ones(1, 7, dtype=DT))
    assert torch.allclose(torque.torque_cost(basis, w, ones), plain, rtol=1e-12, atol=0)
    tw = targets.prepare(body, [m], weight="inertia")
    omega = 1 / targets.mean_inertia(body, tg)
    assert torch.equal(tw.coord_weight, omega)
    F = (torque.design(basis, w, tg) @ w.vector()[:, None, :, None]).squeeze(-1)
    want = (tg.wt[..., None] * omega[:, None] * (tg.tau - F) ** 2).sum((1, 2)) / \
        (tg.wt[..., None] * omega[:, None] * tg.tau ** 2).sum((1, 2))
    got = torque.torque_cost(basis, w, tw).detach()
    assert torch.allclose(got, want.detach(), rtol=1e-12, atol=0)
    assert 1e-6 < float(plain[0]) < 0.5 and abs(float(got[0]) - float(plain[0])) > 0.1 * float(plain[0])
    with pytest.raises(ValueError, match="weight must be 'uniform' or 'inertia'"):
        targets.prepare(body, [m], weight="mass")


def test_weighted_solves_agree(come_here):
    """Under ω the NNLS weights are optimal for the weighted cost (no other non-negative
    weights found by perturbation do better), candidate scores equal the weight solve's
    (1e-10), and EM's residual norm² is the weighted cost (1e-10)."""
    body, m = come_here
    tw = targets.prepare(body, [m], weight="inertia")
    basis = layout.spanning_basis(body, tw, FieldBasis.empty(7, "diag", body.blocks), 4.0, 3.0, "cross")
    w = MotionWeights.zeros(14, tw.duration, tw.names)
    cost = float(torque.solve_weights(basis, w, tw)[0])
    assert 1e-6 < cost < 0.99
    x = w.vector().clone()
    gen = torch.Generator().manual_seed(3)
    for _ in range(20):
        w.set_vector((x + 0.05 * torch.randn(x.shape, generator=gen, dtype=DT)).clamp_min(0))
        assert float(torque.torque_cost(basis, w, tw)[0].detach()) >= cost - 1e-12
    w.set_vector(x)
    empty = FieldBasis.empty(7, "scalar", [3, 1, 3])
    w0 = MotionWeights.zeros(0, tw.duration, tw.names)
    centre = tw.q[0, 100:101] + 0.5
    scores = search.score_candidates(empty, w0, tw, centre, [0.5])
    one = empty.extend(centre, 0.5 * torch.eye(7, dtype=DT)[None])
    want = float(torque.solve_weights(one, MotionWeights.zeros(1, tw.duration, tw.names), tw)[0])
    assert abs(float(scores[0, 0]) - want) <= 1e-10
    fp = torque._FieldParameters(basis, w, tw, phases=False)
    r = fp.residual(torque.scaled_design(basis, w, tw, fp.scale), w.vector().detach())
    assert abs(float((r ** 2).sum()) - cost) <= 1e-10


def test_ridge_is_nnls_of_the_stacked_design(come_here):
    """solve_weights(ridge=λ) is scipy's NNLS of [Φ̃; √(λ ḡ) I] x ≈ [s ⊙ τ; 0] (ḡ the mean
    of diag Φ̃ᵀΦ̃; 1e-10 relative), returns the unregularised cost of its weights, and on
    the mocap config's layout (simplex, r = 16, κ = 1/16, 16 windows) bounds the
    co-contraction: the largest weight 1905 → 337 for a cost 0.0812 → 0.0891 (measured).
    λ = 0 is the exact NNLS, bit for bit."""
    from scipy.optimize import nnls as scipy_nnls
    body, m = come_here
    tw = targets.prepare(body, [m], weight="inertia")
    basis = layout.spanning_basis(body, tw, FieldBasis.empty(7, "diag", body.blocks), 16.0, 0.0625, "simplex")
    windows = targets.submovement_windows(tw, 16)
    exact, ridged = (MotionWeights.zeros(8, tw.duration, tw.names, windows) for _ in range(2))
    c0 = float(torque.solve_weights(basis, exact, tw)[0])
    c1 = float(torque.solve_weights(basis, ridged, tw, ridge=1e-4)[0])
    again = MotionWeights.zeros(8, tw.duration, tw.names, windows)
    torque.solve_weights(basis, again, tw, ridge=0.0)
    assert torch.equal(again.vector(), exact.vector())
    s = torque.residual_scale(tw)
    Phi = torque.scaled_design(basis, ridged, tw, s)[0].detach().numpy()
    lam = 1e-4 * np.diag(Phi.T @ Phi).mean()
    y = np.concatenate([(s * tw.tau).reshape(-1).numpy(), np.zeros(Phi.shape[1])])
    x, _ = scipy_nnls(np.vstack([Phi, np.sqrt(lam) * np.eye(Phi.shape[1])]), y, maxiter=10_000)
    got = ridged.vector()[0].detach().numpy()
    print("costs", c0, c1, "largest weights", float(exact.vector().max()), got.max())
    assert np.abs(got - x).max() <= 1e-10 * np.abs(x).max()
    assert c1 == pytest.approx(float(torque.torque_cost(basis, ridged, tw)[0]), rel=1e-12)
    assert 0.07 < c0 < c1 < 0.1
    assert float(exact.vector().max()) > 1500 and got.max() < 400


def test_layout_shapes_are_regular_polytopes():
    """cross: ±e_k, gauge ‖x‖₁; simplex: n + 1 unit vertices with Σ u = 0 and
    u_i·u_j = −1/n, gauge max −n u·x. Every vertex has gauge 1 (1e-12), the centre 0, and
    the gauge is positively homogeneous."""
    x = torch.randn(50, 7, generator=torch.Generator().manual_seed(1), dtype=DT)
    assert torch.allclose(layout.reach("cross", x), x.abs().sum(-1), rtol=1e-12)
    for shape, M in (("cross", 14), ("simplex", 8)):
        u, _ = layout.SHAPES[shape](7)
        assert u.shape == (M, 7)
        assert torch.allclose(layout.reach(shape, u), torch.ones(M, dtype=DT), atol=1e-12)
        assert torch.allclose(layout.reach(shape, 2.5 * x), 2.5 * layout.reach(shape, x), rtol=1e-12)
        assert float(layout.reach(shape, torch.zeros(7, dtype=DT))) == 0.0
    u, _ = layout.SHAPES["simplex"](7)
    gram = u @ u.T
    assert torch.allclose(gram, torch.eye(8, dtype=DT) * (1 + 1 / 7) - 1 / 7, atol=1e-12)
    assert float(u.sum(0).abs().max()) <= 1e-12


@pytest.mark.parametrize("shape", ["cross", "simplex"])
def test_spanning_basis_spans_every_torque(come_here, shape):
    """Fields at ν̄ + r u_i with K = κ diag(m̄). At a posture inside the centres' hull
    (gauge 0.9 r, 20 random directions) every torque is a non-negative combination of
    the fields (NNLS residual ≤ 1e-9 for 20 random torques, measured in accelerations);
    just outside it (1.1 r) some torque is not (residual > 0.05). For the cross the hull
    is the ℓ1 ball, not the box: |ν − ν̄|∞ = r/2 in every coordinate is outside. A motion
    leaving the hull is warned of."""
    body, m = come_here
    tg = targets.prepare(body, [m])
    template = FieldBasis.empty(7, "diag", body.blocks, damping=0.2)
    r = 2.0
    basis = layout.spanning_basis(body, tg, template, radius=20.0, stiffness=3.0, shape=shape)
    centre = tg.q[0].mean(0)
    u, _ = layout.SHAPES[shape](7)
    assert basis.M == len(u) and basis.damping == 0.2 and basis.kind == "diag"
    assert torch.allclose(basis.eta.detach(), centre + 20.0 * u, atol=1e-12)
    assert torch.allclose(basis.K()[5], 3.0 * torch.diag(targets.mean_inertia(body, tg)[0]), rtol=1e-12)
    basis = basis.like(centre + r * u, basis.K())
    gen = torch.Generator().manual_seed(7)
    root = targets.mean_inertia(body, tg)[0].sqrt()                # compared by acceleration

    def worst(x):
        chi = basis(centre + x).detach() / root                    # M×n
        tau = torch.randn(20, 7, generator=gen, dtype=DT)
        w = nnls_lstsq(chi.T.expand(20, -1, -1), tau).x
        return float(((w @ chi - tau).norm(dim=-1) / tau.norm(dim=-1)).max())
    for _ in range(20):
        x = torch.randn(7, generator=gen, dtype=DT)
        x = x / layout.reach(shape, x)
        assert worst(0.9 * r * x) <= 1e-9
        assert worst(1.1 * r * x) > 0.05
    if shape == "cross":
        assert worst(torch.full((7,), r / 2, dtype=DT)) > 0.05
    far = float(layout.reach(shape, tg.q[0] - centre).max())
    with pytest.warns(UserWarning, match=rf"come_here leaves the {shape} .* radius of {far:.2f} rad"):
        layout.spanning_basis(body, tg, template, radius=0.9 * far, stiffness=1.0, shape=shape)
    with pytest.raises(ValueError, match="not scalar"):
        layout.spanning_basis(body, tg, FieldBasis.empty(7, "scalar", body.blocks), 2.0, 1.0, "cross")
    with pytest.raises(ValueError, match="unknown shape 'star'"):
        layout.spanning_basis(body, tg, template, 2.0, 1.0, "star")


def test_layout_config_refusals(tmp_path):
    """method layout needs a per-coordinate stiffness and M found by the layout; the
    thesis' SLSQP keeps the thesis' cost. Both refused before any work, naming the keys."""
    from tflearn import train
    base = ["data=gestures", f"out={tmp_path}"]
    for extra, message in ((["solver.method=layout", "model.stiffness=scalar"], "model.stiffness diag"),
                           (["solver.method=layout", "model.fields=3"], "model.fields=0"),
                           (["solver.method=slsqp", "model.fields=3", "solver.torque_weight=inertia"],
                            "solver.torque_weight=uniform")):
        with pytest.raises(ConfigError, match=message):
            train.run(load(None, base + extra))
    assert not tmp_path.joinpath("checkpoint.pt").exists()


@pytest.mark.slow
def test_layout_carries_a_recorded_window(mocap):
    """A recorded 0.8 s window (the wave's busiest, 100 Hz): the spanning layout with 16
    windows and inertia-weighted NNLS alone, no search and no path matching, stays within
    0.1 rad of it (measured 0.074 rad), where the thesis' uniform cost on the same fields
    drifts twice as far (measured 0.158 rad): the light wrist is then not driven."""
    frames = rt.arm_frames(bvh.read(mocap / "dataset-2_wave-right-hand_normal_001.bvh"), "right")
    r, = rt.retarget_all([frames])
    m = r.motion
    i = int(np.searchsorted(m.t.numpy(), 0.08))
    k = i + int(round(0.8 / float(m.t[1] - m.t[0])))
    win = motion_mod.Motion("wave", m.t[i:k + 1] - m.t[i], m.q[i:k + 1], None, r.body)
    win = spline.resample(win, 100.0, r.body)
    errors = {}
    for weight in ("inertia", "uniform"):
        tg = targets.prepare(r.body, [win], weight=weight)
        basis = layout.spanning_basis(r.body, tg, FieldBasis.empty(7, "diag", r.body.blocks, 0.2),
                                       2.0, 1.0, "cross")
        w = MotionWeights.zeros(14, tg.duration, tg.names, targets.submovement_windows(tg, 16))
        torque.solve_weights(basis, w, tg)
        s = score(r.body, basis, w, tg, SimOptions(max_evals=20000))
        errors[weight] = s.rmse[0]
    assert errors["inertia"] <= 0.1 and errors["uniform"] > 1.5 * errors["inertia"]


def _spline_run(tmp_path, *overrides):
    """The config of a three-keyframe come-here spline that the pipeline cannot reproduce
    with one field of its own (``solver.each.max_fields=1``, one Adam step). Its
    simulations stop at 4,000 evaluations at tolerances 1e-6 / 1e-8: the pipeline's model
    needs more than 20,000 (the Adam step's fails at either budget, rescue's models need
    fewer), so the tests take a quarter of the time without changing what they see (at
    the default 1e-7 / 1e-9 rescue's models need more than 4,000 too)."""
    from tflearn.data.keyframes import keyframe_motion
    from tflearn.physics.body import arm
    body = arm()
    (m, _), = gestures.generate(body, gestures=[gestures.GESTURES["come_here"]])
    T = len(m.t)
    keys = keyframe_motion("come_here_keys", body, m.q[[0, T // 2, T - 1]],
                           [0.0, float(m.t[T // 2]), float(m.t[-1])])
    motion_mod.save(keys, tmp_path / "come_here_keys.npz")
    return load(None, [f"data={tmp_path / 'come_here_keys.npz'}", f"out={tmp_path / 'run'}",
                       "model.phases=variable", "model.field_damping=0.2", "model.windows=2",
                       "solver.each.max_fields=1", "solver.init.candidates=8", "solver.em.steps=20",
                       "solver.path.steps=1", "solver.path.max_evals=4000", "solver.path.rtol=1e-6",
                       "solver.path.atol=1e-8", "log.tensorboard=false",
                       "log.progress=false", "solver.method=pipeline", *overrides])


@pytest.mark.slow
def test_rescue_lays_out_fields_for_a_motion_the_pipeline_leaves(tmp_path):
    """A three-keyframe spline the pipeline cannot reproduce with one field of its own
    is rescued by default: the stage
    ``rescue`` lays out a simplex of eight fields around it, adds them to the basis, solves
    its weights on them and fits them over all nine by multiple shooting with the hand's
    distance in the residuals (``solver.rescue``), and that model, not the Adam step's
    best point, is the run's (measured: 0.0256 rad / 1.45 cm, M = 1 → 9). The run is killed right
    after the round's checkpoint and resumed there: nothing is left, no round follows."""
    from tflearn import train
    cfg, save = _spline_run(tmp_path), train.RunContext.save

    def kill(self, state):
        save(self, state)
        if state.stage == "rescue" and state.cursor == 1:
            raise train.Interrupted("killed after rescue's first round")
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(train.RunContext, "save", kill)
        with pytest.raises(train.Interrupted):
            train.run(cfg)
    metrics = train.run(cfg)
    rescue, = metrics["history"]["rescue"]                # one round: nothing is left
    assert rescue["motions"] == rescue["reproduced"] == ["come_here_keys"] and rescue["kept"]
    assert rescue["added"] == 8 and metrics["overall"]["M"] == rescue["M"] == 9
    row = metrics["motions"]["come_here_keys"]
    assert row["success"] and row["rmse"] <= 0.03 and row["tip"] <= 0.02


@pytest.mark.slow
def test_a_rescue_round_that_improves_no_motion_changes_nothing(tmp_path, monkeypatch):
    """With no shooting (``solver.rescue.iterations=0``) the spline's program on the
    simplex alone is farther from it than path matching's (measured: 0.0712 rad before):
    the motion keeps its program, the basis its one field, and the rounds stop after the
    first although three are allowed."""
    from tflearn import train
    from tflearn.train.stages import rescue
    seen = []
    round_ = rescue.rescue_round

    def spy(ctx, state, basis, weights, scores, ok):
        seen.append((basis.M, scores.rmse[0], scores.tip[0]))
        return round_(ctx, state, basis, weights, scores, ok)
    monkeypatch.setattr(rescue, "rescue_round", spy)
    metrics = train.run(_spline_run(tmp_path, "solver.rescue.iterations=0", "solver.rescue.rounds=3"))
    rescue, = metrics["history"]["rescue"]
    assert rescue == {"motions": ["come_here_keys"], "added": 8, "M": 1, "reproduced": [],
                      "improved": [], "kept": False}
    row = metrics["motions"]["come_here_keys"]
    assert seen[0][0] == metrics["overall"]["M"] == 1 and seen[0][1] > 0.03
    assert (row["rmse"], row["tip"]) == pytest.approx(seen[0][1:], rel=1e-9)


@pytest.mark.slow
def test_a_rescue_round_that_reproduces_no_motion_is_not_kept(tmp_path, monkeypatch):
    """Fields that bring a motion closer but reproduce none would only grow the basis:
    with every motion judged closer (``synthesis.closer`` made to say so) and none
    reproduced (no shooting), the round keeps nothing."""
    from tflearn import train
    from tflearn.train.stages import rescue
    monkeypatch.setattr(rescue.synthesis, "closer",
                        lambda before, after, success, ok=None: [True] * len(before))
    metrics = train.run(_spline_run(tmp_path, "solver.rescue.iterations=0"))
    assert metrics["history"]["rescue"][0]["reproduced"] == []
    assert metrics["history"]["rescue"][0]["kept"] is False and metrics["overall"]["M"] == 1
