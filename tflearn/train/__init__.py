"""The training pipeline behind ``train CONFIG``: motions → torques → fit → basis → metrics.

A run goes through an explicit sequence of stages (:mod:`tflearn.train.stages`, one
module each), each unit of work ending in an atomically written checkpoint
(:mod:`~tflearn.train.checkpoint`), so that a run killed at any moment and started again
with the same command resumes at the last unit and ends with the same result:

1. ``each``   — every motion alone (:mod:`~tflearn.train.stages.each`);
2. ``pool``   — all per-motion fields in one basis, the shared ones chosen among them
                by the motions' torque costs (:mod:`~tflearn.train.stages.pool`);
3. ``reduce`` — backward elimination of fields while no motion gets worse
                (:mod:`~tflearn.train.stages.reduce`);
4. ``path``   — path matching for motions not yet reproduced
                (:mod:`~tflearn.train.stages.path`);
5. ``rescue`` — spanning fields for motions still not reproduced
                (:mod:`~tflearn.train.stages.rescue`; ``solver.rescue.enabled``);
6. ``hold``   — damped antagonist pairs added and every program held on its path
                (:mod:`~tflearn.train.stages.hold`; ``solver.hold.enabled``);
7. ``done``   — ``basis.json``, ``metrics.json``, ``config.yaml``, figures, TensorBoard
                (:mod:`~tflearn.train.artefacts`).

With ``solver.method: slsqp`` the single stage ``slsqp`` replaces 1–6 (the thesis'
baseline, :mod:`~tflearn.train.stages.slsqp`); with ``solver.method: layout`` the stage
``layout`` replaces 1–3 (:mod:`~tflearn.train.stages.layout`).

:func:`run` (:mod:`~tflearn.train.pipeline`) imports data naming BVH clips, builds the
run's context (:mod:`~tflearn.train.context`: config, body, targets, log, checkpoints)
and runs the stages on its state (:mod:`~tflearn.train.state`). What the run shows and
logs meanwhile (progress bars, TensorBoard) is :mod:`tflearn.log`.

Many processes (``torchrun --nproc-per-node N -m tflearn.cli train CONFIG``, see
:mod:`tflearn.parallel` and docs/parallel.md): ``each`` fits motions in rounds of one
motion per rank; every simulation that scores the shared model, path matching's loss
and gradient, and EM's weight solves and Gauss–Newton sums are shared by motion
(:func:`tflearn.parallel.shard`), and the results are gathered or summed, so that every
rank holds the same state and takes the same decisions; SLSQP runs whole on every
rank. Rank 0 alone reads and writes the checkpoint (the state is global: a run resumes
with any number of ranks) and writes the artefacts, the progress display and
TensorBoard.
"""
from .artefacts import write_figures
from .checkpoint import CheckpointError, Interrupted, config_changes
from .context import RunContext, check_config, on_device, run_device
from .models import layout_model
from .pipeline import new_context, run
from .stages import SEQUENCES, STAGES
from .stages.reduce import no_worse
from .state import CHECKPOINT_FORMAT, RunState

__all__ = ["CHECKPOINT_FORMAT", "CheckpointError", "Interrupted", "RunContext", "RunState", "SEQUENCES",
           "STAGES", "check_config", "config_changes", "layout_model", "new_context", "no_worse",
           "on_device", "run", "run_device", "write_figures"]
