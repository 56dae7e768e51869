"""tflearn.fit.identity: generating fields matched to learned ones along the directions
their motions excite (centre distance, stiffness ratio), and metrics.json's block."""
from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from tflearn import config, train
from tflearn.data import gestures
from tflearn.data.loading import generating_bases
from tflearn.fit import identity, targets
from tflearn.io import basis as basis_io
from tflearn.log import identity_line
from tflearn.model.fields import FieldBasis, field_torques
from tflearn.physics.body import arm

from conftest import DT

ROOT = Path(__file__).resolve().parents[1]


def test_centre_jacobian_is_the_derivative_of_the_field():
    """J = g (K − K d dᵀK) equals autograd's ∂χ/∂η at random postures, and the excitation
    E_η summed in closed form equals Σ weight JᵀJ."""
    g = torch.Generator().manual_seed(0)
    n = 7
    A = torch.randn(n, n, generator=g, dtype=DT)
    K = A @ A.T / n + 0.5 * torch.eye(n, dtype=DT)
    eta = torch.randn(n, generator=g, dtype=DT) * 0.5
    q = torch.randn(6, n, generator=g, dtype=DT) * 0.7
    J = identity.centre_jacobian(q, eta, K)
    for qs, Js in zip(q, J):
        ref = torch.autograd.functional.jacobian(
            lambda e, qs=qs: field_torques(qs, None, e[None], K[None])[0], eta)
        assert torch.allclose(Js, ref, rtol=0, atol=1e-13)
    w = torch.rand(len(q), generator=g, dtype=DT)
    E_eta, E_K = identity.excitation(q, w, eta, K)
    assert torch.allclose(E_eta, torch.einsum("s,sij,sik->jk", w, J, J), rtol=1e-12, atol=1e-14)
    d = q - eta
    g2 = torch.exp(-torch.einsum("si,ij,sj->s", d, K, d))
    assert torch.allclose(E_K, torch.einsum("s,si,sj->ij", w * g2, d, d), rtol=1e-12, atol=1e-14)


def _planar_problem():
    """A field over n = 4 coordinates, in a frame R (a seeded rotation): its motion moves
    in the plane of e₀, e₁ only (an ellipse around the origin), its centre in that plane,
    K = diag(2, 1.5, 10⁻⁴, 2.5) — soft along e₂, stiff along e₃."""
    n, T = 4, 200
    R, _ = torch.linalg.qr(torch.randn(n, n, generator=torch.Generator().manual_seed(1), dtype=DT))
    s = torch.linspace(0, 2 * math.pi, T, dtype=DT)
    local = torch.stack([0.8 * torch.cos(s), 0.5 * torch.sin(s), 0 * s, 0 * s], -1)
    K_local = torch.diag(torch.tensor([2.0, 1.5, 1e-4, 2.5], dtype=DT))
    eta = R @ torch.tensor([0.3, -0.2, 0.0, 0.0], dtype=DT)
    return {"R": R, "q": local @ R.T, "eta": eta, "K": R @ K_local @ R.T, "K_local": K_local,
            "e": R.T, "T": T}


def _match(p, eta_l, K_l):
    """match_fields for the planar problem's one motion and one generating field."""
    T = p["T"]
    h = torch.full((1, T), 1 / T, dtype=DT)
    return identity.match_fields(p["eta"][None], p["K"][None], torch.zeros(1, 1, dtype=torch.long),
                                 torch.ones(1, T, 1, dtype=DT), p["q"][None], h,
                                 torch.stack(eta_l), torch.stack(K_l))


