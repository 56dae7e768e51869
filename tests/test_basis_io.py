"""tflearn.io.basis: the basis.json format — exact round trips of any body (arm, chains,
branching trees, checked against Pinocchio), the /1 format still loading, an atomic save,
and refusals of malformed documents (every error is a BasisFileError that starts with
the file's path; property-based with hypothesis)."""
from __future__ import annotations

import copy
import json
import math
import os

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tflearn.io import basis as bio
from tflearn.io.basis import BasisFileError
from tflearn.model.fields import FieldBasis
from tflearn.model.program import FieldProgram
from tflearn.model.weights import MotionWeights
from tflearn.physics import body as tb
from tflearn.physics import dynamics as D
from tflearn.simulation.simulate import simulate

from conftest import full_symmetric, make_tree, max_rel_err, q_to_pin, random_coords, to_pin

DT = torch.float64
M, N, NV = 3, 2, 7


def random_spd(gen, n):
    A = torch.randn(n, n, generator=gen, dtype=DT)
    return A @ A.T / n + 0.3 * torch.eye(n, dtype=DT)


def the_arm() -> tb.Body:
    return tb.arm(gravity=[0.0, 0.0, -9.81], damping=0.25,
                  offsets=[[0.1, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, -0.3]],
                  masses=[2.5, 1.1, 0.4])


def make_lb(kind="full", seed=0, body=None) -> bio.LearnedBasis:
    gen = torch.Generator().manual_seed(seed)
    body = body or the_arm()
    nv = body.nv
    eta = torch.randn(M, nv, generator=gen, dtype=DT)
    K = torch.stack([random_spd(gen, nv) for _ in range(M)])

    def r(lo, hi):
        return lo + (hi - lo) * torch.rand(N, M, generator=gen, dtype=DT)
    a, b = r(0.0, 3.0), r(0.0, 2.0)
    a[0, 1] = 0.0                               # exact zeros survive
    weights = MotionWeights(a, b, torch.tensor([2.5, 3.25], dtype=DT),
                            r(-0.2, 0.5), r(0.5, 3.0), r(0.0, 1.0), r(0.3, 2.0),
                            names=["first", "second motion"])
    basis = FieldBasis(eta, K, kind=kind, blocks=body.blocks)
    q0 = torch.randn(N, nv, generator=gen, dtype=DT)
    qd0 = torch.randn(N, nv, generator=gen, dtype=DT)
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
    assert back.body == lb.body                # every link, gravity, damping, tip
    assert back.index("second motion") == 1
    with pytest.raises(bio.UnknownMotionError, match="third"):
        back.index("third")
    # the same document again
    bio.save(back, tmp_path / "again.json")
    d0, d1 = json.loads(path.read_text()), json.loads((tmp_path / "again.json").read_text())
    assert d1["format"] == "tflearn-basis/3" and d0["motions"] == d1["motions"]
    assert d0["body"] == d1["body"]
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
    assert set(doc) == {"format", "body", "fields", "field_damping", "motions"}
    assert set(doc["body"]) == {"name", "links", "gravity", "damping", "tip"}
    assert [set(l) for l in doc["body"]["links"]] == [set(tb.LINK_KEYS)] * 3
    assert doc["body"]["links"][1]["joint"] == "hinge" and doc["body"]["tip"]["link"] == 2
    assert len(doc["fields"]) == M and np.array(doc["fields"][0]["K"]).shape == (NV, NV)
    m = doc["motions"][1]
    assert set(m) == {"name", "duration", "rate", "q0", "qd0", "a", "b", "step_onset",
                      "step_duration", "pulse_onset", "pulse_duration", "window_onset",
                      "window_duration", "c"}
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


def _asymmetric_inertia(doc):
    doc["body"]["links"][2]["inertia"][0][1] = 0.01


