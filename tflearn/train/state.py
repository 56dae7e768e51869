"""The run's state, :class:`RunState`: everything a run needs to resume, saved in its
checkpoint as plain tensors and JSON values only (``torch.load(weights_only=True)``), and
the typed records it keeps — each motion's own fit (:class:`FieldFit`), elimination's
reference (:class:`Reference`), path matching's progress (:class:`PathProgress`) and the
history that metrics.json reports (:class:`History`).

Nothing a run decides lives outside the state: whatever else a stage keeps (the last
check's scores, the library of fields ``each`` reuses) is derived from it again.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import NamedTuple, Optional

import torch

CHECKPOINT_FORMAT = "tflearn-checkpoint/6"
DONE = "done"                   # the stage of a run whose stages are all done


def _plain(record) -> dict:
    """A record's fields as a dict, not copied (tensors are written as they are)."""
    return {f.name: getattr(record, f.name) for f in fields(record)}


class FieldFit(NamedTuple):
    """Motion j's own fit (stage ``each``): its fields' centres η (M_j×n) and stiffnesses
    K (M_j×n×n), and its timing and weights on them (:meth:`MotionWeights.timing`)."""

    eta: torch.Tensor
    K: torch.Tensor
    timing: dict


@dataclass
class Reference:
    """What elimination judges a smaller basis against, per motion: joint RMSE (rad),
    maximum tip error (m), reproduced or not, the relative torque cost C_j on the current
    model (:func:`~tflearn.fit.torque.torque_costs`) and, with ``solver.reduce.growth``,
    the e-folds of local error growth along its path (:mod:`tflearn.fit.stability`), and
    whether a motion not reproduced must stay no worse (``required``, None: every one; a
    motion no fit of its own reproduced need not, :meth:`EachRecord.required`)."""

    rmse: list
    tip: list
    ok: list
    cost: Optional[list] = None
    efolds: Optional[list] = None
    required: Optional[list] = None

    @classmethod
    def of(cls, scores, ok: list, **extra) -> Reference:
        """The reference of a check: its scores and successes (``extra``: cost, efolds)."""
        return cls(list(scores.rmse), list(scores.tip), list(ok), **extra)

    def held(self) -> list:
        """Per motion whether elimination holds it no worse: ``required``, every motion
        where that is None."""
        return list(self.required) if self.required is not None else [True] * len(self.ok)

    def select(self, motions: list) -> Reference:
        """The reference of ``motions`` (indices) only."""
        return Reference(**{k: None if v is None else [v[j] for j in motions]
                            for k, v in _plain(self).items()})


@dataclass
class PathProgress:
    """Path matching so far: whether it is ``needed`` (a motion is not reproduced), the
    learning rate, Adam's state, the best point ({"loss", "model"}) and the motions it
    fits (None: all, with the fields free)."""

    needed: bool
    lr: float
    optimizer: Optional[dict] = None
    best: Optional[dict] = None
    motions: Optional[list] = None


# ------------------------------------------------------------------ the history

@dataclass
class EachRecord:
    """``each``: per motion whether its own fit was reproduced; the motions ``reused``
    (fitted on earlier motions' fields) and, for the others, why those fields did not do."""

    reproduced: list = field(default_factory=list)
    reused: list = field(default_factory=list)
    declined: dict = field(default_factory=dict)

    def required(self) -> Optional[list]:
        """Per motion whether its own fit reproduced it, where that reproduced some
        motion (else None): the motions the shared basis is chosen for and elimination
        keeps no worse. A motion that no fit of its own reproduces cannot say which
        fields it needs; fields only it draws on are no shared fields."""
        return list(self.reproduced) if any(self.reproduced) else None


@dataclass
class ModelRecord:
    """A stage's model (``pool``, ``layout``): M, its summed torque cost, which motions it
    reproduces; for ``pool`` the fields ``merged`` ([kept, merged] pairs), the
    ``selection`` of the shared fields (:func:`tflearn.fit.select.select`: the pooled M,
    the M kept and pruned, the knee's path [m, Σ C_j, served], motions left unserved)
    the motions reproduced by fitting their fields jointly with other motions' paths
    (``shared``), and the motions ``restored`` to fields of their own, ``copied`` those
    of them on fitted copies of the fields they drive (None: none)."""

    M: int
    torque_cost: float
    success: list
    merged: Optional[list] = None
    restored: Optional[list] = None
    selection: Optional[dict] = None
    copied: Optional[list] = None
    shared: Optional[list] = None

    def to_dict(self) -> dict:
        doc = {"M": self.M, "merged": self.merged, "torque_cost": self.torque_cost,
               "success": self.success, "shared": self.shared, "restored": self.restored,
               "copied": self.copied, "selection": self.selection}
        return {k: v for k, v in doc.items() if v is not None}


@dataclass
class Removal:
    """One field tried for removal (``reduce``): whether it was ``removed``, by which
    ``trial`` (refit, held, folded, or none; why it was ``refused`` where the trial
    says), M after."""

    field: int
    removed: bool
    trial: str
    M_after: int
    refused: Optional[str] = None

    def to_dict(self) -> dict:
        return {k: v for k, v in _plain(self).items() if k != "refused" or v is not None}


@dataclass
class RescueRound:
    """One round of ``rescue``: the motions it took on, the fields it laid out, M after,
    the motions it reproduced and those it brought closer, whether the model changed."""

    motions: list
    added: int
    M: int
    reproduced: list
    improved: list
    kept: bool


