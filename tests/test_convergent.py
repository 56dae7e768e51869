"""Convergent fields for motion no field made: antagonist pairs inside joint space
(tflearn.fit.layout ``pairs``) and weights that also give a stiffness about the path
(tflearn.fit.impedance).

The field Jacobian's closed form against autograd; the stiffness design against the
Jacobian of the program's torque; the pairs' centres inside joint space wherever the
motions are; and on eased keyframe animations through random postures, the stiffness
asked is the stiffness given, and with it the animation is reproduced by one simulation
of the NNLS weights, where torque matching alone leaves the limb off its path.
"""
from __future__ import annotations

import math
import warnings

import pytest
import torch
from torch.func import jacrev

from tflearn.data.keyframes import keyframe_motion, random_keyframes
from tflearn.fit import impedance, layout, targets, torque
from tflearn.metrics import score
from tflearn.model.fields import FieldBasis
from tflearn.model.program import FieldProgram
from tflearn.model.weights import MotionWeights
from tflearn.physics import body as tb
from tflearn.simulation.simulate import SimOptions

DT = torch.float64


@pytest.mark.parametrize("kind", ["diag", "full"])
@pytest.mark.parametrize("damping", [0.0, 0.3])
def test_field_jacobian_is_autograds(kind, damping):
    """∂χ_i/∂ν = −g (K − u (K d)ᵀ) equals autograd's Jacobian of the field (1e-12)."""
    g = torch.Generator().manual_seed(3)
    n, M = 7, 4
    A = torch.randn(M, n, n, generator=g, dtype=DT)
    K = A @ A.transpose(-1, -2) / n + 0.3 * torch.eye(n, dtype=DT)
    if kind == "diag":
        K = torch.diag_embed(torch.diagonal(K, dim1=-2, dim2=-1))
    basis = FieldBasis(torch.randn(M, n, generator=g, dtype=DT), K, kind, [3, 1, 3], damping)
    q, v = torch.randn(5, n, generator=g, dtype=DT), torch.randn(5, n, generator=g, dtype=DT)
    want = torch.stack([jacrev(lambda x, vi=vi: basis(x, vi))(qi) for qi, vi in zip(q, v)])   # 5×M×n×n
    got = impedance.field_jacobians(basis, q, v).detach()
    assert float((got - want.detach()).abs().max()) < 1e-12


@pytest.fixture(scope="module")
def keyframes():
    """(body, targets) of three eased three-key animations through random postures."""
    body = tb.arm()
    return body, targets.prepare(body, random_keyframes(body, 3, seed=11))


def _laid(body, tg, windows=16, damping=0.1, shape="pairs"):
    """The convergent layout of ``shape`` (pairs, or joint simplices, which take block K
    themselves) around the motions, and zero weights with ``windows`` sub-movement windows each."""
    tmpl = FieldBasis.empty(body.nv, "diag", body.blocks, damping)
    basis = layout.spanning_basis(body, tg, tmpl, 2.0, 0.25, shape)
    windows = targets.submovement_windows(tg, windows)
    return basis, MotionWeights.zeros(basis.M, tg.duration, tg.names, windows)


def test_stiffness_design_is_the_programs_jacobian(keyframes):
    """J_j(t) = D_j(t) x_j is the Jacobian in ν of the program's torque at the path's
    samples (velocities held), for random weights."""
    body, tg = keyframes
    basis, weights = _laid(body, tg, windows=4)
    g = torch.Generator().manual_seed(0)
    x = torch.rand(tg.N, weights.vector().shape[-1], generator=g, dtype=DT)
    with torch.no_grad():
        weights.set_vector(x)
    D = impedance.stiffness_design(basis, weights, tg)
    J = (D * x[:, None, None, None, :]).sum(-1).detach()
    program = FieldProgram(basis, weights)
    for j, k in [(0, 7), (1, 60), (2, 101)]:
        t, q, v = tg.t[j, k], tg.q[:, k].clone(), tg.v[:, k]

        def tau(qj, t=t, q=q, v=v, j=j):
            return program(t, torch.cat([q[:j], qj[None], q[j + 1:]]), v)[j]
        want = jacrev(tau)(q[j]).detach()
        assert float((J[j, k] - want).abs().max()) <= 1e-10 * float(want.abs().max())


