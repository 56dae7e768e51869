"""Checkpoints: the run's state (:class:`~tflearn.train.state.RunState`) written
atomically to OUT/checkpoint.pt after every unit of work, so that a run killed at any
moment and started again with the same command resumes at the last unit and ends with
the same result. Rank 0 alone reads and writes it (the state is global: a run resumes
with any number of ranks); every rank counts it, for ``stop_after``.

A checkpoint holds plain tensors and JSON values only (``torch.load(weights_only=True)``);
one of another format, an unreadable one and one of another config are refused with a
:class:`CheckpointError` naming the file.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import torch

from .. import config as config_mod
from .. import parallel
from ..errors import InputError
from ..io.files import replacing
from ..simulation import simulate as sim_mod
from .state import CHECKPOINT_FORMAT, RunState


class Interrupted(Exception):
    """Raised after ``stop_after`` checkpoints (used to test resuming)."""


class CheckpointError(InputError):
    """A checkpoint that cannot be resumed; the message names the file and the problem."""


def config_changes(old: dict, new: dict, prefix: str = "") -> list:
    """The dotted keys whose values differ between two dumped configs (sections compared
    key by key; a key only one of them has counts as differing)."""
    out = []
    for key in sorted(old.keys() | new.keys()):
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict) and key != "body":
            out += config_changes(a, b, f"{prefix}{key}.")
        elif a != b:
            out.append(f"{prefix}{key}")
    return out


def decided(out) -> Optional[dict]:
    """The method ``solver.method: auto`` chose for the run in ``out``, from its
    checkpoint's history (None without one, or where it says none; an unreadable
    checkpoint is :meth:`Checkpoints.load`'s to report)."""
    path = Path(out) / "checkpoint.pt"
    try:
        doc = torch.load(path, weights_only=True, map_location="cpu") if path.exists() else None
    except Exception:
        return None
    history = doc.get("history") if isinstance(doc, dict) else None
    return history.get("method") if isinstance(history, dict) else None


class Checkpoints:
    """OUT/checkpoint.pt of a run of config ``cfg``: read at the start (:meth:`start`),
    written after each unit (:meth:`save`); the time and simulations spent since the
    last one are added to the state there. ``stop_after``: raise :class:`Interrupted`
    after that many checkpoints."""

    def __init__(self, cfg, device: torch.device, stop_after: Optional[int] = None):
        self.cfg, self.device, self.stop_after = cfg, device, stop_after
        self.path = Path(cfg.out) / "checkpoint.pt"
        self.count = 0
        self.restart_clock()

    def restart_clock(self) -> None:
        """Count time and simulations from now."""
        self.t0, self.calls0 = time.time(), sim_mod.calls

    def elapsed(self, state: RunState) -> float:
        """The run's compute time so far (s), over resumes."""
        return state.elapsed + time.time() - self.t0

    def simulations(self, state: RunState) -> int:
        """The simulations run so far (this process' share, over resumes)."""
        return state.simulations + sim_mod.calls - self.calls0

    def save(self, state: RunState) -> None:
        """Write the checkpoint (rank 0; every rank counts it for ``stop_after``)."""
        state.elapsed, state.simulations = self.elapsed(state), self.simulations(state)
        self.restart_clock()
        if parallel.rank() == 0:
            self.write(state)
        self.count += 1
        if self.stop_after is not None and self.count >= self.stop_after:
            raise Interrupted(f"stopped after {self.count} checkpoints")

    def write(self, state: RunState) -> None:
        """Write the state as it is (atomically)."""
        with replacing(self.path) as tmp:
            torch.save(state.to_dict(), tmp)

    def load(self) -> Optional[RunState]:
        """The state in the checkpoint, None without one; a checkpoint of another
        version, an unreadable one or one of another config raises :class:`CheckpointError`."""
        if not self.path.exists():
            return None
        try:
            doc = torch.load(self.path, weights_only=True, map_location=self.device)
        except Exception as err:
            raise CheckpointError(f"{self.path}: not a readable checkpoint "
                                  f"({type(err).__name__}); pass --restart to start afresh") from None
        if not isinstance(doc, dict) or doc.get("format") != CHECKPOINT_FORMAT:
            found = doc.get("format") if isinstance(doc, dict) else None
            raise CheckpointError(f"{self.path}: a checkpoint of another tflearn version (format "
                                  f"{found!r}, this version reads {CHECKPOINT_FORMAT!r}); "
                                  f"pass --restart to start afresh")
        try:
            state = RunState.from_dict(doc)
        except TypeError as err:
            raise CheckpointError(f"{self.path}: not a complete checkpoint ({err}); pass --restart") from None
        # a key the checkpoint lacks was added to the config after it was written: it ran
        # as that key's default does (a new key's default keeps the old behaviour)
        # (log: how a run shows its progress, not what it computes)
        old = config_mod.merge(type(self.cfg)().model_dump(), state.config)
        changed = [k for k in config_changes(old, self.cfg.model_dump()) if not k.startswith("log.")]
        if changed:
            raise CheckpointError(
                f"{self.path}: a checkpoint of a different config is in this output folder "
                f"({', '.join(changed[:5])}{', …' if len(changed) > 5 else ''} differ); "
                f"choose another out= or pass --restart")
        return state

    def start(self, restart: bool) -> Optional[RunState]:
        """Rank 0's checkpoint (or None; ``restart``: removed first) on every rank; a bad
        one raises on every rank."""
        state, error = None, None
        if parallel.rank() == 0:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            if restart:
                self.path.unlink(missing_ok=True)
            try:
                state = self.load()
            except CheckpointError as err:
                error = str(err)
        state, error = parallel.broadcast((state, error))
        if error:
            raise CheckpointError(error)
        return state
