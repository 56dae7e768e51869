"""Retargeting a BVH skeleton's arm onto the 7-DOF arm (:func:`tflearn.physics.body.arm`).

Frames. The model's base is the performer's chest, its origin at the shoulder joint:

    F_b = W_chest C_b,   C_b = [left | back | up] (the chest's anatomical axes in its own
                          local coordinates, from the :class:`ArmMap`), x_b = x_shoulder,

so the model's world is x = left, y = back, z = up (the character faces −y), as in
docs/model.md. Every arm segment k (upper arm, forearm, hand) gets the model frame
F_k = W_k C_k, C_k = [h⊥ | −b × h⊥ | −b] with b the bone's direction in the segment's
local frame (the child joint's OFFSET; the hand uses the forearm's) and h the elbow's
flexion axis (declared by the map, or fitted to the clip: :func:`flexion_axis`), so the bone runs
along the model's −z and the hinge is the model's x. Calibration: the neutral pose —
upper arm hanging along −up, elbow axis pointing left, forearm and hand in line — is
the model's rest; BVH zero rotations play no part (the Bandai skeleton's zero pose
folds every bone onto one line, CMU's is a T-pose).

Coordinates (the clavicle is folded into the shoulder, whose base is the chest):

    shoulder  R_s = R0ᵀ F_bᵀ F_ua,          v_s = log R_s
    elbow     R_e = F_uaᵀ F_fa ≈ Rx(θ),     θ = atan2(d_y, −d_z),  d = R_e (0, 0, −1)
    wrist     R_w = Rx(θ)ᵀ R_e F_faᵀ F_hand, v_w = log R_w

θ projects the forearm's direction onto the hinge plane (the angle lost, asin |d_x|, is
reported); what the hinge cannot hold (forearm twist) is carried into the wrist, so the
hand's orientation is kept exactly. R0 (the shoulder's zero orientation, the arm's
``offsets[0]``) is the chart: one rotation shared by a set of clips, their chordal mean
shoulder rotation, so that ‖v_s‖ stays well below π where the principal rotation
vector wraps (:func:`shoulder_zero`).

Sides. The model arm is anatomically a left arm; read with the same coordinates it is
also a right arm (the body is mirror-symmetric: cylinders on the z axis, hinge about x),
whose abduction is a positive y-rotation. ``mirror`` reflects a movement to the other
side (x → −x): R → S R S, S = diag(−1, 1, 1), i.e. rotation vectors (x, y, z) →
(x, −y, −z), hinge angles unchanged; a left arm mirrored moves like a right arm.

Lengths in metres from the skeleton: upper arm |OFFSET(elbow)|, forearm |OFFSET(wrist)|;
the hand, whose BVH bone ends at a short End Site (Bandai 5 cm, CMU 3.5 cm to the finger
base) is Winter's proportion of the arm, 0.108/(0.186 + 0.146) of upper arm + forearm.
Masses and radii are the arm preset's.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from ..motions.motion import Motion
from ..physics import dynamics
from ..physics.body import Body, arm
from . import names
from .bvh import CM, BVHError, Skeleton, channel_values, read

HAND_RATIO = 0.108 / (0.186 + 0.146)     # Winter (2009): hand / (upper arm + forearm)
S = np.diag([-1.0, 1.0, 1.0])


@dataclass(frozen=True)
class ArmMap:
    """Which joints of a skeleton are the arm, and the chest's anatomical axes.

    Attributes:
        chest, shoulder, elbow, wrist: joint names (shoulder = the upper arm's joint).
        up, left: the chest's up and left directions in its local frame (3,).
        hinge: the elbow's flexion axis in its local frame (3,), oriented so that a
            negative angle flexes; None: the axis that best holds the clip's elbow
            (:func:`flexion_axis`).
    """

    chest: str
    shoulder: str
    elbow: str
    wrist: str
    up: tuple
    left: tuple
    hinge: Optional[tuple] = None

    @property
    def names(self) -> tuple:
        return (self.chest, self.shoulder, self.elbow, self.wrist)


def _bandai(s: str) -> ArmMap:
    return ArmMap("Chest", f"UpperArm_{s}", f"LowerArm_{s}", f"Hand_{s}",
                  up=(1.0, 0.0, 0.0), left=(0.0, 0.0, 1.0), hinge=(0.0, 1.0, 0.0))


def _cmu(s: str) -> ArmMap:
    return ArmMap("Spine1", f"{s}Arm", f"{s}ForeArm", f"{s}Hand",
                  up=(0.0, 1.0, 0.0), left=(1.0, 0.0, 0.0), hinge=None)


#: The arm as tflearn writes it alone (:func:`arm_skeleton`): links' names, bones along −z.
ARM_ONLY = ArmMap("chest", "upper_arm", "forearm", "hand", up=(0.0, 0.0, 1.0),
                  left=(1.0, 0.0, 0.0), hinge=(1.0, 0.0, 0.0))
#: Built-in maps: skeleton → side → map (the CMU and Bandai skeletons of the data README).
MAPS = {"bandai": {"right": _bandai("R"), "left": _bandai("L")},
        "cmu": {"right": _cmu("Right"), "left": _cmu("Left")},
        "tflearn": {"right": ARM_ONLY, "left": ARM_ONLY}}


def map_from_dict(doc, where: str) -> ArmMap:
    """An :class:`ArmMap` from a mapping {chest, shoulder, elbow, wrist: joint names,
    up, left: 3-vectors, hinge: a 3-vector or null} (a YAML map file); BVHError naming
    ``where`` for a missing or unknown key or a bad value."""
    keys = ("chest", "shoulder", "elbow", "wrist", "up", "left", "hinge")
    if not isinstance(doc, dict) or set(doc) - set(keys) or set(keys[:6]) - set(doc):
        raise BVHError(where, f"an arm map needs the keys {', '.join(keys)} (hinge may be null)")

    def vec(key):
        x = doc[key]
        if not (isinstance(x, list) and len(x) == 3 and all(isinstance(c, (int, float)) for c in x)):
            raise BVHError(where, f"arm map: {key} must be 3 numbers, got {x!r}")
        return tuple(map(float, x))

    for key in keys[:4]:
        if not isinstance(doc[key], str):
            raise BVHError(where, f"arm map: {key} must be a joint name, got {doc[key]!r}")
    return ArmMap(*(doc[k] for k in keys[:4]), up=vec("up"), left=vec("left"),
                  hinge=None if doc.get("hinge") is None else vec("hinge"))


def find_map(skel: Skeleton, side: str) -> ArmMap:
    """The built-in map of ``side`` whose joints the skeleton has, else the map read from
    its joint names and rest offsets (:func:`infer_map`); BVHError, naming the joints,
    if neither fits."""
    if side not in ("right", "left"):
        raise ValueError(f"side must be 'right' or 'left', got {side!r}")
    for maps in MAPS.values():
        if set(maps[side].names) <= set(skel.joints):
            return maps[side]
    try:
        return infer_map(skel, side)
    except BVHError as e:
        raise BVHError(skel.source, f"no built-in arm map fits this skeleton (the {side} arm of "
                                  f"{' or '.join(MAPS)} needs joints "
                                  f"{' / '.join(', '.join(m[side].names) for m in MAPS.values())}) "
                                  f"and none can be read from its names: {e.problem}; give one with "
                                  f"--map; its joints: {', '.join(skel.joints)}") from None


def infer_map(skel: Skeleton, side: str) -> ArmMap:
    """The ``side`` arm's map read from a skeleton's joint names and rest offsets, for
    skeletons no built-in map knows (Mixamo's ``mixamorig:RightHand``, 3ds Max's
    ``Bip01 R Hand``, …): the wrist is the one joint of that side classed as a hand
    whose parent is a forearm and grandparent an upper arm (the elbow and shoulder;
    :func:`tflearn.mocap.names.arm_chain`),
    the chest the nearest joint both shoulders descend from. In the zero pose every
    joint's frame is the root's, so the chest's axes in its own frame are directions
    between rest positions (OFFSETs summed from the root): up, from the chest to the
    farthest head or neck joint below it; left, between the first joints of the two
    arms' chains from the chest that lie apart (the clavicles, or the shoulders where
    the clavicles sit at the chest). The hinge is fitted to each clip. A constant error
    in these axes turns the base frame, which the shoulder's chart (its chordal mean,
    :func:`shoulder_zero`) takes back: the coordinates do not depend on it."""
    try:
        arms = {s: names.arm_chain(skel.joints, skel.parents, s) for s in ("right", "left")}
    except ValueError as e:
        raise BVHError(skel.source, str(e)) from None
    chest = _common_ancestor(skel, arms["right"][0], arms["left"][0])
    rest = np.zeros((len(skel.joints), 3))
    for j, p in enumerate(skel.parents):
        rest[j] = skel.offsets[j] + (rest[p] if p >= 0 else 0.0)
    below = _descendants(skel, chest)
    heads = [j for j in below if names.segment_class(skel.joints[j]) == "head"]
    if not heads:
        raise BVHError(skel.source, f"no head or neck joint below the chest {skel.joints[chest]!r}")
    up = rest[max(heads, key=lambda j: np.linalg.norm(rest[j] - rest[chest]))] - rest[chest]
    paths = [_path_from(skel, chest, arms[s][0]) for s in ("left", "right")]
    apart = [rest[a] - rest[b] for a, b in zip(*paths) if np.linalg.norm(rest[a] - rest[b]) > 1e-6]
    if not apart:
        raise BVHError(skel.source, "the two arms' rest positions coincide: no left axis")
    left = apart[0] - (apart[0] @ up) / (up @ up) * up
    if not np.linalg.norm(left) > 1e-3 * np.linalg.norm(apart[0]):
        raise BVHError(skel.source, "the arms lie along the chest-to-head direction: no left axis")
    shoulder, elbow, wrist = arms[side]
    return ArmMap(skel.joints[chest], skel.joints[shoulder], skel.joints[elbow], skel.joints[wrist],
                  up=tuple(map(float, up / np.linalg.norm(up))),
                  left=tuple(map(float, left / np.linalg.norm(left))))


def _ancestors(skel: Skeleton, j: int) -> list:
    """j and its ancestors, j first."""
    out = [j]
    while skel.parents[out[-1]] >= 0:
        out.append(skel.parents[out[-1]])
    return out


def _common_ancestor(skel: Skeleton, a: int, b: int) -> int:
    """The nearest joint that ``a`` and ``b`` both descend from (strictly)."""
    above = set(_ancestors(skel, b)[1:])
    return next(j for j in _ancestors(skel, a)[1:] if j in above)


def _descendants(skel: Skeleton, j: int) -> list:
    """The joints below j (file order: parents before children)."""
    inside = {j}
    for k, p in enumerate(skel.parents):
        if p in inside:
            inside.add(k)
    return sorted(inside - {j})


def _path_from(skel: Skeleton, top: int, j: int) -> list:
    """The joints from ``top``'s child down to j."""
    line = _ancestors(skel, j)
    return line[:line.index(top)][::-1]


