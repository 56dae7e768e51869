"""Modal analysis (tflearn.modes.analysis), mode-driven motion (tflearn.modes.motion) and the
``tflearn modes`` command."""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from tflearn import cli, config
from tflearn.modes import analysis as md
from tflearn.modes import command as modal
from tflearn.modes import motion as mm
from tflearn.modes.config import ModesConfig
from tflearn.motions.motion import load as load_motion
from tflearn.physics import body as tb
from tflearn.physics import dynamics
from tflearn.physics.configspace import difference, rotvec_to_rotmat

ROOT = Path(__file__).resolve().parents[1]
ARM_POSE = np.array([0.3, -0.2, 0.5, -1.0, 0.2, 0.1, -0.3])


def creature(name: str) -> ModesConfig:
    return config.load(ROOT / "configs" / "modes" / f"{name}.yaml", schema=ModesConfig)


def test_two_link_chain_against_closed_form():
    """Two hinged cylinders (no gravity, straight): by hand, about the joints,
    I₁ = m(3r² + L²)/12 + m(L/2)² (link 1 about joint 1, link 2 likewise about joint 2),
    M = [[I₁ + I₂ + mL² + 2m L (L/2), I₂ + m L (L/2)], [·, I₂]], and the frequencies solve
    det(K − λM) = 0: (M₁₁M₂₂ − M₁₂²) λ² − (k₁M₂₂ + k₂M₁₁) λ + k₁k₂ = 0. With k₁ = 0 the
    base joint is free: one rigid mode and λ = k₂ M₁₁ / det M."""
    L, m, r = 0.3, 1.0, 0.03
    body = tb.chain(2, length=L, mass=m, radius=r)
    Ic = m * (3 * r * r + L * L) / 12 + m * (L / 2) ** 2
    M = np.array([[2 * Ic + m * L * L + m * L * L, Ic + m * L * L / 2],
                  [Ic + m * L * L / 2, Ic]])
    detM = np.linalg.det(M)
    for k1, k2 in ((2.0, 1.0), (5.0, 0.3)):
        a, b, c = detM, -(k1 * M[1, 1] + k2 * M[0, 0]), k1 * k2
        lam = np.sort(np.roots([a, b, c]).real)
        res = md.analyse(body, np.zeros(2), np.diag([k1, k2]))
        np.testing.assert_allclose(res.eigenvalues, lam, rtol=1e-12)
        np.testing.assert_allclose(res.frequencies, np.sqrt(lam) / (2 * np.pi), rtol=1e-12)
        assert not res.rigid.any()
    res = md.analyse(body, np.zeros(2), md.stiffness_matrix(body, 1.0, {"link0": 0.0}))
    assert res.rigid.tolist() == [True, False] and res.frequencies[0] == 0.0
    assert res.eigenvalues[1] == pytest.approx(1.0 * M[0, 0] / detM, rel=1e-12)


def test_shapes_are_m_orthonormal_eigenvectors():
    """Uᵀ M U = I and K U = M U Λ on the arm at a general pose with a full stiffness."""
    body = tb.arm()
    rng = np.random.default_rng(3)
    A = rng.normal(size=(7, 7))
    K = A @ A.T + 7 * np.eye(7)
    res = md.analyse(body, ARM_POSE, md.stiffness_matrix(body, matrix=K.tolist()))
    U = res.shapes
    np.testing.assert_allclose(U.T @ res.M @ U, np.eye(7), atol=1e-12)
    np.testing.assert_allclose(res.K @ U, res.M @ U * res.eigenvalues, atol=1e-10)
    assert np.all(np.diff(res.frequencies) >= 0)
    np.testing.assert_allclose(res.M, dynamics.mass_matrix(body, torch.as_tensor(ARM_POSE)),
                               atol=0)


