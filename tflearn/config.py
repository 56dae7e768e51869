"""Training configuration: typed sections read once, from YAML files plus dotted overrides.

A config is a :class:`Config` (pydantic models, frozen, strict: no key outside the
schema, no value of another type). It is built from the defaults below ← a YAML file ←
``key=value`` overrides with dotted keys (``solver.em.steps=200``; values parsed as YAML
scalars: ``1e-3``, ``true``, ``[1, 2]``). ``body`` is a mapping read by
:func:`tflearn.physics.body.from_config` and is replaced whole, never merged. Every failure is a
:class:`ConfigError` naming the file or override, the key and the problem: an unknown key
with the closest known ones, a bad value with what it must be.
"""
from __future__ import annotations

import copy
import difflib
import re
from pathlib import Path
from typing import Annotated, Any, Literal, Optional, Type, Union

import yaml
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from .errors import InputError

SOLVERS = ("dopri5", "dopri8", "bosh3", "fehlberg2", "adaptive_heun", "euler", "midpoint",
           "heun3", "rk4", "explicit_adams", "implicit_adams")

class Section(BaseModel):
    """A config section: strict types, unknown keys refused, immutable."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)


class ModelSection(Section):
    fields: int = Field(0, ge=0)                 # M; 0 = the smallest M reproducing every motion
    stiffness: Literal["scalar", "diag", "block", "full"] = "diag"
    phases: Literal["fixed", "variable"] = "fixed"   # variable: learned onsets/durations
    # ζ (s): every field's damping D_i = ζ K_i, gated like its stiffness (0: the thesis)
    field_damping: float = Field(0.0, ge=0, allow_inf_nan=False)
    # P: activation sequences, each motion cut into P sub-movement windows (at the slowest
    # minima of its joint speed) on which every field has a pulse weight (0: the thesis)
    windows: int = Field(0, ge=0)
    # windows per second instead (> 0): P = ⌈rate × the longest motion's duration⌉, and
    # each motion uses ⌈rate × its own duration⌉ of them, the others past its end, inert
    # (tflearn.train.pipeline.sized_windows, fit.targets.submovement_windows; 0: model.windows)
    window_rate: float = Field(0.0, ge=0, allow_inf_nan=False)
    # with window_rate: a motion that path matching leaves unreproduced is cut into twice as
    # many windows and fitted again (NNLS, then shooting), up to this many times, keeping the
    # program simulated closer (tflearn.train.stages.path; P sized for the finest; 0: off)
    finer: int = Field(0, ge=0, le=4)

    @model_validator(mode="after")
    def _finer_needs_a_rate(self):
        if self.finer and not self.window_rate:
            raise ValueError("finer windows are twice model.window_rate's: set model.window_rate too")
        return self


class InitSection(Section):
    candidates: int = Field(48, ge=1)            # multi-start candidates per field added
    stiffness_grid: list[float] = [0.25, 0.5, 1.0, 2.0, 4.0, 8.0]


class EachSection(Section):                     # per-motion growth
    max_fields: int = Field(3, ge=1)
    tol: float = Field(1e-5, ge=0)               # relative torque cost
    # B > 0: motions in blocks of B; a motion first tries the fields found for the motions
    # of the blocks before its own (near-duplicates merged) — NNLS weights, within tol (or
    # reuse_tol) and reproduced by simulation: those fields are its fit — and is searched
    # only if they do not do; 0: every motion searched alone (for many motions of a shared
    # basis)
    reuse: int = Field(0, ge=0)
    # with reuse: the torque cost on the library under which a motion is tried by
    # simulation (null: tol). Simulation is the bar; an own search too may end above tol
    # when a further field gains too little, so a library fit within a few tol often does
    reuse_tol: Optional[float] = Field(None, ge=0)


class EMSection(Section):                       # Levenberg–Marquardt steps per EM refinement
    steps: int = Field(100, ge=0)
    tol: float = Field(1e-6, ge=0)               # stop when a step gains < tol (relative)
    max_step: Optional[float] = Field(None, gt=0)  # trust region: |δθ| ≤ this (rad, log L); None: off


class PathSection(Section):                     # simulation options and path matching
    steps: int = Field(20, ge=0)
    lr: float = Field(0.003, ge=0)
    method: Literal[SOLVERS] = "dopri5"
    rtol: float = Field(1e-7, ge=0)
    atol: float = Field(1e-9, ge=0)
    max_evals: int = Field(20000, ge=1)          # right-hand-side evaluations; past it: failed
    adjoint: bool = False
    velocity_weight: float = Field(0.1, ge=0)
    # each: every motion its own steps (dopri5; compiled where no gradient is carried);
    # shared: the batch stepped together (torchdiffeq)
    batch: Literal["shared", "each"] = "each"
    # the path stage's Adam steps: all = every motion simulated, fields and weights moved;
    # unreproduced = only the motions not reproduced when it starts, their weights only
    # (the fields held, so the reproduced motions stay exactly as they are: for many motions)
    motions: Literal["all", "unreproduced"] = "all"

    def options(self):
        """These settings as :class:`tflearn.simulation.simulate.SimOptions`."""
        from .simulation.simulate import SimOptions
        return SimOptions(method=self.method, rtol=self.rtol, atol=self.atol,
                          max_evals=self.max_evals, adjoint=self.adjoint, batch=self.batch)


class ShootingSection(Section):
    # multiple-shooting Levenberg–Marquardt on each motion's weights (and, with
    # model.phases: variable, its activation timing), the basis fixed
    # (tflearn.fit.shooting): first in the path stage, on the motions not reproduced,
    # and in held-out synthesis; iterations per horizon, 0 = off
    iterations: int = Field(6, ge=0)
    horizon: float = Field(0.25, gt=0)           # the first segments' length (s), doubled to the whole motion
    velocity_weight: float = Field(0.1, ge=0)
    # γ (rad²/m²): the hand tip's distance in the residuals too (0: joints and velocities only)
    tip_weight: float = Field(0.0, ge=0, allow_inf_nan=False)
    # in the per-motion stage, a motion its own fields do not reproduce has those fields
    # (centres, stiffnesses) fitted to its path too, with its weights, before pooling
    fields: bool = True
    # true: after a step that lowers a motion's cost, its Jacobian is updated by Broyden's
    # formula (one simulation) instead of D + 1 differenced copies; differences again at
    # each horizon, after a poorly predicted step, and before a motion is let stop
    broyden: bool = False
    # true: each motion is fitted alone on the fields it has a weight on, its others held
    # at 0 (len(θ) ∝ those fields, not M: for a basis of many fields; in rescue, the new
    # fields its weights start on; not in the per-motion stage, whose fields are its own)
    used: bool = False
    # true: a weight at 0 when shooting starts stays at 0, so a sparse program
    # (solver.layout.sparsity) keeps its support and only its non-zero weights move
    sparse: bool = False
    # a motion with sub-movement windows (model.windows, model.window_rate) longer than
    # this (s) has its window weights fitted one window at a time, each from where its
    # own simulation arrives, with `ahead` windows after it (tflearn.fit.receding): time
    # linear in its length, for whole recorded clips (the horizon, fields, broyden and
    # used settings do not apply to it); shorter ones by horizons doubled up to the whole
    # motion. null: never; 0: every motion with windows
    receding: Optional[float] = Field(None, ge=0, allow_inf_nan=False)
    ahead: int = Field(1, ge=0)

    def options(self, phases: bool):
        """These settings as :class:`tflearn.fit.shooting.ShootingOptions`."""
        from .fit.shooting import ShootingOptions
        return ShootingOptions(horizon=self.horizon, iterations=self.iterations, phases=phases,
                               velocity_weight=self.velocity_weight, tip_weight=self.tip_weight,
                               broyden=self.broyden, used=self.used, sparse=self.sparse,
                               receding=self.receding, ahead=self.ahead)


class PoolSection(Section):
    # joint: every motion's weights solved over every pooled field; own: each motion
    # starts on its own fields only (the union of the per-motion fits, each as it was
    # alone), and a motion may use the other fields once one of its own is eliminated
    sharing: Literal["joint", "own"] = "joint"
    # the pooled EM also stops once a step lowers the mean motion's relative torque cost
    # by less than this (absolute; 0: off). solver.em.tol is relative to the summed cost,
    # which grows with the motions, so with many motions every step passes it: 1e-7
    # (1% of solver.each.tol) stops the refit where it no longer pays (docs/benchmarks.md)
    min_gain: float = Field(0.0, ge=0, allow_inf_nan=False)


class ReduceSection(Section):                   # backward elimination of pooled fields
    # true: each field's removal tried first with every field refitted by EM (one EM of
    # the whole model per field), then with the others held; false: held only (only the
    # motions that used the field are re-solved and simulated: for many motions)
    refit: bool = True
    # e-folds of local error growth along its path (tflearn.fit.stability) a removal may
    # add to any motion it touches; null: removals are judged by simulation alone
    growth: Optional[float] = Field(None, ge=0)
    # with solver.pool.sharing own, a motion that loses one of its fields may draw on its
    # own fields left and on those whose Gaussian exp(−½ dᵀKd) reaches this somewhere on
    # its path (0: on every field left; for a thousand motions, whose every weight solve
    # over every field left costs O(M²): docs/benchmarks.md)
    reach: float = Field(0.0, ge=0, le=1)
    # a held trial's users simulated this many at a time, those whose torque cost the
    # removal raised most first, until one is worse than before (the trial refused, as it
    # would be after simulating them all); 0: all users in one check (for a field that
    # hundreds of motions use and none can lose: docs/benchmarks.md)
    chunk: int = Field(0, ge=0)
    # a held trial that loses at most this many reproduced motions first path-matches
    # them on the smaller basis by multiple shooting (solver.select.shooting iterations),
    # and is judged after: a field whose users need only their weights moved goes; 0: a
    # held trial is judged on its NNLS weights alone
    shoot: int = Field(4, ge=0)
    # true: a field whose removal the held trial refuses, and that nearly coincides with
    # a field left (solver.merge's distance and stiffness: a copy of one field), is tried
    # once more folded into it — that field fitted, free, to the paths of the motions the
    # removal lost and of the users of strongest error growth (solver.select.users), all
    # at once, by multiple shooting — and removed if every motion stays as good
    fold: bool = True


class SelectSection(Section):                   # the shared basis chosen among pooled fields
    # true: the fewest pooled fields that serve every motion, judged by each motion's
    # torque cost (tflearn.fit.select: copies of one field are one where the motions
    # look; docs/model.md); false: near-duplicates merged by distance (solver.merge)
    enabled: bool = True
    # the relative torque cost a motion may gain over its own fit's on the chosen fields
    tol: float = Field(1e-4, ge=0, allow_inf_nan=False)
    # a pooled field is one of a motion's candidates where its Gaussian exp(−½ dᵀKd)
    # reaches this on the motion's path (or it is one of its own), relative to the
    # peak of the motion's weakest own field there
    reach: float = Field(1e-4, ge=0, le=1)
    # with more motions than this, a screen first: the motions in blocks of this many,
    # each block choosing among its own motions' fields, then every motion among the
    # fields some block chose (memory ∝ N, not N·F²); 0: one selection over all
    block: int = Field(100, ge=0)
    # multiple-shooting iterations per horizon (solver.shooting's other settings) for a
    # motion its own fields reproduced and the chosen basis does not, before it gets its
    # own fields back: a restored motion costs fields for good, an iteration only time
    shooting: int = Field(20, ge=0)
    # a motion still lost then has its fewest chosen fields fitted to its path and to the
    # paths of up to this many reproduced motions whose fewest fields share one with them
    # (those these fields alone serve first), all at once, the fields free and shared,
    # before it gets fields of its own; 0: off
    users: int = Field(8, ge=0)


class MergeSection(Section):                    # merge pooled fields that nearly coincide
    distance: float = Field(0.05, ge=0)          # centres closer than this (rad)
    stiffness: float = Field(0.05, ge=0)         # and stiffnesses within this fraction


class SlsqpSection(Section):
    max_iter: int = Field(200, ge=1)             # iterations of the baseline


class Layout(Section):
    # the fields of a spanning layout (tflearn.fit.layout), method layout's and rescue's.
    # cross: 2n fields at ν̄ ± radius e_k | simplex: n + 1 at a regular simplex's vertices |
    # pairs: convergent antagonist pairs, 2n fields each pulling one coordinate, centres
    # within joint space (configs/convergent.yaml) | joints: convergent joint simplices, b + 1
    # fields per joint of b coordinates (n + the joints: 10 on the arm), centres within
    # joint space, block K whatever model.stiffness (not for rescue). The defaults carry
    # recorded, keyframed and reaching motion (docs/model.md)
    shape: Literal["cross", "simplex", "pairs", "joints"] = "simplex"
    radius: float = Field(16.0, gt=0, allow_inf_nan=False)    # centres at ν̄ + radius u_i (rad)
    stiffness: float = Field(0.0625, gt=0, allow_inf_nan=False)  # K = stiffness · diag(m̄) (1/s²)


def _budget_of_joints(section):
    """``fields`` is a budget of the ``joints`` shape; refused with any other."""
    if section.fields is not None and section.shape != "joints":
        raise ValueError(f"fields (a budget of {section.fields}) applies to shape joints, "
                         f"not {section.shape}")
    return section


class LayoutSection(Layout):                    # method layout: fields spanning joint space
    # the stiffness the weights give about the path (tflearn.fit.impedance): the closed
    # loop's natural frequency ω (rad/s; 0: torques only) and the deviation δ (rad) at
    # which a stiffness error weighs as much as a torque error
    frequency: float = Field(0.0, ge=0, allow_inf_nan=False)
    deviation: float = Field(0.1, gt=0, allow_inf_nan=False)
    # shape joints: a budget of fields (null: n + the joints); the joints of most anisotropic
    # inertia take a pair per coordinate instead of their simplex while M stays within it
    fields: Optional[int] = Field(None, ge=2)
    # λ of an ℓ1 term that first sets the least useful weights to 0 (then the others are
    # solved again without it; 0: off): fewer numbers per motion
    sparsity: float = Field(0.0, ge=0, allow_inf_nan=False)

    def impedance(self):
        """These settings as :class:`tflearn.fit.impedance.Impedance`."""
        from .fit.impedance import Impedance
        return Impedance(frequency=self.frequency, deviation=self.deviation, sparsity=self.sparsity)

    _budget = model_validator(mode="after")(_budget_of_joints)

    @model_validator(mode="before")
    @classmethod
    def _moved(cls, doc):
        if isinstance(doc, dict) and "rescue" in doc:
            raise PydanticCustomError("moved", "solver.layout.rescue is now solver.rescue.enabled, "
                                      "with its own layout and shooting settings (solver.rescue)")
        return doc


class RescueSection(Layout):
    # method pipeline: the motions the path stage leaves unreproduced get fields laid out
    # around them (tflearn.fit.layout) added to the basis, their weights by NNLS on those
    # fields, then multiple shooting over the whole basis (solver.shooting's horizon); a
    # motion takes the new program where it reproduces it or comes closer. Its own
    # settings, not the run's: those of configs/mocap.yaml, which carry recorded,
    # keyframed and reaching motion (docs/model.md "Rescue"). Rounds: the motions a round
    # leaves unreproduced get a layout of their own in the next, until all are reproduced
    # or a round improves none
    enabled: bool = True
    shape: Literal["cross", "simplex", "pairs"] = "simplex"          # added to a basis of the run's kind
    rounds: int = Field(2, ge=1)
    iterations: int = Field(6, ge=0)                                 # its shooting's, per horizon
    ridge: float = Field(1e-4, ge=0, allow_inf_nan=False)            # its NNLS' λ (solver.ridge)
    torque_weight: Literal["uniform", "inertia"] = "inertia"         # its NNLS' (solver.torque_weight)
    tip_weight: float = Field(100.0, ge=0, allow_inf_nan=False)      # its shooting's γ
    velocity_weight: float = Field(0.01, ge=0)                       # and β


class HoldSection(Layout):
    # method pipeline: the learned programs held on their paths (tflearn.train.stages.hold;
    # docs/model.md, "Learned programs held on their paths"). Antagonist pairs (the layout's
    # `shape`, `radius`, `stiffness`) join the learned fields, every field damped by
    # `damping` ζ (s), and every motion's weights on all the fields are solved again by one
    # NNLS on its torques and a stiffness about its path (natural frequency `frequency` ω,
    # as solver.layout's). Each motion takes the first of the settings (each of
    # `deviations` δ, stiffest first, with each of `window_rates` sub-movement windows a
    # second) whose program one simulation finds reproducing it. The held model is kept
    # when every motion reproduced before still is. Off by default: M grows by the pairs
    enabled: bool = False
    shape: Literal["cross", "simplex", "pairs", "joints"] = "pairs"
    radius: float = Field(2.0, gt=0, allow_inf_nan=False)
    stiffness: float = Field(0.25, gt=0, allow_inf_nan=False)
    fields: Optional[int] = Field(None, ge=2)      # shape joints: as solver.layout.fields
    _budget = model_validator(mode="after")(_budget_of_joints)
    frequency: float = Field(10.0, gt=0, allow_inf_nan=False)
    damping: float = Field(0.1, ge=0, allow_inf_nan=False)
    deviations: list[Annotated[float, Field(gt=0, allow_inf_nan=False)]] = Field([0.1, 0.02], min_length=1)
    window_rates: list[Annotated[float, Field(gt=0, allow_inf_nan=False)]] = Field([8.0, 16.0], min_length=1)

    def settings(self) -> list:
        """The (window rate, :class:`tflearn.fit.impedance.Impedance`) a motion tries, in order."""
        from .fit.impedance import Impedance
        return [(rate, Impedance(frequency=self.frequency, deviation=d))
                for d in self.deviations for rate in self.window_rates]


class AutoSection(Section):
    # method auto (tflearn.train.choice): each of up to `probes` motions, spread over the
    # data, searched alone on torques (solver.each.max_fields fields, no simulation); the
    # pipeline when at least half reach a relative torque cost ≤ tol (motions a few fields
    # made: ≤ 8.4e-4; keyframed and recorded motion: ≥ 4.2e-3, docs/model.md), else CONVERGENT
    tol: float = Field(2e-3, gt=0, allow_inf_nan=False)
    probes: int = Field(5, ge=1)


class SolverSection(Section):
    # auto: the pipeline or convergent pairs (CONVERGENT), decided from the data (solver.auto)
    # | pipeline | slsqp: the thesis' baseline, SLSQP with numerical derivatives on the
    # torque cost from a seeded random guess (needs model.fields ≥ 1, diag K) | layout:
    # a fixed basis of fields spanning joint space around the motions, weights by
    # NNLS, then path matching (tflearn.fit.layout; for recorded and keyframed motion)
    method: Literal["auto", "pipeline", "slsqp", "layout"] = "auto"
    auto: AutoSection = AutoSection()
    # the torque costs' coordinate weights: uniform (the thesis) | inertia (each joint's
    # torque error over its mean inertia: errors counted by the accelerations they cause)
    torque_weight: Literal["uniform", "inertia"] = "uniform"
    # λ: the layout stage's and held-out synthesis' NNLS of weights on a fixed basis
    # minimise C + λ·mean(diag G)·‖x‖² (tflearn.fit.torque.solve_weights): nearly
    # collinear fields cannot cancel each other with huge weights (0: exact NNLS)
    ridge: float = Field(0.0, ge=0, allow_inf_nan=False)
    init: InitSection = InitSection()
    each: EachSection = EachSection()
    em: EMSection = EMSection()
    path: PathSection = PathSection()
    shooting: ShootingSection = ShootingSection()
    pool: PoolSection = PoolSection()
    select: SelectSection = SelectSection()
    merge: MergeSection = MergeSection()
    reduce: ReduceSection = ReduceSection()
    slsqp: SlsqpSection = SlsqpSection()
    layout: LayoutSection = LayoutSection()
    rescue: RescueSection = RescueSection()
    hold: HoldSection = HoldSection()


#: What ``solver.method: auto`` sets when a few fields do not explain the motions' torques:
#: antagonist pairs inside joint space held on the path (configs/convergent.yaml holds
#: the same keys; docs/model.md, "Convergent pairs held on the path").
CONVERGENT = {
    "model": {"fields": 0, "stiffness": "diag", "field_damping": 0.1, "windows": 16},
    "solver": {"method": "layout",
               "layout": {"shape": "pairs", "radius": 2.0, "stiffness": 0.25, "frequency": 10.0,
                          "deviation": 0.1},
               "path": {"steps": 0, "rtol": 1e-6, "atol": 1e-8, "batch": "shared", "max_evals": 100000},
               "shooting": {"receding": 2.0, "tip_weight": 100.0}},
}


class SuccessSection(Section):
    rmse: float = Field(0.03, ge=0)              # joint RMSE (rad)
    tip: float = Field(0.02, ge=0)               # maximum hand-tip error (m)


class LogSection(Section):
    tensorboard: bool = True
    progress: bool = True
    # path figures (TensorBoard, RUN/figures/) of at most this many motions each time,
    # those furthest from their paths first; null: every motion
    figures: Optional[int] = Field(16, ge=0)


def _body_builds(body: dict) -> dict:
    """A body section must build a body (:func:`tflearn.physics.body.from_config`)."""
    from .physics.body import from_config
    try:
        from_config(body)
    except (ValueError, TypeError) as err:
        raise PydanticCustomError("body", "{problem}", {"problem": str(err)}) from None
    return body


#: A ``body:`` section (any config that has one): checked to build a body.
BodySection = Annotated[dict[str, Any], AfterValidator(_body_builds)]


def _device_named(name: str) -> str:
    """A ``device:`` is one torch names: ``cpu``, ``cuda`` or ``cuda:K`` (whether this
    machine has it is asked when a run starts, not here)."""
    import torch
    try:
        kind = torch.device(name).type
    except RuntimeError:
        kind = None
    if kind not in ("cpu", "cuda"):
        raise PydanticCustomError("device", "a device is cpu, cuda or cuda:K")
    return name


#: A ``device:`` setting: where the run's tensors live and its arithmetic runs.
DeviceName = Annotated[str, AfterValidator(_device_named)]


class ClipChoice(Section):
    # one clip's own choices (bvh.clips.NAME, NAME its file name without .bvh)
    arm: Optional[Literal["right", "left"]] = None    # its performer's arm (null: bvh.arm)
    fps: Optional[float] = Field(None, gt=0, allow_inf_nan=False)   # its true frame rate (null: header)


class BvhSection(Section):
    # when data names BVH clips: imported into OUT/imported (tflearn.mocap.clips.import_config)
    # the performer's arm; moving: per clip the one whose hand travels further (left ones
    # mirrored onto the right, so that one arm serves every clip)
    arm: Literal["right", "left", "moving"] = "right"
    mirror: bool = False                         # reflect the arms onto the other side
    clips: dict[str, ClipChoice] = {}            # per clip: {arm, fps} (e.g. a header's wrong rate)
    # samples per second after import; null: each clip's own frame rate
    rate: Optional[float] = Field(None, gt=0, allow_inf_nan=False)
    # [start, stop] (s): the part of every clip that is learned; null: the whole clip
    window: Optional[list[float]] = Field(None, min_length=2, max_length=2)
    # instead of a window: each clip's busiest this many seconds (largest joint path length)
    busiest: Optional[float] = Field(None, gt=0, allow_inf_nan=False)
    # cut what is kept into consecutive pieces of this many seconds, each its own motion
    # NAME_partKK (a remainder under half a piece joins the last); null: one motion per clip
    split: Optional[float] = Field(None, gt=0, allow_inf_nan=False)

    @field_validator("window")
    @classmethod
    def _ordered(cls, w):
        if w is not None and not 0 <= w[0] < w[1]:
            raise ValueError(f"a window is [start, stop] with 0 ≤ start < stop (seconds), got {list(w)}")
        return w

    @model_validator(mode="after")
    def _one_part(self):
        if self.window is not None and self.busiest is not None:
            raise ValueError("window and busiest both choose the part of a clip learned: give one")
        return self


class Config(Section):
    """The training config (``train CONFIG``); see configs/gestures.yaml."""

    # "gestures" (the built-in library), a folder of .npz motions, a list of .npz files,
    # or BVH clips (.bvh files, or a folder of them): imported with the bvh section's
    # options, the body then the performer's (tflearn.mocap.clips.import_config)
    data: Union[str, list[str]] = "gestures"
    bvh: BvhSection = BvhSection()
    strict: bool = False                         # stop at the first bad motion file
    out: str = "runs/gestures"
    seed: int = Field(0, ge=0)
    body: BodySection = {"preset": "arm"}
    # the shoulder's base: fixed (inertial), or moving — each motion on its performer's torso,
    # torso/NAME.npz beside the motions (tflearn bvh import writes them; docs/mocap.md)
    torso: Literal["fixed", "moving"] = "fixed"
    # where the fit runs: cpu, or cuda (cuda:K) — the targets, the model and every stage's
    # arithmetic there; simulations take the torch solvers (the compiled ones are the CPU's)
    device: DeviceName = "cpu"
    model: ModelSection = ModelSection()
    solver: SolverSection = SolverSection()
    success: SuccessSection = SuccessSection()
    log: LogSection = LogSection()

    # the keys the command line gave (:func:`load`'s overrides, as one nested mapping):
    # what ``solver.method: auto`` leaves as they are (:func:`without`)
    _given: dict = PrivateAttr(default_factory=dict)

    def __eq__(self, other) -> bool:            # the values alone: what was given is provenance
        return type(other) is type(self) and self.__dict__ == other.__dict__

    __hash__ = Section.__hash__

    @property
    def given(self) -> dict:
        """The keys :func:`load`'s overrides set, nested ({} for a config built otherwise)."""
        return copy.deepcopy(self._given)

    def replace(self, **changes) -> Config:
        """A validated copy with top-level keys replaced (nested sections as mappings);
        it keeps :attr:`given`."""
        out = validate(merge(self.model_dump(), changes), type(self))
        out._given = self._given
        return out


