"""Controllers (tflearn.control.controllers), perturbations and their measures (tflearn.control.pushes).

Small problems: a 1.2 s come-here gesture (one field, exact torques from its generating
program), batched wherever the controllers allow it."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tflearn.control import controllers as C
from tflearn.control import pushes as P
from tflearn.data import gestures
from tflearn.model.program import FieldProgram
from tflearn.physics import body as tb
from tflearn.physics import dynamics
from tflearn.simulation.simulate import SimOptions, simulate

DT = torch.float64
OPT = SimOptions(rtol=1e-6, atol=1e-8)
PUSH = P.Push.from_impulse((0.0, 0.12, 0.0), onset=0.4, duration=0.1)   # hand, sideways


@pytest.fixture(scope="module")
def gesture():
    """(body, motion, fields program, exact-torque target) of a short come-here."""
    g = gestures.GESTURES["come_here"]
    g = gestures.Gesture("short", g.eta, g.k, g.a, g.b, duration=1.2)
    (motion, lb), = gestures.generate(gestures=[g])
    program = FieldProgram(lb.basis, lb.weights)
    return lb.body, motion, program, C.Target(lb.body, motion, C.OneMotion(program))


def _start(target, n=1):
    q0, v0, _ = target(target.motion.t[0])
    return q0.expand(n, -1), v0.expand(n, -1)


def test_fields_controller_is_its_program(gesture):
    """`fields` reproduces the program's own simulation exactly (same path, bit for bit)."""
    body, motion, program, exact = gesture
    q0, v0 = _start(exact)
    r = P.respond(body, C.build("fields", exact, program), P.Perturbation(), q0, v0, motion.t, OPT)
    with torch.no_grad():                 # as respond: the same (compiled) dynamics
        ref = simulate(body, program, q0[:, None], v0[:, None], motion.t, OPT, track_work=True)
    assert torch.equal(r.q, ref.q[:, 0]) and torch.equal(r.v, ref.v[:, 0])
    with pytest.raises(C.ControllerError, match="needs the motion's learned program"):
        C.build("fields", exact)
    with pytest.raises(C.ControllerError, match="unknown controller 'pd'"):
        C.build("pd", exact)


def test_fields_controller_keeps_the_fields_damping(gesture):
    """Damped fields (ζ > 0) under `fields` are damped as in the program's own simulation:
    the controller passes the velocity on (a controller that dropped it left a keyframe
    run's fields 0.15–0.49 rad off the path its training reproduced)."""
    body, motion, program, exact = gesture
    b = program.basis
    damped = FieldProgram(type(b)(b.eta.detach(), b.K().detach(), b.kind, b.blocks, damping=0.2),
                          program.weights)
    q0, v0 = _start(exact)
    r = P.respond(body, C.build("fields", exact, damped), P.Perturbation(), q0, v0, motion.t, OPT)
    with torch.no_grad():
        ref = simulate(body, damped, q0[:, None], v0[:, None], motion.t, OPT, track_work=True)
        free = simulate(body, program, q0[:, None], v0[:, None], motion.t, OPT, track_work=True)
    assert torch.equal(r.q, ref.q[:, 0])
    assert float((ref.q - free.q).abs().max()) > 1e-3          # the damping matters here


def _pair(body, ctrl, q0, v0, t, push=PUSH):
    """(unperturbed, pushed) responses of one controller, as one batch of two."""
    zero = P.Push(tuple(np.stack([np.zeros(3), push.force])), push.onset, push.duration)
    r = P.respond(body, ctrl, P.Perturbation((zero,)), q0.expand(2, -1), v0.expand(2, -1), t, OPT)
    return [P.Response(r.t, r.q[i], r.v[i], r.tau[i], r.hand[i], r.push_work[i], r.work[i])
            for i in (0, 1)]


@pytest.fixture(scope="module")
def responses(gesture):
    """controller → (unperturbed, pushed) on the exact-torque target."""
    body, motion, program, exact = gesture
    q0, v0 = _start(exact)
    return {name: _pair(body, C.build(name, exact, program), q0[0], v0[0], motion.t)
            for name in C.CONTROLLERS}


