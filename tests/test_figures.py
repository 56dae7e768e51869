"""Figures (tflearn.plots: fields, profiles, weights, learning curves) and animations
(tflearn.render, ``tflearn render``)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from matplotlib.patches import Rectangle
from PIL import Image
from scipy.spatial.transform import Rotation

from tflearn import body as tb
from tflearn import cli, config, gestures, plots, render
from tflearn import motion as motion_mod
from tflearn.errors import InputError
from tflearn.fields import FieldBasis, pulse_profile, step_profile
from tflearn.io import basis as bio

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


@pytest.mark.parametrize("offsets", [None, [[0.1, 0.2, -0.3], [0.3, -0.1, 0.2], [-0.2, 0.4, 0.1]]])
def test_hand_jacobian_matches_finite_differences(offsets):
    """J is the Jacobian in velocity coordinates (child-frame angular velocities), not
    ∂p/∂ν: it matches central differences along composed rotations (measured ≤ 1e-9)
    and differs from ∂p/∂ν at a posture with ball rotations."""
    body = tb.arm(offsets=offsets)
    J = plots.hand_jacobian(body, torch.tensor(POSTURE, dtype=DT)).numpy()
    assert J.shape == (3, 7)
    np.testing.assert_allclose(J, fd_jacobian(body, POSTURE), rtol=0, atol=1e-8)
    dp_dq = torch.autograd.functional.jacobian(
        lambda q: plots.dynamics.tip_position(body, q), torch.tensor(POSTURE, dtype=DT)).numpy()
    assert np.abs(dp_dq - J).max() > 1e-2
    # batched: the same matrix for each of a stack of postures
    Jb = plots.hand_jacobian(body, torch.tensor(np.stack([POSTURE, 0.5 * POSTURE]), dtype=DT))
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
    F = plots.hand_force(body, q, torch.tensor(tau, dtype=DT)).numpy()
    np.testing.assert_allclose(F, F0, rtol=0, atol=1e-7)
    np.testing.assert_allclose(J.T @ F, tau, rtol=0, atol=1e-7)
    _, eta, K = plots.gallery_fields()[2]
    chi = FieldBasis(eta[None], K[None], kind="full")(q)[0].detach()
    assert float(chi.norm()) > 0.1
    F = plots.hand_force(body, q, chi).numpy()
    np.testing.assert_allclose(J @ (J.T @ F - chi.numpy()), 0.0, rtol=0, atol=1e-7)


# ------------------------------------------------------------------ field figures

def test_field_figure_draws_the_field_and_its_hand_forces():
    """field_figure's arrows: (χ_i, χ_j) of the field at the slice postures (left) and
    the least-squares hand forces of those torques, projected onto the plane of the hand
    positions (right): their torques satisfy the normal equations J(JᵀF − χ) = 0."""
    body = tb.arm()
    _, eta, K = plots.gallery_fields()[2]
    s = plots.field_slice(body, eta, K, dims=(0, 3), n=7)
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

    fig = plots.field_figure(body, eta, K, title="full")
    left, right = fig.axes[:2]
    full = plots.field_slice(body, eta, K)
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
    fig = plots.fields_gallery(tb.arm())
    kinds = [K for _, _, K in plots.gallery_fields()]
    off = ~torch.eye(7, dtype=torch.bool)
    assert torch.allclose(kinds[0], kinds[0][0, 0] * torch.eye(7, dtype=DT))
    assert not kinds[1][off].any() and not torch.allclose(kinds[1], kinds[1][0, 0] * torch.eye(7, dtype=DT))
    assert kinds[2][0, 3] != 0 and bool((torch.linalg.eigvalsh(kinds[2]) > 0).all())
    assert len(fig.axes) == 6
    titles = [fig.axes[k].get_title() for k in (0, 2, 4)]
    assert [t.split("\n")[0] for t in titles] == [label for label, _, _ in plots.gallery_fields()]
    plots.plt.close(fig)


def test_profiles_figure_plots_psi_and_phi():
    fig = plots.profiles_figure()
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
    fig = plots.weights_bars(["m0", "m1", "m2"], a, b, title="w")
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
    fig = plots.learning_curves(curves, title="t")
    ax = fig.axes[0]
    assert ax.get_yscale() == "log" and ax.get_ylabel() == "relative torque cost"
    lines = ax.get_lines()
    assert [line.get_label() for line in lines] == ["em", "path"]
    for line, ys in zip(lines, curves.values()):
        np.testing.assert_array_equal(line.get_xdata(), np.arange(len(ys)))
        np.testing.assert_array_equal(line.get_ydata(), ys)
    plots.plt.close(fig)


# ------------------------------------------------------------------ render

@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A run folder without training: two short random programs (0.3–0.4 s at 100 Hz)
    saved as the data, their generating fields and weights as basis.json, and a
    config.yaml pointing at the data."""
    base = tmp_path_factory.mktemp("tiny_run")
    data, run = base / "data", base / "run"
    data.mkdir()
    run.mkdir()
    programs = gestures.random_gestures(2, seed=3, ranges={"duration": (0.3, 0.4)})
    for m, _ in gestures.generate(gestures=programs):
        motion_mod.save(m, data / f"{m.name}.npz")
    basis, weights, _ = gestures.library_model(programs)
    z = torch.zeros(2, 7, dtype=DT)
    bio.save(bio.LearnedBasis(tb.arm(), basis, weights, z, z, torch.full((2,), 100.0, dtype=DT)),
             run / "basis.json")
    config.dump(config.load(None, [f"data={data}", f"out={run}"]), run / "config.yaml")
    return {"run": run, "programs": programs}