# ----------------------------------------------------------------------------- perturb

CONTROLLER_NAMES = ("fields", "ff+pd", "ff", "pd-high")     # tflearn.control.controllers.CONTROLLERS


class PushSection(Section):
    """One push: force F (N, world) with the cosine-pulse profile over [at, at + duration]."""

    force: list[float] = Field(min_length=3, max_length=3)
    at: float = Field(ge=0)
    duration: float = Field(0.1, gt=0)
    point: str = "hand"


class SweepSection(Section):
    """Pushes of each impulse (N·s) along each direction (normalised), all batched."""

    directions: list[list[float]] = []
    impulses: list[float] = []
    at: float = Field(1.0, ge=0)
    duration: float = Field(0.1, gt=0)
    point: str = "hand"


class GainsSection(Section):
    """ff+pd: K = scale·K₀ + bilinear·|τ_ff|, B = √scale·B₀; pd-high: high_gain·K₀,
    √high_gain·B₀ (K₀, B₀ per joint: tflearn.control.controllers.HUMAN_ARM_GAINS)."""

    scale: float = Field(1.0, gt=0)
    bilinear: float = Field(0.0, ge=0)
    high_gain: float = Field(20.0, gt=0)


class SimulationSection(Section):
    """How a command simulates; a simulation needing more than ``max_evals``
    right-hand-side evaluations fails (:class:`tflearn.simulation.simulate.SimulationFailed`)."""

    method: Literal[SOLVERS] = "dopri5"
    rtol: float = Field(1e-6, gt=0)
    atol: float = Field(1e-8, gt=0)
    max_evals: int = Field(400_000, ge=1)
    batch: Literal["shared", "each"] = "shared"  # each: every motion its own steps (dopri5)

    def options(self):
        """These settings as :class:`tflearn.simulation.simulate.SimOptions`."""
        from .simulation.simulate import SimOptions
        return SimOptions(method=self.method, rtol=self.rtol, atol=self.atol,
                          max_evals=self.max_evals, batch=self.batch)