@pytest.mark.slow
def test_zero_force_ff_and_ff_pd_reproduce_the_target(gesture, responses):
    """Exact feed-forward torques replay the gesture open loop and with feedback."""
    body, motion, _, _ = gesture
    for name in ("ff", "ff+pd"):
        rmse = P.tracking_rmse(body, responses[name][0], motion.q)
        assert rmse <= 1e-3, (name, rmse)
    assert P.tracking_rmse(body, responses["pd-high"][0], motion.q) > 1e-3   # no feed-forward


def test_spline_feedforward_is_the_learners_torque(gesture):
    """The default τ_ff is motion.torques (the spline's inverse dynamics) at any time, and
    within 1e-3 relative of the generating program's exact torque mid-motion."""
    from tflearn.motions.spline import torques
    body, motion, _, exact = gesture
    spline = C.Target(body, motion)
    t = motion.t[40:50]
    ref, _, _ = torques(body, motion, t)
    ours = torch.stack([spline(tk)[2] for tk in t])
    np.testing.assert_allclose(ours.numpy(), ref.numpy(), rtol=1e-12, atol=1e-12)
    true = torch.stack([exact(tk)[2] for tk in t]).detach()
    assert float((ours - true).norm() / true.norm()) < 1e-3


@pytest.mark.slow
def test_a_push_separates_the_controllers(gesture, responses):
    """ff ends further from the target than ff+pd and fields; pd-high deviates least but
    with the largest peak torque."""
    body, motion, _, _ = gesture
    m = {name: P.measure(body, base, pushed, motion.q, (PUSH.onset, PUSH.end))
         for name, (base, pushed) in responses.items()}
    assert m["ff"]["final_joint_error"] > max(m["ff+pd"]["final_joint_error"],
                                              m["fields"]["final_joint_error"])
    assert m["pd-high"]["max_hand_dev"] < min(m[c]["max_hand_dev"] for c in ("ff", "ff+pd", "fields"))
    assert m["pd-high"]["peak_torque"] > max(m[c]["peak_torque"] for c in ("ff", "ff+pd", "fields"))
    assert m["ff"]["recovery_s"] is None and m["pd-high"]["recovery_s"] is not None
    assert m["ff+pd"]["max_hand_dev"] > 0.01            # the push is felt


@pytest.mark.slow
def test_recovery_time_falls_as_gains_rise(gesture):
    """ff+pd at K₀·s, B₀·√s for s = 1, 2, 4 (one batch: each scale unperturbed and pushed)."""
    body, motion, program, exact = gesture
    K, B = C.joint_gains(body)
    s = torch.tensor([1.0, 1.0, 2.0, 2.0, 4.0, 4.0], dtype=DT)[:, None]
    ctrl = C.Impedance(exact, s * K, s.sqrt() * B)
    F = np.zeros((6, 3))
    F[1::2] = PUSH.force
    q0, v0 = _start(exact, 6)
    r = P.respond(body, ctrl, P.Perturbation((P.Push(tuple(F), PUSH.onset, PUSH.duration),)),
                  q0, v0, motion.t, OPT)
    rows = [P.measure(body, *[P.Response(r.t, r.q[i], r.v[i], r.tau[i], r.hand[i], r.push_work[i],
                                         r.work[i]) for i in (k, k + 1)], motion.q,
                      (PUSH.onset, PUSH.end)) for k in (0, 2, 4)]
    rec = [row["recovery_s"] for row in rows]
    assert None not in rec and rec[0] > rec[1] > rec[2], rec
    dev = [row["max_hand_dev"] for row in rows]
    assert dev[0] > dev[1] > dev[2], dev


