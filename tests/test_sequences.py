"""Activation sequences: P sub-movement windows per motion, a pulse weight c_jik ≥ 0 of
every field on each (tflearn.model.weights.MotionWeights).

The activation against its formula, non-negative and C¹; P = 0 is the thesis' model
exactly; a motion driven by one field switched on twice is fitted by its own windows to
the spline's error, and far worse without them; the windows placed from the data cut a
go-and-return at its stop; the model algebra, the model state, the basis file and the
candidate search all carry the windows.
"""
from __future__ import annotations

import json
import math

import pytest
import torch

from tflearn.data import gestures
from tflearn.fit import search, targets, torque
from tflearn.io import basis as bio
from tflearn.model.fields import FieldBasis
from tflearn.model.program import FieldProgram, model_from_state, model_state
from tflearn.model.weights import MotionWeights, pulse_profile, step_profile
from tflearn.motions.motion import Motion
from tflearn.simulation.simulate import SimOptions, simulate

DT = torch.float64


def _weights(P=2, M=3, N=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=DT)
    return MotionWeights(r(N, M), r(N, M), torch.tensor([2.0, 3.0], dtype=DT)[:N],
                         step_onset=0.3 * r(N, M), step_duration=1 + r(N, M),
                         pulse_onset=0.2 * r(N, M), pulse_duration=1 + r(N, M),
                         c=r(N, M, P), window_onset=r(N, P) * 1.5 - 0.2, window_duration=0.5 + r(N, P))


def test_activation_equals_its_formula_and_is_non_negative():
    w = _weights().requires_grad_(False)
    t = torch.linspace(-0.5, 3.5, 81, dtype=DT)
    act = w.activation(t)                                       # T×N×M
    assert act.shape == (81, 2, 3)
    for k, tk in enumerate(t.tolist()):
        for j in range(2):
            for i in range(3):
                want = (w.a[j, i] * step_profile((tk - w.step_onset[j, i]) / w.step_duration[j, i])
                        + w.b[j, i] * pulse_profile((tk - w.pulse_onset[j, i]) / w.pulse_duration[j, i])
                        + sum(w.c[j, i, p] * pulse_profile((tk - w.window_onset[j, p])
                                                           / w.window_duration[j, p]) for p in range(2)))
                assert abs(float(act[k, j, i] - want)) <= 1e-14
    assert bool((act >= 0).all())
    # the scalar-time form is the same
    one = torch.tensor(1.3, dtype=DT)
    assert torch.allclose(w.activation(one), w.activation(one[None])[0])


def test_activation_is_c1():
    """Second differences are O(h²) everywhere (a kink would make them O(h)): halving h
    divides the largest by about 4 (measured ratio printed), not 2."""
    w = _weights(seed=3)
    peaks = []
    for h in (1e-3, 5e-4):
        t = torch.arange(-0.5, 3.5, h, dtype=DT)
        a = w.activation(t)
        peaks.append(float((a[2:] - 2 * a[1:-1] + a[:-2]).abs().max()))
    print(f"second-difference ratio {peaks[0] / peaks[1]:.2f}")
    assert peaks[0] / peaks[1] > 3.5


def test_no_windows_is_the_thesis_model():
    w = _weights(P=0)
    t = torch.linspace(0, 3, 31, dtype=DT)
    psi, phi = w.profiles(t)
    assert torch.equal(w.activation(t), w.a * psi + w.b * phi)
    assert w.P == 0 and w.vector().shape == (2, 6)