def _unit(x, what: str, where: str) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    n = np.linalg.norm(x)
    if not n > 1e-9:
        raise BVHError(where, f"{what} has zero length")
    return x / n


def _frame(bone: np.ndarray, x_axis: np.ndarray) -> np.ndarray:
    """Columns [x⊥, z × x⊥, z] with z = −bone (a unit direction) and x⊥ ⟂ z."""
    z = -bone
    x = x_axis - (x_axis @ z) * z
    x = x / np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def _chain(skel: Skeleton, amap: ArmMap) -> list:
    """Indices of chest, shoulder, elbow, wrist, checked to form one chain."""
    idx = []
    for name in amap.names:
        if name not in skel.joints:
            raise BVHError(skel.source, f"joint {name!r} of the arm map is missing "
                                      f"(joints: {', '.join(skel.joints)})")
        idx.append(skel.index(name))
    for a, b in zip(idx[1:], idx[2:]):
        if skel.parents[b] != a:
            raise BVHError(skel.source, f"joint {skel.joints[b]!r} is not a child of {skel.joints[a]!r}")
    j = skel.parents[idx[1]]
    while j >= 0 and j != idx[0]:
        j = skel.parents[j]
    if j != idx[0]:
        raise BVHError(skel.source, f"joint {amap.shoulder!r} does not descend from {amap.chest!r}")
    return idx