def test_energy_gained_equals_controller_plus_push_work(gesture):
    """ΔE = ∫τ_ctrl·v dt + ∫f·ẋ dt (trapezoid on 1 kHz samples), and the simulator's own
    work integral (controller + push torques) equals ΔE to integration accuracy."""
    body, motion, program, exact = gesture
    t = torch.linspace(0.3, 0.7, 401, dtype=DT)
    q0, v0 = exact(t[0])[:2]
    r = P.respond(body, C.build("fields", exact, program), P.Perturbation((PUSH,)), q0, v0, t,
                  SimOptions(rtol=1e-11, atol=1e-12))
    E = dynamics.kinetic_energy(body, r.q, r.v) + dynamics.potential_energy(body, r.q)
    gained = float(E[-1] - E[0])
    ctrl_work = float(torch.trapezoid((r.tau * r.v).sum(-1), t))
    assert abs(float(r.push_work)) > 0.02                  # the push does real work
    assert abs(gained - float(r.work[-1])) < 1e-8 * max(1.0, abs(gained))
    assert gained == pytest.approx(ctrl_work + float(r.push_work), rel=1e-4, abs=1e-6)


def test_impulse_and_push_torque():
    """from_impulse gives ∫f dt = the impulse; the torque is J_linᵀ f at the named point."""
    push = P.Push.from_impulse([[0.3, -0.2, 0.1], [0.0, 0.0, 1.0]], onset=0.2, duration=0.05,
                               point="elbow")
    t = torch.linspace(0.1, 0.4, 30001, dtype=DT)
    f = torch.stack([push.force_at(tk) for tk in t])
    np.testing.assert_allclose(torch.trapezoid(f, t, dim=0).numpy(), [[0.3, -0.2, 0.1], [0, 0, 1]],
                               atol=1e-9)
    arm = tb.arm()
    q = torch.tensor([0.3, -0.4, 0.2, -1.1, 0.2, 0.1, -0.3], dtype=DT)
    tau = push.torque(arm, torch.tensor(0.225, dtype=DT), q)
    J = dynamics.point_jacobian(arm, q, 1, (0.0, 0.0, 0.0))[:3]
    np.testing.assert_allclose(tau.numpy(), (push.force_at(0.225) @ J).numpy(), rtol=1e-14)
    assert torch.all(tau[:, 3:] == 0)            # a force at the elbow moves no joint below it
    with pytest.raises(P.PerturbationError, match="no point 'knee'"):
        P.point_on(arm, "knee")
    with pytest.raises(P.PerturbationError, match="duration > 0"):
        P.Push((1.0, 0, 0), 0.1, 0.0)


def test_carried_mass_equals_a_fixed_point_mass_link():
    """carry(body, m) has the dynamics of the body with a fixed child link holding a point
    mass m at the hand tip (an independent tree)."""
    arm = tb.arm(gravity=(0.0, 0.0, -9.81))
    m = 0.8
    held = P.carry(arm, m)
    extra = tb.Link("object", parent=2, joint="fixed", origin=arm.tip_point, mass=m,
                    com=(0.0, 0.0, 0.0), inertia=((0.0, 0, 0), (0, 0.0, 0), (0, 0, 0.0)))
    ref = arm.with_(links=arm.links + (extra,))
    g = torch.Generator().manual_seed(3)
    q, v, a = (torch.randn(5, 7, generator=g, dtype=DT) for _ in range(3))
    np.testing.assert_allclose(dynamics.rnea(held, q, v, a).numpy(), dynamics.rnea(ref, q, v, a).numpy(),
                               rtol=1e-12, atol=1e-12)
    assert held.links[2].mass == pytest.approx(arm.links[2].mass + m)
    assert math.isclose(float(dynamics.tip_position(held, q[0]).norm()),
                        float(dynamics.tip_position(arm, q[0]).norm()))


def test_gains_need_every_moving_link():
    chain = tb.chain(2)
    with pytest.raises(C.ControllerError, match="link0"):
        C.joint_gains(chain)
    K, B = C.joint_gains(chain, {"link0": (3.0, 0.1), "link1": (2.0, 0.05)})
    assert K.tolist() == [3.0, 2.0] and B.tolist() == [0.1, 0.05]


# ----------------------------------------------------------------------------- the command