def test_pairs_centres_stay_inside_joint_space():
    """Every pair's centre has each joint block within JOINT_LIMIT, also for a motion
    whose shoulder turns to 3.05 rad (beyond the limit: the layout warns that it leaves
    the box), and without a warning for motions of an ordinary range."""
    body = tb.arm()
    keys = torch.zeros(3, body.nv, dtype=DT)
    keys[:, 3] = -0.5
    keys[1, 0], keys[2, 0] = 1.5, 3.05
    tg = targets.prepare(body, [keyframe_motion("far", body, keys, [0.0, 0.8, 1.6])])
    with pytest.warns(UserWarning, match="beyond the pairs' centres"):
        basis = layout.spanning_basis(body, tg, FieldBasis.empty(body.nv, "diag", body.blocks), 3.0,
                                      0.25, "pairs")
    for i in range(len(body.links)):
        norms = basis.eta[:, body.slice(i)].detach().norm(dim=-1)
        assert float(norms.max()) <= layout.JOINT_LIMIT + 1e-12
    tg = targets.prepare(body, random_keyframes(body, 2, seed=5))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        basis = layout.spanning_basis(body, tg, FieldBasis.empty(body.nv, "diag", body.blocks), 2.0,
                                      0.25, "pairs")
    inside = [(basis.eta[:, body.slice(i)].norm(dim=-1) < math.pi).all() for i in range(len(body.links))]
    assert all(inside)


@pytest.mark.parametrize("fields, paired", [(None, (False, False, False)), (12, (False, False, True))])
def test_joint_simplices_push_every_way_from_inside_joint_space(keyframes, fields, paired):
    """The ``joints`` layout: b + 1 fields per joint of b coordinates (10 on the arm), or
    within a budget of 12 the wrist, whose inertia is the most anisotropic, paired (2b);
    each centre a posture the joint can hold that differs from the middle of the range on
    its own joint only; at every sample of the motions every torque is a non-negative
    combination of the fields' (an NNLS leaves no residual), and all of them active at
    once hold the limb: their summed Jacobian is negative definite. A diagonal or scalar
    kind cannot hold an oblique pull, so the basis is of block kind whatever the run's."""
    from scipy.optimize import nnls
    body, tg = keyframes
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        basis = layout.spanning_basis(body, tg, FieldBasis.empty(body.nv, "block", body.blocks), 2.0,
                                      0.25, "joints", fields)
    assert basis.M == fields or basis.M == body.nv + len(body.blocks) == 10
    eta = basis.eta.detach()
    moved = (eta - eta.median(0).values).abs() > 1e-12                     # M×n: off the middle
    start = 0
    for b, pairs in zip(body.blocks, paired):
        own = slice(start, start + b)
        assert float(eta[:, own].norm(dim=-1).max()) <= layout.JOINT_LIMIT + 1e-12
        mine = moved[:, own].any(-1)
        assert int(mine.sum()) == (2 * b if pairs else b + 1) and not bool(moved[mine][:, :start].any())
        start += b
    q = tg.q[tg.mask][::25]                                                # postures on the paths
    chi = basis(q)                                                         # S×M×n
    torques = torch.randn(len(q), body.nv, generator=torch.Generator().manual_seed(0), dtype=DT)
    for s in range(len(q)):
        w, residual = nnls(chi[s].detach().T.numpy(), torques[s].numpy())
        assert residual <= 1e-9 * float(torques[s].norm()), (s, residual)
    J = impedance.field_jacobians(basis, q).detach().sum(-3)              # S×n×n
    assert float(torch.linalg.eigvalsh(-0.5 * (J + J.mT)).min()) > 0
    for kind in ("diag", "scalar"):                                        # a kind that holds them
        laid = layout.spanning_basis(body, tg, FieldBasis.empty(body.nv, kind, body.blocks, 0.2), 2.0,
                                     0.25, "joints", fields)
        assert laid.kind == "block" and laid.damping == 0.2 and torch.allclose(laid.K(), basis.K())


