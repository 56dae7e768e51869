"""A moving base (the torso): RNEA and forward dynamics against Pinocchio with a
free-flyer root whose motion is prescribed, the default path unchanged, and simulation
on a moving base against the equivalence principle."""
from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
import torch

from tflearn.physics import dynamics as D

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
    from tflearn.simulation.simulate import SimOptions, simulate
    t = torch.linspace(0, T, 9, dtype=DT)
    q0 = torch.tensor([0.3, -0.2, 0.1, -0.8, 0.2, 0.1, -0.3], dtype=DT)
    return simulate(body, program, q0, torch.zeros(7, dtype=DT), t,
                    SimOptions(rtol=1e-9, atol=1e-11), base=base)


def test_base_motion_derivatives():
    """The spline of a base turning about a fixed axis at ω(t) = ω0 + α t and moving on
    x(t) = ½ a t², as tflearn.motions.torso.Bases (members at shifted times, one past the end,
    clamped there), gives each member gravity Rᵀg, ω, ω̇ and the acceleration in the base
    frame at its time."""
    from tflearn.motions.torso import BaseMotion, Bases
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    t = np.linspace(0, 1, 201)
    ang = 0.5 * t + 0.5 * 1.5 * t ** 2
    R = np.array([pin.exp3(a * axis) for a in ang])
    acc = np.array([0.3, -1.0, 2.0])
    bases = Bases.of([BaseMotion(t, R, 0.5 * t[:, None] ** 2 * acc)]).take(
        torch.zeros(3, dtype=torch.long), shift=torch.tensor([0.0, 0.3, 0.9], dtype=DT))
    g, (w, dw, a) = bases.terms(GRAVITY, torch.tensor([0.37, 0.07, 0.5], dtype=DT))
    for k, s in enumerate([0.37, 0.37, 1.0]):
        Rs = pin.exp3((0.5 * s + 0.75 * s ** 2) * axis)
        np.testing.assert_allclose(g[k].numpy(), Rs.T @ np.array(GRAVITY), atol=1e-8)
        np.testing.assert_allclose(w[k].numpy(), (0.5 + 1.5 * s) * axis, atol=1e-7)
        np.testing.assert_allclose(dw[k].numpy(), 1.5 * axis, atol=1e-5)
        np.testing.assert_allclose(a[k].numpy(), Rs.T @ acc, atol=1e-7)


def test_simulation_on_a_moving_base():
    """Equivalence principle: a base accelerating at a (no gravity) moves the arm as a
    fixed base under gravity −a; a base held turned by R under gravity g as a fixed one
    under Rᵀ g. And gravity fed forward holds the arm still under gravity."""
    from tflearn.motions.torso import BaseMotion, gravity_feedforward
    from tflearn.physics.body import arm
    from tflearn.simulation.simulate import zero_program
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


@pytest.mark.slow
def test_bases_of_a_batch():
    """Simulating a batch on one tflearn.motions.torso.BaseMotion equals the same batch on
    Bases, one per member, batch each and shared alike; a wrong number of bases is
    refused."""
    from tflearn.motions.torso import BaseMotion, Bases
    from tflearn.physics.body import arm
    from tflearn.simulation.simulate import SimOptions, simulate, zero_program
    t = np.linspace(0, 0.5, 51)
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    one = BaseMotion(t, np.array([pin.exp3((0.5 * s + 2 * s ** 2) * axis) for s in t]),
                     0.5 * t[:, None] ** 2 * np.array([1.0, -2.0, 4.0]) + np.sin(5 * t)[:, None])
    bases = Bases.of([one]).take(torch.zeros(3, dtype=torch.long))
    body = arm(gravity=list(GRAVITY))
    q0 = torch.tensor([[0.3, -0.2, 0.1, -0.8, 0.2, 0.1, -0.3],
                       [0.1, 0.4, -0.2, -1.2, 0.0, 0.3, 0.2]], dtype=DT)
    ts = torch.linspace(0, 0.4, 9, dtype=DT)
    for options in (SimOptions(rtol=1e-9, atol=1e-11), SimOptions(rtol=1e-9, atol=1e-11, batch="each")):
        a = simulate(body, zero_program, q0, torch.zeros_like(q0), ts, options, base=one)
        b = simulate(body, zero_program, q0, torch.zeros_like(q0), ts, options,
                     base=Bases.of([one, one]))
        assert float((a.q - b.q).abs().max()) < 1e-9 and float((a.q[:, -1] - q0).abs().max()) > 0.05
    with pytest.raises(ValueError, match="3 moving bases for a batch of 2"):
        simulate(body, zero_program, q0, torch.zeros_like(q0), ts, base=bases)