@pytest.mark.slow
def test_perturb_command(tmp_path, capsys):
    """tflearn perturb on a gesture's basis.json (its NAME.npz beside it is the target):
    results.json with the figures per case, the push and sweep plots, the GIF and
    TensorBoard events; bad input is one line and exit status 2."""
    import json

    from tflearn import cli
    g = gestures.GESTURES["come_here"]
    gestures.write(tmp_path, gestures=[gestures.Gesture("short", g.eta, g.k, g.a, g.b, duration=0.8)],
                   plots=False)
    cfg = tmp_path / "perturb.yaml"
    cfg.write_text(f"model: {tmp_path / 'short.json'}\nmotions: [short]\ncontrollers: [fields]\n"
                   f"pushes: [{{force: [1.0, 0, 0], at: 0.3, duration: 0.1}}]\n"
                   f"sweep: {{directions: [[0, 1, 0]], impulses: [0.01, 0.02], at: 0.3}}\n"
                   f"out: {tmp_path / 'out'}\n")
    assert cli.main(["perturb", "--config", str(cfg)]) == 0
    doc = json.loads((tmp_path / "out" / "results.json").read_text())
    rows = doc["motions"]["short"]["fields"]["cases"]
    assert [r["case"] for r in rows] == ["push (1.0, 0.0, 0.0) N at 0.3 s", "sweep", "sweep"]
    assert rows[0]["impulse_Ns"] == pytest.approx(0.05)
    assert rows[2]["max_hand_dev"] > rows[1]["max_hand_dev"] > 0
    assert doc["motions"]["short"]["fields"]["rmse"] < 1e-6
    for name in ("short_push.png", "short_sweep.png", "short.gif"):
        assert (tmp_path / "out" / "figures" / name).stat().st_size > 1000
    assert list((tmp_path / "out" / "tensorboard").glob("events.*"))
    assert "fields" in capsys.readouterr().out
    model = str(tmp_path / "short.json")
    for argv, word in ((["--motion", "short", "--force", "1,2"], "--force"),
                       (["--motion", "short", "--controller", "pd"], "controllers"),
                       (["--motion", "wave", "--out", str(tmp_path / "o2")], "wave"),
                       (["--motion", "short", "--point", "knee", "--out", str(tmp_path / "o3")], "knee")):
        assert cli.main(["perturb", model, *argv]) == 2, argv
        err = capsys.readouterr().err.strip()
        assert err.startswith("tflearn: ") and word in err and "\n" not in err, err


@pytest.mark.slow
def test_perturb_a_folder_of_imported_motions(tmp_path, capsys):
    """MODEL may be a folder of motions without a basis (NAME.npz and body.yaml, as
    ``tflearn bvh import`` writes clips): the tracking controllers run on the body of
    body.yaml; ``fields`` is refused, naming the folder, before any work."""
    import json

    from tflearn import cli
    from tflearn.motions.motion import save
    g = gestures.GESTURES["come_here"]
    (m, _), = gestures.generate(gestures=[gestures.Gesture("clip", g.eta, g.k, g.a, g.b, duration=0.8)])
    save(m, tmp_path / "clip.npz")
    (tmp_path / "body.yaml").write_text("body:\n  preset: arm\n  lengths: [0.3, 0.27, 0.19]\n")
    out = tmp_path / "out"
    argv = ["perturb", str(tmp_path), "--motion", "clip", "--force", "1,0,0", "--at", "0.3",
            "--duration", "0.1", "--no-animation", "--out", str(out)]
    assert cli.main([*argv, "--controller", "ff+pd"]) == 0
    rows = json.loads((out / "results.json").read_text())["motions"]["clip"]["ff+pd"]
    assert rows["rmse"] < 0.01 and 0 < rows["cases"][0]["max_hand_dev"] < 0.05
    capsys.readouterr()
    assert cli.main([*argv, "--controller", "fields"]) == 2
    err = capsys.readouterr().err
    assert "no basis.json" in err and str(tmp_path) in err
    (tmp_path / "body.yaml").unlink()
    assert cli.main([*argv, "--controller", "ff"]) == 2
    assert "no body.yaml" in capsys.readouterr().err