def test_a_budget_of_2n_fields_pairs_every_joint(keyframes):
    """With room for 2n = 14 fields every joint takes a pair per coordinate: the centres
    are the pairs' (``pairs_basis``) and the stiffness differs only by the pairs' small
    coupling on the pulled coordinate; a budget below the simplices' 10 is refused."""
    body, tg = keyframes
    template = FieldBasis.empty(body.nv, "diag")
    pairs = layout.pairs_basis(body, tg, template, 2.0, 0.25)
    both = layout.spanning_basis(body, tg, template, 2.0, 0.25, "joints", 14)
    assert both.M == pairs.M == 14
    eta = both.eta.detach()
    order = [min(range(14), key=lambda i: float((eta[i] - e).abs().max())) for e in pairs.eta.detach()]
    assert sorted(order) == list(range(14))
    assert torch.allclose(eta[order], pairs.eta.detach(), atol=1e-12)
    Kb, Kp = both.K().detach(), pairs.K().detach()
    rel = (Kb[order] - Kp).abs().amax((-1, -2)) / Kp.abs().amax((-1, -2))
    assert float(rel.max()) <= 1.1 * layout.PAIR_COUPLING
    with pytest.raises(ValueError, match="budget of 9 fields"):
        layout.spanning_basis(body, tg, template, 2.0, 0.25, "joints", 9)


def test_the_stiffness_asked_is_given(keyframes):
    """With ω = 10 rad/s asked, the fields' stiffness about each path is of that order
    (median √λ_min(M⁻¹K_s) within a factor of 2), where torque matching alone gives far
    less; the torque cost stays a fit."""
    body, tg = keyframes
    asked = impedance.Impedance(frequency=10.0, deviation=0.1)
    basis, weights = _laid(body, tg)
    costs = impedance.solve_weights(body, basis, weights, tg, asked)
    held = impedance.path_stiffness(body, basis, weights, tg)
    basis0, weights0 = _laid(body, tg)
    torque.solve_weights(basis0, weights0, tg)
    loose = impedance.path_stiffness(body, basis0, weights0, tg)
    assert bool(((held > 5.0) & (held < 20.0)).all()), held
    assert bool((loose < 0.5 * held).all()), (loose, held)
    assert float(costs.max()) < 0.5


def test_a_joints_rows_weigh_the_co_activations_its_fields_leave_free(keyframes):
    """The stiffness residual's rows are weighted by the share of each coordinate's
    stiffness its joint's own fields leave free of its torque (m − b of m fields on b
    coordinates, over b): 1 on every coordinate of the pairs (and of a far ``cross``),
    1/3 on a ball joint's simplex and 1 on the elbow's pair, 1 on the wrist paired within
    12 fields, also beside learned fields (``solver.hold``'s model); 1 everywhere on
    fields that are no joint's own (learned ones)."""
    body, tg = keyframes
    third = [1 / 3] * 3
    g = torch.Generator().manual_seed(0)
    learned = FieldBasis(torch.randn(6, 7, generator=g, dtype=DT), torch.eye(7, dtype=DT).repeat(6, 1, 1),
                         "block", body.blocks)
    assert impedance.free_share(body, learned).tolist() == [1.0] * 7
    tmpl = FieldBasis.empty(body.nv, "block", body.blocks)
    for shape, fields, want in [("pairs", None, [1.0] * 7), ("joints", None, third + [1.0] + third),
                                ("joints", 12, third + [1.0] * 4)]:
        basis = layout.spanning_basis(body, tg, tmpl, 2.0, 0.25, shape, fields)
        held = basis.like(torch.cat([learned.eta, basis.eta]), torch.cat([learned.K(), basis.K()]))
        for b in (basis, held):
            assert impedance.free_share(body, b).tolist() == pytest.approx(want), (shape, fields, b.M)
    far = layout.spanning_basis(body, tg, tmpl, 16.0, 1 / 16, "cross")
    assert impedance.free_share(body, far).tolist() == [1.0] * 7


