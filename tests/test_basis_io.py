"""tflearn.io.basis: the basis.json format — exact round trips and refusals of malformed
documents (every error is a BasisFileError naming the file)."""
from __future__ import annotations

import copy
import json

import numpy as np
import pytest
import torch

from tflearn import body as tb
from tflearn.fields import FieldBasis, MotionWeights
from tflearn.io import basis as bio
from tflearn.io.basis import BasisFileError

DT = torch.float64
M, N, NV = 3, 2, 7


def random_spd(gen, n):
    A = torch.randn(n, n, generator=gen, dtype=DT)
    return A @ A.T / n + 0.3 * torch.eye(n, dtype=DT)


def make_lb(kind="full", seed=0) -> bio.LearnedBasis:
    gen = torch.Generator().manual_seed(seed)
    body = tb.arm(gravity=[0.0, 0.0, -9.81], damping=0.25,
                  offsets=[[0.1, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, -0.3]],
                  masses=[2.5, 1.1, 0.4])
    eta = torch.randn(M, NV, generator=gen, dtype=DT)
    K = torch.stack([random_spd(gen, NV) for _ in range(M)])

    def r(lo, hi):
        return lo + (hi - lo) * torch.rand(N, M, generator=gen, dtype=DT)
    a, b = r(0.0, 3.0), r(0.0, 2.0)
    a[0, 1] = 0.0                               # exact zeros survive
    weights = MotionWeights(a, b, torch.tensor([2.5, 3.25], dtype=DT),
                            r(-0.2, 0.5), r(0.5, 3.0), r(0.0, 1.0), r(0.3, 2.0),
                            names=["first", "second motion"])
    basis = FieldBasis(eta, K, kind=kind, blocks=body.blocks)
    q0 = torch.randn(N, NV, generator=gen, dtype=DT)
    qd0 = torch.randn(N, NV, generator=gen, dtype=DT)
    return bio.LearnedBasis(body, basis, weights, q0, qd0, torch.tensor([100.0, 60.0], dtype=DT))


def max_diff(x, y) -> float:
    return float((torch.as_tensor(x) - torch.as_tensor(y)).detach().abs().max())


@pytest.mark.parametrize("kind", ["full", "diag", "scalar", "block"])
def test_round_trip(tmp_path, kind):
    lb = make_lb(kind)
    path = tmp_path / "basis.json"
    bio.save(lb, path)
    back = bio.load(path)                      # loaded as "full": any K is representable
    assert back.names == ["first", "second motion"]
    assert back.basis.M == M and back.basis.n == NV
    assert max_diff(back.basis.eta, lb.basis.eta) == 0.0
    K0 = lb.basis.K().detach()
    # K goes through a Cholesky factorisation on load (K = L Lᵀ, L stored as parameters)
    assert max_diff(back.basis.K(), K0) <= 1e-15 * max(1.0, float(K0.abs().max()))
    w0, w1 = lb.weights, back.weights
    for name in ("a", "b", "step_onset", "step_duration", "pulse_onset", "pulse_duration",
                 "duration"):
        assert max_diff(getattr(w1, name), getattr(w0, name)) == 0.0, name
    assert float(w1.a[0, 1].detach()) == 0.0
    assert max_diff(back.q0, lb.q0) == 0.0 and max_diff(back.qd0, lb.qd0) == 0.0
    assert max_diff(back.rate, lb.rate) == 0.0
    assert back.body == lb.body                # lengths, masses, radii, gravity, damping, offsets
    assert back.index("second motion") == 1
    with pytest.raises(KeyError, match="third"):
        back.index("third")
    # the same document again
    bio.save(back, tmp_path / "again.json")
    d0, d1 = json.loads(path.read_text()), json.loads((tmp_path / "again.json").read_text())
    assert d1["format"] == "tflearn-basis/1" and d0["motions"] == d1["motions"]
    assert np.abs(np.array([f["K"] for f in d1["fields"]])
                  - np.array([f["K"] for f in d0["fields"]])).max() <= 1e-15 * 10


def test_load_with_other_kind(tmp_path):
    """A diag basis saved and loaded as diag keeps its K to rounding."""
    lb = make_lb("diag")
    bio.save(lb, tmp_path / "b.json")
    back = bio.load(tmp_path / "b.json", kind="diag")
    assert back.basis.stiffness.kind == "diag"
    K0 = lb.basis.K().detach()
    assert max_diff(back.basis.K(), K0) <= 1e-15 * float(K0.abs().max())


def test_document_is_plain_json(tmp_path):
    lb = make_lb()
    bio.save(lb, tmp_path / "b.json")
    doc = json.loads((tmp_path / "b.json").read_text())
    assert set(doc) == {"format", "body", "fields", "motions"}
    assert set(doc["body"]) >= {"lengths", "masses", "radii", "gravity", "damping"}
    assert len(doc["fields"]) == M and np.array(doc["fields"][0]["K"]).shape == (NV, NV)
    m = doc["motions"][1]
    assert set(m) == {"name", "duration", "rate", "q0", "qd0", "a", "b", "step_onset",
                      "step_duration", "pulse_onset", "pulse_duration"}
    assert m["rate"] == 60.0 and m["duration"] == 3.25 and len(m["a"]) == M


