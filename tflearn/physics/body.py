"""Kinematic trees of rigid links: an immutable model, presets, a config reader and a JSON form.

A body is a tree of links. Link ``i`` hangs from link ``parent`` (or the fixed base
when ``parent`` is -1) through a joint whose frame sits at ``origin`` in the parent
frame, turned by a fixed zero orientation ``R0``. The child frame relative to the
parent is then

    R = R0 · exp([v]×)          ball joint, v ∈ R³ the rotation vector (|v| ≤ π)
    R = R0 · Rot(axis, θ)       hinge joint, θ ∈ R about a unit axis of the child frame
    R = R0                      fixed joint
    R = R0 · exp([v]×), origin + R0 t      free joint (6 DOF), ν = (v, t)

Coordinates ν stack the joints' v and θ in link order (ball 3, hinge 1, fixed 0, free 6:
rotation vector v then translation t, the child origin at origin + R0 t in the parent).
Velocities use the same layout: a ball joint's velocity is the child's angular
velocity relative to its parent expressed in the child frame (Pinocchio's spherical
convention), a hinge's is θ̇, a free joint's is (ω, u): the child's angular velocity
and the velocity of its origin, both relative to the parent and in the child frame
(Pinocchio's free-flyer LOCAL velocity with its two halves swapped: pin orders
(linear, angular)), so ṫ = exp([v]×) u; torques are the dual quantities (power = τ·v;
a free joint's is (moment, force) in the child frame).

The default body is the thesis' arm: shoulder (ball) → upper arm → elbow (hinge
about the forearm's local x) → forearm → wrist (ball) → hand, hanging along −z at
rest, world z up, gravity off.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

JOINT_DOFS = {"ball": 3, "hinge": 1, "fixed": 0, "free": 6}
LINK_KEYS = ("name", "parent", "joint", "origin", "offset", "axis", "mass", "com", "inertia",
             "length", "radius")
BODY_KEYS = ("name", "links", "gravity", "damping", "tip")
#: Names of the joints of the thesis' arm, by the link they move (:func:`arm`); a link
#: not listed names its joint itself.
JOINT_NAMES = {"upper_arm": "shoulder", "forearm": "elbow", "hand": "wrist"}


@dataclass(frozen=True)
class Link:
    """One rigid link and the joint that moves it.

    Attributes:
        name: link name.
        parent: index of the parent link, -1 for the fixed base.
        joint: "ball", "hinge", "fixed" or "free".
        origin: joint position in the parent frame (3,).
        offset: zero orientation R0 of the joint as a rotation vector (3,).
        axis: hinge axis in the child frame (3,), ignored for other joints.
        mass: kg.
        com: centre of mass in the link frame (3,).
        inertia: rotational inertia about the centre of mass, link frame (3, 3).
        length, radius: cylinder size when the link was built by :func:`cylinder_link`
            (NaN otherwise); kept for export and drawing.
    """

    name: str
    parent: int
    joint: str
    origin: tuple
    mass: float
    com: tuple
    inertia: tuple
    offset: tuple = (0.0, 0.0, 0.0)
    axis: tuple = (1.0, 0.0, 0.0)
    length: float = float("nan")
    radius: float = float("nan")

    def __post_init__(self):
        if self.joint not in JOINT_DOFS:
            raise ValueError(f"link {self.name!r}: unknown joint type {self.joint!r} "
                             f"(expected one of {sorted(JOINT_DOFS)})")
        if not 0 < self.mass < math.inf:
            raise ValueError(f"link {self.name!r}: mass must be positive and finite, "
                             f"got {self.mass}")
        inertia = np.asarray(self.inertia, dtype=float)
        if (inertia.shape != (3, 3) or not np.isfinite(inertia).all()
                or not np.allclose(inertia, inertia.T)):
            raise ValueError(f"link {self.name!r}: inertia must be a finite symmetric 3x3 matrix")
        if np.linalg.eigvalsh(inertia).min() < 0:
            raise ValueError(f"link {self.name!r}: inertia must be positive semi-definite")
        if self.joint == "hinge":
            axis = np.asarray(self.axis, dtype=float)
            if axis.shape != (3,) or not np.isclose(np.linalg.norm(axis), 1.0):
                raise ValueError(f"link {self.name!r}: hinge axis must be a unit 3-vector")

    @property
    def dof(self) -> int:
        return JOINT_DOFS[self.joint]

    def to_dict(self) -> dict:
        """Plain-JSON description: the attributes under their names, vectors as lists,
        inertia as 3 rows, NaN length/radius as None (JSON null)."""
        return {"name": self.name, "parent": int(self.parent), "joint": self.joint,
                "origin": _floats(self.origin), "offset": _floats(self.offset),
                "axis": _floats(self.axis), "mass": float(self.mass),
                "com": _floats(self.com), "inertia": [_floats(row) for row in self.inertia],
                "length": _or_null(self.length), "radius": _or_null(self.radius)}


def _floats(xs) -> list:
    return [float(x) for x in xs]


def _or_null(x: float):
    return None if math.isnan(x) else float(x)


def cylinder_link(name: str, parent: int, joint: str, origin: Sequence[float],
                  length: float, mass: float, radius: float, **kw) -> Link:
    """A uniform solid cylinder along the link's local −z, centre of mass at mid-length.

    Inertia about the centre: Ixx = Iyy = m(3r² + L²)/12, Izz = m r²/2.
    """
    # x * x, not x**2: too large a size gives inf (refused by Link), not OverflowError
    ixx = mass * (3 * radius * radius + length * length) / 12.0
    izz = mass * radius * radius / 2.0
    inertia = ((ixx, 0.0, 0.0), (0.0, ixx, 0.0), (0.0, 0.0, izz))
    return Link(name=name, parent=parent, joint=joint, origin=tuple(map(float, origin)),
                mass=float(mass), com=(0.0, 0.0, -length / 2.0), inertia=inertia,
                length=float(length), radius=float(radius), **kw)


@dataclass(frozen=True)
class Body:
    """An immutable kinematic tree (links in topological order) with world settings.

    Attributes:
        links: tuple of :class:`Link`, each parent before its children.
        gravity: world gravity vector (3,), m/s²; default zero.
        damping: viscous joint damping c (torque −c·v), scalar, default zero.
        tip_link, tip_point: the end effector, a point in a link's frame.
    """

    links: tuple
    gravity: tuple = (0.0, 0.0, 0.0)
    damping: float = 0.0
    tip_link: int = -1
    tip_point: tuple = (0.0, 0.0, 0.0)
    name: str = "body"
    _slices: tuple = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        for i, link in enumerate(self.links):
            if not -1 <= link.parent < i:
                raise ValueError(f"link {link.name!r}: parent index {link.parent} must "
                                 f"name an earlier link (links are in topological order)")
        if self.damping < 0:
            raise ValueError(f"damping must be non-negative, got {self.damping}")
        slices, start = [], 0
        for link in self.links:
            slices.append(slice(start, start + link.dof))
            start += link.dof
        object.__setattr__(self, "_slices", tuple(slices))

    @property
    def nv(self) -> int:
        """Number of coordinates (= velocities, = torques)."""
        return sum(link.dof for link in self.links)

    @property
    def blocks(self) -> list[int]:
        """Sizes of the joints' coordinate blocks, e.g. [3, 1, 3] for the arm."""
        return [link.dof for link in self.links if link.dof]

    def slice(self, i: int) -> slice:
        """Coordinates of link i's joint within ν."""
        return self._slices[i]

    def with_(self, **changes) -> Body:
        """A copy with some attributes replaced (bodies are immutable)."""
        return replace(self, **changes)

    def to_dict(self) -> dict:
        """Plain-JSON description of the whole tree (the basis.json ``body``)::

            {"name", "links": [Link.to_dict(), ...], "gravity": [3], "damping": c,
             "tip": {"link": i, "point": [3]}}

        :func:`from_dict` inverts it exactly (JSON writes floats by their repr)."""
        return {"name": self.name, "links": [link.to_dict() for link in self.links],
                "gravity": _floats(self.gravity), "damping": float(self.damping),
                "tip": {"link": int(self.tip_link), "point": _floats(self.tip_point)}}