@pytest.mark.slow
@pytest.mark.parametrize("shape, deviation", [("pairs", 0.1), ("joints", 0.1)])
def test_held_keyframes_are_reproduced_by_one_simulation(keyframes, shape, deviation):
    """Eased keyframe animations through random postures: the NNLS weights with the
    stiffness asked reproduce every one in a single simulation (joint RMSE ≤ 0.03 rad,
    hand ≤ 2 cm), no path matching, on the pairs and on the joint simplices (the same δ:
    a simplex's rows weigh a third, :func:`~tflearn.fit.impedance.free_share`); torque
    matching alone on the same fields does not."""
    body, tg = keyframes
    opt = SimOptions(rtol=1e-7, atol=1e-9)
    basis, weights = _laid(body, tg, shape=shape)
    impedance.solve_weights(body, basis, weights, tg, impedance.Impedance(10.0, deviation))
    held = score(body, basis, weights, tg, opt)
    assert max(held.rmse) <= 0.03 and max(held.tip) <= 0.02, (held.rmse, held.tip)
    basis0, weights0 = _laid(body, tg, shape=shape)
    torque.solve_weights(basis0, weights0, tg)
    loose = score(body, basis0, weights0, tg, opt)
    assert max(loose.rmse) > 0.03, loose.rmse


def test_one_fields_equilibrium_is_its_centre():
    """A motion one field made (come_here) gives back its field's equilibrium: wherever the
    field is active, the equilibrium of the program is the field's centre η (1e-9 rad)."""
    from tflearn.data import gestures
    (motion, lb), = gestures.generate(gestures=[gestures.GESTURES["come_here"]])
    tg = targets.prepare(lb.body, [motion])
    nu, found = impedance.equilibria(lb.basis, lb.weights, tg)
    active = lb.weights.activation_at(tg.t.transpose(0, 1)).transpose(0, 1)[..., 0] > 1e-6
    assert bool(found[active & tg.mask].all())
    assert float((nu[found] - lb.basis.eta[0].detach()).abs().max()) < 1e-9


def test_held_equilibrium_stays_near_the_path(keyframes):
    """The held weights' equilibrium trajectory is a stable posture at every sample, inside
    joint space and near the limb (the stiffness ω²M makes the offset K⁻¹τ small): closer
    than the equilibrium of torque matching alone on the same fields."""
    body, tg = keyframes
    basis, weights = _laid(body, tg)
    impedance.solve_weights(body, basis, weights, tg, impedance.Impedance(10.0, 0.1))
    nu, found = impedance.equilibria(basis, weights, tg)
    basis0, weights0 = _laid(body, tg)
    torque.solve_weights(basis0, weights0, tg)
    nu0, found0 = impedance.equilibria(basis0, weights0, tg)
    real = tg.mask & (tg.wt > 0)
    assert bool(found[real].all())
    off = (nu - tg.q).norm(dim=-1)[real]
    off0 = torch.where(found0, (nu0 - tg.q).norm(dim=-1), torch.inf)[real]
    assert float(off.median()) < 0.5 * float(off0.median()), (off.median(), off0.median())
    for i in range(len(body.links)):
        assert float(nu[..., body.slice(i)][real].norm(dim=-1).max()) < math.pi


def test_sparsity_keeps_fewer_weights_unshrunk(keyframes):
    """With ``sparsity`` the ℓ1 term leaves fewer non-zero weights (under 70% of the plain
    solve's), and those are solved again without it: on them the gradient of the plain
    cost vanishes (to the NNLS tolerance), against the ℓ1 term λ√A_cc that shrunk weights
    would be left with."""
    body, tg = keyframes
    plain, sparse = impedance.Impedance(10.0, 0.1), impedance.Impedance(10.0, 0.1, sparsity=0.01)
    basis, weights = _laid(body, tg)
    impedance.solve_weights(body, basis, weights, tg, plain)
    full = (weights.vector() > 0).sum(-1)
    impedance.solve_weights(body, basis, weights, tg, sparse)
    x = weights.vector().detach()
    on = x > 0
    assert bool((on.sum(-1) < 0.7 * full).all()), (on.sum(-1), full)
    G, h = torque.normal_equations(basis, weights, tg)
    Gs, hs = impedance.stiffness_equations(body, basis, weights, tg, plain)
    grad = ((G + Gs) @ x.unsqueeze(-1)).squeeze(-1) - (h + hs)
    l1 = 0.01 * torch.diagonal(G + Gs, dim1=-2, dim2=-1).sqrt()
    ratio = (grad.abs() / l1)[on]                 # 1 for every weight the ℓ1 term shrank
    assert float(ratio.median()) <= 1e-4 and float(ratio.max()) <= 0.25


