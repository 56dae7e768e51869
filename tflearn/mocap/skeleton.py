"""A whole-body :class:`~tflearn.physics.body.Body` from a BVH hierarchy (:mod:`tflearn.mocap.bvh`), for
modal analysis of any skeleton a user has.

Every BVH joint j becomes link j, moved by a ball joint at its OFFSET in the parent link
(zero orientation: the file's own rest pose, all channels zero); the root's joint is
fixed (give the modes config ``floating: true`` for a free body). Link j carries the
bone from joint j towards its children: the segment d = the mean of its children's
OFFSETs (its End Site's when it has no child), length L = max(|d|, 2 cm).

Masses and inertias (anthropometric table, Winter, *Biomechanics and Motor Control of
Human Movement*, 4th ed. 2009, table 4.1): each bone is classed by its joint's name
(:data:`tflearn.mocap.names.CLASSES`, first match wins, case-insensitive) and, for the
limbs, side (Left/L…/…_L, Right/R…/…_R: :func:`tflearn.mocap.names.side`); a limb
class and side, or the trunk or head as a whole, gets its fraction of the total mass
(:data:`SEGMENTS`), shared among its bones in proportion to their lengths; the masses are
then scaled to sum to the total (a skeleton without, say, hands gives their share to
the rest). A bone's centre of mass is at d/2 and its inertia about it is that of a
segment with radius of gyration ρL transverse to d and 0.4 ρL about d (ρ the class's
radius of gyration about the centre of mass, as a fraction of the segment length).
The trunk's and head's ρ, for bones that split those segments, are ours (0.3).
"""
from __future__ import annotations

import numpy as np

from ..physics.body import Body, Link
from .bvh import Skeleton
from .names import segment_class, side

#: class → (fraction of body mass, per side for limbs; radius of gyration / length).
SEGMENTS = {
    "hand": (0.006, 0.297), "forearm": (0.016, 0.303), "upper_arm": (0.028, 0.322),
    "foot": (0.0145, 0.475), "shank": (0.0465, 0.302), "thigh": (0.100, 0.323),
    "head": (0.081, 0.3), "trunk": (0.497, 0.3),
}
AXIAL = ("trunk", "head")     # one segment each, whatever the side of its bones
MIN_LENGTH = 0.02


def _bones(skel: Skeleton) -> np.ndarray:
    """Segment vector d of every joint (J×3, metres, in its own frame)."""
    J = len(skel.joints)
    d = np.zeros((J, 3))
    for j in range(J):
        kids = [k for k, p in enumerate(skel.parents) if p == j]
        if kids:
            d[j] = np.mean([skel.offsets[k] for k in kids], axis=0)
        elif j in skel.end_sites:
            d[j] = skel.end_sites[j]
    return d


def _inertia(mass: float, d: np.ndarray, length: float, rho: float) -> np.ndarray:
    """m (ρL)² transverse to d, m (0.4ρL)² about d (3×3, link frame)."""
    n = d / np.linalg.norm(d) if np.linalg.norm(d) > 1e-12 else np.array([0.0, 0.0, 1.0])
    it, ia = mass * (rho * length) ** 2, mass * (0.4 * rho * length) ** 2
    return it * np.eye(3) + (ia - it) * np.outer(n, n)


def masses(skel: Skeleton, total: float = 70.0) -> np.ndarray:
    """Mass of every joint's bone (J, kg), summing to ``total`` (see the module)."""
    d = _bones(skel)
    length = np.maximum(np.linalg.norm(d, axis=1), MIN_LENGTH)
    keys = [(c, side(n) if c not in AXIAL else "centre")
            for n, c in ((n, segment_class(n)) for n in skel.joints)]
    m = np.zeros(len(keys))
    for key in set(keys):
        idx = [j for j, k in enumerate(keys) if k == key]
        m[idx] = SEGMENTS[key[0]][0] * length[idx] / length[idx].sum()
    return total * m / m.sum()


def body_from_skeleton(skel: Skeleton, total_mass: float = 70.0) -> Body:
    """The body of a BVH hierarchy (see the module); links named after the joints."""
    if not total_mass > 0:
        raise ValueError(f"skeleton mass must be positive, got {total_mass}")
    d = _bones(skel)
    length = np.maximum(np.linalg.norm(d, axis=1), MIN_LENGTH)
    m = masses(skel, total_mass)
    links = []
    for j, name in enumerate(skel.joints):
        rho = SEGMENTS[segment_class(name)][1]
        inertia = _inertia(m[j], d[j], length[j], rho)
        links.append(Link(name=name, parent=int(skel.parents[j]),
                          joint="fixed" if skel.parents[j] < 0 else "ball",
                          origin=tuple(map(float, skel.offsets[j])), mass=float(m[j]),
                          com=tuple(map(float, d[j] / 2)),
                          inertia=tuple(map(tuple, inertia.tolist()))))
    return Body(links=tuple(links), name=skel.name, tip_link=len(links) - 1,
                tip_point=tuple(map(float, d[-1])))


def rotations(skel: Skeleton, body: Body, q: np.ndarray) -> np.ndarray:
    """BVH local rotations (F×J×3×3) of coordinates q (F×nv) of :func:`body_from_skeleton`'s
    body: exp([ν_j]×) per ball joint, the identity at the root."""
    from scipy.spatial.transform import Rotation
    q = np.atleast_2d(q)
    R = np.broadcast_to(np.eye(3), (q.shape[0], len(skel.joints), 3, 3)).copy()
    for j, link in enumerate(body.links):
        if link.joint == "ball":
            R[:, j] = Rotation.from_rotvec(q[:, body.slice(j)]).as_matrix()
    return R