def test_algebra_and_state_keep_the_windows():
    w = _weights()
    s = w.select_fields([2, 0])
    assert torch.equal(s.c, w.c[:, [2, 0]]) and torch.equal(s.window_onset, w.window_onset)
    e = w.extend_fields(2)
    assert e.c.shape == (2, 5, 2) and bool((e.c[:, 3:] == 0).all())
    assert torch.equal(e.window_duration, w.window_duration)
    m = w.select_motions([1])
    assert torch.equal(m.c[0], w.c[1]) and torch.equal(m.window_onset[0], w.window_onset[1])
    assert torch.equal(w.timing(1)["window_onset"], w.window_onset[1])
    basis = FieldBasis(torch.zeros(3, 4, dtype=DT), torch.eye(4, dtype=DT).expand(3, 4, 4))
    b2, w2 = model_from_state(model_state(basis, w))
    assert torch.equal(w2.c, w.c) and torch.equal(w2.window_duration, w.window_duration)
    old = model_state(basis, _weights(P=0))
    for key in ("c_raw", "window_onset", "window_duration"):
        del old["weights"][key]                             # a checkpoint from before windows
    assert model_from_state(old)[1].P == 0
    x = w.vector()
    w3 = _weights(seed=9)
    w3.set_vector(x)
    assert torch.equal(w3.vector(), x)


def test_bad_window_shapes_refused():
    z = torch.zeros(2, 3, dtype=DT)
    with pytest.raises(ValueError, match="N×P"):
        MotionWeights(z, z, torch.ones(2, dtype=DT), c=torch.zeros(2, 3, 2, dtype=DT),
                      window_onset=torch.zeros(2, 1, dtype=DT))


# ------------------------------------------------------------- a field switched on twice

@pytest.fixture(scope="module")
def twice():
    """come_here's field (k = 1) switched on over [0, 1.4] s and again over [1.6, 3] s
    (a = b = 0, c = 3 and 2), from rest at 100 Hz, 3 s."""
    (m, lb), = gestures.generate(gestures=[gestures.GESTURES["come_here"]])
    z = torch.zeros(1, 1, dtype=DT)
    weights = MotionWeights(z, z, torch.tensor([3.0], dtype=DT), c=torch.tensor([[[3.0, 2.0]]], dtype=DT),
                            window_onset=torch.tensor([[0.0, 1.6]], dtype=DT),
                            window_duration=torch.tensor([[1.4, 1.4]], dtype=DT))
    with torch.no_grad():
        tr = simulate(lb.body, FieldProgram(lb.basis, weights), lb.q0, lb.qd0, m.t,
                      SimOptions(method="dopri8", rtol=1e-10, atol=1e-10,
                                 solver_options={"step_t": m.t[1:]}))
    motion = Motion("twice", m.t, tr.q[0], tr.v[0])
    return lb, weights, targets.prepare(lb.body, [motion])


def test_windows_fit_a_field_used_twice(twice):
    """With its generating windows the NNLS weights are c = (3, 2) to 1e-4 at the spline's
    own error (cost ≤ 1e-8); the thesis' step and pulse alone leave a cost above 1e-2."""
    lb, gen, tg = twice
    w = MotionWeights.zeros(1, tg.duration, tg.names, (gen.window_onset, gen.window_duration))
    cost = float(torque.solve_weights(lb.basis, w, tg)[0])
    assert cost <= 1e-8
    assert torch.allclose(w.c.detach(), gen.c, atol=1e-4)
    plain = float(torque.solve_weights(lb.basis, MotionWeights.zeros(1, tg.duration, tg.names), tg)[0])
    assert plain > 1e-2


def test_candidate_scores_carry_the_windows(twice):
    """score_candidates' cost of a candidate equals solve_weights' on a basis holding it,
    windows included (to 1e-10)."""
    lb, gen, tg = twice
    windows = (gen.window_onset, gen.window_duration)
    empty = FieldBasis.empty(7, "scalar", [3, 1, 3])
    w0 = MotionWeights.zeros(0, tg.duration, tg.names, windows)
    centres = torch.stack([lb.basis.eta.detach()[0], lb.basis.eta.detach()[0] + 0.3])
    scores = search.score_candidates(empty, w0, tg, centres, [1.0])
    for c in range(2):
        one = empty.extend(centres[c:c + 1], torch.eye(7, dtype=DT)[None])
        want = float(torque.solve_weights(one, MotionWeights.zeros(1, tg.duration, tg.names, windows), tg)[0])
        assert abs(float(scores[c, 0]) - want) <= 1e-10
    # and with a field already in the basis (the shared block of the normal equations)
    first = empty.extend(centres[1:], 2 * torch.eye(7, dtype=DT)[None])
    w1 = MotionWeights.zeros(1, tg.duration, tg.names, windows)
    torque.solve_weights(first, w1, tg)
    both = float(search.score_candidates(first, w1, tg, centres[:1], [1.0])[0, 0])
    two = first.extend(centres[:1], torch.eye(7, dtype=DT)[None])
    want = float(torque.solve_weights(two, MotionWeights.zeros(2, tg.duration, tg.names, windows), tg)[0])
    assert abs(both - want) <= 1e-10