def test_frequencies_do_not_depend_on_zero_orientations():
    """The same physical arm and pose with joint zero orientations R0 (shoulder and wrist:
    rest ν' = log(R0ᵀ exp ν); elbow: an offset φ about its axis and θ' = θ − φ) gives
    the same frequencies: the tangent chart is the child frame, which R0 does not move."""
    off = [[0.4, -0.3, 0.2], [0.7, 0.0, 0.0], [-0.5, 0.6, 0.1]]
    plain, shifted = tb.arm(), tb.arm(offsets=off)
    q = torch.as_tensor(ARM_POSE)
    q2 = q.clone()
    for s, o in ((slice(0, 3), off[0]), (slice(4, 7), off[2])):
        R = rotvec_to_rotmat(torch.tensor(o, dtype=torch.float64)).T @ rotvec_to_rotmat(q[s])
        q2[s] = torch.as_tensor(__import__("roma").rotmat_to_rotvec(R))
    q2[3] = q[3] - off[1][0]
    np.testing.assert_allclose(dynamics.forward_kinematics(shifted, q2),
                               dynamics.forward_kinematics(plain, q), atol=1e-14)
    K = md.stiffness_matrix(plain, 4.0, {"forearm": 2.5})
    a = md.analyse(plain, ARM_POSE, K)
    b = md.analyse(shifted, q2.numpy(), K)
    np.testing.assert_allclose(b.frequencies, a.frequencies, rtol=1e-11)


def test_frequencies_do_not_depend_on_the_chart():
    """The springs of the tangent chart written in rotation vectors, K_r = Tᵀ K_t T with
    T = diag(J_r(ν₀), 1, J_r(ν₀)), give the same frequencies and shapes u_t = T u_r; the
    same matrix read in the two charts does not (ν₀ ≠ 0)."""
    body = tb.arm()
    Kt = md.stiffness_matrix(body, 3.0)
    T = md.chart_jacobian(body, ARM_POSE)
    assert not np.allclose(T, np.eye(7))
    t = md.analyse(body, ARM_POSE, Kt)
    r = md.analyse(body, ARM_POSE, T.T @ Kt @ T, options=md.ModalOptions(chart="rotvec"))
    np.testing.assert_allclose(r.frequencies, t.frequencies, rtol=1e-11)
    mapped = T @ r.shapes
    signs = np.sign((mapped * t.shapes).sum(0))
    np.testing.assert_allclose(mapped * signs, t.shapes, atol=1e-9)
    np.testing.assert_allclose(md.tangent_stiffness(r), Kt, atol=1e-12)
    other = md.analyse(body, ARM_POSE, Kt, options=md.ModalOptions(chart="rotvec"))
    assert np.abs(other.frequencies / t.frequencies - 1).max() > 1e-3


def test_floating_base_mass_matrix():
    """The free base's mass matrix: its joint block is dynamics.mass_matrix; with a ball
    root at the origin instead of a fixed one (and ν_root = 0, so its child-frame rates are
    world rates) the [angular base, joints] block is that body's dynamics.mass_matrix; its
    linear block is the total mass. Six rigid modes come first."""
    cfg = creature("linear_creature")
    body = tb.from_config(cfg.body)
    q0 = torch.zeros(body.nv, dtype=torch.float64)
    q0[:] = torch.linspace(-0.3, 0.4, body.nv, dtype=torch.float64)
    Mf = md.floating_mass_matrix(body, q0)
    np.testing.assert_allclose(Mf[6:, 6:], dynamics.mass_matrix(body, q0), atol=1e-15)
    mass = sum(link.mass for link in body.links)
    np.testing.assert_allclose(Mf[:3, :3], mass * np.eye(3), atol=1e-15)
    ball = body.with_(links=(replace(body.links[0], joint="ball"),) + body.links[1:])
    Mb = dynamics.mass_matrix(ball, torch.cat([torch.zeros(3, dtype=torch.float64), q0]))
    S = np.eye(body.nv + 3)                      # child-frame rates → world: R0 (the offset)
    S[:3, :3] = rotvec_to_rotmat(torch.tensor(body.links[0].offset, dtype=torch.float64))
    np.testing.assert_allclose(S.T @ Mf[3:, 3:] @ S, Mb, atol=1e-15)
    res = modal.analyse_config(cfg)
    assert res.shapes.shape == (21, 21) and res.n_rigid == 6
    assert res.rigid[:6].all() and not res.rigid[6:].any()