# ------------------------------------------------------------------- malformed documents

def _doc():
    return bio.to_dict(make_lb())


def _set(path, value):
    def edit(doc):
        node = doc
        for k in path[:-1]:
            node = node[k]
        node[path[-1]] = value
    return edit


def _delete(path):
    def edit(doc):
        node = doc
        for k in path[:-1]:
            node = node[k]
        del node[path[-1]]
    return edit


def _non_pd(doc):
    K = np.array(doc["fields"][1]["K"])
    w, V = np.linalg.eigh(K)
    w[0] = -0.1
    doc["fields"][1]["K"] = (V * w @ V.T).tolist()


def _semi_definite(doc):
    K = np.array(doc["fields"][0]["K"])
    w, V = np.linalg.eigh(K)
    w[0] = 0.0
    doc["fields"][0]["K"] = (V * w @ V.T).tolist()


BAD = {
    "format tag": (_set(["format"], "tflearn-basis/2"), "tflearn-basis/1"),
    "no format": (_delete(["format"]), "tflearn-basis/1"),
    "missing body": (_delete(["body"]), "body"),
    "missing fields": (_delete(["fields"]), "fields"),
    "missing motions": (_delete(["motions"]), "motions"),
    "body lengths": (_set(["body", "lengths"], [0.3, 0.2]), "body"),
    "body masses missing": (_delete(["body", "masses"]), "body"),
    "body negative mass": (_set(["body", "masses"], [1.0, -1.0, 1.0]), "body"),
    "eta length": (_set(["fields", 0, "eta"], [0.0] * 6), "fields"),
    "eta missing": (_delete(["fields", 2, "eta"]), "fields"),
    "K shape": (_set(["fields", 1, "K"], np.eye(6).tolist()), "fields"),
    "K ragged": (_set(["fields", 1, "K"], [[1.0] * 7] * 6 + [[1.0]]), "fields"),
    "K not PD": (_non_pd, "positive definite"),
    "K strings": (_set(["fields", 0, "K"], "identity"), "fields"),
    "a length": (_set(["motions", 0, "a"], [1.0] * (M + 1)), "motions"),
    "a missing": (_delete(["motions", 1, "a"]), "motions"),
    "b missing": (_delete(["motions", 0, "b"]), "motions"),
    "onsets missing": (_delete(["motions", 0, "pulse_onset"]), "motions"),
    "q0 length": (_set(["motions", 0, "q0"], [0.0] * 6), "motions"),
    "qd0 missing": (_delete(["motions", 1, "qd0"]), "motions"),
    "rate missing": (_delete(["motions", 0, "rate"]), "motions"),
    "duration text": (_set(["motions", 0, "duration"], "long"), "motions"),
    "negative a": (_set(["motions", 1, "a"], [1.0, -0.5, 0.0]), "non-negative"),
    "negative b": (_set(["motions", 0, "b"], [-1e-3, 0.5, 0.0]), "non-negative"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_malformed_document(tmp_path, case):
    edit, words = BAD[case]
    doc = copy.deepcopy(_doc())
    edit(doc)
    path = tmp_path / f"{case.replace(' ', '_')}.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(BasisFileError) as err:
        bio.load(path)
    msg = str(err.value)
    assert str(path) in msg and words in msg


@pytest.mark.parametrize("text", ["{not json", "", "[1, 2, 3]", "\"tflearn-basis/1\"", "null"])
def test_not_a_basis_document(tmp_path, text):
    path = tmp_path / "bad.json"
    path.write_text(text)
    with pytest.raises(BasisFileError) as err:
        bio.load(path)
    assert str(path) in str(err.value)


def test_missing_file(tmp_path):
    path = tmp_path / "missing" / "basis.json"
    with pytest.raises(BasisFileError) as err:
        bio.load(path)
    assert str(path) in str(err.value) and "cannot read" in str(err.value)


def test_from_dict_names_its_source():
    with pytest.raises(BasisFileError, match=r"^somewhere: "):
        bio.from_dict({"format": "x"}, where="somewhere")


def test_non_symmetric_K_refused(tmp_path):
    doc = _doc()
    K = np.array(doc["fields"][0]["K"])
    K[0, 1] += 0.5
    doc["fields"][0]["K"] = K.tolist()
    path = tmp_path / "asym.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(BasisFileError):
        bio.load(path)


def test_singular_K_refused(tmp_path):
    doc = _doc()
    _semi_definite(doc)
    path = tmp_path / "singular.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(BasisFileError) as err:
        bio.load(path)
    assert str(path) in str(err.value)