def test_render_writes_gif(tiny_run, tmp_path):
    """One frame per 1/fps over [0, λ]; the frames are logged to TensorBoard as images
    (tests/test_tensorboard.py reads them back) and the log line says so."""
    run, g = tiny_run["run"], tiny_run["programs"][0]
    messages = []
    out = render.render(run, g.name, out=tmp_path / "a.gif", fps=10, log=messages.append)
    assert out == tmp_path / "a.gif"
    with Image.open(out) as im:
        assert im.format == "GIF" and im.n_frames == math.floor(g.duration * 10 + 1e-9) + 1
    assert len(messages) == 1
    assert list((run / "tensorboard").glob("events.*"))
    assert f"render/{g.name}/frames" in messages[0]


def test_render_cli(tiny_run, capsys):
    run, g = tiny_run["run"], tiny_run["programs"][1]
    assert cli.main(["render", str(run), "--motion", g.name, "--fps", "20", "--no-tensorboard"]) == 0
    gif = run / "figures" / f"{g.name}.gif"
    assert capsys.readouterr().out.strip() == str(gif)
    with Image.open(gif) as im:
        assert im.n_frames == math.floor(g.duration * 20 + 1e-9) + 1
    # an unknown motion: exit 2, the message names it and the known motions, nothing written
    assert cli.main(["render", str(run), "--motion", "wave", "--out", str(run / "x.gif")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tflearn render: error:") and "'wave'" in err
    assert all(p.name in err for p in tiny_run["programs"])
    assert not (run / "x.gif").exists()
    with pytest.raises(InputError, match="wave"):
        render.render(run, "wave")
    with pytest.raises(ValueError):
        render.render(run, g.name, fps=0)
    with pytest.raises(SystemExit):
        cli.main(["render", str(run), "--motion", g.name, "--fps", "0"])


def test_frame_samples():
    t = np.arange(0, 101) / 100.0            # 1 s at 100 Hz
    np.testing.assert_array_equal(render.frame_samples(t, 4), [0, 25, 50, 75, 100])
    assert len(render.frame_samples(t[:-1], 4)) == 4