def test_loop_creature_modes_respect_the_closure():
    """The loop creature (configs/modes/loop_creature.yaml): 19 admissible directions (the
    paper's DOF), 6 rigid; every mode keeps the loop closed, |G u| ≤ 1e-10 |G| |u|, and
    (a ring of identical joints) the lowest elastic modes come in equal pairs; moving
    along a mixture of modes by ε opens the loop only to second order (gap ∝ ε²)."""
    cfg = creature("loop_creature")
    res = modal.analyse_config(cfg)
    assert res.frequencies.size == 19 and res.n_rigid == 6
    G, U = res.G, res.shapes
    assert np.abs(G @ U).max() <= 1e-10 * np.abs(G).max() * np.abs(U).max()
    np.testing.assert_allclose(res.frequencies[7], res.frequencies[6], rtol=1e-9)
    np.testing.assert_allclose(res.frequencies[9], res.frequencies[8], rtol=1e-9)
    body = res.body
    c = cfg.constraints[0]
    gaps = []
    for eps in (1e-3, 1e-4):
        u = res.joint_shapes[:, 6] + 0.7 * res.joint_shapes[:, 8] + 0.4 * res.joint_shapes[:, 11]
        x = eps * u / np.abs(u).max()
        q = mm.retract(res, torch.as_tensor(x))
        Rw, xw = dynamics.forward_kinematics_rot(body, dynamics.joint_rotations(body, q), q)
        end = xw[-2] + Rw[-1] @ torch.tensor(c.point, dtype=torch.float64)
        gaps.append(float((end - xw[0]).norm()))
    assert gaps[1] == pytest.approx(gaps[0] / 100, rel=0.01)
    assert gaps[0] < 1e-6


def test_fixed_hand_raises_frequencies():
    """A hand held fixed: the modes keep it still (|G u| tiny), there are 7 − 3 of them and
    by Cauchy interlacing each is at least the free arm's frequency of the same rank."""
    body = tb.arm()
    K = md.stiffness_matrix(body, 3.0)
    free = md.analyse(body, ARM_POSE, K)
    held = md.analyse(body, ARM_POSE, K, [md.Constraint("hand", (0.0, 0.0, -0.19))])
    assert held.frequencies.size == 4
    assert np.abs(held.G @ held.shapes).max() < 1e-12
    assert np.all(held.frequencies >= free.frequencies[:4] * (1 - 1e-12))
    np.testing.assert_allclose(held.shapes.T @ held.M @ held.shapes, np.eye(4), atol=1e-12)


@pytest.mark.parametrize("chart", md.CHARTS)
def test_free_vibration_at_the_computed_frequency(chart):
    """Released from θ₀ ⊕ 10⁻⁴ u₃ at rest under τ = K_t (θ₀ ⊖ θ), no damping, the arm at a
    general pose oscillates in mode 3 at its computed frequency (to 1%; measured from
    the upward zero crossings of the modal coordinate uᵀ M x(t)). Both charts: their
    frequencies differ by ~1% for the same matrix, and each simulation matches its own.
    The other modes stay below 1% of it (they are excited at second order in the
    amplitude only)."""
    body = tb.arm()
    res = md.analyse(body, ARM_POSE, md.stiffness_matrix(body, 20.0),
                     options=md.ModalOptions(chart=chart))
    i = 3
    f = res.frequencies[i]
    q_start = mm.retract(res, torch.as_tensor(1e-4 * res.joint_shapes[:, i]))
    t = torch.linspace(0.0, 3.3 / f, 200, dtype=torch.float64)
    from tflearn.simulation.simulate import SimOptions
    fol = mm.follow(res, [], t, q_start=q_start, options=SimOptions(rtol=1e-7, atol=1e-11))
    c = mm.modal_coordinate(res, fol.trajectory.q, i)
    measured = mm.measured_frequency(t.numpy(), c)
    assert measured == pytest.approx(f, rel=0.01)
    others = [mm.modal_coordinate(res, fol.trajectory.q, j) for j in range(7) if j != i]
    assert np.abs(others).max() < 0.01 * np.abs(c).max()


def test_soft_limits():
    """Past a limit by d a coordinate ends d·Δ/(d + Δ) past it (moved back by d²/(d + Δ)):
    untouched inside, continuous with slope 1 at the limit, never more than Δ past."""
    lim = mm.Limits(np.array([-1.0]), np.array([0.5]), soft=0.1)
    q = torch.tensor([[0.2], [0.5], [0.6], [10.0], [-1.3]], dtype=torch.float64)
    out = mm.soft_limit(q, lim)[:, 0].numpy()
    d = np.array([0.1, 9.5, 0.3])
    np.testing.assert_allclose(out[:2], [0.2, 0.5])
    np.testing.assert_allclose(out[2:], [0.5 + d[0] * 0.1 / 0.2, 0.5 + 9.5 * 0.1 / 9.6,
                                         -1.0 - 0.3 * 0.1 / 0.4], rtol=1e-14)
    h = 1e-7
    slope = (mm.soft_limit(torch.tensor([[0.5 + h]], dtype=torch.float64), lim) - 0.5) / h
    assert float(slope) == pytest.approx(1.0, abs=1e-5)