class PerturbConfig(Section):
    """``tflearn perturb``: controllers × perturbations on motions of a trained model."""

    model: str                                   # a run folder or its basis.json
    motions: list[str] = Field(min_length=1)
    controllers: list[Literal[CONTROLLER_NAMES]] = list(CONTROLLER_NAMES)
    pushes: list[PushSection] = []
    sweep: SweepSection = SweepSection()
    carry: float = Field(0.0, ge=0)              # kg held at the hand (with every push)
    gains: GainsSection = GainsSection()
    simulation: SimulationSection = SimulationSection()
    tol: float = Field(0.01, gt=0)               # m: recovered when back within tol for good
    out: str = "runs/perturb"
    animation: bool = True
    tensorboard: bool = True


class ConfigError(InputError):
    """A bad config file, key or value; the message names it."""


class _Loader(yaml.SafeLoader):
    """SafeLoader that also reads YAML 1.2 floats such as 1e-3 (YAML 1.1 wants 1.0e-3)."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^[-+]?(?:[0-9][0-9_]*)?(?:\.[0-9_]*)?(?:[eE][-+]?[0-9]+)$|^[-+]?[0-9][0-9_]*\.[0-9_]*$"""),
    list("-+0123456789."))


# ------------------------------------------------------------------------ error messages