def test_one_piece_bases_pose_as_the_whole_path():
    """Bases.at (each member cut to the polynomial piece it is on at its time) gives the
    poses and base terms of Bases.take at those times, bit for bit, before the path's
    start, inside it and past its end; paths of different lengths in one batch."""
    from tflearn.motions.torso import BaseMotion, Bases
    t = np.linspace(0, 0.5, 51)
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    long = BaseMotion(t, np.array([pin.exp3((0.5 * s + 2 * s ** 2) * axis) for s in t]),
                      0.5 * t[:, None] ** 2 * np.array([1.0, -2.0, 4.0]) + np.sin(5 * t)[:, None])
    short = BaseMotion(t[:21], np.array([pin.exp3(s * axis) for s in t[:21]]),
                       np.cos(3 * t[:21])[:, None] * [1.0, 0.0, 0.5])
    bases = Bases.of([long, short], start=[0.05, 0.0])
    idx = torch.tensor([0, 1, 0, 1, 0, 1])
    times = torch.tensor([-0.1, 0.0, 0.2371, 0.1503, 0.7, 0.4], dtype=DT)
    whole, cut = bases.take(idx), bases.at(idx, times)
    assert cut.coef.shape[1] == 1 and whole.coef.shape[1] > 1
    for a, b in zip(whole.poses(times), cut.poses(times)):
        assert torch.equal(a, b)
    g, terms = whole.terms(GRAVITY, times)
    g2, terms2 = cut.terms(GRAVITY, times)
    assert torch.equal(g, g2) and all(torch.equal(x, y) for x, y in zip(terms, terms2))


def _on_a_torso(rate=200.0, duration=1.2):
    """come_here's program simulated on a torso that turns and sways (gravity on, so the
    base also turns gravity in the arm's frame): (body, basis, weights, motion, its torso
    BaseMotion, the torso's samples t, R, x)."""
    from tflearn.data import gestures
    from tflearn.model.program import FieldProgram
    from tflearn.motions.motion import Motion
    from tflearn.motions.torso import BaseMotion
    from tflearn.physics.body import arm
    from tflearn.simulation.simulate import SimOptions, simulate
    body = arm(gravity=list(GRAVITY))
    basis, weights, _ = gestures.library_model([gestures.GESTURES["come_here"]], body=body)
    ts = np.linspace(0, duration + 0.2, 141)
    axis = np.array([0.2, 1.0, 0.3]) / np.linalg.norm([0.2, 1.0, 0.3])
    R = np.array([pin.exp3(0.4 * np.sin(2.5 * s) * axis) for s in ts])
    x = 0.15 * np.stack([np.sin(3 * ts), np.zeros_like(ts), 0.5 * np.sin(5 * ts)], 1)
    base = BaseMotion(ts, R, x)
    t = torch.arange(0, round(duration * rate) + 1, dtype=DT) / rate
    q0 = torch.zeros(1, body.nv, dtype=DT)
    from tflearn.motions.torso import Bases, gravity_feedforward
    with torch.no_grad():
        fed = gravity_feedforward(body, FieldProgram(basis, weights), Bases.of([base]))
        tr = simulate(body, fed, q0, q0, t,
                      SimOptions(rtol=1e-11, atol=1e-12, max_evals=None), base=base)
    return body, basis, weights, Motion("on_torso", t, tr.q[0], tr.v[0], body), base, (ts, R, x)


@pytest.mark.slow
def test_targets_and_scores_on_each_motions_torso():
    """A motion made on a moving torso under gravity by come_here's field with its
    model's gravity torques fed forward: tflearn.fit.targets.prepare with its base gives
    inverse-dynamics torques equal to the field's plus gravity's, and metrics.score
    simulates it back onto its path; on a fixed base the same weights miss it. A
    multiple-shooting residual at those weights (segments started on the path, each on
    its own stretch of the torso) is zero."""
    from tflearn.fit import shooting, targets
    from tflearn.metrics import score
    from tflearn.model.program import FieldProgram
    from tflearn.motions.torso import Bases
    from tflearn.simulation.simulate import SimOptions
    body, basis, weights, m, base, _ = _on_a_torso()
    moving = targets.prepare(body, [m], base=Bases.of([base]))
    fixed = targets.prepare(body, [m])
    with torch.no_grad():
        zero = torch.zeros_like(moving.q)
        gravity = moving.base.take(torch.zeros(moving.q.shape[1], dtype=torch.long)).terms(
            body.gravity, moving.t[0])[0]
        program = FieldProgram(basis, weights)
        field = torch.cat([program(t, q[None], v[None])
                           for t, q, v in zip(moving.t[0], moving.q[0], moving.v[0])])
        ff = D.rnea(body, moving.q[0], zero[0], zero[0], gravity=gravity)
    inner = moving.wt[0] > 0
    err = lambda tau: float((tau[0][inner] - (field + ff)[inner]).norm() / (field + ff)[inner].norm())
    print("relative torque error, moving / fixed base:", err(moving.tau), err(fixed.tau))
    assert err(moving.tau) < 1e-4 and err(fixed.tau) > 0.1
    options = SimOptions(rtol=1e-9, atol=1e-10, batch="each")
    fed = body.with_(gravity=(0.0, 0.0, 0.0))   # gravity fed forward exactly: as none at all
    on, off = score(fed, basis, weights, moving, options), score(fed, basis, weights, fixed, options)
    print("rmse moving / fixed base:", on.rmse[0], off.rmse[0])
    assert on.rmse[0] < 1e-5 and off.rmse[0] > 1e-2
    seg = shooting.segments(moving, 0.3)
    assert len(seg.motion) == 4 and float(seg.base.start[1]) == pytest.approx(0.3)
    q, v = shooting._simulate(fed, basis, weights, seg, options)
    r = shooting._residuals(fed, moving, seg, q, v, beta=0.1)
    assert float(r.abs().max()) < 1e-5