def flexion_axis(skel: Skeleton, elbow: int, wrist: int) -> np.ndarray:
    """The hinge axis h that best holds a clip's elbow: with d_f the forearm's direction
    in the upper arm's frame (frame f) and b the upper arm's bone, h ⟂ b minimises
    Σ_f (h·d_f)² (the smallest right singular vector of the d_f projected off b),
    oriented so that flexion is a negative angle (mean h·(b × d_f) < 0)."""
    b = skel.offsets[elbow] / np.linalg.norm(skel.offsets[elbow])
    d = skel.rotations[:, elbow] @ (skel.offsets[wrist] / np.linalg.norm(skel.offsets[wrist]))
    d_perp = d - (d @ b)[:, None] * b
    h = np.linalg.svd(np.concatenate([d_perp, b[None]]))[2][-1]
    return -h if (np.cross(b, d) @ h).mean() > 0 else h


@dataclass(frozen=True, eq=False)
class ArmFrames:
    """A clip's arm in model frames, before the shoulder chart is chosen.

    base_R (F×3×3), base_x (F×3): the base frame F_b and the shoulder position in the
    BVH world (metres); shoulder (F×3×3) = F_bᵀ F_ua; elbow, wrist (F×3×3) the relative
    model rotations R_e and F_faᵀ F_hand; joints (F×2×3): the BVH's elbow and wrist
    positions in the base frame; lengths (3,) metres.
    """

    skeleton: Skeleton
    side: str
    mirror: bool
    base_R: np.ndarray
    base_x: np.ndarray
    shoulder: np.ndarray
    elbow: np.ndarray
    wrist: np.ndarray
    joints: np.ndarray
    lengths: tuple