def _schema_at(schema: Type[BaseModel], loc: tuple) -> Optional[Type[BaseModel]]:
    """The section model reached by following ``loc`` from ``schema`` (None past a leaf)."""
    for key in loc:
        field = schema.model_fields.get(key) if isinstance(key, str) else None
        ann = field.annotation if field else None
        if not (isinstance(ann, type) and issubclass(ann, BaseModel)):
            return None
        schema = ann
    return schema


_WANTS = {"int_type": "an integer", "int_parsing": "an integer", "int_from_float": "an integer",
          "float_type": "a number", "float_parsing": "a number", "bool_type": "true or false",
          "bool_parsing": "true or false", "string_type": "a str", "list_type": "a list",
          "dict_type": "a mapping", "model_type": "a mapping", "model_attributes_type": "a mapping"}


def _message(err: dict, schema: Type[BaseModel]) -> str:
    """One pydantic error as a sentence naming the dotted key."""
    loc = tuple(k for k in err["loc"] if isinstance(k, str))
    key = ".".join(loc)
    kind, value = err["type"], err.get("input")
    if kind == "extra_forbidden":
        known = list((_schema_at(schema, loc[:-1]) or schema).model_fields)
        close = difflib.get_close_matches(loc[-1], known, n=3)
        hint = f"did you mean {', '.join(close)}?" if close else f"known: {', '.join(known)}"
        return f"unknown config key {key!r} ({hint})"
    if err["loc"][:1] == ("data",):
        return (f"config key 'data' must be a folder, a list of .npz files or 'gestures', "
                f"got {value!r}")
    if kind in ("greater_than_equal", "greater_than"):
        limit = err.get("ctx", {}).get("ge", err.get("ctx", {}).get("gt"))
        what = "non-negative" if limit == 0 and kind == "greater_than_equal" else f"≥ {limit}"
        return f"config key {key!r} must be {what}, got {value!r}"
    if kind in ("body", "layout"):                 # a problem found within the key's value
        return f"config key {key!r}: {err['ctx']['problem']}"
    if kind == "literal_error":
        return f"config key {key!r} must be one of {err['ctx']['expected']}, got {value!r}"
    if kind.startswith("int") and (isinstance(value, str) or isinstance(value, bool)):
        return f"config key {key!r} must be a number (an integer), got {value!r}"
    if kind.startswith("float") and isinstance(value, bool):
        return f"config key {key!r} must be a number, got {value!r}"
    wants = _WANTS.get(kind)
    if wants:
        return f"config key {key!r} must be {wants}, got {value!r}"
    return f"config key {key!r}: {err['msg']} (got {value!r})"


