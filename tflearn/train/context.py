"""The run context every stage works in (:class:`RunContext`): the config, the body, the
run's targets, the simulation options, the log (:class:`~tflearn.log.RunLog`, injected),
the checkpoints, the sequence of stages — and the services the stages share: judging a
model by simulation (:meth:`RunContext.check`), EM refinement (:meth:`RunContext.em`) and
the global iteration count (:meth:`RunContext.tick`).

The TensorBoard step of every entry is the run's global iteration count,
:attr:`RunState.iteration <tflearn.train.state.RunState>` (checkpointed, so that a
resumed run continues its curves): it grows by one for each iteration of the run's
optimisers — a motion fitted alone (``each``), an EM step (``pool``; a refitted
elimination trial's steps counted when the trial is applied), the weight solve of the
pooled or laid-out model (``pool``, ``layout``), an elimination trial (``reduce``), a
multiple-shooting pass and an Adam step (``path``), a rescue round, an SLSQP iteration —
and by one for the scoring of the result (``done``). An entry is written at the
iteration that made what it shows, one per tag and iteration.
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass, field, replace
from typing import Optional

import torch

from .. import parallel, synthesis
from ..config import Config, ConfigError
from ..fit import shooting, stability, torque
from ..fit.targets import Targets
from ..log import RunLog
from ..metrics import Scores, score
from ..model.fields import FieldBasis
from ..model.program import model_state
from ..physics.body import Body
from .checkpoint import Checkpoints
from .models import empty_basis, weight_support
from .state import RunState


def check_config(cfg: Config) -> None:
    """Refuse, before any work, a config whose ``solver.method`` cannot run with its
    model (:class:`~tflearn.config.ConfigError` naming the keys)."""
    m = cfg.model
    if cfg.solver.method == "layout" and (m.stiffness == "scalar" or m.fields):
        raise ConfigError("solver.method 'layout' lays out its fields with a stiffness per "
                          "coordinate: it needs model.fields=0 and model.stiffness diag, block "
                          f"or full (got {m.fields}, {m.stiffness!r})")
    if cfg.solver.method == "slsqp" and (m.fields < 1 or m.stiffness != "diag" or m.phases != "fixed"
                                         or m.field_damping or m.windows or m.window_rate
                                         or cfg.solver.torque_weight != "uniform"):
        raise ConfigError(
            "solver.method 'slsqp' (the thesis' baseline) fits a basis of a given size "
            "with diagonal stiffness, fixed phases, no field damping and no windows: it "
            "needs model.fields ≥ 1, model.stiffness=diag, model.phases=fixed, "
            f"model.field_damping=0, model.windows=0 (and window_rate) and solver.torque_weight=uniform "
            f"(got {m.fields}, {m.stiffness!r}, {m.phases!r}, {m.field_damping}, "
            f"{m.windows}, {cfg.solver.torque_weight!r})")


def run_device(name: str) -> torch.device:
    """The device a run's config names, checked to be on this machine (ConfigError naming
    it otherwise); plain ``cuda`` is this process' GPU (:func:`tflearn.parallel.local`)."""
    device = parallel.local(name)
    if device.type != "cuda":
        return device
    if not torch.cuda.is_available():
        raise ConfigError(f"device {name!r}: this machine has no CUDA device that torch "
                          f"{torch.__version__} can use; set device: cpu")
    if device.index >= torch.cuda.device_count():
        raise ConfigError(f"device {name!r}: this machine has {torch.cuda.device_count()} CUDA "
                          f"device(s), numbered from 0")
    return device


def on_device(device: torch.device):
    """``with on_device(d):`` tensors made without a device are made on ``d`` (torch's
    default device); on the CPU nothing changes."""
    return contextlib.nullcontext() if device.type == "cpu" else device