@pytest.mark.slow
def test_training_on_each_motions_torso(tmp_path):
    """``torso: moving``: train reads each motion's torso file (torso/NAME.npz beside it,
    as tflearn bvh import writes) and learns the motion made on that torso (gravity fed
    forward exactly, so the gravity-free world) back from no guess, reproduced by
    simulation on the torso; evaluate and ``tflearn simulate`` of the run ride the torso
    too, and so does ``perturb`` (the unpushed fields as trained, the feed-forward torques
    with the torso's terms replaying the motion); the run's motions are found by name
    (one it lacks is named); ``torso: fixed`` keeps the fixed
    base; a motion without a torso file, or with one that does not cover its times, is
    refused, naming the file."""
    from tflearn import config, train
    from tflearn.control import recovery
    from tflearn.data.loading import named_motions, torsos
    from tflearn.errors import InputError
    from tflearn.evaluate import evaluate_run, simulate_basis_motion
    from tflearn.motions.motion import MotionFileError, load, save
    from tflearn.physics.body import from_config

    from test_learning import small_config
    *_, m, _, (ts, R, x) = _on_a_torso()
    data = tmp_path / "data"
    (data / "torso").mkdir(parents=True)
    save(m, data / "on_torso.npz")
    np.savez(data / "torso" / "on_torso.npz", t=ts, R=R, x=x)
    cfg = small_config(data, tmp_path / "run", "torso=moving")
    metrics, body = train.run(cfg), from_config(cfg.body)
    row = metrics["motions"]["on_torso"]
    print("on its torso:", row["rmse"], row["tip"], metrics["overall"]["M"])
    assert row["success"] and row["rmse"] < 0.01                  # measured: 0.0043 rad
    assert metrics["overall"]["M"] <= 2          # the bar: M ≤ G + 1, G = 1 generating field
    again = evaluate_run(tmp_path / "run")["motions"]["on_torso"]
    assert again["rmse"] == pytest.approx(row["rmse"], rel=1e-6)
    played = load(simulate_basis_motion(tmp_path / "run" / "basis.json", "on_torso", tmp_path / "sim.npz",
                                        rate=200.0, duration=float(m.t[-1])))
    err = float((played.q - m.q).pow(2).mean().sqrt())
    print("tflearn simulate on the torso:", err)
    assert err < 0.01
    pushed = recovery.run(config.PerturbConfig(                  # pushed on the torso it rides
        model=str(tmp_path / "run"), motions=["on_torso"], controllers=["fields", "ff", "ff+pd"],
        pushes=[{"force": [0.0, 1.0, 0.0], "at": 0.4, "duration": 0.1}], out=str(tmp_path / "push"),
        animation=False, tensorboard=False, tol=0.05), progress=False)["motions"]["on_torso"]
    print("perturb on the torso:", {c: (r["rmse"], r["cases"][0]["max_hand_dev"]) for c, r in pushed.items()})
    assert pushed["fields"]["rmse"] == pytest.approx(row["rmse"], abs=1e-4)   # as trained on it
    assert pushed["ff"]["rmse"] < 1e-5            # the torso's terms fed forward: measured 3e-7
    dev = {c: r["cases"][0]["max_hand_dev"] for c, r in pushed.items()}
    assert 0 < dev["ff+pd"] < dev["ff"] / 3       # feedback resists it (measured 1.6 against 11.4 cm)
    assert [x.name for x in named_motions(data, body, ["on_torso"], "run")] == ["on_torso"]
    with pytest.raises(InputError, match=r"^run: motion\(s\) 'wave' are not in the run's data"):
        named_motions(data, body, ["on_torso", "wave"], "run")
    assert torsos(data, [m], "fixed") is None
    np.savez(data / "torso" / "on_torso.npz", t=ts[:50], R=R[:50], x=x[:50])
    short = "the torso covers 0.000–0.490 s, motion 'on_torso' 0.000–1.200 s"
    with pytest.raises(MotionFileError, match=short):
        torsos(data, [m], "moving")
    (data / "torso" / "on_torso.npz").unlink()
    with pytest.raises(MotionFileError, match=r"torso.on_torso\.npz: no torso file for motion 'on_torso'"):
        torsos(data, [m], "moving")
