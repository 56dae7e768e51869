"""What a BVH joint is, read from its name: its anthropometric class and its side, and
the arm chains of a hierarchy found by them (``mixamorig:RightHand``, ``Bip01 R Hand``,
``Hand_R``, ``hand.l``, ``RightHand`` …). Used to weigh a whole-body skeleton's bones
(:mod:`tflearn.mocap.skeleton`), to read a file's length unit (:mod:`tflearn.mocap.bvh`)
and to map an arm no built-in map knows (:func:`tflearn.mocap.retarget.infer_map`).
"""
from __future__ import annotations

import re

__all__ = ["CLASSES", "arm_chain", "segment_class", "side"]

#: (regular expression on the joint name, class), tried in order.
CLASSES = (
    (r"forearm|lowerarm|elbow", "forearm"),
    (r"hand|finger|thumb|index|wrist", "hand"),
    (r"upperarm|uparm|humerus|(^|_)arm|arm($|_)", "upper_arm"),
    (r"upleg|upperleg|thigh|femur", "thigh"),
    (r"lowerleg|leg|shin|knee|tibia", "shank"),
    (r"foot|toe|ankle", "foot"),
    (r"head|neck", "head"),
)


def _bare(name: str) -> str:
    """A joint name without its namespace (``mixamorig:RightHand`` → ``RightHand``)."""
    return name.rsplit(":", 1)[-1]


def segment_class(name: str) -> str:
    """The anthropometric class of a joint's bone (:data:`CLASSES`; else "trunk")."""
    low = _bare(name).lower()
    for pattern, cls in CLASSES:
        if re.search(pattern, low):
            return cls
    return "trunk"


def side(name: str) -> str:
    """"left", "right" or "centre" from a joint name (LeftArm, LHipJoint, Hand_L, hand.l,
    mixamorig:RightHand, Bip01 R Hand …)."""
    bare = _bare(name)
    for word in ("left", "right"):
        letter = word[0].upper()
        if bare.lower().startswith(word) or re.match(rf"{letter}[A-Z]", bare) or \
                re.search(rf"[_.\s]{letter}$|\s{letter}\s", bare, flags=re.IGNORECASE):
            return word
    return "centre"


def arm_chain(joints, parents, arm_side: str) -> tuple:
    """(shoulder, elbow, wrist) indices of one side's arm: the one joint of that side
    classed as a hand whose parent is a forearm and grandparent an upper arm; ValueError
    saying what was found where there is not exactly one."""
    cls = [segment_class(n) for n in joints]

    def up(j: int, k: int = 1) -> int:
        for _ in range(k):
            j = parents[j] if j >= 0 else -1
        return j
    found = [(up(j, 2), up(j), j) for j, n in enumerate(joints)
             if cls[j] == "hand" and side(n) == arm_side and up(j) >= 0 and cls[up(j)] == "forearm"
             and up(j, 2) >= 0 and cls[up(j, 2)] == "upper_arm"]
    if len(found) != 1:
        raise ValueError(f"{len(found) or 'no'} {arm_side} hand joint(s) below a forearm below an upper arm")
    return found[0]