BAD = {
    "format version": (_set(["format"], "tflearn-basis/4"), "unknown format tag"),
    "format tag": (_set(["format"], "basis"), "not a basis document"),
    "format number": (_set(["format"], 2), "not a basis document"),
    "no format": (_delete(["format"]), "format"),
    "missing body": (_delete(["body"]), "missing section 'body'"),
    "missing fields": (_delete(["fields"]), "missing section 'fields'"),
    "missing motions": (_delete(["motions"]), "missing section 'motions'"),
    "body not object": (_set(["body"], [1, 2]), "body: expected an object"),
    "body links missing": (_delete(["body", "links"]), "body: missing key 'links'"),
    "body links empty": (_set(["body", "links"], []), "body.links"),
    "body unknown key": (_set(["body", "lengths"], [0.3, 0.2, 0.1]), "unknown key 'lengths'"),
    "body link key": (_delete(["body", "links", 1, "inertia"]),
                      "body.links[1] ('forearm'): missing key 'inertia'"),
    "body negative mass": (_set(["body", "links", 1, "mass"], -1.0), "mass must be positive"),
    "body mass text": (_set(["body", "links", 0, "mass"], "2"), "links[0] ('upper_arm').mass"),
    "body joint type": (_set(["body", "links", 2, "joint"], "slider"), "unknown joint type"),
    "body parent order": (_set(["body", "links", 1, "parent"], 1), "parent index"),
    "body parent float": (_set(["body", "links", 1, "parent"], 0.0), "parent: expected an integer"),
    "body inertia": (_asymmetric_inertia, "inertia"),
    "body inertia shape": (_set(["body", "links", 0, "inertia"], [[1.0, 0.0], [0.0, 1.0]]),
                           "links[0] ('upper_arm').inertia"),
    "body hinge axis": (_set(["body", "links", 1, "axis"], [1.0, 1.0, 0.0]), "unit"),
    "body origin nan": (_set(["body", "links", 1, "origin"], [0.0, float("nan"), 0.0]),
                        "origin[1]: expected a finite number"),
    "body gravity": (_set(["body", "gravity"], [0.0, -9.81]), "body.gravity"),
    "body damping": (_set(["body", "damping"], -0.5), "damping must be non-negative"),
    "body tip link": (_set(["body", "tip", "link"], 3), "body.tip.link"),
    "eta length": (_set(["fields", 0, "eta"], [0.0] * 6), "fields[0].eta: expected a list of 7"),
    "eta missing": (_delete(["fields", 2, "eta"]), "fields[2]: missing key 'eta'"),
    "eta inf": (_set(["fields", 2, "eta", 3], float("inf")), "fields[2].eta[3]"),
    "fields not list": (_set(["fields"], {"eta": []}), "fields: expected a list"),
    "K shape": (_set(["fields", 1, "K"], np.eye(6).tolist()), "fields[1].K"),
    "K ragged": (_set(["fields", 1, "K"], [[1.0] * 7] * 6 + [[1.0]]), "fields[1].K[6]"),
    "K not PD": (_non_pd, "positive definite"),
    "K strings": (_set(["fields", 0, "K"], "identity"), "fields[0].K"),
    "K nan": (_set(["fields", 0, "K", 2, 2], float("nan")), "finite"),
    "a length": (_set(["motions", 0, "a"], [1.0] * (M + 1)), "motions[0] ('first').a"),
    "a missing": (_delete(["motions", 1, "a"]), "motions[1] ('second motion'): missing key 'a'"),
    "b missing": (_delete(["motions", 0, "b"]), "motions"),
    "onsets missing": (_delete(["motions", 0, "pulse_onset"]), "pulse_onset"),
    "q0 length": (_set(["motions", 0, "q0"], [0.0] * 6), "q0: expected a list of 7"),
    "qd0 missing": (_delete(["motions", 1, "qd0"]), "qd0"),
    "rate missing": (_delete(["motions", 0, "rate"]), "rate"),
    "rate zero": (_set(["motions", 0, "rate"], 0.0), "rate: must be positive"),
    "duration text": (_set(["motions", 0, "duration"], "long"), "duration: expected a number"),
    "duration negative": (_set(["motions", 1, "duration"], -3.0), "must be positive"),
    "step duration zero": (_set(["motions", 1, "step_duration", 0], 0.0), "must be positive"),
    "pulse duration nan": (_set(["motions", 1, "pulse_duration", 2], float("nan")), "finite"),
    "name missing": (_delete(["motions", 0, "name"]), "motions[0].name"),
    "name number": (_set(["motions", 0, "name"], 3), "motions[0].name"),
    "duplicate names": (_set(["motions", 1, "name"], "first"), "duplicate motion name 'first'"),
    "motion not object": (_set(["motions", 1], [1.0]), "motions[1]: expected an object"),
    "huge integer": (_set(["motions", 0, "q0", 0], 10 ** 400), "q0[0]"),
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
    assert msg.startswith(f"{path}: ") and words in msg, msg


@pytest.mark.parametrize("text", ["{not json", "", "[1, 2, 3]", "\"tflearn-basis/2\"", "null",
                                  "\ufeff{}", pytest.param("[" * 100000, id="deep")])
def test_not_a_basis_document(tmp_path, text):
    path = tmp_path / "bad.json"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(BasisFileError) as err:
        bio.load(path)
    assert str(err.value).startswith(f"{path}: ")


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


# ------------------------------------------------------------------ any body round-trips

def branching_tree() -> tb.Body:
    """A torso (ball, turned at rest) with two arms: left = hinge shoulder about a skew
    axis and a ball elbow; right = a fixed mount, a ball shoulder and a hand fixed to it
    that is a general (non-cylinder) link. Gravity, damping, a custom tip on the left arm."""
    s = 1 / math.sqrt(3)
    links = (
        tb.cylinder_link("torso", -1, "ball", (0.0, 0.0, 0.0), 0.5, 8.0, 0.12,
                         offset=(0.05, -0.1, 0.2)),
        tb.cylinder_link("left_upper", 0, "hinge", (0.18, 0.0, -0.05), 0.28, 1.5, 0.04,
                         offset=(0.0, 0.3, 0.0), axis=(s, -s, s)),
        tb.cylinder_link("left_fore", 1, "ball", (0.0, 0.0, -0.28), 0.25, 1.0, 0.035),
        tb.cylinder_link("right_mount", 0, "fixed", (-0.18, 0.0, -0.05), 0.05, 0.3, 0.05,
                         offset=(0.0, 0.0, math.pi / 2)),
        tb.cylinder_link("right_upper", 3, "ball", (0.0, 0.0, -0.05), 0.3, 1.4, 0.04,
                         offset=(-0.2, 0.0, 0.1)),
        tb.Link(name="right_hand", parent=4, joint="fixed", origin=(0.01, 0.0, -0.3),
                mass=0.4, com=(0.01, -0.02, -0.06),
                inertia=((2e-3, 1e-4, 0.0), (1e-4, 1.5e-3, -2e-4), (0.0, -2e-4, 8e-4)),
                offset=(0.1, 0.2, -0.3)),
    )
    return tb.Body(links=links, gravity=(0.0, 0.0, -9.81), damping=0.1, tip_link=2,
                   tip_point=(0.01, 0.02, -0.25), name="two_arms")


BODIES = {"chain3_ball": lambda: tb.chain(3, joint="ball"),
          "chain4_hinge": lambda: tb.chain(4, joint="hinge", gravity=(0.0, 0.0, -9.81),
                                           damping=0.2),
          "two_arms": branching_tree,
          "tree": lambda: make_tree((0.0, 0.0, -9.81))}


@pytest.fixture(params=list(BODIES))
def saved(request, tmp_path):
    """(original LearnedBasis, the one loaded back from its saved file)."""
    lb = make_lb(body=BODIES[request.param](), seed=3)
    bio.save(lb, tmp_path / "basis.json")
    return lb, bio.load(tmp_path / "basis.json")


def test_any_body_round_trips_exactly(saved):
    lb, back = saved
    assert back.body == lb.body and back.body.to_dict() == lb.body.to_dict()
    for a, b in zip(back.body.links, lb.body.links):       # field by field, NaN-aware
        assert a.to_dict() == b.to_dict()
    assert back.body.nv == lb.body.nv and back.basis.blocks == lb.body.blocks
    assert max_diff(back.basis.eta, lb.basis.eta) == 0.0
    assert max_diff(back.q0, lb.q0) == 0.0 and max_diff(back.qd0, lb.qd0) == 0.0


def test_any_body_resimulates_identically(saved):
    lb, back = saved
    t = torch.linspace(0.0, 0.2, 5, dtype=DT)
    paths = [simulate(x.body, FieldProgram(x.basis, x.weights), x.q0, 0.3 * x.qd0, t)
             for x in (lb, back)]
    with torch.no_grad():
        assert max_diff(paths[0].q, paths[1].q) <= 1e-12
        assert max_diff(paths[0].v, paths[1].v) <= 1e-12


def test_loaded_body_matches_pinocchio(saved, rng):
    """Pinocchio's model of the LOADED body (fixed links merged into their parent joint)
    against tflearn's RNEA and mass matrix."""
    import pinocchio as pin
    body = saved[1].body
    model = to_pin(body)
    data = model.createData()
    q = random_coords(body, rng, 8)
    v, a = rng.normal(size=q.shape), rng.normal(size=q.shape)
    tq, tv, ta = (torch.as_tensor(x, dtype=DT) for x in (q, v, a))
    tau, Mq = D.rnea(body, tq, tv, ta).numpy(), D.mass_matrix(body, tq).numpy()
    for k in range(len(q)):
        qp = q_to_pin(body, q[k])
        assert max_rel_err(tau[k], pin.rnea(model, data, qp, v[k], a[k])) <= 1e-9
        assert max_rel_err(Mq[k], full_symmetric(pin.crba(model, data, qp))) <= 1e-9


# A tflearn-basis/1 document as the previous writer produced it (M = 1 field, one motion).
V1_DOC = {
    "format": "tflearn-basis/1",
    "body": {"lengths": [0.3, 0.27, 0.19], "masses": [2.0, 1.2, 0.45],
             "radii": [0.04, 0.035, 0.03], "gravity": [0.0, 0.0, -9.81], "damping": 0.5,
             "offsets": [[0.1, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.2]]},
    "fields": [{"eta": [0.1, -0.2, 0.3, -0.4, 0.5, 0.0, 0.25],
                "K": [[2.0 if i == j else 0.1 if abs(i - j) == 1 else 0.0 for j in range(7)]
                      for i in range(7)]}],
    "motions": [{"name": "reach", "duration": 2.0, "rate": 100.0,
                 "q0": [0.0] * 7, "qd0": [0.0, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0],
                 "a": [1.5], "b": [0.25], "step_onset": [0.0], "step_duration": [2.0],
                 "pulse_onset": [0.0], "pulse_duration": [2.0]}],
}


def test_v1_document_still_loads(tmp_path):
    path = tmp_path / "old.json"
    path.write_text(json.dumps(V1_DOC))
    lb = bio.load(path)
    assert lb.body == tb.arm(gravity=[0.0, 0.0, -9.81], damping=0.5,
                             offsets=V1_DOC["body"]["offsets"])
    assert lb.names == ["reach"] and lb.weights.a[0, 0].item() == 1.5
    assert max_diff(lb.basis.K()[0], torch.tensor(V1_DOC["fields"][0]["K"], dtype=DT)) <= 1e-15
    no_extras = copy.deepcopy(V1_DOC)                 # gravity, damping, offsets optional
    for key in ("gravity", "damping", "offsets"):
        del no_extras["body"][key]
    assert bio.from_dict(no_extras).body == tb.arm()
    bio.save(lb, tmp_path / "new.json")               # re-saved as /3, same model
    again = bio.load(tmp_path / "new.json")
    assert json.loads((tmp_path / "new.json").read_text())["format"] == "tflearn-basis/3"
    assert again.body == lb.body


@pytest.mark.parametrize("edit, words", [
    (_set(["body", "lengths"], [0.3, 0.2]), "body.lengths: expected a list of 3"),
    (_delete(["body", "masses"]), "body: missing key 'masses'"),
    (_set(["body", "masses"], [1.0, -1.0, 1.0]), "mass must be positive"),
    (_set(["body", "radii"], [0.04, float("nan"), 0.03]), "body.radii[1]"),
    (_set(["body", "damping"], float("inf")), "body.damping"),
    (_set(["body", "links"], []), "unknown key"),     # a /2 body under a /1 tag is ignored...
])
def test_bad_v1_body(tmp_path, edit, words):
    doc = copy.deepcopy(V1_DOC)
    edit(doc)
    path = tmp_path / "old.json"
    path.write_text(json.dumps(doc))
    if words == "unknown key":                        # ... extra keys were always allowed
        bio.load(path)
        return
    with pytest.raises(BasisFileError) as err:
        bio.load(path)
    assert str(err.value).startswith(f"{path}: ") and words in str(err.value), str(err.value)


# ------------------------------------------------------------------------- atomic save

def test_save_replaces_the_file_atomically(tmp_path, monkeypatch):
    """An interrupted save leaves the previous file whole and no temporary file behind."""
    path = tmp_path / "basis.json"
    bio.save(make_lb(seed=1), path)
    before = path.read_bytes()

    def interrupted(fd):
        raise KeyboardInterrupt
    monkeypatch.setattr(os, "fsync", interrupted)
    with pytest.raises(KeyboardInterrupt):
        bio.save(make_lb(seed=2), path)
    assert path.read_bytes() == before and os.listdir(tmp_path) == ["basis.json"]
    monkeypatch.undo()
    bio.save(make_lb(seed=2), path)
    assert path.read_bytes() != before and os.listdir(tmp_path) == ["basis.json"]
    assert max_diff(bio.load(path).basis.eta, make_lb(seed=2).basis.eta) == 0.0


def test_save_refuses_non_finite_numbers(tmp_path):
    lb = make_lb()
    lb.q0[0, 0] = float("nan")
    with pytest.raises(ValueError):
        bio.save(lb, tmp_path / "basis.json")
    assert os.listdir(tmp_path) == []


# ----------------------------------------------------------- malformed files, at random

FUZZ = settings(max_examples=60, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])
ODD_NUMBERS = st.sampled_from([1e308, -1e308, 1e-308, 5e-324, -5e-324, 0.0, -0.0, -1.0,
                               1e16, 10 ** 400, -(10 ** 30), float("nan"), float("inf"),
                               float("-inf")]) | st.floats() | st.integers()