def test_a_copy_moved_where_the_motion_does_not_look_is_the_same_field():
    """Moved 1 rad along e₂ (soft, never visited) the copy's torque along the path is the
    generating field's to 10⁻³ and its centre distance ≈ 0 while the Euclidean one is 1;
    moved 0.3 rad along e₀ (visited) or e₃ (never visited, but stiff: the field pulls
    along it, so a shifted centre shows in the torque) it is 0.3 rad away and fails."""
    p = _planar_problem()
    e, K = p["e"], p["K"]
    soft, along, stiff = p["eta"] + 1.0 * e[2], p["eta"] + 0.3 * e[0], p["eta"] + 0.3 * e[3]
    chi = field_torques(p["q"], None, p["eta"][None], K[None])[:, 0]
    scale = chi.norm(dim=-1).max()
    for eta_l, far in ((soft, False), (along, True), (stiff, True)):
        diff = (field_torques(p["q"], None, eta_l[None], K[None])[:, 0] - chi).norm(dim=-1).max()
        assert (diff > 0.1 * scale) == far and (diff < 1e-3 * scale) == (not far)
    m, = _match(p, [along, soft], [K, K])
    assert (m.learned, m.centre_dim, m.stiffness_dim, m.matched) == (1, 3, 2, True)
    assert m.centre_distance < 1e-9 and abs(m.euclidean - 1.0) < 1e-12
    assert abs(m.stiffness_ratio - 1) < 1e-12
    for eta_l in (along, stiff):
        m, = _match(p, [eta_l], [K])
        assert abs(m.centre_distance - 0.3) < 1e-9 and not m.matched


def test_stiffness_ratio_along_the_excited_directions():
    """1.5 K along the plane the motion moves in gives r = 1.5 (fails); any stiffness
    along e₂, e₃ (never displaced along) gives r = 1; ×1.1 and ×0.7 along the plane's two
    axes gives the worst, 0.7 — a ratio of traces would have said 0.93."""
    p = _planar_problem()
    R, KL = p["R"], p["K_local"]
    plane = torch.diag(torch.tensor([1.0, 1.0, 0.0, 0.0], dtype=DT))
    cases = {1.5: KL + 0.5 * plane @ KL @ plane,
             1.0: torch.diag(torch.tensor([2.0, 1.5, 5e-3, 25.0], dtype=DT)),
             0.7: torch.diag(torch.tensor([2.2, 1.05, 1e-4, 2.5], dtype=DT))}
    for ratio, K_local in cases.items():
        m, = _match(p, [p["eta"]], [R @ K_local @ R.T])
        assert abs(m.stiffness_ratio - ratio) < 1e-10 and m.centre_distance < 1e-12
        assert m.matched == (ratio == 1.0)


@pytest.fixture(scope="module")
def gesture_targets():
    """The gestures (100 Hz) as targets, and their generating programs by name."""
    pairs = gestures.generate()
    tg = targets.prepare(arm(), [m for m, _ in pairs])
    return tg, {lb.names[0]: lb for _, lb in pairs}


def test_the_generating_basis_matches_itself(gesture_targets):
    """A learned basis holding the gestures' 7 generating fields (in reverse order)
    matches each to its own copy, d = 0 and r = 1, no two to the same learned field;
    without planar_line's pulse field, that field's match is another one, short of the
    bar."""
    tg, generating = gesture_targets
    eta = torch.cat([generating[n].basis.eta.detach() for n in tg.names])
    K = torch.cat([generating[n].basis.K().detach() for n in tg.names])
    own = [f"{n}/{i}" for n in tg.names for i in range(generating[n].basis.M)]
    block = identity.identify(generating, FieldBasis(eta.flip(0), K.flip(0), kind="full"), tg)
    assert (block["G"], block["M"], block["matched"]) == (7, 7, 7)
    assert [f["field"] for f in block["fields"]] == own
    assert [f["learned"] for f in block["fields"]] == list(range(6, -1, -1))
    for f in block["fields"]:
        assert f["centre_distance_rad"] < 1e-12 and abs(f["stiffness_ratio"] - 1) < 1e-12
        assert f["users"] == [f["field"].split("/")[0]]
        assert f["centre_dim"] == 7 and 1 <= f["stiffness_dim"] < 7     # K = k·I: J full rank
    pulse = own.index("planar_line/1")
    keep = [i for i in range(7) if i != pulse]
    block = identity.identify(generating, FieldBasis(eta[keep], K[keep], kind="full"), tg)
    assert block["matched"] == 6
    missing = block["fields"][pulse]
    assert not missing["matched"] and missing["centre_distance_rad"] > 0.1
    assert identity_line(block) == (f"generating fields matched: 6/7 (centre ≤ 0.0000 rad, stiffness within "
                                    f"0.00%); not: planar_line/1 (nearest field {missing['learned']}: "
                                    f"{missing['centre_distance_rad']:.3f} rad, stiffness "
                                    f"×{missing['stiffness_ratio']:.2f})")


