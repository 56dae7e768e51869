"""``basis.json``: a learned basis of torque fields and its motions' weights.

Format ``tflearn-basis/1`` (plain JSON, readable without tflearn)::

    {"format": "tflearn-basis/1",
     "body": {"lengths": [3], "masses": [3], "radii": [3], "gravity": [3], "damping": c},
     "fields": [{"eta": [7], "K": 7×7}, ...],                      # M fields
     "motions": [{"name", "duration", "rate", "q0": [7], "qd0": [7],
                  "a": [M], "b": [M], "step_onset": [M], "step_duration": [M],
                  "pulse_onset": [M], "pulse_duration": [M]}, ...]}

It defines, for each motion, the torque program
    τ(t) = Σ_i (a_i ψ((t − s_i)/d_i) + b_i φ((t − p_i)/e_i)) χ_i(ν(t)) − c v
with χ_i, ψ, φ as in :mod:`tflearn.fields`, started from (q0, qd0) at t = 0.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch

from ..body import Body, arm
from ..fields import FieldBasis, MotionWeights

FORMAT = "tflearn-basis/1"
_MOTION_ARRAYS = ("a", "b", "step_onset", "step_duration", "pulse_onset", "pulse_duration")


class BasisFileError(ValueError):
    """A basis.json that cannot be read: the message names the file and the problem."""


@dataclass
class LearnedBasis:
    """Everything a basis.json holds, as tflearn objects.

    body; basis (M fields); weights (N motions); q0, qd0 (N×nv); rate (N)."""

    body: Body
    basis: FieldBasis
    weights: MotionWeights
    q0: torch.Tensor
    qd0: torch.Tensor
    rate: torch.Tensor

    @property
    def names(self) -> list:
        return self.weights.names

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no motion named {name!r} in the basis (has {self.names})") from None


def _lst(x) -> list:
    return torch.as_tensor(x).detach().cpu().double().tolist()


def to_dict(lb: LearnedBasis) -> dict:
    """The JSON document of a :class:`LearnedBasis`."""
    w = lb.weights
    K = lb.basis.K()
    arrays = {"a": w.a, "b": w.b, "step_onset": w.step_onset, "step_duration": w.step_duration,
              "pulse_onset": w.pulse_onset, "pulse_duration": w.pulse_duration}
    motions = []
    for j, name in enumerate(w.names):
        m = {"name": name, "duration": float(w.duration[j]), "rate": float(lb.rate[j]),
             "q0": _lst(lb.q0[j]), "qd0": _lst(lb.qd0[j])}
        m.update({k: _lst(v[j]) for k, v in arrays.items()})
        motions.append(m)
    return {"format": FORMAT, "body": lb.body.summary,
            "fields": [{"eta": _lst(lb.basis.eta[i]), "K": _lst(K[i])} for i in range(lb.basis.M)],
            "motions": motions}


def save(lb: LearnedBasis, path) -> None:
    """Write ``path`` (basis.json)."""
    Path(path).write_text(json.dumps(to_dict(lb), indent=1))


def from_dict(doc: dict, kind: str = "full", blocks=None, where: str = "basis") -> LearnedBasis:
    """Build a :class:`LearnedBasis` from a parsed document (``kind``: stiffness kind to fit)."""
    def fail(msg):
        raise BasisFileError(f"{where}: {msg}")
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        fail(f"not a {FORMAT} document (format = {doc.get('format') if isinstance(doc, dict) else None!r})")
    for key in ("body", "fields", "motions"):
        if key not in doc:
            fail(f"missing key {key!r}")
    b = doc["body"]
    try:
        body = arm(lengths=b["lengths"], masses=b["masses"], radii=b["radii"],
                   gravity=b.get("gravity", [0, 0, 0]), damping=b.get("damping", 0.0),
                   offsets=b.get("offsets"))
    except (KeyError, ValueError, TypeError) as err:
        fail(f"body: {err}")
    try:
        eta = torch.tensor([f["eta"] for f in doc["fields"]], dtype=torch.float64)
        K = torch.tensor([f["K"] for f in doc["fields"]], dtype=torch.float64)
    except (KeyError, TypeError, ValueError) as err:
        fail(f"fields: {err}")
    M, nv = len(doc["fields"]), body.nv
    if eta.shape != (M, nv) or K.shape != (M, nv, nv):
        fail(f"fields: expected eta of length {nv} and K {nv}×{nv}")
    if M and not torch.allclose(K, K.transpose(-1, -2), rtol=1e-10, atol=1e-12):
        fail("fields: every K must be symmetric")
    if M:
        eig = torch.linalg.eigvalsh(K)
        if not bool((eig > 1e-12 * eig.abs().amax(-1, keepdim=True).clamp_min(1e-300)).all()):
            fail("fields: every K must be positive definite")
    ms = doc["motions"]
    try:
        cols = {k: torch.tensor([m[k] for m in ms], dtype=torch.float64).reshape(len(ms), M)
                for k in _MOTION_ARRAYS}
        q0 = torch.tensor([m["q0"] for m in ms], dtype=torch.float64).reshape(len(ms), nv)
        qd0 = torch.tensor([m["qd0"] for m in ms], dtype=torch.float64).reshape(len(ms), nv)
        duration = torch.tensor([m["duration"] for m in ms], dtype=torch.float64)
        rate = torch.tensor([m["rate"] for m in ms], dtype=torch.float64)
        names = [str(m["name"]) for m in ms]
    except (KeyError, TypeError, ValueError, RuntimeError) as err:
        fail(f"motions: {err}")
    if bool((cols["a"] < 0).any() or (cols["b"] < 0).any()):
        fail("motions: weights a and b must be non-negative")
    basis = FieldBasis(eta, K, kind=kind, blocks=blocks or body.blocks)
    weights = MotionWeights(cols["a"], cols["b"], duration, cols["step_onset"],
                            cols["step_duration"], cols["pulse_onset"], cols["pulse_duration"],
                            names=names)
    return LearnedBasis(body, basis, weights, q0, qd0, rate)


def load(path, kind: str = "full") -> LearnedBasis:
    """Read a basis.json; errors name the file and the problem."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise BasisFileError(f"{path}: cannot read JSON ({err})") from None
    return from_dict(doc, kind=kind, where=str(path))