def test_held_out_synthesis_asks_the_runs_stiffness(keyframes):
    """`evaluate`'s synthesis on a frozen pairs basis solves new motions' weights with the
    stiffness the run asked (``held``): they are held about their paths as trained ones
    are, where the torques alone leave them far softer."""
    from tflearn.evaluate import synthesize
    from tflearn.io.basis import LearnedBasis
    body, tg = keyframes
    basis, weights = _laid(body, tg.select([0]))
    lb = LearnedBasis(body, basis, weights, tg.q0[:1], tg.qd0[:1], torch.full((1,), 100.0, dtype=DT))
    new = tg.select([1, 2])
    held = synthesize(lb, new, shooting=None, held=impedance.Impedance(10.0, 0.1))
    loose = synthesize(lb, new, shooting=None)
    stiff = impedance.path_stiffness(body, basis, held, new)
    soft = impedance.path_stiffness(body, basis, loose, new)
    assert bool((stiff > 5.0).all()) and bool((soft < 0.5 * stiff).all()), (stiff, soft)


def test_windows_per_second_follow_the_longest_motion(keyframes, tmp_path):
    """``model.window_rate``: P = ⌈rate × the longest motion's duration⌉, written into the
    run's config (so a resumed run and its checkpoint agree); 0 leaves model.windows."""
    import math

    from tflearn import config
    from tflearn.train.pipeline import sized_windows
    _, tg = keyframes
    longest = float(tg.duration.max())
    cfg = config.load(None, ["model.windows=16", "model.window_rate=8"])
    assert sized_windows(cfg, tg).model.windows == math.ceil(8 * longest) != 16
    assert sized_windows(config.load(None, ["model.windows=16"]), tg).model.windows == 16
    with pytest.raises(config.ConfigError, match="window_rate"):
        config.load(None, ["model.window_rate=-1"])


def test_each_motion_uses_the_windows_its_length_asks(keyframes):
    """With a rate, motion j is cut into ⌈rate·λ_j⌉ windows of the P, as it would be with
    that many alone; the rest start 1 s after its end, where their pulses are 0 all along
    it: their torque columns are 0 and NNLS leaves their weights at 0."""
    body, tg = keyframes
    basis = _laid(body, tg)[0]
    rate, P = 2.0, math.ceil(2.0 * float(tg.duration.max()))
    onset, length = targets.submovement_windows(tg, P, rate=rate)
    for j in range(tg.N):
        mine = math.ceil(rate * float(tg.duration[j]))
        alone = targets.submovement_windows(tg.select([j]), mine)
        assert torch.equal(onset[j, :mine], alone[0][0]) and torch.equal(length[j, :mine], alone[1][0])
        assert bool((onset[j, mine:] > tg.duration[j]).all())
    assert any(math.ceil(rate * float(d)) < P for d in tg.duration)      # windows past some motion's end
    weights = MotionWeights.zeros(basis.M, tg.duration, tg.names, (onset, length))
    torque.solve_weights(basis, weights, tg)
    inert = onset > tg.duration[:, None]                                  # N×P
    assert bool((weights.c.detach().permute(0, 2, 1)[inert] == 0).all())
    assert bool((weights.c.detach().permute(0, 2, 1)[~inert].sum(-1) > 0).any())


# ------------------------------------------------------------------ learned programs held

@pytest.fixture(scope="module")
def tuck():
    """(body, targets, generating basis, generating weights) of the tuck gesture: one
    field with scalar K, the soft program a learned basis gives back."""
    from tflearn.data import gestures
    body = tb.arm()
    (m, _), = gestures.generate(body, gestures=[gestures.GESTURES["tuck"]])
    basis, weights, _ = gestures.library_model([gestures.GESTURES["tuck"]], body)
    return body, targets.prepare(body, [m]), basis, weights