def test_shared_generating_fields_are_one(tmp_path):
    """Programs drawing on a library of shared fields, written as NAME.json and read back
    (K through a Cholesky factor): the fields the programs share are one, G as the
    benchmark counts it."""
    programs = gestures.random_gestures(8, seed=1, library=3)
    for lb in gestures.generating_bases(programs):
        basis_io.save(lb, tmp_path / f"{lb.names[0]}.json")
    names = [p.name for p in programs]
    generating = generating_bases(tmp_path, arm(), names)
    assert list(generating) == names
    eta = torch.cat([generating[n].basis.eta.detach() for n in names])
    K = torch.cat([generating[n].basis.K().detach() for n in names])
    _, _, index = identity.shared_fields(eta, K)
    drawn = [(e, k) for p in programs for e, k in zip(p.eta, p.k)]
    first = {}
    assert index.tolist() == [first.setdefault(f, len(first)) for f in drawn]
    assert len(first) == len(set(drawn)) == 3


@pytest.mark.slow
def test_main_job_reports_its_generating_fields(tmp_path):
    """``train configs/gestures.yaml`` (~30 s): metrics.json's identity block holds the 7
    generating fields for M = 6 learned. Every field but planar_line's two matches within
    the bar, each to a learned field of its own (measured: centre ≤ 0.0003 rad, stiffness
    within 0.04%). The planar line is learned on one field of its own, which stands for
    both its step and its pulse field: the block matches both to it, neither within the
    bar (measured: the step field's centre 0.47 rad away, stiffness ×0.69; the pulse
    field's 1.82 rad, ×1.08)."""
    cfg = config.load(ROOT / "configs" / "gestures.yaml",
                      [f"out={tmp_path / 'run'}", "log.progress=false", "log.tensorboard=false"])
    train.run(cfg)
    block = json.loads((tmp_path / "run" / "metrics.json").read_text())["identity"]
    doc = json.loads((tmp_path / "run" / "basis.json").read_text())
    fields = {f["field"]: f for f in block["fields"]}
    assert (block["G"], block["M"], block["matched"]) == (7, 6, 5)
    assert list(fields) == ["come_here/0", "stiff_elbow_lift/0", "tuck/0", "planar_line/0", "planar_line/1",
                            "backwards_reach/0", "backwards_reach/1"]
    alone = [f for name, f in fields.items() if not name.startswith("planar_line")]
    assert all(f["matched"] for f in alone) and len({f["learned"] for f in alone}) == 5
    assert max(f["centre_distance_rad"] for f in alone) < 0.01
    assert max(abs(f["stiffness_ratio"] - 1) for f in alone) < 0.01
    line, = [m for m in doc["motions"] if m["name"] == "planar_line"]
    own = max(range(block["M"]), key=lambda i: line["a"][i] + line["b"][i])
    step, pulse = fields["planar_line/0"], fields["planar_line/1"]
    assert step["learned"] == pulse["learned"] == own and own not in {f["learned"] for f in alone}
    assert not step["matched"] and not pulse["matched"]
    assert 0.1 < step["centre_distance_rad"] < pulse["centre_distance_rad"]