def test_windows_from_the_data_cut_at_the_stop():
    """A reach out and back (minimum-jerk, stopping at 1.5 s) is cut at its stop within one
    sample; the windows' pulses leave no gap (their sum > 0 inside the motion)."""
    t = torch.linspace(0, 3, 301, dtype=DT)
    u = torch.where(t < 1.5, t / 1.5, (3 - t) / 1.5)
    s = 10 * u ** 3 - 15 * u ** 4 + 6 * u ** 5
    q = s[:, None] * torch.tensor([0.8, -0.3, 0.2, -1.0, 0.1, 0.0, 0.0], dtype=DT)
    v = torch.gradient(q, spacing=(t,), dim=0)[0]
    tg = targets.Targets(names=["out_and_back"], t=t[None], mask=torch.ones(1, 301, dtype=torch.bool),
                         w=torch.ones(1, 301, dtype=DT), wt=torch.ones(1, 301, dtype=DT), q=q[None],
                         v=v[None], tau=torch.zeros(1, 301, 7, dtype=DT),
                         duration=torch.tensor([3.0], dtype=DT), q0=q[:1], qd0=v[:1],
                         grid=t, index=torch.arange(301)[None])
    onset, length = targets.submovement_windows(tg, 2, spread=0.25)
    cut = float(onset[0, 1] + 0.25 * (length[0, 1] / 1.5))
    assert abs(cut - 1.5) <= 0.01 + 1e-9
    w = MotionWeights.zeros(1, tg.duration, tg.names, (onset, length))
    inside = w.windows(t[1:-1]).sum(-1)
    assert bool((inside > 0).all())
    # more windows than stops: the longest pieces are halved
    onset, length = targets.submovement_windows(tg, 4, spread=0.0)
    assert torch.allclose(onset[0], torch.tensor([0.0, 0.75, 1.5, 2.25], dtype=DT), atol=0.011)


# ------------------------------------------------------------------------- basis file

def test_basis_file_round_trips_windows(twice, tmp_path):
    lb, gen, _ = twice
    src = bio.LearnedBasis(lb.body, lb.basis, gen, lb.q0, lb.qd0, lb.rate)
    bio.save(src, tmp_path / "basis.json")
    back = bio.load(tmp_path / "basis.json")
    assert torch.equal(back.weights.c, gen.c) and torch.equal(back.weights.window_onset, gen.window_onset)
    doc = json.loads((tmp_path / "basis.json").read_text())
    assert doc["motions"][0]["c"] == [[3.0, 2.0]]
    bad = json.loads(json.dumps(doc))
    bad["motions"][0]["c"] = [[3.0, -1.0]]
    with pytest.raises(bio.BasisFileError, match="non-negative"):
        bio.from_dict(bad)
    two = json.loads(json.dumps(doc))
    two["motions"].append(dict(two["motions"][0], name="other", window_onset=[0.0],
                               window_duration=[3.0], c=[[1.0]]))
    with pytest.raises(bio.BasisFileError, match="same number of windows"):
        bio.from_dict(two)
    del bad["motions"][0]["window_onset"]
    with pytest.raises(bio.BasisFileError, match="window_onset"):
        bio.from_dict(bad)
    assert math.isclose(float(back.weights.window_duration[0, 1]), 1.4)