def test_held_model_adds_damped_pairs_and_windows(tuck):
    """``hold.held_model``: the learned fields first, unchanged, then the 2n pairs; every
    field damped by ζ; the motion cut into ⌈rate × λ⌉ windows; the learned weights kept,
    zero on the pairs and on every window."""
    from tflearn.config import HoldSection
    from tflearn.train.stages import hold
    body, tg, basis, weights = tuck
    h = HoldSection(window_rates=[4.0, 6.0], damping=0.3)
    grown, held = hold.held_model(body, tg, basis, weights, h)
    assert grown.M == basis.M + 2 * body.nv and grown.damping == 0.3 and grown.kind == "diag"
    assert torch.equal(grown.eta[:basis.M], basis.eta) and torch.allclose(grown.K()[:basis.M], basis.K())
    lam = float(tg.duration[0])
    assert held.P == math.ceil(6.0 * lam)                 # room for the most windows asked
    assert int((held.window_onset < lam).sum()) == math.ceil(4.0 * lam)     # the first rate's
    assert torch.equal(held.a[:, :basis.M], weights.a) and torch.equal(held.b[:, :basis.M], weights.b)
    assert not held.a[:, basis.M:].any() and not held.c.any()
    simplices, _ = hold.held_model(body, tg, basis, weights, HoldSection(shape="joints"))
    assert simplices.M == basis.M + body.nv + len(body.blocks) and simplices.kind == "block"
    assert torch.allclose(simplices.K()[:basis.M], basis.K())            # the joint blocks hold them


def test_held_weights_stiffen_a_field_made_motion_it_still_follows(tuck):
    """The tuck's own program is soft about its path (its field's w K while the step
    rises: under 1 rad/s); the held weights on its field and the damped pairs (NNLS on
    torques and ω = 10 rad/s asked) give several rad/s and one simulation still
    reproduces the tuck (0.03 rad, 2 cm)."""
    from tflearn.config import HoldSection
    from tflearn.train.stages import hold
    body, tg, basis, weights = tuck
    h = HoldSection()
    grown, held = hold.held_model(body, tg, basis, weights, h)
    impedance.solve_weights(body, grown, held, tg, h.settings()[0][1])
    soft = float(impedance.path_stiffness(body, basis, weights, tg)[0])
    stiff = float(impedance.path_stiffness(body, grown, held, tg)[0])
    assert soft < 1.0 and stiff > 4.0, (soft, stiff)
    s = score(body, grown, held, tg, SimOptions(rtol=1e-7, atol=1e-9))
    assert s.rmse[0] <= 0.03 and s.tip[0] <= 0.02, (s.rmse, s.tip)


def _held_run(tmp_path, out: str):
    """The config of a pipeline run on the tuck and come_here gestures with the stage
    ``hold`` on (held programs need more than 20,000 evaluations)."""
    from tflearn.config import load
    from tflearn.data import gestures
    from tflearn.motions import motion as motion_mod
    for m, _ in gestures.generate(tb.arm(), gestures=[gestures.GESTURES[n] for n in ("tuck", "come_here")]):
        motion_mod.save(m, tmp_path / f"{m.name}.npz")
    return load(None, [f"data={tmp_path}", f"out={tmp_path / out}", "solver.method=pipeline",
                       "solver.hold.enabled=true", "solver.path.max_evals=100000", "log.tensorboard=false",
                       "log.progress=false"])