def validate(doc: dict, schema: Type[BaseModel] = Config, where: str = ""):
    """``doc`` as a ``schema`` instance; raises :class:`ConfigError` (prefixed by ``where``)
    naming the first bad key."""
    try:
        return schema.model_validate(doc)
    except ValidationError as err:
        msg = _message(err.errors()[0], schema)
        raise ConfigError(f"{where}: {msg}" if where else msg) from None


# ----------------------------------------------------------------------------- reading

def parse_override(text: str) -> dict:
    """``a.b.c=value`` → {"a": {"b": {"c": parsed value}}}."""
    key, sep, raw = text.partition("=")
    if not sep or not key:
        raise ConfigError(f"override {text!r} is not of the form key=value")
    try:
        value = yaml.load(raw, Loader=_Loader) if raw != "" else ""
    except yaml.YAMLError as err:
        raise ConfigError(f"override {text!r}: cannot parse value ({_yaml_problem(err)})") from None
    node: dict = {}
    cur = node
    keys = key.split(".")
    for k in keys[:-1]:
        cur = cur.setdefault(k, {})
    cur[keys[-1]] = value
    return node


def _yaml_problem(err: yaml.YAMLError) -> str:
    """A YAML error on one line: what, and where (line and column, from 1)."""
    mark = getattr(err, "problem_mark", None)
    what = getattr(err, "problem", None) or str(err).splitlines()[0]
    return f"{what} at line {mark.line + 1}, column {mark.column + 1}" if mark else what


