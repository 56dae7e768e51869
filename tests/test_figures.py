"""Figures (tflearn.plots.figures: motions; tflearn.plots.model: fields, hand forces, profiles,
weights, learning curves) and animations (tflearn.render, ``tflearn render``)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from matplotlib.patches import Rectangle
from PIL import Image
from scipy.spatial.transform import Rotation

from tflearn import cli, render
from tflearn.data import gestures
from tflearn.errors import InputError
from tflearn.model.fields import FieldBasis
from tflearn.model.weights import pulse_profile, step_profile
from tflearn.physics import body as tb
from tflearn.physics import dynamics
from tflearn.plots import figures as plots
from tflearn.plots import model as model_plots

DT = torch.float64


# ------------------------------------------------------------------ hand Jacobian, forces

def compose(body: tb.Body, q: np.ndarray, dv: np.ndarray) -> np.ndarray:
    """The posture reached from q by a velocity-coordinate step dv: per ball joint the
    rotation exp([v]×) becomes exp([v]×)·exp([dv]×) (dv a child-frame angular
    displacement), hinges add dv. Independent of tflearn (scipy rotations)."""
    out = q.copy()
    for i, link in enumerate(body.links):
        s = body.slice(i)
        if link.joint == "ball":
            out[s] = (Rotation.from_rotvec(q[s]) * Rotation.from_rotvec(dv[s])).as_rotvec()
        else:
            out[s] = q[s] + dv[s]
    return out


def fd_jacobian(body: tb.Body, q: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """Central differences of the hand tip along each velocity coordinate (3×nv)."""
    def tip(x):
        return plots.joint_positions(body, x[None])[0, -1]
    cols = []
    for k in range(body.nv):
        e = np.zeros(body.nv)
        e[k] = h
        cols.append((tip(compose(body, q, e)) - tip(compose(body, q, -e))) / (2 * h))
    return np.stack(cols, -1)


POSTURE = np.array([-1.2, 0.3, 0.4, -1.1, -0.5, 0.2, 0.3])


def hand_jacobian(body: tb.Body, q) -> torch.Tensor:
    """The hand tip's Jacobian as hand_force takes it: the linear rows of the tip's
    point Jacobian."""
    return dynamics.point_jacobian(body, torch.as_tensor(q, dtype=DT), body.tip_link,
                                   body.tip_point)[..., :3, :]


@pytest.mark.parametrize("offsets", [None, [[0.1, 0.2, -0.3], [0.3, -0.1, 0.2], [-0.2, 0.4, 0.1]]])
def test_hand_jacobian_matches_finite_differences(offsets):
    """The tip Jacobian behind hand_force (tflearn.physics.dynamics.point_jacobian) is the
    Jacobian in velocity coordinates (child-frame angular velocities), not ∂p/∂ν: it
    matches central differences along composed rotations (measured ≤ 1e-9) and differs
    from ∂p/∂ν at a posture with ball rotations."""
    body = tb.arm(offsets=offsets)
    J = hand_jacobian(body, POSTURE).numpy()
    assert J.shape == (3, 7)
    np.testing.assert_allclose(J, fd_jacobian(body, POSTURE), rtol=0, atol=1e-8)
    dp_dq = torch.autograd.functional.jacobian(
        lambda q: dynamics.tip_position(body, q), torch.tensor(POSTURE, dtype=DT)).numpy()
    assert np.abs(dp_dq - J).max() > 1e-2
    # batched: the same matrix for each of a stack of postures
    Jb = hand_jacobian(body, np.stack([POSTURE, 0.5 * POSTURE]))
    assert Jb.shape == (2, 3, 7)
    np.testing.assert_allclose(Jb[0].numpy(), J, rtol=0, atol=1e-14)


def test_hand_force_inverts_transpose_jacobian(rng):
    """At a posture where J (3×7) has full row rank: a torque τ = Jᵀ F0 gives back F0 and
    Jᵀ F = τ; a general torque (a field's) gives the least-squares force, the residual
    Jᵀ F − τ orthogonal to every force's torque (J (Jᵀ F − τ) = 0)."""
    body = tb.arm()
    q = torch.tensor(POSTURE, dtype=DT)
    J = fd_jacobian(body, POSTURE)
    assert np.linalg.matrix_rank(J) == 3
    F0 = rng.normal(size=3)
    tau = J.T @ F0
    F = model_plots.hand_force(body, q, torch.tensor(tau, dtype=DT)).numpy()
    np.testing.assert_allclose(F, F0, rtol=0, atol=1e-7)
    np.testing.assert_allclose(J.T @ F, tau, rtol=0, atol=1e-7)
    _, eta, K = model_plots.gallery_fields()[2]
    chi = FieldBasis(eta[None], K[None], kind="full")(q)[0].detach()
    assert float(chi.norm()) > 0.1
    F = model_plots.hand_force(body, q, chi).numpy()
    np.testing.assert_allclose(J @ (J.T @ F - chi.numpy()), 0.0, rtol=0, atol=1e-7)


# ------------------------------------------------------------------ field figures

def test_field_figure_draws_the_field_and_its_hand_forces():
    """field_figure's arrows: (χ_i, χ_j) of the field at the slice postures (left) and
    the least-squares hand forces of those torques, projected onto the plane of the hand
    positions (right): their torques satisfy the normal equations J(JᵀF − χ) = 0."""
    body = tb.arm()
    _, eta, K = model_plots.gallery_fields()[2]
    s = model_plots.field_slice(body, eta, K, dims=(0, 3), n=7)
    assert s["q"].shape == (7, 7, 7) and s["F"].shape == (7, 7, 3)
    # the slice: η's other coordinates, ν_0 along columns and ν_3 along rows
    np.testing.assert_allclose(s["q"][2, 5][[1, 2, 4, 5, 6]], eta.numpy()[[1, 2, 4, 5, 6]])
    assert s["q"][2, 5, 0] == s["x"][5] and s["q"][2, 5, 3] == s["y"][2]
    d = s["q"][2, 5] - eta.numpy()
    chi = -K.numpy() @ d * math.exp(-0.5 * d @ K.numpy() @ d)
    np.testing.assert_allclose(s["chi"][2, 5], chi, rtol=1e-12, atol=1e-15)
    for r, c in [(0, 0), (2, 5), (6, 3)]:
        J = fd_jacobian(body, s["q"][r, c])
        np.testing.assert_allclose(J @ (J.T @ s["F"][r, c] - s["chi"][r, c]), 0.0, atol=1e-6)

    fig = model_plots.field_figure(body, eta, K, title="full")
    left, right = fig.axes[:2]
    full = model_plots.field_slice(body, eta, K)
    qv = [c for c in left.collections if type(c).__name__ == "Quiver"][0]
    np.testing.assert_allclose(qv.U, full["chi"][::2, ::2, 0].ravel())
    np.testing.assert_allclose(qv.V, full["chi"][::2, ::2, 3].ravel())
    hq = [c for c in right.collections if type(c).__name__ == "Quiver"][0]
    F = full["F"][::2, ::2].reshape(-1, 3)
    Fp = np.stack([hq.U, hq.V], -1)
    # the arrows are F's coordinates along two orthonormal directions; here (rotations
    # about x only) the hand stays in the plane x = 0, so nothing is lost
    np.testing.assert_allclose(np.linalg.norm(Fp, axis=-1), np.linalg.norm(F, axis=-1), rtol=1e-9)
    plots.plt.close(fig)


def test_fields_gallery():
    fig = model_plots.fields_gallery(tb.arm())
    kinds = [K for _, _, K in model_plots.gallery_fields()]
    off = ~torch.eye(7, dtype=torch.bool)
    assert torch.allclose(kinds[0], kinds[0][0, 0] * torch.eye(7, dtype=DT))
    assert not kinds[1][off].any() and not torch.allclose(kinds[1], kinds[1][0, 0] * torch.eye(7, dtype=DT))
    assert kinds[2][0, 3] != 0 and bool((torch.linalg.eigvalsh(kinds[2]) > 0).all())
    assert len(fig.axes) == 6
    titles = [fig.axes[k].get_title() for k in (0, 2, 4)]
    assert [t.split("\n")[0] for t in titles] == [label for label, _, _ in model_plots.gallery_fields()]
    plots.plt.close(fig)


def test_profiles_figure_plots_psi_and_phi():
    fig = model_plots.profiles_figure()
    step, pulse = fig.axes[0].get_lines()[:2]
    u = step.get_xdata()
    assert u[0] == pytest.approx(-0.2) and u[-1] == pytest.approx(1.2)
    for line, f in ((step, step_profile), (pulse, pulse_profile)):
        np.testing.assert_allclose(line.get_ydata(), f(torch.tensor(u, dtype=DT)).numpy(), rtol=0, atol=0)
    # known values: ψ(0) = 0, ψ(½) = ½, ψ(1) = 1 and φ(0) = 0, φ(½) = 1, φ(1) = 0
    k = [int(np.abs(u - v).argmin()) for v in (0.0, 0.5, 1.0)]
    np.testing.assert_allclose(step.get_ydata()[k], [0.0, 0.5, 1.0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(pulse.get_ydata()[k], [0.0, 1.0, 0.0], rtol=0, atol=1e-9)
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert "sin(2" in labels[0] and "cos 2" in labels[1]
    plots.plt.close(fig)


def test_weights_bars_heights(rng):
    N, M = 3, 2
    a, b = rng.uniform(0.1, 3, size=(N, M)), rng.uniform(0.1, 3, size=(N, M))
    fig = model_plots.weights_bars(["m0", "m1", "m2"], a, b, title="w")
    ax = fig.axes[0]
    bars = [p for p in ax.patches if isinstance(p, Rectangle)]
    assert len(bars) == N * M * 2
    solid = sorted((p.get_x(), p.get_height()) for p in bars if not p.get_hatch())
    hatched = sorted((p.get_x(), p.get_height()) for p in bars if p.get_hatch())
    assert len(solid) == len(hatched) == N * M
    # bars sorted by position: motion-major, field-minor
    np.testing.assert_allclose([h for _, h in solid], a.ravel(), rtol=0, atol=0)
    np.testing.assert_allclose([h for _, h in hatched], b.ravel(), rtol=0, atol=0)
    assert [t.get_text() for t in ax.get_xticklabels()] == ["m0", "m1", "m2"]
    plots.plt.close(fig)


def test_learning_curves():
    curves = {"em": [1.0, 0.1, 1e-3], "path": [0.5, 0.4, 0.3, 0.2]}
    fig = model_plots.learning_curves(curves, title="t")
    ax = fig.axes[0]
    assert ax.get_yscale() == "log" and ax.get_ylabel() == "relative torque cost"
    lines = ax.get_lines()
    assert [line.get_label() for line in lines] == ["em", "path"]
    for line, ys in zip(lines, curves.values()):
        np.testing.assert_array_equal(line.get_xdata(), np.arange(len(ys)))
        np.testing.assert_array_equal(line.get_ydata(), ys)
    plots.plt.close(fig)


# ------------------------------------------------------------------ motion figures

ARM_NAMES = ["shoulder rotation vector x", "shoulder rotation vector y",
             "shoulder rotation vector z", "elbow angle", "wrist rotation vector x",
             "wrist rotation vector y", "wrist rotation vector z"]


@pytest.fixture(scope="module")
def motion_paths():
    """come_here as the target and a "simulated" copy off by 0.02 sin 3t in three
    coordinates, with a coordinate (wrist y) that the target holds at 0 and the copy
    only by 1e-8 noise."""
    body = tb.arm()
    (m, _), = gestures.generate(body, gestures=[gestures.GESTURES["come_here"]])
    q = m.q.clone()
    sim = q + 0.02 * torch.sin(3 * m.t)[:, None] * torch.tensor([1, 0, 0, 1, 0, 0, 1.0], dtype=DT)
    sim[:, 5] = q[:, 5] + 1e-8 * torch.randn(len(m.t), dtype=DT, generator=torch.Generator().manual_seed(0))
    return body, m.t, {"target": q, "simulated": sim}


def _span(ax) -> float:
    lo, hi = ax.get_ylim()
    return hi - lo


def test_coordinate_names_from_the_body():
    assert plots.coordinate_names(tb.arm()) == ARM_NAMES
    assert plots.coordinate_names(None, 7) == ARM_NAMES
    assert plots.coordinate_names(tb.chain(2)) == ["link0 angle", "link1 angle"]
    assert plots.coordinate_names(tb.chain(1, joint="ball")) == [
        f"link0 rotation vector {a}" for a in "xyz"]
    assert plots.coordinate_names(None, 2) == ["q[0]", "q[1]"]


def test_trajectories_axes_units_and_spans(motion_paths):
    """Every panel: t (s) and the coordinate's name with rad; no empty axis (7 panels,
    a row per joint); each y axis spans the target's range and at least MIN_SPAN, so
    the wrist y noise (1e-8) stays flat; the target is drawn dashed above the
    simulated line."""
    body, t, paths = motion_paths
    fig = plots.trajectories(t, paths, title="come_here", body=body)
    assert len(fig.axes) == 7
    q = paths["target"].numpy()
    for k, ax in enumerate(fig.axes):
        assert ax.get_xlabel() == "t (s)"
        assert ax.get_ylabel() == f"{ARM_NAMES[k]} (rad)"
        assert len(ax.get_lines()) == 2
        assert _span(ax) >= max(np.ptp(q[:, k]), plots.MIN_SPAN)
        lo, hi = ax.get_ylim()
        assert lo <= q[:, k].min() and q[:, k].max() <= hi
        target, sim = ax.get_lines()
        assert target.get_linestyle() == "--" and target.get_zorder() > sim.get_zorder()
        assert target.get_linewidth() < sim.get_linewidth()
    # the elbow (a hinge) spans its whole row, the ball joints' components share theirs
    widths = [ax.get_position().width for ax in fig.axes]
    assert widths[3] > 2.5 * widths[0]
    plots.plt.close(fig)


def test_joint_errors_span_the_targets_range(motion_paths):
    body, t, paths = motion_paths
    fig = plots.joint_errors(body, t, paths, title="errors")
    assert len(fig.axes) == 7
    q = paths["target"].numpy()
    for k, ax in enumerate(fig.axes):
        assert ax.get_xlabel() == "t (s)" and ax.get_ylabel() == f"{ARM_NAMES[k]} error (rad)"
        assert _span(ax) >= max(np.ptp(q[:, k]), plots.MIN_SPAN)
        lo, hi = ax.get_ylim()
        assert lo < 0 < hi and abs(lo + hi) < 1e-9 * (hi - lo)       # centred on 0
    plots.plt.close(fig)


def test_motion_sheet_layout_labels_and_spans(motion_paths):
    """A panel per joint and the 3-D hand path: no empty or switched-off axes; joint
    axes in s and rad with the joint's quantity, the components named in the legend;
    3-D axes in m; the target's hand path dashed and drawn above the simulated one."""
    body, t, paths = motion_paths
    fig = plots.motion_sheet(body, t, paths, title="come_here: rmse 0.0100 rad, tip 1.00 cm")
    assert len(fig.axes) == 4
    for ax in fig.axes:
        assert ax.get_visible() and ax.get_lines()
    assert all(ax.axison for ax in fig.axes[:3])            # none switched off
    q = paths["target"].numpy()
    expect = [("shoulder rotation vector (rad)", slice(0, 3), ["x", "y", "z"]),
              ("elbow angle (rad)", slice(3, 4), []),
              ("wrist rotation vector (rad)", slice(4, 7), ["x", "y", "z"])]
    for ax, (ylabel, s, comps) in zip(fig.axes[:3], expect):
        assert ax.get_xlabel() == "t (s)" and ax.get_ylabel() == ylabel
        legend = [x.get_text() for x in ax.get_legend().get_texts()]
        assert legend == comps + ["target", "simulated"]
        assert _span(ax) >= max(np.ptp(q[:, s]), plots.MIN_SPAN)
    ax3 = fig.axes[3]
    assert (ax3.get_xlabel(), ax3.get_ylabel(), ax3.get_zlabel()) == ("x (m)", "y (m)", "z (m)")
    assert not ax3.computed_zorder
    lines = {line.get_label(): line for line in ax3.get_lines()}
    target, sim = lines["target hand path"], lines["simulated hand path"]
    assert target.get_linestyle() == "--" and target.get_zorder() > sim.get_zorder()
    assert [x.get_text() for x in ax3.get_legend().get_texts()] == [
        "target hand path", "simulated hand path", "arm at start (faint) and end"]
    plots.plt.close(fig)


def test_motion_sheet_other_bodies():
    """Names come from the body: a two-hinge chain gets "link0 angle", "link1 angle"."""
    body = tb.chain(2)
    t = torch.linspace(0, 1, 21, dtype=DT)
    q = torch.stack([torch.sin(t), 0 * t], -1)
    fig = plots.motion_sheet(body, t, {"target": q}, title="chain")
    assert [ax.get_ylabel() for ax in fig.axes[:2]] == ["link0 angle (rad)", "link1 angle (rad)"]
    assert _span(fig.axes[1]) >= plots.MIN_SPAN
    assert len(fig.axes) == 3 and all(ax.get_lines() for ax in fig.axes)
    plots.plt.close(fig)
    fig = plots.trajectories(t, {"q": q})          # no body, nv ≠ 7: q[k]
    assert [ax.get_ylabel() for ax in fig.axes] == ["q[0] (rad)", "q[1] (rad)"]
    plots.plt.close(fig)


def test_hand_paths_and_strip_axes_in_metres(motion_paths):
    body, _, paths = motion_paths
    for fig in (plots.hand_paths(body, paths, title="h"), plots.stick_strip(body, paths, frames=3)):
        for ax in fig.axes:
            assert (ax.get_xlabel(), ax.get_ylabel(), ax.get_zlabel()) == ("x (m)", "y (m)", "z (m)")
        plots.plt.close(fig)


def test_field_figure_axis_names():
    fig = model_plots.field_figure(tb.arm(), *model_plots.gallery_fields()[0][1:], title="f")
    assert fig.axes[0].get_xlabel() == "shoulder rotation vector x (rad)"
    assert fig.axes[0].get_ylabel() == "elbow angle (rad)"
    plots.plt.close(fig)


def test_summarize_has_a_units_block():
    """metrics.json's keys stay as they are; their units are in "units"."""
    from tflearn import metrics
    from tflearn.fit.stability import Growth
    from tflearn.fit.targets import prepare
    (m, _), = gestures.generate(tb.arm(), gestures=[gestures.GESTURES["come_here"]])
    tg = prepare(tb.arm(), [m])
    s = metrics.Scores([0.01], [0.005], [0.02], tg.q.clone(), [None])
    growth = Growth(torch.tensor([[1.0, 2.0]]), torch.tensor([2.5]), torch.tensor([0.75]))
    doc = metrics.summarize(s, [True], tg, 3, 1.5, growth, torch.tensor([4.0]), torch.tensor([30.0]))
    assert doc["units"] == {"rmse": "rad", "tip": "m", "torque_rel_rms": "fraction of the RMS torque",
                            "wall_time_s": "s", "torque_resolution": "fraction", "growth_rate": "1/s",
                            "growth_efolds": "e-folds (natural log of an error's growth factor)",
                            "path_stiffness":
                                "rad/s (natural frequency of the fields' stiffness about the path)",
                            "numbers": "count (non-zero weights, onset and duration of each window in the "
                                       "motion, initial state)",
                            "numbers_per_s": "1/s (numbers per second of motion)"}
    rate = 30.0 / float(tg.duration[0])
    assert doc["motions"]["come_here"] == {"rmse": 0.01, "tip": 0.005, "torque_rel_rms": 0.02,
                                           "growth_rate": 2.5, "growth_efolds": 0.75, "path_stiffness": 4.0,
                                           "numbers": 30, "numbers_per_s": rate, "success": True}
    assert set(doc["overall"]) == {"rmse", "tip", "torque_rel_rms", "growth_rate", "growth_efolds",
                                   "path_stiffness", "numbers_per_s", "success", "M", "wall_time_s"}
    assert doc["overall"]["numbers_per_s"] == rate
    doc["units"]["tip"] = "cm"
    assert metrics.UNITS["tip"] == "m"         # a copy per document


def test_numbers_count_weights_windows_and_the_initial_state():
    """``numbers``: non-zero weights, two per window starting inside the motion, 2 nv."""
    from tflearn import metrics
    from tflearn.fit.targets import prepare
    from tflearn.model.weights import MotionWeights
    body = tb.arm()
    (m, _), = gestures.generate(body, gestures=[gestures.GESTURES["come_here"]])
    tg = prepare(body, [m])
    T = float(tg.duration[0])
    a, b = torch.tensor([[1.0, 0.0, 2.0]]), torch.zeros(1, 3)
    c = torch.zeros(1, 3, 4)
    c[0, 1, 0] = c[0, 2, 3] = 0.5
    onsets = torch.tensor([[0.0, T / 3, 2 * T / 3, T + 0.1]])      # the last starts after the motion
    w = MotionWeights(a, b, tg.duration, c=c, window_onset=onsets)
    assert metrics.numbers(w, tg, body.nv).tolist() == [4 + 2 * 3 + 2 * 7]


def test_figures_of_the_motions_furthest_from_their_paths(tmp_path):
    """``log.figures``: Scores.worst orders the motions by joint RMSE, a failed
    simulation first; write_figures draws only those."""
    from tflearn import metrics, train
    from tflearn.fit.targets import prepare
    programs = gestures.random_gestures(4, seed=3, ranges={"duration": (0.3, 0.4)})
    motions = [m for m, _ in gestures.generate(tb.arm(), gestures=programs)]
    tg = prepare(tb.arm(), motions)
    s = metrics.Scores([0.02, 0.5, 0.01, float("inf")], [0.0] * 4, [0.0] * 4, tg.q.clone(),
                       [None, None, None, "budget"])
    assert s.worst(2) == [3, 1] and s.worst(None) == [0, 1, 2, 3] and s.worst(0) == []
    assert s.worst(9) == [3, 1, 0, 2]
    train.write_figures(tb.arm(), tg, s, tmp_path, 2)
    assert sorted(p.name for p in (tmp_path / "figures").iterdir()) == sorted(
        f"{tg.names[j]}.png" for j in (3, 1))


# ------------------------------------------------------------------ render

@pytest.mark.slow
def test_render_writes_gif(tiny_run, tmp_path):
    """One frame per 1/fps over [0, λ]; the frames are logged to TensorBoard as images
    (tests/test_tensorboard.py reads them back) and the log line says so."""
    run, g = tiny_run["run"], tiny_run["programs"][0]
    messages = []
    out = render.render(run, g.name, out=tmp_path / "a.gif", fps=10, log=messages.append)
    assert out == tmp_path / "a.gif"
    with Image.open(out) as im:
        assert im.format == "GIF" and im.n_frames == math.floor(g.duration * 10 + 1e-9) + 1
        assert im.size[0] >= render.GIF_MIN_WIDTH >= 900 and im.size[1] >= 450
    assert len(messages) == 1
    assert list((run / "tensorboard").glob("events.*"))
    assert f"render/{g.name}/frames" in messages[0]


@pytest.mark.slow
def test_render_cli(tiny_run, capsys):
    run, g = tiny_run["run"], tiny_run["programs"][1]
    assert cli.main(["render", str(run), "--motion", g.name, "--fps", "20", "--no-tensorboard"]) == 0
    gif = run / "figures" / f"{g.name}.gif"
    assert capsys.readouterr().out.strip().splitlines()[-1] == f"wrote {gif}"
    with Image.open(gif) as im:
        assert im.n_frames == math.floor(g.duration * 20 + 1e-9) + 1
    # an unknown motion: exit 2, the message names it and the known motions, nothing written
    assert cli.main(["render", str(run), "--motion", "wave", "--out", str(run / "x.gif")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tflearn: ") and "'wave'" in err
    assert all(p.name in err for p in tiny_run["programs"])
    assert not (run / "x.gif").exists()
    with pytest.raises(InputError, match="wave"):
        render.render(run, "wave")
    with pytest.raises(ValueError):
        render.render(run, g.name, fps=0)
    with pytest.raises(SystemExit):
        cli.main(["render", str(run), "--motion", g.name, "--fps", "0"])


@pytest.mark.slow
def test_gif_frames_are_large_and_evaluation_has_units(tiny_run, tmp_path):
    """write_gif's frames: ≥ GIF_MIN_WIDTH px wide, fonts ≥ 10 pt; evaluation.json
    carries the same units block as metrics.json."""
    assert render.GIF_MIN_WIDTH >= 900 and render.GIF_FONT - 1 >= 10
    body = tb.arm()
    q = torch.zeros(11, 7, dtype=DT)
    q[:, 3] = -torch.linspace(0, 1, 11, dtype=DT)
    P = plots.joint_positions(body, q)
    t = np.linspace(0, 1, 11)
    for paths in ({"target": P}, {"target": P, "reproduced": P}):
        frames = render.write_gif(paths, t, render.frame_samples(t, 2), 2, tmp_path / "x.gif",
                                   "x: rmse 0.0000 rad, tip error 0.00 cm", keep=True)
        assert len(frames) == 3 and frames[0].shape[1] >= 900 and frames[0].shape[0] >= 450
    from tflearn import evaluate, metrics
    doc = evaluate.evaluate_run(tiny_run["run"], out=tmp_path / "evaluation.json")
    assert doc["units"] == metrics.UNITS
    assert set(doc["overall"]) == {"rmse", "tip", "numbers_per_s", "success", "M"}


def test_frame_samples():
    t = np.arange(0, 101) / 100.0            # 1 s at 100 Hz
    np.testing.assert_array_equal(render.frame_samples(t, 4), [0, 25, 50, 75, 100])
    assert len(render.frame_samples(t[:-1], 4)) == 4