ARM_DEFAULTS = {
    "lengths": [0.30, 0.27, 0.19],
    "masses": [2.0, 1.2, 0.45],
    "radii": [0.04, 0.035, 0.03],
    "gravity": [0.0, 0.0, 0.0],
    "damping": 0.0,
    "offsets": [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
}


def arm(lengths=None, masses=None, radii=None, gravity=None, damping=None,
        offsets=None) -> Body:
    """The thesis' 7-DOF arm: shoulder ball, elbow hinge about local x, wrist ball.

    At rest (ν = 0) the arm hangs along −z from the shoulder at the world origin.
    Reading it anatomically: this is a LEFT arm of a character facing −y (its left
    is +x). Negative shoulder x-rotation flexes the arm forward and up (−π/2 holds it
    horizontal, pointing forward along −y); negative shoulder y-rotation abducts it
    out to the side (+x); negative elbow angle flexes the elbow.
    """
    p = dict(ARM_DEFAULTS)
    for key, val in dict(lengths=lengths, masses=masses, radii=radii, gravity=gravity,
                         damping=damping, offsets=offsets).items():
        if val is not None:
            p[key] = val
    for key in ("lengths", "masses", "radii", "offsets"):
        if len(p[key]) != 3:
            raise ValueError(f"arm: {key} needs 3 entries (upper arm, forearm, hand), "
                             f"got {len(p[key])}")
    if len(p["gravity"]) != 3:
        raise ValueError("arm: gravity must be a 3-vector")
    L, m, r, off = p["lengths"], p["masses"], p["radii"], p["offsets"]
    links = (
        cylinder_link("upper_arm", -1, "ball", (0, 0, 0), L[0], m[0], r[0],
                      offset=tuple(off[0])),
        cylinder_link("forearm", 0, "hinge", (0, 0, -L[0]), L[1], m[1], r[1],
                      offset=tuple(off[1]), axis=(1.0, 0.0, 0.0)),
        cylinder_link("hand", 1, "ball", (0, 0, -L[1]), L[2], m[2], r[2],
                      offset=tuple(off[2])),
    )
    return Body(links=links, gravity=tuple(map(float, p["gravity"])),
                damping=float(p["damping"]), tip_link=2, tip_point=(0.0, 0.0, -L[2]),
                name="arm")


def chain(n: int = 2, joint: str = "hinge", length: float = 0.3, mass: float = 1.0,
          radius: float = 0.03, gravity=(0.0, 0.0, 0.0), damping: float = 0.0) -> Body:
    """A serial chain of n identical cylinders (planar when joint="hinge")."""
    links = tuple(cylinder_link(f"link{i}", i - 1, joint, (0, 0, -length if i else 0.0),
                                length, mass, radius) for i in range(n))
    return Body(links=links, gravity=tuple(gravity), damping=damping, tip_link=n - 1,
                tip_point=(0.0, 0.0, -length), name=f"chain{n}")


PRESETS = {"arm": arm, "chain": chain}


def _tuples(x):
    """Config lists (nested) as tuples, other values unchanged."""
    return tuple(map(_tuples, x)) if isinstance(x, list) else x


def _link_from_config(spec: dict, i: int) -> Link:
    spec = {k: _tuples(v) for k, v in spec.items()}
    spec.setdefault("name", f"link{i}")
    try:
        if "inertia" in spec:
            return Link(**{"com": (0.0, 0.0, 0.0), **spec})
        return cylinder_link(spec.pop("name"), spec.pop("parent"), spec.pop("joint"),
                             spec.pop("origin"), spec.pop("length"), spec.pop("mass"),
                             spec.pop("radius"), **spec)
    except KeyError as err:
        raise ValueError(f"body.links[{i}]: missing key {err}") from None
    except TypeError as err:
        raise ValueError(f"body.links[{i}]: {err}") from None


def from_config(cfg: dict | None) -> Body:
    """Build a body from a config mapping.

    Either ``{"preset": "arm", ...overrides}`` (the default when ``cfg`` is empty), or a
    tree: ``{"links": [...], "tip": {"link": i, "point": [x, y, z]}, "gravity", "damping"}``
    whose links are cylinders ``{"name", "parent", "joint", "origin", "length", "mass",
    "radius", "offset"?, "axis"?}`` or, when they give ``inertia`` (3×3 about the centre of
    mass), general links ``{"name", "parent", "joint", "origin", "mass", "com"?, "inertia",
    "offset"?, "axis"?}``. The tip defaults to the end of the last cylinder (its origin
    for a general link).
    """
    cfg = dict(cfg or {})
    if "links" in cfg:
        links = tuple(_link_from_config(spec, i) for i, spec in enumerate(cfg.pop("links")))
        end = links[-1].length
        tip = cfg.pop("tip", {"link": len(links) - 1,
                              "point": [0, 0, -end if math.isfinite(end) else 0.0]})
        body = Body(links=links, gravity=tuple(cfg.pop("gravity", (0, 0, 0))),
                    damping=float(cfg.pop("damping", 0.0)), tip_link=int(tip["link"]),
                    tip_point=tuple(tip["point"]), name=cfg.pop("name", "tree"))
        if cfg:
            raise ValueError(f"body: unknown keys {sorted(cfg)}")
        return body
    preset = cfg.pop("preset", "arm")
    if preset not in PRESETS:
        raise ValueError(f"body.preset: unknown preset {preset!r} (known: {sorted(PRESETS)})")
    try:
        return PRESETS[preset](**cfg)
    except TypeError as err:
        raise ValueError(f"body: {err}") from None


def from_dict(doc) -> Body:
    """The body of a :meth:`Body.to_dict` document (its exact inverse).

    Every key is required and no other is accepted; numbers must be finite JSON numbers
    (length and radius may be null). Raises ValueError naming the link and key at fault.
    """
    _require_keys(doc, BODY_KEYS, "body")
    if not isinstance(doc["links"], list) or not doc["links"]:
        raise ValueError(f"body.links: expected a non-empty list, got {json_kind(doc['links'])}")
    links = tuple(_link_from_dict(spec, i) for i, spec in enumerate(doc["links"]))
    tip = doc["tip"]
    _require_keys(tip, ("link", "point"), "body.tip")
    tip_link = _json_int(tip["link"], "body.tip.link")
    if not -len(links) <= tip_link < len(links):
        raise ValueError(f"body.tip.link: {tip_link} is not a link index (the body has "
                         f"{len(links)} links)")
    return Body(links=links, gravity=tuple(json_numbers(doc["gravity"], (3,), "body.gravity")),
                damping=json_numbers(doc["damping"], (), "body.damping"), tip_link=tip_link,
                tip_point=tuple(json_numbers(tip["point"], (3,), "body.tip.point")),
                name=_json_str(doc["name"], "body.name"))


def _link_from_dict(spec, i: int) -> Link:
    where = f"body.links[{i}]"
    if isinstance(spec, dict) and isinstance(spec.get("name"), str):
        where = f"{where} ({spec['name']!r})"
    _require_keys(spec, LINK_KEYS, where)
    name = _json_str(spec["name"], f"{where}.name")
    vectors = {k: tuple(json_numbers(spec[k], (3,), f"{where}.{k}"))
               for k in ("origin", "offset", "axis", "com")}
    sizes = {k: json_numbers(spec[k], (), f"{where}.{k}")
             for k in ("length", "radius") if spec[k] is not None}
    inertia = tuple(map(tuple, json_numbers(spec["inertia"], (3, 3), f"{where}.inertia")))
    return Link(name=name, parent=_json_int(spec["parent"], f"{where}.parent"),
                joint=_json_str(spec["joint"], f"{where}.joint"),
                mass=json_numbers(spec["mass"], (), f"{where}.mass"), inertia=inertia,
                **vectors, **sizes)


def _require_keys(doc, keys: Sequence[str], where: str) -> None:
    if not isinstance(doc, dict):
        raise ValueError(f"{where}: expected an object, got {json_kind(doc)}")
    missing = [k for k in keys if k not in doc]
    if missing:
        raise ValueError(f"{where}: missing key {missing[0]!r}")
    unknown = sorted(set(doc) - set(keys))
    if unknown:
        raise ValueError(f"{where}: unknown key {unknown[0]!r}")


def _json_str(x, where: str) -> str:
    if not isinstance(x, str):
        raise ValueError(f"{where}: expected a string, got {json_kind(x)}")
    return x


def _json_int(x, where: str) -> int:
    if isinstance(x, bool) or not isinstance(x, int):
        raise ValueError(f"{where}: expected an integer, got {json_kind(x)}")
    return x


def json_numbers(x, shape: Sequence[int], where: str):
    """x checked to be nested JSON lists of the given shape holding finite numbers:
    a float for shape (), else nested lists of floats. ValueError naming ``where`` (with
    the index at fault) otherwise."""
    if not shape:
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            raise ValueError(f"{where}: expected a number, got {json_kind(x)}")
        try:
            v = float(x)
        except OverflowError:
            v = math.inf
        if not math.isfinite(v):
            raise ValueError(f"{where}: expected a finite number, got {json_kind(x)}")
        return v
    if not isinstance(x, list) or len(x) != shape[0]:
        raise ValueError(f"{where}: expected a list of {shape[0]}, got {json_kind(x)}")
    return [json_numbers(e, shape[1:], f"{where}[{k}]") for k, e in enumerate(x)]


def json_kind(x) -> str:
    """A short description of a parsed JSON value for error messages."""
    if isinstance(x, list):
        return f"a list of {len(x)}"
    if isinstance(x, dict):
        return "an object"
    if isinstance(x, str):
        return "a string"
    if x is None or isinstance(x, bool):
        return json.dumps(x)
    if isinstance(x, int) and x.bit_length() > 64:
        return "an integer too large"
    return repr(x)