def read(path) -> dict:
    """The mapping in a YAML file (not validated); errors name the file."""
    path = Path(path)
    try:
        text = path.read_bytes().decode("utf-8")
    except OSError as err:
        raise ConfigError(f"{path}: cannot read config ({err.strerror})") from None
    except UnicodeDecodeError as err:
        raise ConfigError(f"{path}: not a YAML text file (not UTF-8 at byte {err.start})") from None
    try:
        doc = yaml.load(text, Loader=_Loader)
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML ({_yaml_problem(err)})") from None
    if doc is None:
        return {}
    if not isinstance(doc, dict):
        raise ConfigError(f"{path}: a config must be a mapping of keys to values")
    return doc


def read_body(path):
    """The :class:`~tflearn.physics.body.Body` of a YAML file's ``body:`` section (a config, or the
    body.yaml that ``tflearn bvh import`` writes); errors name the file."""
    from .physics.body import from_config
    doc = read(path)
    if not isinstance(doc.get("body"), dict):
        raise ConfigError(f"{path}: no 'body:' section")
    try:
        return from_config(doc["body"])
    except ValueError as err:
        raise ConfigError(f"{path}: {err}") from None


def merge(base: dict, new: dict) -> dict:
    """``base`` updated recursively by ``new`` (copies; "body" is replaced whole)."""
    out = copy.deepcopy(base)
    for key, val in new.items():
        if isinstance(val, dict) and isinstance(out.get(key), dict) and key != "body":
            out[key] = merge(out[key], val)
        else:
            out[key] = copy.deepcopy(val)
    return out