def _same(x, y) -> bool:
    """Equal values: dicts key by key, tensors by shape and content."""
    if isinstance(x, dict):
        return x.keys() == y.keys() and all(_same(x[k], y[k]) for k in x)
    if isinstance(x, torch.Tensor):
        return x.shape == y.shape and bool(torch.equal(x, y))
    return x == y


def _same_check(a: tuple, b: tuple) -> bool:
    """Whether two checks' keys (targets, model state, flags) are the same: the same
    targets object, equal tensors and equal values."""
    return a[0] is b[0] and a[2:] == b[2:] and _same(a[1], b[1])


@dataclass
class RunContext:
    """One run's fixed parts: its config, body, targets ``tg`` (on the run's device), log
    and checkpoints, the ``sequence`` of its stages, and what its data showed: each
    motion's torque resolution and the bad data files skipped ({"file", "reason"}). The
    last check is remembered (``checked``: derived, the same model's scores)."""

    cfg: Config
    body: Body
    tg: Optional[Targets]
    log: RunLog
    checkpoints: Checkpoints
    sequence: tuple = ()
    resolution: list = field(default_factory=list)
    skipped: list = field(default_factory=list)
    checked: Optional[tuple] = field(default=None, repr=False)

    @property
    def options(self):
        """The simulation options of scoring and path matching (``solver.path``)."""
        return self.cfg.solver.path.options()

    @property
    def variable_phases(self) -> bool:
        """Whether the motions' activation timing is learned (``model.phases: variable``)."""
        return self.cfg.model.phases == "variable"

    def template(self) -> FieldBasis:
        """An empty basis of the configured kind and field damping on the body's blocks."""
        return empty_basis(self.cfg, self.body)

    def save(self, state: RunState) -> None:
        """A unit of work done: the checkpoint (:meth:`Checkpoints.save`)."""
        self.checkpoints.save(state)

    def tick(self, state: RunState) -> int:
        """One more iteration of the run (the module docstring); its number, the step of
        what it logs."""
        state.iteration += 1
        return state.iteration

    def check(self, basis, weights, tg: Targets, distributed: bool = True,
              until_failure: bool = False) -> tuple[Scores, list]:
        """(scores, success per motion: ``success.rmse``, ``success.tip``) of a model by
        simulation (:func:`~tflearn.metrics.score`); ``distributed``: the simulations
        shared by the ranks (every rank gets all motions' scores), else simulated here;
        ``until_failure``: for a judge that refuses any failure. The model checked last,
        checked again on the same targets, is not simulated again."""
        key = (tg, model_state(basis, weights), distributed, until_failure)
        if self.checked is None or not _same_check(self.checked[0], key):
            self.checked = (key, score(self.body, basis, weights, tg, self.options, distributed=distributed,
                                       until_failure=until_failure))
        scores = self.checked[1]
        return scores, scores.succeeded(self.cfg.success.rmse, self.cfg.success.tip)

    def efolds(self, basis, weights, tg: Targets) -> list:
        """Each motion's e-folds of local error growth along its path (:mod:`tflearn.fit.stability`)."""
        return stability.growth(self.body, basis, weights, tg).efolds.tolist()

    def shoot_fields(self, basis, weights, tg: Targets, free: Optional[tuple] = None,
                     distributed: bool = False) -> bool:
        """Motions' fields and weights fitted to their paths by multiple shooting with the
        fields free (``free``: those fields, indices; None: all; shared by the motions of
        ``tg``; ``solver.shooting``'s settings, its fields on), in place; False, with
        nothing done, where ``solver.shooting.fields`` or ``iterations`` turn it off.
        ``distributed``: every rank fits the same motions, each simulating its share of
        their segments."""
        c = self.cfg.solver.shooting
        if not (c.fields and c.iterations):
            return False
        self.log.busy(shooting="fields")
        options = replace(c.options(self.variable_phases), fields=True, free=free)
        shooting.shooting_match(self.body, basis, weights, tg, options=options, sim=self.options,
                                distributed=distributed)
        return True

    def fit_shared(self, basis, weights, motions: list, drives: list, free: list) -> Optional[tuple]:
        """``motions`` (indices into the run's) each on the fields it drives (``drives``:
        positions, per motion) alone, their NNLS weights on them, then the ``free`` fields
        and every motion's weights fitted to all their paths at once by multiple shooting,
        the other fields held (:meth:`shoot_fields`, every rank simulating its share of the
        segments): (basis, weights of every motion, whether simulation reproduces each of
        ``motions``) with the ``free`` fields moved and those motions' weights on their
        fields alone; None where shooting of fields is off."""
        fields = list(dict.fromkeys(free + [i for d in drives for i in d]))
        tg, b = self.tg.select(motions), basis.select(fields)
        w = weights.select_motions(motions).select_fields(fields)
        torque.solve_weights(b, w, tg, weight_support([[i in d for i in fields] for d in drives], w.P))
        if not self.shoot_fields(b, w, tg, free=tuple(range(len(free))), distributed=True):
            return None
        fine = self.check(b, w, tg)[1]
        eta, K = basis.eta.detach().clone(), basis.K().detach().clone()
        eta[free], K[free] = b.eta.detach()[:len(free)], b.K().detach()[:len(free)]
        nw = weights.select_motions(range(weights.N))
        for i, j in enumerate(motions):
            nw.put_(j, fields, w.timing(i, weights=True))
        return basis.like(eta, K), nw, fine

    def shoot(self, state: Optional[RunState], basis, weights, motions: list, options=None) -> None:
        """Multiple-shooting path matching of ``motions``' programs, the basis fixed
        (:func:`tflearn.synthesis.shoot`; ``options``, by default ``solver.shooting``'s),
        the motions shared by the ranks, ``weights`` changed in place; ``state``'s
        ``history.shooting`` (unless None) records each motion's path loss left and why
        shooting stopped early."""
        options = options or self.cfg.solver.shooting.options(self.variable_phases)
        self.log.busy(shooting=len(motions))
        record = synthesis.shoot(self.body, basis, weights, self.tg, motions, options, self.options,
                                 distributed=True,
                                 progress=lambda where: self.log.busy(shooting=len(motions), at=where))
        if state is not None:
            state.history.shooting = record

    def path_matched(self, basis, weights, motions: list, state: Optional[RunState] = None) -> tuple:
        """``motions``' weights (indices into the run's motions; ``weights`` holds them
        all) path-matched on the basis by multiple shooting (``solver.select.shooting``
        iterations per horizon, ``solver.shooting``'s other settings), in place
        (:meth:`shoot`, recorded in ``state``): their (scores, success) after."""
        options = replace(self.cfg.solver.shooting.options(self.variable_phases),
                          iterations=self.cfg.solver.select.shooting)
        self.shoot(state, basis, weights, motions, options)
        return self.check(basis, weights.select_motions(motions), self.tg.select(motions))

    def em(self, basis, weights, tg: Targets, state: Optional[RunState] = None, tag: Optional[str] = None,
           support: Optional[list] = None, min_gain: float = 0.0) -> list:
        """EM refinement (:func:`tflearn.fit.torque.em`, ``solver.em``), its cost history;
        with ``state`` each step is an iteration of the run (logged under ``tag``: the
        summed torque cost Σ_j C_j); ``support``: the fields each motion may use (N×M
        bools; None: all)."""
        c = self.cfg.solver.em

        def step(k, costs):
            cost = float(costs.sum())
            if state is not None:
                self.tick(state)
                if tag:
                    self.log.scalar(tag, cost, state.iteration)
            self.log.busy(em_step=k + 1, cost=cost)
        return torque.em(basis, weights, tg, steps=c.steps, tol=c.tol, max_step=c.max_step,
                         phases=self.variable_phases, callback=step, distributed=True,
                         support=weight_support(support, weights.P), min_gain=min_gain)