def test_kinematic_motion_is_the_mode_sum():
    """θ₀ ⊖ θ(t) = α û sin(2π f̃ t + γ) + β û' in the tangent chart (no limits), with
    the shapes û scaled to a largest coordinate of 1."""
    body = tb.arm()
    res = md.analyse(body, ARM_POSE, md.stiffness_matrix(body, 2.0))
    drives = [mm.ModeDrive(1, amplitude=0.3, phase=0.4), mm.ModeDrive(2, offset=-0.05)]
    t = np.linspace(0.0, 1.0, 11)
    q = mm.kinematic(res, drives, t)
    x = difference(body, torch.as_tensor(ARM_POSE).expand(q.shape), q).numpy()
    U = res.shapes / np.abs(res.shapes).max(axis=0)
    want = (0.3 * np.sin(2 * np.pi * res.frequencies[1] * t + 0.4)[:, None] * U[:, 1]
            - 0.05 * U[:, 2])
    np.testing.assert_allclose(x, want, atol=1e-12)
    with pytest.raises(md.ModalError, match="mode 9 does not exist"):
        mm.kinematic(res, [mm.ModeDrive(9, amplitude=1.0)], t)


def test_bad_input_is_one_clear_error():
    body = tb.arm()
    with pytest.raises(md.ModalError, match=r"expected 7×7 .* got shape \(6, 6\)"):
        md.analyse(body, np.zeros(7), np.eye(6))
    with pytest.raises(md.ModalError, match=r"no joint matches 'spine\*' \(joints: upper_arm"):
        md.stiffness_matrix(body, 1.0, {"spine*": 10})
    with pytest.raises(md.ModalError, match="no link named 'foot'"):
        md.analyse(body, np.zeros(7), np.eye(7), [md.Constraint("foot")])
    with pytest.raises(md.ModalError, match="0.19 m apart"):
        md.analyse(body, np.zeros(7), np.eye(7), [md.Constraint("hand", (0, 0, -0.19), "hand")])
    point = tb.Link("bead", -1, "ball", (0, 0, 0), 1.0, (0, 0, 0), ((0.0,) * 3,) * 3)
    with pytest.raises(md.ModalError, match="mass matrix is singular"):
        md.analyse(tb.Body(links=(point,)), np.zeros(3), np.eye(3))
    assert issubclass(md.ModalError, __import__("tflearn").InputError)