def arm_frames(skel: Skeleton, side: str = "right", amap: Optional[ArmMap] = None,
               mirror: bool = False) -> ArmFrames:
    """The clip's arm in model frames (see the module doc); BVHError for a missing
    joint, a broken chain or a zero-length bone."""
    amap = find_map(skel, side) if amap is None else amap
    c, s, e, w = _chain(skel, amap)
    L_ua, L_fa = (np.linalg.norm(skel.offsets[k]) for k in (e, w))
    for k, L in ((e, L_ua), (w, L_fa)):
        if not L > 1e-6:
            raise BVHError(skel.source, f"joint {skel.joints[k]!r}: zero-length bone from "
                                      f"{skel.joints[skel.parents[k]]!r}")
    up = _unit(amap.up, "the map's up axis", skel.source)
    left = _unit(amap.left, "the map's left axis", skel.source)
    Cb = _frame(-up, left)        # columns: left⊥, back = up × left, up
    hinge = flexion_axis(skel, e, w) if amap.hinge is None else _unit(amap.hinge, "hinge", skel.source)
    C_ua = _frame(skel.offsets[e] / L_ua, hinge)
    C_fa = _frame(skel.offsets[w] / L_fa, hinge)
    W, x = skel.world()
    Fb = W[:, c] @ Cb
    F_ua, F_fa, F_hd = W[:, s] @ C_ua, W[:, e] @ C_fa, W[:, w] @ C_fa
    T = lambda A: np.swapaxes(A, -1, -2)
    rel = np.einsum("fba,fjb->fja", Fb, x[:, [e, w]] - x[:, s, None])    # F_bᵀ (x − x_s)
    sh, el, wr = T(Fb) @ F_ua, T(F_ua) @ F_fa, T(F_fa) @ F_hd
    if mirror:
        sh, el, wr = S @ sh @ S, S @ el @ S, S @ wr @ S
        rel = rel @ S
    lengths = (float(L_ua), float(L_fa), float(HAND_RATIO * (L_ua + L_fa)))
    return ArmFrames(skel, side, mirror, Fb, x[:, s], sh, el, wr, rel, lengths)


def shoulder_zero(frames: list) -> np.ndarray:
    """The shared shoulder zero orientation R0 (rotation vector, 3): the chordal mean
    of the shoulder rotations of all frames of all clips."""
    R = np.concatenate([f.shoulder for f in frames])
    return Rotation.from_matrix(R).mean().as_rotvec()


