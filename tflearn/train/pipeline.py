"""The pipeline: a run's front (:func:`run`), its data, and the loop that runs the
sequence of stages (:func:`tflearn.train.stages.sequence`) unit by unit, each stage's
``run(ctx, state)`` doing one unit and moving the state on to the next stage when it is
done (:meth:`RunState.advance`), then the artefacts (:func:`~tflearn.train.artefacts.finish`).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import torch

from .. import parallel
from ..config import Config
from ..data.loading import check_resolution, load_motions, skipped_files, torsos
from ..fit.targets import prepare
from ..log import RunLog, method_line
from ..mocap import clips as mocap
from ..physics.body import from_config
from .artefacts import finish
from .checkpoint import Checkpoints, decided
from .choice import choose
from .context import RunContext, check_config, on_device, run_device
from .stages import STAGES, sequence, titles
from .state import DONE, RunState


def run(cfg: Config, restart: bool = False, stop_after: Optional[int] = None,
        progress: Optional[bool] = None) -> dict:
    """Train with a validated config (:class:`tflearn.config.Config`); returns
    metrics.json's dict. Data naming BVH clips are imported first, into OUT/imported
    (:func:`tflearn.mocap.clips.import_config`: the run then trains on that folder, with
    the performer's arm); a device this machine lacks, or a ``solver.method`` the model
    does not suit, is refused before any work (:class:`~tflearn.config.ConfigError`);
    ``solver.method: auto`` is decided from the motions (:func:`~tflearn.train.choice.choose`;
    a resumed run takes the decision from its checkpoint), the run, its checkpoint and its
    config.yaml then holding the method chosen.
    ``restart``: the checkpoint removed first; ``stop_after``: raise
    :class:`~tflearn.train.checkpoint.Interrupted` after that many checkpoints;
    ``progress``: overrides ``log.progress``."""
    cfg, imported = mocap.import_config(cfg)
    body, device = from_config(cfg.body), run_device(cfg.device)
    check_config(cfg)
    with parallel.group(str(device)):
        torch.manual_seed(cfg.seed)
        tg, resolution, skipped = load(cfg, body)
        earlier = decided(cfg.out) if cfg.solver.method == "auto" and not restart else None
        cfg, decision = choose(cfg, body, tg, earlier)
        cfg = sized_windows(cfg, tg)
        checkpoints = Checkpoints(cfg, device, stop_after)
        with on_device(device):
            ctx = new_context(cfg, tg.to(device), checkpoints, resolution=resolution, skipped=skipped)
            state = checkpoints.start(restart) or RunState(
                config=cfg.model_dump(), stage=ctx.sequence[0],
                rng=torch.Generator().manual_seed(cfg.seed).get_state())
            state.history.method = decision
            ctx.log = _log(cfg, body, ctx.sequence, state, progress)
            if imported is not None:
                ctx.log.message(f"imported {len(imported['clips'])} BVH clip(s) into {cfg.data} "
                                f"(report.json there); body: the performer's arm")
            if decision is not None:
                ctx.log.message(method_line(decision))
            return execute(ctx, state)


def load(cfg: Config, body) -> tuple:
    """The run's data: (targets on the CPU, each motion's torque resolution, the bad files
    skipped). The motions ``data`` names (bad files in a folder skipped, unless
    ``strict``), warned about when their samples do not resolve them, on their torsos."""
    motions = load_motions(cfg.data, body, strict=cfg.strict)
    skipped = skipped_files(cfg.data, body, motions)
    resolution = check_resolution(body, motions)
    tg = prepare(body, motions, weight=cfg.solver.torque_weight, base=torsos(cfg.data, motions, cfg.torso))
    return tg, resolution, skipped


def sized_windows(cfg: Config, tg) -> Config:
    """``cfg`` with ``model.windows`` P = ⌈``model.window_rate`` × 2^``model.finer`` × the
    longest motion's duration⌉ when that rate is set (> 0), else as it is: the run, its
    checkpoint and its config.yaml then hold that P."""
    rate = cfg.model.window_rate * 2 ** cfg.model.finer          # the finest windows asked
    if not rate:
        return cfg
    P = max(1, math.ceil(rate * float(tg.duration.max()) - 1e-9))
    return cfg.replace(model={"windows": P})


def new_context(cfg: Config, tg, checkpoints: Optional[Checkpoints] = None, **data) -> RunContext:
    """The context of a run of ``cfg`` on targets ``tg``: its body, its sequence of
    stages, a silent log (the run's own comes with its state), its checkpoints (by
    default on the CPU); ``data``: ``resolution``, ``skipped``."""
    return RunContext(cfg, from_config(cfg.body), tg, RunLog(cfg.out, tensorboard=False, progress=False),
                      checkpoints or Checkpoints(cfg, torch.device("cpu")), sequence(cfg), **data)


def _log(cfg: Config, body, names: tuple, state: RunState, progress: Optional[bool]) -> RunLog:
    """The run's log: rank 0's progress bars (``log.progress``, unless ``progress`` says)
    and TensorBoard (``log.tensorboard``; not for a finished run: it adds no events)."""
    lead = parallel.rank() == 0
    progress = cfg.log.progress if progress is None else progress
    return RunLog(cfg.out, tensorboard=cfg.log.tensorboard and lead and not state.finished,
                  progress=progress and lead, body=body, stages=titles(names), figures=cfg.log.figures)


def execute(ctx: RunContext, state: RunState) -> dict:
    """The stages from where ``state`` is, one unit at a time, then the artefacts."""
    if state.finished:
        ctx.log.message(f"{Path(ctx.cfg.out)}: finished; its artefacts written again")
    elif state.iteration or state.stage != ctx.sequence[0]:
        ctx.log.message(f"resuming {Path(ctx.cfg.out)} at stage {state.stage} ({state.cursor})")
    with ctx.log:
        ctx.log.open(state.iteration)
        while state.stage != DONE:
            STAGES[state.stage].run(ctx, state)
        return finish(ctx, state)