@dataclass
class HoldRecord:
    """``hold``: the fields it added, M after, the motions it lost (reproduced before, not
    after), whether the model changed (none lost), and the setting each motion's held
    program took ({"window_rate", "deviation"}; None: none reproduces it)."""

    added: int
    M: int
    lost: list
    kept: bool
    settings: dict


@dataclass
class History:
    """What the run did, reported in metrics.json (``history``; docs/guide.md): the method
    ``solver.method: auto`` chose and why (``method``: :func:`tflearn.train.choice.choose`'s
    decision; a resumed run takes it from here), one entry per stage that ran,
    ``shooting`` per motion {"loss", "failure"} of the last multiple shooting, ``finer`` per
    motion cut into finer windows the windows a second it kept (``model.finer``), ``path`` why
    path matching stopped when its simulation failed, ``slsqp`` the baseline's report
    (:func:`tflearn.fit.slsqp.fit_slsqp`)."""

    method: Optional[dict] = None
    each: Optional[EachRecord] = None
    pool: Optional[ModelRecord] = None
    layout: Optional[ModelRecord] = None
    reduce: list = field(default_factory=list)
    shooting: Optional[dict] = None
    finer: Optional[dict] = None
    path: Optional[str] = None
    rescue: list = field(default_factory=list)
    hold: Optional[HoldRecord] = None
    slsqp: Optional[dict] = None

    def to_dict(self) -> dict:
        """metrics.json's ``history``: the entries of the stages that ran, in this order."""
        doc = {"method": self.method, "each": None if self.each is None else _plain(self.each),
               "pool": None if self.pool is None else self.pool.to_dict(),
               "layout": None if self.layout is None else self.layout.to_dict(),
               "reduce": [r.to_dict() for r in self.reduce] or None, "shooting": self.shooting,
               "finer": self.finer, "path": self.path, "rescue": [_plain(r) for r in self.rescue] or None,
               "hold": None if self.hold is None else _plain(self.hold), "slsqp": self.slsqp}
        return {k: v for k, v in doc.items() if v is not None}

    @classmethod
    def from_dict(cls, doc: dict) -> History:
        each, pool, layout = doc.get("each"), doc.get("pool"), doc.get("layout")
        return cls(method=doc.get("method"), each=None if each is None else EachRecord(**each),
                   pool=None if pool is None else ModelRecord(**pool),
                   layout=None if layout is None else ModelRecord(**layout),
                   reduce=[Removal(**r) for r in doc.get("reduce", [])], shooting=doc.get("shooting"),
                   finer=doc.get("finer"), path=doc.get("path"),
                   rescue=[RescueRound(**r) for r in doc.get("rescue", [])],
                   hold=None if doc.get("hold") is None else HoldRecord(**doc["hold"]),
                   slsqp=doc.get("slsqp"))


# ------------------------------------------------------------------ the state

@dataclass
class RunState:
    """Where the run is (``stage``, ``cursor``: units done within it), the random
    generator, the global iteration count (``iteration``, the TensorBoard step:
    :mod:`tflearn.train.context`), the per-motion fits of ``each`` (until ``pool``), the
    current model (:func:`~tflearn.model.program.model_state`), elimination's reference,
    its order of fields (ids by share), the ids kept and how many trials it checks
    together next (``window``), path matching's progress, the fields each motion may use
    (``support``, N×M bools; None: all), the history, whether the run is ``finished`` (its
    artefacts written), and the compute time and simulations spent so far (rank 0's,
    over resumes)."""

    config: dict
    stage: str
    rng: torch.Tensor
    cursor: int = 0
    iteration: int = 0
    elapsed: float = 0.0
    simulations: int = 0
    fits: list = field(default_factory=list)           # [FieldFit], one per motion: until pool
    model: Optional[dict] = None
    history: History = field(default_factory=History)
    reference: Optional[Reference] = None
    order: Optional[list] = None
    ids: Optional[list] = None
    window: int = 1
    path: Optional[PathProgress] = None
    support: Optional[list] = None
    finished: bool = False

    def generator(self) -> torch.Generator:
        """The run's random generator at its saved state."""
        gen = torch.Generator()
        gen.set_state(self.rng.cpu())             # a checkpoint's tensors load on the run's device
        return gen

    def advance(self, sequence: tuple) -> None:
        """On to the next stage of ``sequence`` (after the last: :data:`DONE`)."""
        i = sequence.index(self.stage) + 1
        self.stage, self.cursor = sequence[i] if i < len(sequence) else DONE, 0

    def to_dict(self) -> dict:
        """The checkpoint's content: plain values, the tensors as they are, not copied
        (``torch.save`` writes them at once: a deep copy of a thousand motions' state
        cost a second per checkpoint)."""
        doc = _plain(self)
        doc.update(fits=[tuple(f) for f in self.fits], history=self.history.to_dict(),
                   reference=None if self.reference is None else _plain(self.reference),
                   path=None if self.path is None else _plain(self.path))
        return {"format": CHECKPOINT_FORMAT, **doc}

    @classmethod
    def from_dict(cls, doc: dict) -> RunState:
        """The state of a checkpoint's content (:meth:`to_dict`; TypeError for an
        incomplete one)."""
        state = cls(**{k: v for k, v in doc.items() if k != "format"})
        state.fits = [FieldFit(*f) for f in state.fits]
        state.history = History.from_dict(state.history)
        state.reference = None if state.reference is None else Reference(**state.reference)
        state.path = None if state.path is None else PathProgress(**state.path)
        return state
