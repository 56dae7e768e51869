"""The stages of a run, behind one registry: :data:`STAGES`, each stage a module with
its ``NAME`` (the name its checkpoints and metrics.json use), ``TITLE`` and ``UNIT``
(what its progress bar says, and the unit of work it counts) and ``run(ctx, state)``,
which does one unit of work (:mod:`tflearn.train.pipeline` calls it until the stage
moves the state on); :data:`SEQUENCES` the stages of each ``solver.method``.
"""
from __future__ import annotations

from . import each, hold, layout, path, pool, reduce, rescue, slsqp

STAGES = {m.NAME: m for m in (each, pool, reduce, path, rescue, hold, slsqp, layout)}
SEQUENCES = {"pipeline": (each, pool, reduce, path, rescue, hold), "slsqp": (slsqp,),
             "layout": (layout, path)}


def sequence(cfg) -> tuple:
    """The names of the stages a config runs, in order (``rescue`` with
    ``solver.rescue.enabled`` only, ``hold`` with ``solver.hold.enabled``).
    ``solver.method: auto`` has none until the data decides it
    (:func:`tflearn.train.choice.choose`, which :func:`tflearn.train.run` calls): ValueError."""
    if cfg.solver.method not in SEQUENCES:
        raise ValueError(f"solver.method {cfg.solver.method!r} is decided from the data by "
                         f"tflearn.train.choice.choose (train.run calls it); give a method that runs")
    optional = {rescue: cfg.solver.rescue.enabled, hold: cfg.solver.hold.enabled}
    return tuple(m.NAME for m in SEQUENCES[cfg.solver.method] if optional.get(m, True))


def titles(names) -> dict:
    """{name: (title, unit)} of the stages ``names``, in order (for :class:`~tflearn.log.RunLog`)."""
    return {name: (STAGES[name].TITLE, STAGES[name].UNIT) for name in names}