def loads_or_refuses(path) -> None:
    """Loading either succeeds or raises BasisFileError "<path>: ..." — nothing else."""
    try:
        bio.load(path)
    except BasisFileError as err:
        assert str(err).startswith(f"{path}: "), str(err)


def leaves(node, kind, at=()):
    """Paths to the values of a parsed document for which kind(value) holds."""
    if kind(node):
        yield at
    if isinstance(node, dict):
        for k, v in node.items():
            yield from leaves(v, kind, at + (k,))
    elif isinstance(node, list):
        for k, v in enumerate(node):
            yield from leaves(v, kind, at + (k,))


def is_number(x):
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def replaced(doc, at, value):
    doc = copy.deepcopy(doc)
    if not at:
        return value
    _set(list(at), value)(doc)
    return doc


@pytest.fixture(scope="module")
def documents():
    """Valid documents: the arm and the branching tree in /3, and the /1 document."""
    return {"arm": bio.to_dict(make_lb()),
            "two_arms": bio.to_dict(make_lb(body=branching_tree())),
            "v1": V1_DOC}


@FUZZ
@given(data=st.binary(max_size=300))
def test_random_bytes(tmp_path, data):
    path = tmp_path / "basis.json"
    path.write_bytes(data)
    loads_or_refuses(path)