def test_modes_command(tmp_path, capsys):
    """``tflearn modes`` on the linear creature writes modes.json (the analysis' numbers),
    each animated mode as a Motion .npz and a .png, logs the frequencies and shape
    figures to TensorBoard, and prints the table."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    out = tmp_path / "lin"
    cfg = ROOT / "configs" / "modes" / "linear_creature.yaml"
    assert cli.main(["modes", str(cfg), "animation.modes=2", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    res = modal.analyse_config(creature("linear_creature"))
    assert f"{res.frequencies[6]:10.4f}" in printed and "rigid" in printed
    doc = json.loads((out / "modes.json").read_text())
    assert doc["format"] == "tflearn-modes/1" and doc["floating"] is True
    np.testing.assert_allclose([m["frequency_hz"] for m in doc["modes"]], res.frequencies,
                               rtol=1e-12)
    assert np.array(doc["stiffness"]).shape == (15, 15) and len(doc["coordinates"]) == 21
    body = tb.from_dict(doc["body"])
    for i in (6, 7):
        m = load_motion(out / f"mode_{i:02d}.npz", body)
        assert m.q.shape[1] == 15 and np.abs(m.q.numpy()).max() == pytest.approx(0.2, rel=1e-3)
        assert (out / f"mode_{i:02d}.png").stat().st_size > 10_000
    assert (out / "motion.npz").exists() and not (out / "mode_08.npz").exists()
    ea = EventAccumulator(str(out / "tensorboard"), size_guidance={"scalars": 0, "images": 0})
    ea.Reload()
    logged = [e.value for e in ea.Scalars("modes/frequency_hz")]
    np.testing.assert_allclose(logged, res.frequencies, rtol=1e-6)
    assert set(ea.Tags()["images"]) == {"modes/shape_06", "modes/shape_07"}


def test_modes_command_bad_input(tmp_path, capsys):
    cfg = ROOT / "configs" / "modes" / "arm.yaml"
    assert cli.main(["modes", str(cfg), "stiffness.scale={spine*: 10}",
                     "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"tflearn: {cfg}: stiffness.scale: no joint matches 'spine*'")
    assert cli.main(["modes", str(cfg), "stiffness.uniform=-1", "--out", str(tmp_path)]) == 2
    assert "stiffness.uniform" in capsys.readouterr().err


def test_human_from_a_bvh_hierarchy(mocap):
    """The CMU skeleton as a body: a ball per non-root joint (30 → 90 coordinates); masses
    sum to the total with Winter's per-segment fractions (a thigh 10%, a hand 0.6%, the
    trunk 49.7% over its bones); inertias positive definite; on a floating base six
    rigid modes, then elastic ones."""
    from tflearn.mocap import bvh, names
    from tflearn.mocap import skeleton as sk
    skel = bvh.read(mocap / "cmu_141_16_wave-hello.bvh")
    body = sk.body_from_skeleton(skel, 70.0)
    assert body.nv == 90 and [link.name for link in body.links] == list(skel.joints)
    m = {link.name: link.mass for link in body.links}
    assert sum(m.values()) == pytest.approx(70.0, rel=1e-12)
    assert m["LeftUpLeg"] == pytest.approx(7.0, rel=1e-12)
    hand = sum(v for k, v in m.items() if names.segment_class(k) == "hand" and names.side(k) == "right")
    assert hand == pytest.approx(0.42, rel=1e-12)
    trunk = sum(v for k, v in m.items() if names.segment_class(k) == "trunk")
    assert trunk == pytest.approx(0.497 * 70, rel=1e-12)
    assert all(np.linalg.eigvalsh(np.array(link.inertia)).min() > 0 for link in body.links)
    res = md.analyse(body, np.zeros(90), md.stiffness_matrix(body, 100.0, {"Spine*": 10}),
                     options=md.ModalOptions(floating=True))
    assert res.n_rigid == 6 and res.frequencies[6] > 0.1


def test_modes_command_writes_bvh(mocap, tmp_path):
    """For a skeleton, each mode's animation also as BVH in the file's hierarchy: read
    back, its joint rotations are the motion's (to 1e-9) and its root stays put."""
    from scipy.spatial.transform import Rotation

    from tflearn.mocap import bvh
    clip = mocap / "dataset-1_bye_normal_001.bvh"
    out = tmp_path / "human"
    cfg = tmp_path / "bandai.yaml"
    cfg.write_text(f"skeleton: {{file: {clip}}}\nfloating: true\n"
                   "stiffness: {uniform: 100.0, scale: {Spine: 10, Chest: 10}}\n")
    assert cli.main(["modes", str(cfg), "animation.modes=1", "log.tensorboard=false",
                     "--out", str(out)]) == 0
    skel = bvh.read(clip)
    back = bvh.read(out / "mode_06.bvh", scale=skel.scale)
    assert back.joints == skel.joints and back.parents == skel.parents
    doc = json.loads((out / "modes.json").read_text())
    body = tb.from_dict(doc["body"])
    q = load_motion(out / "mode_06.npz", body).q.numpy()
    assert back.frames == q.shape[0]
    for j, link in enumerate(body.links):
        if link.joint == "ball":
            want = Rotation.from_rotvec(q[:, body.slice(j)]).as_matrix()
            np.testing.assert_allclose(back.rotations[:, j], want, atol=1e-9)
    np.testing.assert_allclose(back.positions[:, 0], skel.positions[:1, 0].repeat(back.frames, 0),
                               atol=1e-9)


def test_bvh_without_hierarchy_is_one_error(tmp_path, capsys):
    bad = tmp_path / "nohier.bvh"
    bad.write_text("MOTION\nFrames: 1\nFrame Time: 0.01\n0 0 0\n")
    assert cli.main(["modes", str(ROOT / "configs" / "modes" / "human.yaml"),
                     f"skeleton.file={bad}", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(bad) in err and "HIERARCHY" in err