@pytest.mark.slow
def test_the_hold_stage_holds_learned_programs_and_refuses_to_lose_a_motion(tmp_path, monkeypatch):
    """Two gestures learned on their fields, then held: the 14 pairs join the learned
    fields, both motions are still reproduced, now each at several rad/s of stiffness about
    its path (the learned programs: none), and each records the setting it took. A
    gesture it never saw, synthesised on the held basis (``tflearn evaluate RUN --data``),
    is held as well. Where a held program would lose a motion, the run keeps its learned
    model and names it."""
    from tflearn import train
    from tflearn.data import gestures
    from tflearn.evaluate import evaluate_run
    from tflearn.motions import motion as motion_mod
    from tflearn.train.stages import hold
    metrics = train.run(_held_run(tmp_path, "held"))
    record = metrics["history"]["hold"]
    assert record["kept"] and record["lost"] == [] and record["added"] == 14
    assert metrics["overall"]["M"] == record["M"]
    for name in ("tuck", "come_here"):
        row = metrics["motions"][name]
        assert row["success"] and row["path_stiffness"] > 4.0, row
        assert record["settings"][name]["deviation"] in (0.1, 0.02)
    (tmp_path / "new").mkdir()
    (m, _), = gestures.generate(tb.arm(), gestures=[gestures.GESTURES["stiff_elbow_lift"]])
    motion_mod.save(m, tmp_path / "new" / f"{m.name}.npz")
    new = evaluate_run(tmp_path / "held", data=str(tmp_path / "new"), progress=False)["motions"][m.name]
    assert new["synthesized"] and new["success"] and new["path_stiffness"] > 4.0, new
    real = hold.held_programs

    def losing(ctx, basis, weights, settings):          # the second motion's held program lost
        chosen, ok, failures = real(ctx, basis, weights, settings)
        return chosen, [ok[0], False], failures
    monkeypatch.setattr(hold, "held_programs", losing)
    refused = train.run(_held_run(tmp_path, "refused"))
    second = list(refused["motions"])[1]
    assert refused["history"]["hold"]["lost"] == [second] and not refused["history"]["hold"]["kept"]
    assert refused["overall"]["M"] == refused["history"]["hold"]["M"] == record["M"] - 14
    assert all(row["success"] and row["path_stiffness"] < 1.0 for row in refused["motions"].values())


def test_a_refused_hold_names_what_it_would_lose_and_why():
    """The run's message when the held model is not kept: the motions it would lose, and
    where a simulation failed, which and the budget to raise."""
    from tflearn.train.stages.hold import _refusal
    text = _refusal(["tuck", "come_here"], [None, "ran past 20000 evaluations"])
    assert "2 motion(s) would be lost: tuck, come_here" in text
    assert "come_here (ran past 20000 evaluations)" in text and "solver.path.max_evals" in text
    assert "max_evals" not in _refusal(["tuck"], [None])


@pytest.mark.slow
def test_a_motion_its_windows_leave_unreproduced_is_cut_finer(tmp_path):
    """Windows sized by what a motion needs (``model.finer``): a three-key animation at 1
    window a second, which the NNLS and two shooting iterations leave unreproduced on the
    convergent pairs (2.1 cm at the hand), is cut into 2 windows a second, fitted again
    and reproduced; the run records the rate it kept, and the motion is described by
    more numbers for it. Held-out synthesis on that run cuts a new motion finer too."""
    from pathlib import Path

    from tflearn import config, evaluate, train
    from tflearn.io import basis as basis_io
    from tflearn.motions import motion as motion_mod
    for m in random_keyframes(tb.arm(), 1, seed=11):
        motion_mod.save(m, tmp_path / f"{m.name}.npz")

    def run(finer):
        preset = Path(__file__).resolve().parents[1] / "configs" / "convergent.yaml"
        return train.run(config.load(preset, [
            f"data={tmp_path}", f"out={tmp_path / str(finer)}", "model.window_rate=1", f"model.finer={finer}",
            "solver.shooting.iterations=2", "log.progress=false", "log.tensorboard=false"]))
    coarse, fine = run(0)["motions"]["keys11_0"], run(2)
    assert not coarse["success"]
    assert fine["history"]["finer"] == {"keys11_0": 2.0}
    row = fine["motions"]["keys11_0"]
    assert row["success"] and row["tip"] < coarse["tip"] and row["numbers"] > coarse["numbers"]

    # held out: an animation the frozen basis' 1 window a second leaves 2.4 cm off at the
    # hand is synthesised on finer windows too, and reproduced
    held = tmp_path / "held"
    held.mkdir()
    for m in random_keyframes(tb.arm(), 1, seed=12):
        motion_mod.save(m, held / f"{m.name}.npz")
    doc = evaluate.evaluate_run(tmp_path / "2", data=held, progress=False)
    assert doc["motions"]["keys12_0"]["success"]
    new = basis_io.load(tmp_path / "2" / "synthesized" / "basis.json").weights
    assert int((new.window_onset < new.duration[:, None]).sum()) > math.ceil(float(new.duration[0]))