def without(doc: dict, given: dict) -> dict:
    """``doc`` less every key ``given`` sets (recursively: a section ``given`` names in
    part loses only those keys; "body" is one key)."""
    out = {}
    for key, val in doc.items():
        if key not in given:
            out[key] = copy.deepcopy(val)
        elif isinstance(val, dict) and isinstance(given[key], dict) and key != "body":
            if rest := without(val, given[key]):
                out[key] = rest
    return out


def layer(doc: dict, overrides, schema: Type[BaseModel]) -> dict:
    """``doc`` with each override applied in turn, each checked (errors name it)."""
    for text in overrides:
        doc = merge(doc, parse_override(text))
        validate(doc, schema, f"override {text!r}")
    return doc


def load(path=None, overrides=(), schema: Type[BaseModel] = Config):
    """The defaults ← the YAML file at ``path`` ← dotted overrides, as a validated
    ``schema`` instance (a :class:`Config` remembers the overrides' keys:
    :attr:`Config.given`). Raises :class:`ConfigError`."""
    doc = {}
    if path is not None:
        doc = read(path)
        validate(doc, schema, str(path))
    cfg = validate(layer(doc, overrides, schema), schema)
    if isinstance(cfg, Config):
        for text in overrides:
            cfg._given = merge(cfg._given, parse_override(text))
    return cfg


def dump(cfg: BaseModel, path) -> None:
    """Write a config as YAML (readable back by :func:`load`), atomically."""
    from .io.files import write_text
    write_text(path, yaml.safe_dump(cfg.model_dump(), sort_keys=False))