def performer_arm(frames: ArmFrames, zero: np.ndarray) -> Body:
    """The arm preset with the performer's lengths and the shoulder zero orientation."""
    offsets = [list(map(float, zero)), [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    return arm(lengths=list(frames.lengths), offsets=offsets)


def _kabsch(a: np.ndarray, b: np.ndarray):
    """The rigid motion (R, t) minimising Σ‖R a + t − b‖² over points (N×3)."""
    ca, cb = a.mean(0), b.mean(0)
    U, _, Vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, cb - R @ ca


def coordinates(frames: ArmFrames, zero: np.ndarray):
    """Arm coordinates ν (F×7), the hinge projection's lost angle (F,) and the angle of
    the elbow rotation the hinge cannot hold, |Rx(θ)ᵀ R_e| (F,), in radians."""
    R0 = Rotation.from_rotvec(zero).as_matrix()
    v_s = Rotation.from_matrix(R0.T @ frames.shoulder).as_rotvec()
    d = frames.elbow[:, :, 2] * -1.0                        # R_e (0, 0, −1)
    theta = np.unwrap(np.arctan2(d[:, 1], -d[:, 2]))
    lost = np.arcsin(np.clip(np.abs(d[:, 0]), 0.0, 1.0))
    Rx = Rotation.from_rotvec(theta[:, None] * np.array([1.0, 0.0, 0.0])).as_matrix()
    rest = np.swapaxes(Rx, -1, -2) @ frames.elbow
    v_w = Rotation.from_matrix(rest @ frames.wrist).as_rotvec()
    return np.concatenate([v_s, theta[:, None], v_w], axis=1), lost, Rotation.from_matrix(rest).magnitude()


@dataclass(frozen=True, eq=False)
class Retargeted:
    """One imported clip: the motion of the performer's arm and its report."""

    motion: Motion
    body: Body
    frames: ArmFrames
    report: dict


def torso_report(frames: ArmFrames) -> dict:
    """How far and how fast the base (chest frame at the shoulder) moved over the clip."""
    dt = frames.skeleton.frame_time
    x, R = frames.base_x, frames.base_R
    speed = np.linalg.norm(np.diff(x, axis=0), axis=1) / dt
    turn = Rotation.from_matrix(np.swapaxes(R[:-1], -1, -2) @ R[1:]).magnitude() / dt
    tilt = Rotation.from_matrix(np.swapaxes(R[:1], -1, -2) @ R).magnitude()
    return {"travel_m": float(np.linalg.norm(x - x[0], axis=1).max()),
            "speed_max_m_s": float(speed.max()),
            "rotation_max_deg": float(np.degrees(tilt.max())),
            "angular_speed_max_deg_s": float(np.degrees(turn.max()))}


def retarget(frames: ArmFrames, zero: np.ndarray) -> Retargeted:
    """The clip as a :class:`~tflearn.motions.motion.Motion` of the performer's arm, and its
    report: hinge projection loss (RMS, max, degrees), forearm twist carried into the
    wrist, the largest shoulder angle, the position check (the model's elbow and wrist
    against the BVH's in the base frame, metres, as they are and after the best rigid
    alignment of all frames, whose angle is reported: zero up to the hinge loss), the
    torso's motion."""
    skel = frames.skeleton
    body = performer_arm(frames, zero)
    q, lost, twist = coordinates(frames, zero)
    t = np.arange(skel.frames) * skel.frame_time
    motion = Motion(skel.name + ("_mirrored" if frames.mirror else ""), t, q, None, body)
    fk = dynamics.forward_kinematics(body, torch.from_numpy(q)).numpy()[:, 1:3]
    a, b = fk.reshape(-1, 3), frames.joints.reshape(-1, 3)
    R, tr = _kabsch(a, b)
    err = np.linalg.norm(a @ R.T + tr - b, axis=1).reshape(-1, 2)
    raw = np.linalg.norm(fk - frames.joints, axis=-1)
    report = {
        "clip": skel.name, "side": frames.side, "mirrored": frames.mirror,
        "frames": skel.frames, "fps": 1.0 / skel.frame_time,
        "lengths_m": list(frames.lengths),
        "hinge_lost_deg": {"rms": float(np.degrees(np.sqrt((lost ** 2).mean()))),
                           "max": float(np.degrees(lost.max()))},
        "forearm_twist_deg": {"rms": float(np.degrees(np.sqrt((twist ** 2).mean()))),
                              "max": float(np.degrees(twist.max()))},
        "shoulder_angle_max_deg": float(np.degrees(np.linalg.norm(q[:, :3], axis=1).max())),
        "position_error_m": {"elbow_max": float(raw[:, 0].max()), "wrist_max": float(raw[:, 1].max()),
                             "aligned_elbow_max": float(err[:, 0].max()),
                             "aligned_wrist_max": float(err[:, 1].max()),
                             "alignment_deg": float(np.degrees(Rotation.from_matrix(R).magnitude()))},
        "torso": torso_report(frames),
    }
    return Retargeted(motion, body, frames, report)



# ----------------------------------------------------------------------------------------
# Several clips; writing arm motions back as BVH
# ----------------------------------------------------------------------------------------

class BVHWarning(UserWarning):
    """A BVH file skipped when importing several; the message names it and the problem."""


def read_clips(paths, make: Callable[[Skeleton], ArmFrames] = arm_frames, strict: bool = False) -> list:
    """:class:`ArmFrames` of BVH files and folders (``*.bvh`` in name order), each made
    by ``make`` from its skeleton (default: the right arm, :func:`arm_frames`). A file
    that cannot be read or mapped is skipped with a :class:`BVHWarning` naming it and
    the problem, or, with ``strict``, raises its BVHError; nothing left raises, once:
    the one file's own BVHError, or one naming the paths and every problem."""
    files = []
    for p in map(Path, paths):
        files.extend(sorted(p.glob("*.bvh")) if p.is_dir() else [p])
    out, errors = [], []
    for f in files:
        try:
            out.append(make(read(f)))
        except BVHError as err:
            if strict:
                raise
            errors.append(err)
    if not out:
        if len(errors) == 1:
            raise errors[0]
        raise BVHError(", ".join(map(str, paths)) or "no paths",
                       "no readable BVH clip" + (f" ({'; '.join(map(str, errors))})" if errors else ""))
    for err in errors:
        warnings.warn(f"{err}; skipped", BVHWarning, stacklevel=2)
    return out


def hand_travel(frames: ArmFrames) -> float:
    """The wrist's path length relative to the chest (metres, Σ‖Δx‖ in the base frame)."""
    return float(np.linalg.norm(np.diff(frames.joints[:, 1], axis=0), axis=1).sum())


#: ``moving_arm``: the other arm is taken only when its hand travels this many times further.
BOTH_ARMS = 1.25

#: Each arm's other one.
OTHER = {"right": "left", "left": "right"}


def moving_arm(skel: Skeleton, prefer: str = "right") -> str:
    """The arm of a clip that performs it: the one whose hand travels further relative
    to the chest (:func:`hand_travel`); ``prefer`` unless the other's travel is
    :data:`BOTH_ARMS` times its own (a clip moving both arms alike keeps ``prefer``), or
    ``prefer``'s arm cannot be mapped (built-in maps, :func:`find_map`)."""
    other = OTHER[prefer]
    try:
        own = hand_travel(arm_frames(skel, prefer))
    except BVHError:
        return other
    try:
        far = hand_travel(arm_frames(skel, other))
    except BVHError:
        return prefer
    return other if far > BOTH_ARMS * own else prefer


def retarget_all(frames: list, zero: Optional[np.ndarray] = None) -> list:
    """:func:`retarget` of each clip with one shared shoulder chart (default
    :func:`shoulder_zero` of all of them)."""
    zero = shoulder_zero(frames) if zero is None else np.asarray(zero, dtype=float)
    return [retarget(f, zero) for f in frames]


#: The BVH world of exported arms: X = the model's x (left), Y = z (up), Z = −y (front).
P = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _model_frames(body: Body, q: np.ndarray, mirror: bool):
    """Model rotations shoulder F_bᵀF_ua, forearm F_uaᵀF_fa = Rx(θ), wrist (T×3×3)
    from coordinates (undoing a mirror)."""
    R0 = Rotation.from_rotvec(body.links[0].offset).as_matrix()
    sh = R0 @ Rotation.from_rotvec(q[:, :3]).as_matrix()
    el = Rotation.from_rotvec(q[:, 3:4] * np.array([1.0, 0.0, 0.0])).as_matrix()
    wr = Rotation.from_rotvec(q[:, 4:7]).as_matrix()
    if mirror:
        sh, el, wr = S @ sh @ S, S @ el @ S, S @ wr @ S
    return sh, el, wr


def arm_skeleton(body: Body, t: np.ndarray, q: np.ndarray, name: str = "arm") -> Skeleton:
    """The arm alone as a BVH skeleton (centimetres, Y up: chest root fixed in the
    rotation :data:`P`, joints upper_arm, forearm, hand with Z X Y rotation channels)
    moving through coordinates q (T×7) at times t (uniform)."""
    L = [float(link.length) for link in body.links]
    sh, el, wr = _model_frames(body, q, False)
    T = q.shape[0]
    R = np.stack([np.broadcast_to(P, (T, 3, 3)), sh, el, wr], axis=1)
    offsets = np.array([[0, 0, 0], [0, 0, 0], [0, 0, -L[0]], [0, 0, -L[1]]], dtype=float)
    channels = (("Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation"),
                *(("Zrotation", "Xrotation", "Yrotation"),) * 3)
    skel = Skeleton(name=name, joints=ARM_ONLY.names, parents=(-1, 0, 1, 2), offsets=offsets,
                    channels=channels, end_sites={3: np.array([0.0, 0.0, -L[2]])},
                    frame_time=float(t[1] - t[0]), values=np.zeros((T, 15)), scale=CM,
                    rotations=R, positions=np.broadcast_to(offsets, (T, 4, 3)).copy(), source=name)
    return replace(skel, values=channel_values(skel, skel.rotations, skel.positions))


def replace_arm(frames: ArmFrames, body: Body, t: np.ndarray, q: np.ndarray,
                amap: Optional[ArmMap] = None) -> Skeleton:
    """The clip's skeleton with its arm moved through q (T×7) at times t: the clip's
    frames nearest to t (the rest of the body as recorded), the shoulder, elbow and
    wrist joints' local rotations solved from the model frames (the inverse of
    :func:`arm_frames`; the forearm's twist, which the hinge cannot hold, is in the
    hand), frame time t[1] − t[0]."""
    skel = frames.skeleton
    amap = find_map(skel, frames.side) if amap is None else amap
    c, s, e, w = _chain(skel, amap)
    idx = np.clip(np.rint(t / skel.frame_time).astype(int), 0, skel.frames - 1)
    W, _ = skel.world()
    W = W[idx]
    sh, el, wr = _model_frames(body, q, frames.mirror)
    hinge = flexion_axis(skel, e, w) if amap.hinge is None else _unit(amap.hinge, "hinge", skel.source)
    C_ua = _frame(skel.offsets[e] / np.linalg.norm(skel.offsets[e]), hinge)
    C_fa = _frame(skel.offsets[w] / np.linalg.norm(skel.offsets[w]), hinge)
    F_ua = frames.base_R[idx] @ sh
    F_fa = F_ua @ el
    W_ua, W_fa, W_hd = F_ua @ C_ua.T, F_fa @ C_fa.T, F_fa @ wr @ C_fa.T
    Tr = lambda A: np.swapaxes(A, -1, -2)
    R = skel.rotations[idx].copy()
    R[:, s] = Tr(W[:, skel.parents[s]]) @ W_ua
    R[:, e] = Tr(W_ua) @ W_fa
    R[:, w] = Tr(W_fa) @ W_hd
    pos = skel.positions[idx]
    values = skel.values[idx].copy()
    cols = np.cumsum([0] + [len(ch) for ch in skel.channels])
    new = channel_values(skel, R, pos)
    for j in (s, e, w):
        values[:, cols[j]:cols[j + 1]] = new[:, cols[j]:cols[j + 1]]
    return replace(skel, values=values, frame_time=float(t[1] - t[0]), rotations=R, positions=pos)
