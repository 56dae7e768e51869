"""Mode-driven locomotion (tflearn.modes.locomotion) on a small floating chain: internal torques
cannot move the centre of mass (free fall is a parabola whatever the PD does), the
controller leaves the base unactuated, a body at rest on the ground stays put."""
from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from tflearn.modes import analysis as md
from tflearn.modes import locomotion as lo
from tflearn.modes import motion as mm
from tflearn.physics import body as tb
from tflearn.physics import dynamics as D
from tflearn.simulation.simulate import SimOptions

from conftest import DT


def small_creature() -> tb.Body:
    """Four hinged cylinders (0.1 m, 0.05 kg) lying along +x, root on a fixed joint."""
    links = [tb.cylinder_link("s0", -1, "fixed", (0, 0, 0), 0.1, 0.05, 0.01,
                              offset=(0.0, -math.pi / 2, 0.0))]
    links += [tb.cylinder_link(f"s{i}", i - 1, "hinge", (0, 0, -0.1), 0.1, 0.05, 0.01,
                               axis=(0.0, 1.0, 0.0)) for i in range(1, 4)]
    return tb.Body(links=tuple(links), name="small")


def _modes():
    body = small_creature()
    return md.analyse(body, md.rest_pose(body), md.stiffness_matrix(body, 1.0),
                      options=md.ModalOptions(floating=True))


DRIVES = [mm.ModeDrive(6, amplitude=0.3, frequency=4.0), mm.ModeDrive(7, amplitude=0.3,
                                                                      frequency=4.0, phase=1.57)]
FAST = SimOptions(method="rk4", solver_options={"step_size": 1e-3}, max_evals=None)


def test_free_fall_centre_of_mass_is_a_parabola_while_the_joints_move():
    """Dropped from 10 m (the ground out of reach): the PD moves the joints by tenths of a
    radian, the centre of mass falls as z₀ − g t²/2 and does not move sideways (to 1e-8 m:
    RK4's error at 1 ms, the centre of mass being a nonlinear function of the state)."""
    opts = lo.LocomotionOptions(duration=0.2, settle=0.0, rate=50.0, sim=FAST, lift=10.0)
    gait = lo.locomote(_modes(), DRIVES, options=opts)
    t = gait.trajectory.t.numpy()
    com = gait.com
    assert abs(com[:, 2] - (com[0, 2] - 0.5 * 9.81 * t * t)).max() < 1e-8
    assert abs(com[:, :2] - com[0, :2]).max() < 1e-8
    joints = gait.trajectory.q[:, lo.N_FREE:]
    assert float((joints - joints[0]).abs().max()) > 0.05
    assert gait.evals == 4 * 200


def test_controller_leaves_the_base_unactuated():
    modes = _modes()
    body = lo.free_body(modes.body)
    q = lo.free_start(modes.body, torch.zeros(3, dtype=DT)) + 0.1
    tau = lo.pd_torques(modes, DRIVES, None, 0.01, torch.tensor(0.2, dtype=DT), q,
                        torch.ones(body.nv, dtype=DT))
    assert torch.equal(tau[:lo.N_FREE], torch.zeros(lo.N_FREE, dtype=DT))
    assert float(tau[lo.N_FREE:].abs().min()) > 0


def test_undriven_creature_rests_on_the_ground():
    """No drives: lying on the ground it settles with its five contact points' springs
    carrying its weight (mean depth m g/(5 k), 1%) and does not travel."""
    opts = lo.LocomotionOptions(duration=0.3, settle=0.1, rate=50.0, sim=FAST)
    gait = lo.locomote(_modes(), [], options=opts)
    assert gait.distance < 1e-9
    q = gait.trajectory.q[-1]
    links, points = lo.contact_points(gait.body, q)
    assert len(links) == 5
    p, _ = D.points_kinematics_rot(gait.body, D.joint_rotations(gait.body, q), q, links, points)
    weight = 4 * 0.05 * 9.81
    assert abs(float(-p[:, 2].mean()) / (weight / (5 * opts.ground.stiffness)) - 1) < 0.01


def test_free_body_needs_a_fixed_root():
    body = small_creature()
    links = (replace(body.links[0], joint="ball"),) + body.links[1:]
    with pytest.raises(md.ModalError, match="root"):
        lo.free_body(body.with_(links=links))


@pytest.mark.slow
def test_locomotion_command_writes_the_gait_its_path_and_a_gif(tmp_path, capsys):
    """``tflearn locomotion CONFIG``: the small creature, driven by modes 6 and 7 at 4 Hz,
    travels along its own axis and stays in its vertical plane; locomotion.json's travel
    is the centre of mass's horizontal travel over [settle, duration] of the path written
    to locomotion.npz, and its speed that travel per second in body lengths (0.4 m)."""
    import json

    import numpy as np
    import yaml
    from PIL import Image

    from tflearn import cli
    from tflearn.motions.motion import load as load_motion
    cfg = {"body": small_creature().to_dict(), "stiffness": {"uniform": 1.0}, "floating": True,
           "motion": {"drives": [{"mode": 6, "amplitude": 0.3, "frequency": 4.0},
                                 {"mode": 7, "amplitude": 0.3, "frequency": 4.0, "phase": 1.57}]}}
    (tmp_path / "small.yaml").write_text(yaml.safe_dump(cfg))
    out = tmp_path / "out"
    assert cli.main(["locomotion", str(tmp_path / "small.yaml"), "--out", str(out), "--duration", "0.6",
                     "--settle", "0.2", "--step", "1e-3"]) == 0
    assert "wrote locomotion.json, locomotion.npz, locomotion.gif" in capsys.readouterr().out
    doc = json.loads((out / "locomotion.json").read_text())
    assert doc["creature"] == "small" and doc["evals"] == 4 * 600
    assert doc["distance_m"] > 5e-3                                 # it moved (measured 1.4 cm)
    assert abs(abs(doc["direction_xy"][0]) - 1) < 1e-9 and doc["com_lateral_max_m"] < 1e-9
    assert doc["body_length_m"] == pytest.approx(0.4, rel=1e-12)
    assert doc["speed_body_lengths_per_s"] == pytest.approx(doc["distance_m"] / 0.4 / 0.4, rel=1e-12)
    body = lo.free_body(small_creature()).with_(gravity=(0.0, 0.0, -9.81))
    path = load_motion(out / "locomotion.npz", body)
    assert path.T == 301 and path.qd is not None
    com = lo.centre_of_mass(body, path.q).numpy()
    keep = path.t.numpy() >= 0.2 - 1e-12
    travel = com[keep][-1, :2] - com[keep][0, :2]
    assert np.linalg.norm(travel) == pytest.approx(doc["distance_m"], rel=1e-9)
    with Image.open(out / "locomotion.gif") as gif:                 # 25 frames per second
        assert gif.n_frames >= 10