@FUZZ
@given(cut=st.floats(0.0, 1.0, exclude_max=True), which=st.sampled_from(["arm", "two_arms", "v1"]))
def test_truncated_file(tmp_path, documents, cut, which):
    text = json.dumps(documents[which], indent=1)
    path = tmp_path / "basis.json"
    path.write_text(text[:int(cut * len(text))])
    with pytest.raises(BasisFileError) as err:
        bio.load(path)
    assert str(err.value).startswith(f"{path}: ")


@FUZZ
@given(data=st.data(), which=st.sampled_from(["arm", "two_arms", "v1"]))
def test_odd_number_anywhere(tmp_path, documents, data, which):
    doc = documents[which]
    at = data.draw(st.sampled_from(list(leaves(doc, is_number))), label="at")
    path = tmp_path / "basis.json"
    path.write_text(json.dumps(replaced(doc, at, data.draw(ODD_NUMBERS, label="value"))))
    loads_or_refuses(path)


SHAPE_EDITS = st.sampled_from(["drop", "extend", "scalar", "string", "null", "object", "nest"])


@FUZZ
@given(data=st.data(), which=st.sampled_from(["arm", "two_arms", "v1"]), edit=SHAPE_EDITS)
def test_wrong_shape_anywhere(tmp_path, documents, data, which, edit):
    doc = documents[which]
    at = data.draw(st.sampled_from(list(leaves(doc, lambda x: isinstance(x, (list, dict))))),
                   label="at")
    node = doc
    for k in at:
        node = node[k]
    items = list(node) if isinstance(node, list) else list(node.values())
    value = {"drop": items[:-1], "extend": items + items[-1:], "scalar": 1.0, "string": "x",
             "null": None, "object": {"k": items}, "nest": [items]}[edit]
    if edit in ("drop", "extend") and isinstance(node, dict):
        value = dict(list(node.items())[:-1]) if edit == "drop" else {**node, "extra": 1}
    path = tmp_path / "basis.json"
    path.write_text(json.dumps(replaced(doc, at, value)))
    loads_or_refuses(path)


@FUZZ
@given(tag=st.text(max_size=20) | st.sampled_from(["tflearn-basis/0", "tflearn-basis/4",
                                                     "tflearn-basis/2.0", "TFLEARN-BASIS/2"])
       | st.none() | st.integers() | st.lists(st.integers(), max_size=2))
def test_wrong_tag_or_version(tmp_path, documents, tag):
    path = tmp_path / "basis.json"
    path.write_text(json.dumps(replaced(documents["arm"], ("format",), tag)))
    if tag == bio.FORMAT:
        bio.load(path)
        return
    with pytest.raises(BasisFileError) as err:
        bio.load(path)
    assert str(err.value).startswith(f"{path}: ")
