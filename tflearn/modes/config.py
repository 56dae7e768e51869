"""The ``tflearn modes CONFIG`` config: typed sections (:class:`tflearn.config.Section`),
read by :func:`tflearn.config.load` with ``schema=ModesConfig`` (defaults ← YAML ← dotted
``key=value`` overrides; every failure a :class:`~tflearn.config.ConfigError` naming the
key). See configs/modes/*.yaml and docs/modes.md.
"""
from __future__ import annotations

from typing import Literal, Optional, Union

from pydantic import Field

from ..config import BodySection, Section


class StiffnessSection(Section):
    uniform: float = Field(1.0, ge=0)            # N·m/rad on every joint coordinate
    scale: dict[str, float] = {}                  # joint-name glob → factor ("spine*": 10)
    matrix: Optional[list[list[float]]] = None    # nv×nv; replaces uniform and scale


class ConstraintSection(Section):
    link: str                                     # a point of this link ...
    point: list[float] = [0.0, 0.0, 0.0]          # (link frame, m)
    to: Optional[str] = None                      # ... held to this link's to_point (None: the world)
    to_point: list[float] = [0.0, 0.0, 0.0]
    weld: bool = False                            # hold the orientation too
    stiffness: float = Field(0.0, ge=0)           # N·m/rad spring on the links' relative rotation


class DriveSection(Section):                      # one term of the mode-driven motion
    mode: int = Field(ge=0)                       # 0-based, lowest first, rigid modes included
    amplitude: float = 0.0                        # α, rad of the shape's most-moving joint
    frequency: Optional[float] = Field(None, ge=0)  # f̃ (Hz); None: the mode's own
    phase: float = 0.0                            # γ (rad)
    offset: float = 0.0                           # β, likewise


class AnimationSection(Section):                  # each mode's own animation
    modes: int = Field(8, ge=1)                   # the lowest non-rigid modes animated and drawn
    amplitude: float = Field(0.3, gt=0)           # rad: the largest joint excursion
    periods: float = Field(2.0, gt=0)
    samples: int = Field(32, ge=4)                # per period


class MotionSection(Section):                     # the mode combination (paper eq. 4)
    drives: list[DriveSection] = []
    duration: float = Field(2.0, gt=0)            # s
    rate: float = Field(100.0, gt=0)              # samples per second
    limits: dict[str, list[float]] = {}           # link → [lower, upper] rad, per coordinate
    soft: float = Field(0.1, gt=0)                # Δθ_soft (rad)
    dynamic: bool = True                          # also follow it with the PD controller
    damping: float = Field(0.0, ge=0)             # c of the PD controller (N·m·s/rad)


class SkeletonSection(Section):                   # a body from a BVH hierarchy (tflearn.mocap.skeleton)
    file: str                                     # .bvh (relative to the working folder)
    mass: float = Field(70.0, gt=0)               # total body mass, kg
    scale: Optional[float] = Field(None, gt=0)    # metres per file unit; None: tflearn.mocap.bvh's guess


class ModesLogSection(Section):
    tensorboard: bool = True


class ModesConfig(Section):
    """The modal-analysis config (``tflearn modes CONFIG``)."""

    body: BodySection = {"preset": "arm"}
    skeleton: Optional[SkeletonSection] = None    # replaces body when given
    pose: Union[list[float], dict[str, list[float]], None] = None   # θ₀; None: zeros
    stiffness: StiffnessSection = StiffnessSection()
    constraints: list[ConstraintSection] = []
    chart: Literal["tangent", "rotvec"] = "tangent"
    floating: bool = False                        # a free base: six rigid modes come first
    table: int = Field(12, ge=1)                  # modes printed
    animation: AnimationSection = AnimationSection()
    motion: MotionSection = MotionSection()
    out: str = "runs/modes"
    log: ModesLogSection = ModesLogSection()
