"""Kinematic trees of rigid links: an immutable model, presets and a config reader.

A body is a tree of links. Link ``i`` hangs from link ``parent`` (or the fixed base
when ``parent`` is -1) through a joint whose frame sits at ``origin`` in the parent
frame, turned by a fixed zero orientation ``R0``. The child frame relative to the
parent is then

    R = R0 · exp([v]×)          ball joint, v ∈ R³ the rotation vector (|v| ≤ π)
    R = R0 · Rot(axis, θ)       hinge joint, θ ∈ R about a unit axis of the child frame
    R = R0                      fixed joint

Coordinates ν stack the joints' v and θ in link order (ball 3, hinge 1, fixed 0).
Velocities use the same layout: a ball joint's velocity is the child's angular
velocity relative to its parent expressed in the child frame (Pinocchio's spherical
convention), a hinge's is θ̇; torques are the dual quantities (power = τ·v).

The default body is the thesis' arm: shoulder (ball) → upper arm → elbow (hinge
about the forearm's local x) → forearm → wrist (ball) → hand, hanging along −z at
rest, world z up, gravity off.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

JOINT_DOFS = {"ball": 3, "hinge": 1, "fixed": 0}


@dataclass(frozen=True)
class Link:
    """One rigid link and the joint that moves it.

    Attributes:
        name: link name.
        parent: index of the parent link, -1 for the fixed base.
        joint: "ball", "hinge" or "fixed".
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
        if not self.mass > 0:
            raise ValueError(f"link {self.name!r}: mass must be positive, got {self.mass}")
        inertia = np.asarray(self.inertia, dtype=float)
        if inertia.shape != (3, 3) or not np.allclose(inertia, inertia.T):
            raise ValueError(f"link {self.name!r}: inertia must be a symmetric 3x3 matrix")
        if np.linalg.eigvalsh(inertia).min() < 0:
            raise ValueError(f"link {self.name!r}: inertia must be positive semi-definite")
        if self.joint == "hinge":
            axis = np.asarray(self.axis, dtype=float)
            if axis.shape != (3,) or not np.isclose(np.linalg.norm(axis), 1.0):
                raise ValueError(f"link {self.name!r}: hinge axis must be a unit 3-vector")

    @property
    def dof(self) -> int:
        return JOINT_DOFS[self.joint]


def cylinder_link(name: str, parent: int, joint: str, origin: Sequence[float],
                  length: float, mass: float, radius: float, **kw) -> Link:
    """A uniform solid cylinder along the link's local −z, centre of mass at mid-length.

    Inertia about the centre: Ixx = Iyy = m(3r² + L²)/12, Izz = m r²/2.
    """
    ixx = mass * (3 * radius**2 + length**2) / 12.0
    izz = mass * radius**2 / 2.0
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

    def with_(self, **changes) -> "Body":
        """A copy with some attributes replaced (bodies are immutable)."""
        return replace(self, **changes)

    @property
    def summary(self) -> dict:
        """Plain-JSON description of a chain of cylinder links (the basis.json ``body``)."""
        out = {"lengths": [l.length for l in self.links],
               "masses": [l.mass for l in self.links],
               "radii": [l.radius for l in self.links],
               "gravity": list(self.gravity), "damping": self.damping}
        offsets = [list(l.offset) for l in self.links]
        if any(any(o) for o in offsets):
            out["offsets"] = offsets
        return out


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


def from_config(cfg: dict | None) -> Body:
    """Build a body from a config mapping.

    Either ``{"preset": "arm", ...overrides}`` (the default when ``cfg`` is empty), or a
    tree: ``{"links": [{"name", "parent", "joint", "origin", "length", "mass", "radius",
    "offset"?, "axis"?}, ...], "tip": {"link": i, "point": [x, y, z]}, "gravity", "damping"}``.
    """
    cfg = dict(cfg or {})
    if "links" in cfg:
        links = []
        for i, spec in enumerate(cfg.pop("links")):
            spec = dict(spec)
            try:
                links.append(cylinder_link(
                    spec.pop("name", f"link{i}"), spec.pop("parent"), spec.pop("joint"),
                    spec.pop("origin"), spec.pop("length"), spec.pop("mass"),
                    spec.pop("radius"),
                    **{k: tuple(v) if isinstance(v, list) else v for k, v in spec.items()}))
            except KeyError as err:
                raise ValueError(f"body.links[{i}]: missing key {err}") from None
            except TypeError as err:
                raise ValueError(f"body.links[{i}]: {err}") from None
        tip = cfg.pop("tip", {"link": len(links) - 1, "point": [0, 0, -links[-1].length]})
        body = Body(links=tuple(links), gravity=tuple(cfg.pop("gravity", (0, 0, 0))),
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
