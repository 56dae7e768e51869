"""``basis.json``: a learned basis of torque fields and its motions' weights.

Format ``tflearn-basis/3`` (plain JSON, readable without tflearn; nv coordinates, M
fields)::

    {"format": "tflearn-basis/3",
     "body": {"name", "gravity": [3], "damping": c, "tip": {"link": i, "point": [3]},
              "links": [{"name", "parent", "joint", "origin": [3], "offset": [3],
                         "axis": [3], "mass", "com": [3], "inertia": 3×3,
                         "length", "radius"}, ...]},                  # Body.to_dict()
     "fields": [{"eta": [nv], "K": nv×nv}, ...],                   # M fields
     "field_damping": ζ,                                            # s, ≥ 0
     "motions": [{"name", "duration", "rate", "q0": [nv], "qd0": [nv],
                  "a": [M], "b": [M], "step_onset": [M], "step_duration": [M],
                  "pulse_onset": [M], "pulse_duration": [M],
                  "window_onset": [P], "window_duration": [P], "c": M×P}, ...]}

The body is the whole kinematic tree of :mod:`tflearn.physics.body` (links in topological order,
parent −1 the base, joint "ball" / "hinge" / "fixed", offset the zero orientation as a
rotation vector, inertia about the centre of mass in the link frame, length and radius
null unless the link is a cylinder). Files of the earlier formats still load, with
ζ = 0 and P = 0: ``tflearn-basis/2`` is ``/3`` without ``field_damping`` and the
motions' windows; a ``tflearn-basis/1``
body ``{"lengths": [3], "masses": [3], "radii": [3], "gravity": [3], "damping": c,
"offsets"?: 3×3}`` is the arm of :func:`tflearn.physics.body.arm`.

It defines, for each motion, the torque program
    τ(t) = Σ_i (a_i ψ((t − s_i)/d_i) + b_i φ((t − p_i)/e_i) + Σ_k c_ik φ((t − o_k)/l_k))
           χ_i(ν(t), v(t)) − c v,
    χ_i(ν, v) = −K_i (ν − η_i + ζ v) exp(−½ (ν − η_i)ᵀ K_i (ν − η_i)),
with ψ, φ as in :mod:`tflearn.model.fields`, started from (q0, qd0) at t = 0.

Loading checks every number (finite; a, b, c, ζ ≥ 0; durations and rates > 0), every size
against the body's nv and M, that each K is symmetric positive definite and that motion
names are unique; a file that fails raises :class:`BasisFileError` "<path>: <problem>".
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import torch

from ..errors import InputError
from ..model.fields import FieldBasis
from ..model.weights import MotionWeights
from ..physics.body import Body, arm, json_kind, json_numbers
from ..physics.body import from_dict as body_from_dict
from .files import write_text

FORMAT = "tflearn-basis/3"
FORMATS = ("tflearn-basis/1", "tflearn-basis/2", FORMAT)
_MOTION_ARRAYS = ("a", "b", "step_onset", "step_duration", "pulse_onset", "pulse_duration")
_WINDOW_ARRAYS = ("window_onset", "window_duration", "c")        # tflearn-basis/3
_POSITIVE = ("duration", "rate", "step_duration", "pulse_duration", "window_duration")
_NON_NEGATIVE = ("a", "b", "c")


class UnknownMotionError(InputError):
    """A motion name that a basis does not hold."""


class BasisFileError(InputError):
    """A basis.json that cannot be read: the message names the file and the problem."""


@dataclass
class LearnedBasis:
    """Everything a basis.json holds, as tflearn objects.

    body; basis (M fields); weights (N motions); q0, qd0 (N×nv); rate (N); source: the
    file it was read from, if any (named in errors)."""

    body: Body
    basis: FieldBasis
    weights: MotionWeights
    q0: torch.Tensor
    qd0: torch.Tensor
    rate: torch.Tensor
    source: Optional[str] = None

    @property
    def names(self) -> list:
        return self.weights.names

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise UnknownMotionError(f"{self.source or 'basis'}: no motion named {name!r} "
                                     f"(it has {', '.join(self.names)})") from None


def _lst(x) -> list:
    return torch.as_tensor(x).detach().cpu().double().tolist()


def to_dict(lb: LearnedBasis) -> dict:
    """The JSON document of a :class:`LearnedBasis` (format ``tflearn-basis/3``)."""
    w = lb.weights
    K = lb.basis.K()
    arrays = {"a": w.a, "b": w.b, "step_onset": w.step_onset, "step_duration": w.step_duration,
              "pulse_onset": w.pulse_onset, "pulse_duration": w.pulse_duration,
              "window_onset": w.window_onset, "window_duration": w.window_duration, "c": w.c}
    motions = []
    for j, name in enumerate(w.names):
        m = {"name": name, "duration": float(w.duration[j]), "rate": float(lb.rate[j]),
             "q0": _lst(lb.q0[j]), "qd0": _lst(lb.qd0[j])}
        m.update({k: _lst(v[j]) for k, v in arrays.items()})
        motions.append(m)
    return {"format": FORMAT, "body": lb.body.to_dict(),
            "fields": [{"eta": _lst(lb.basis.eta[i]), "K": _lst(K[i])} for i in range(lb.basis.M)],
            "field_damping": lb.basis.damping, "motions": motions}


def save(lb: LearnedBasis, path) -> None:
    """Write ``path`` (basis.json) atomically (:func:`tflearn.io.files.write_text`): it is
    always either the old file or the whole new one. Non-finite numbers raise ValueError
    (a diverged model never reaches a basis file)."""
    try:
        text = json.dumps(to_dict(lb), indent=1, allow_nan=False)
    except ValueError:
        raise ValueError(f"{path}: not written: the model holds NaN or Inf") from None
    write_text(path, text)


def from_dict(doc: dict, kind: str = "full", blocks=None, where: str = "basis") -> LearnedBasis:
    """Build a :class:`LearnedBasis` from a parsed document (``kind``: stiffness kind to fit).

    Raises :class:`BasisFileError` "<where>: <problem>" for any malformed document."""
    try:
        return _from_dict(doc, kind, blocks)
    except ValueError as err:
        raise BasisFileError(f"{where}: {err}") from None


def _from_dict(doc, kind: str, blocks) -> LearnedBasis:
    if not isinstance(doc, dict):
        raise ValueError(f"not a basis document (a JSON object), got {json_kind(doc)}")
    tag = doc.get("format")
    if tag not in FORMATS:
        known = " or ".join(FORMATS)
        raise ValueError(f"unknown format tag {tag[:40]!r} (expected {known}; written by a "
                         f"newer tflearn?)"
                         if isinstance(tag, str) and tag.startswith("tflearn-basis/")
                         else f"not a basis document: format is {json_kind(tag)}, "
                              f"expected {known}")
    for key in ("body", "fields", "motions"):
        if key not in doc:
            raise ValueError(f"missing section {key!r}")
    body = _body(doc["body"], tag)
    eta, K = _fields(doc["fields"], body.nv)
    damping = _field_damping(doc, tag)
    q0, qd0, rate, weights = _motions(doc["motions"], len(eta), body.nv, tag == FORMAT)
    try:
        basis = FieldBasis(eta, K, kind=kind, blocks=blocks or body.blocks, damping=damping)
    except torch.linalg.LinAlgError as err:        # a Cholesky factorisation that fails
        raise ValueError(f"fields: cannot factor K ({err})") from None
    return LearnedBasis(body, basis, weights, q0, qd0, rate)


def _body(b, tag: str) -> Body:
    try:
        return _arm_v1(b) if tag == "tflearn-basis/1" else body_from_dict(b)
    except ValueError as err:
        text = str(err)
        raise ValueError(text if text.startswith("body") else f"body: {text}") from None


_V1_BODY = {"lengths": (3,), "masses": (3,), "radii": (3,), "gravity": (3,), "damping": (),
            "offsets": (3, 3)}
_V1_DEFAULTS = {"gravity": [0.0, 0.0, 0.0], "damping": 0.0, "offsets": None}


def _arm_v1(b) -> Body:
    """The arm of a ``tflearn-basis/1`` body section (gravity, damping, offsets optional)."""
    if not isinstance(b, dict):
        raise ValueError(f"body: expected an object, got {json_kind(b)}")
    args = {}
    for key, shape in _V1_BODY.items():
        if key not in b and key not in _V1_DEFAULTS:
            raise ValueError(f"body: missing key {key!r}")
        val = b.get(key, _V1_DEFAULTS.get(key))
        args[key] = None if val is None else json_numbers(val, shape, f"body.{key}")
    return arm(**args)


def _section(x, where: str) -> list:
    if not isinstance(x, list):
        raise ValueError(f"{where}: expected a list, got {json_kind(x)}")
    for k, entry in enumerate(x):
        if not isinstance(entry, dict):
            raise ValueError(f"{where}[{k}]: expected an object, got {json_kind(entry)}")
    return x


def _entry(entry: dict, key: str, shape: tuple, where: str) -> torch.Tensor:
    if key not in entry:
        raise ValueError(f"{where}: missing key {key!r}")
    return torch.tensor(json_numbers(entry[key], shape, f"{where}.{key}"), dtype=torch.float64)


def _stack(xs: list, shape: tuple) -> torch.Tensor:
    return torch.stack(xs) if xs else torch.zeros((0,) + shape, dtype=torch.float64)


def _fields(fields, nv: int):
    """η (M×nv) and K (M×nv×nv), each K symmetric positive definite."""
    eta, K = [], []
    for i, f in enumerate(_section(fields, "fields")):
        eta.append(_entry(f, "eta", (nv,), f"fields[{i}]"))
        K.append(_entry(f, "K", (nv, nv), f"fields[{i}]"))
        _check_spd(K[-1], f"fields[{i}].K")
    return _stack(eta, (nv,)), _stack(K, (nv, nv))


def _field_damping(doc: dict, tag: str) -> float:
    """ζ (s, ≥ 0): required by ``/3``, 0 for the earlier formats (which had none, so a
    ``field_damping`` under their tag is refused rather than dropped)."""
    if tag != FORMAT:
        if "field_damping" in doc:
            raise ValueError(f"'field_damping' belongs to {FORMAT}, but the file is tagged {tag}")
        return 0.0
    if "field_damping" not in doc:
        raise ValueError("missing key 'field_damping'")
    zeta = float(json_numbers(doc["field_damping"], (), "field_damping"))
    if zeta < 0:
        raise ValueError(f"field_damping: must be non-negative, got {zeta}")
    return zeta


def _check_spd(K: torch.Tensor, where: str) -> None:
    """K symmetric (to 1e-10 relative) with eigenvalues > 1e-12 · the largest |eigenvalue|."""
    if not torch.allclose(K, K.T, rtol=1e-10, atol=1e-12):
        raise ValueError(f"{where}: not symmetric")
    try:
        eig = torch.linalg.eigvalsh(K)
    except torch.linalg.LinAlgError:
        raise ValueError(f"{where}: no eigenvalues (numbers too large?)") from None
    if not bool((eig > 1e-12 * eig.abs().max().clamp_min(1e-300)).all()):
        raise ValueError(f"{where}: not positive definite (smallest eigenvalue "
                         f"{float(eig.min()):.3g})")


def _motions(motions, M: int, nv: int, windows: bool):
    """q0, qd0 (N×nv), rate (N) and the :class:`MotionWeights` of the motions; with
    ``windows`` (format /3) each motion's P windows, P the same for every motion."""
    motions = _section(motions, "motions")
    P = _windows(motions) if windows else 0
    cols = {k: [] for k in ("q0", "qd0", "duration", "rate") + _MOTION_ARRAYS
            + (_WINDOW_ARRAYS if windows else ())}
    shapes = {"q0": (nv,), "qd0": (nv,), "duration": (), "rate": (),
              "window_onset": (P,), "window_duration": (P,), "c": (M, P)}
    names = []
    for j, m in enumerate(motions):
        where = f"motions[{j}]"
        name = m.get("name")
        if not isinstance(name, str):
            raise ValueError(f"{where}.name: expected a string, got {json_kind(name)}")
        if name in names:
            raise ValueError(f"{where}: duplicate motion name {name!r}")
        names.append(name)
        where = f"{where} ({name!r})"
        for key, col in cols.items():
            col.append(_entry(m, key, shapes.get(key, (M,)), where))
            if key in _POSITIVE and not bool((col[-1] > 0).all()):
                raise ValueError(f"{where}.{key}: must be positive")
            if key in _NON_NEGATIVE and not bool((col[-1] >= 0).all()):
                raise ValueError(f"{where}.{key}: weights must be non-negative")
    t = {k: _stack(v, shapes.get(k, (M,))) for k, v in cols.items()}
    weights = MotionWeights(t["a"], t["b"], t["duration"], t["step_onset"], t["step_duration"],
                            t["pulse_onset"], t["pulse_duration"], names=names, c=t.get("c"),
                            window_onset=t.get("window_onset"),
                            window_duration=t.get("window_duration"))
    return t["q0"], t["qd0"], t["rate"], weights


def _windows(motions: list) -> int:
    """P, the number of windows of every motion (the length of its ``window_onset``)."""
    sizes = set()
    for j, m in enumerate(motions):
        w = m.get("window_onset")
        if not isinstance(w, list):
            raise ValueError(f"motions[{j}].window_onset: expected a list, got {json_kind(w)}"
                             if "window_onset" in m else f"motions[{j}]: missing key 'window_onset'")
        sizes.add(len(w))
    if len(sizes) > 1:
        raise ValueError(f"motions: every motion needs the same number of windows, got {sorted(sizes)}")
    return sizes.pop() if sizes else 0


def load(path, kind: str = "full") -> LearnedBasis:
    """Read a basis.json; errors are :class:`BasisFileError` "<path>: <problem>"."""
    path = Path(path)
    try:
        doc = json.loads(path.read_bytes())
    except OSError as err:
        raise BasisFileError(f"{path}: cannot read ({err.strerror or err})") from None
    except (ValueError, RecursionError) as err:     # JSONDecodeError, UnicodeDecodeError
        raise BasisFileError(f"{path}: not JSON ({err})") from None
    lb = from_dict(doc, kind=kind, where=str(path))
    lb.source = str(path)
    return lb
