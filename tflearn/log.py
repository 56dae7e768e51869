"""What a training run shows while it works and writes for TensorBoard: :class:`RunLog`,
and :func:`summary_table`, the table of results printed at the end.

The progress display is one tqdm bar per stage, on stderr: the stage, how far it is
out of how many units (``each``: motions; ``reduce``: fields to try; ``path``:
``solver.path.steps``; ``slsqp``: ``solver.slsqp.max_iter``), elapsed time and ETA, and
the quantities that matter at that stage. ``log.progress: false`` turns it off.

TensorBoard (``log.tensorboard``, OUT/tensorboard, one run) — the tag layout:

* ``0_overview/``  the current shared model, logged at every change: ``M`` (fields;
  during ``each`` the fields found so far), and once the model is simulated,
  ``rmse_rad`` (over all samples of all motions), ``worst_tip_cm`` and ``torque_cost``
  (Σ_j C_j, the summed relative torque cost);
* ``torque_cost/STAGE``  one curve per stage: ``each`` (the cost of each motion's own
  fit), ``pool`` (EM steps after pooling), ``reduce`` (each trial's cost after EM),
  ``slsqp`` (iterations), ``layout`` (the spanning basis' weights); ``path/loss`` and
  ``path/lr`` per path-matching step;
  ``reduce/removed`` (1 when the field tried went);
* ``motion/NAME/`` ``rmse_rad``, ``tip_cm``, ``torque_error_pct`` of motion NAME under
  the current model (its own fit during ``each``);
* histograms ``weights/a``, ``weights/b`` (and ``weights/c`` with windows),
  ``stiffness/eigenvalues`` at every model change; figures ``paths/NAME`` (target and
  simulated path) at the stage ends;
* hyper-parameters: every key of the run's config, dotted (``seed``, ``model.fields``,
  ``solver.em.steps``, …), with the final ``0_overview`` metrics in the same run
  (TensorBoard's HPARAMS tab).

Steps are the run's global iteration count (:mod:`tflearn.train.context`), saved in the
checkpoint, so that a resumed run continues its curves; events written after the last
checkpoint of an interrupted run are purged on resuming.
"""
from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path
from typing import Optional

import torch

from .metrics import Scores, pooled_rmse

BAR_FORMAT = ("{desc}: {percentage:3.0f}%|{bar:24}| {n_fmt}/{total_fmt} {unit} "
              "[{elapsed}<{remaining}{postfix}]")


def progress_bar(total: Optional[int], desc: str, unit: str, progress: bool = True, initial: int = 0):
    """A progress bar on stderr in the form of the run's (:data:`BAR_FORMAT`): ``desc``,
    ``initial`` of ``total`` units of ``unit`` done, elapsed time and ETA; close it (or
    use it as a context manager) when done. ``progress=False``: a disabled bar whose calls
    do nothing (the commands' ``--quiet``, ``log.progress: false``).

    The bar is first drawn once it is built: a Ctrl-C that lands while tqdm builds it
    (during its first write, under load) would leave a bar its caller never holds, and so
    never closes, its line unended before the command's last message; one that lands
    during the first drawing closes the bar before it goes on."""
    from tqdm import tqdm
    bar = tqdm(total=total, initial=initial, desc=desc, unit=unit, bar_format=BAR_FORMAT, dynamic_ncols=True,
               file=sys.stderr, leave=True, disable=not progress, delay=1e-9)    # nothing drawn yet
    bar.delay = 0                                     # drawn from here on, and ended by close()
    try:
        bar.refresh()
    except BaseException:
        bar.close()
        raise
    return bar


def _fmt(value) -> str:
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return f"{value:.3g}"
    return str(value)


class RunLog:
    """The progress display and the TensorBoard writer of one training run.

    ``out``: the run folder (events go to OUT/tensorboard); ``tensorboard``, ``progress``:
    ``log.tensorboard``, ``log.progress``; ``body``: for the path figures;
    ``stages``: the run's stages in order, {name: (what the bar says, unit of work)}
    (:func:`tflearn.train.stages.titles`; the "[i/n]" of the bar)."""

    def __init__(self, out, tensorboard: bool, progress: bool, body=None,
                 stages: Optional[dict] = None, figures: int | None = None):
        self.out = Path(out)
        self.figures = figures
        self.tensorboard = tensorboard
        self.progress = progress
        self.body = body
        self.stages = dict(stages or {})
        self.writer = None
        self.bar = None
        self._stage = None
        self._drawn = 0.0
        self._showwarning = None

    # ---- lifetime
    def open(self, step: int = 0) -> None:
        """Open the writer; ``step``: the last step of a resumed run's checkpoint (events
        at later steps, written after that checkpoint, are purged)."""
        if self.progress and self._showwarning is None:     # warnings above the bar, not through it
            self._showwarning = warnings.showwarning
            warnings.showwarning = self._warning
        if self.tensorboard and self.writer is None:
            from torch.utils.tensorboard import SummaryWriter
            self.writer = SummaryWriter(str(self.out / "tensorboard"),
                                        purge_step=step + 1 if step > 0 else None)

    def _warning(self, message, category, filename, lineno, file=None, line=None):
        from tqdm import tqdm
        tqdm.write(warnings.formatwarning(message, category, filename, lineno, line).rstrip(),
                   file=sys.stderr)

    def close(self) -> None:
        self.end_stage(finished=False)
        if self._showwarning is not None:
            warnings.showwarning = self._showwarning
            self._showwarning = None
        if self.writer is not None:
            self.writer.close()
            self.writer = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def message(self, text: str) -> None:
        """A line for the user (only with progress), without breaking the bar."""
        if self.progress:
            from tqdm import tqdm
            tqdm.write(text, file=sys.stderr)

    # ---- progress
    def stage(self, name: str, total: Optional[int], done: int = 0) -> None:
        """Start the bar of stage ``name`` (unless it is already showing): ``total``
        units, ``done`` of them already done (a resumed run)."""
        if not self.progress or self._stage == name:
            return
        self.end_stage()
        label, unit = self.stages.get(name, (name, "units"))
        i = list(self.stages).index(name) + 1 if name in self.stages else 0
        desc = f"[{i}/{len(self.stages)}] {label}" if i else label
        self.bar = progress_bar(total, desc, unit, initial=done)
        self._stage = name

    def status(self, advance: int = 1, total: Optional[int] = None, **values) -> None:
        """Advance the bar by ``advance`` units and show ``values`` (name=value)."""
        if self.bar is None:
            return
        if total is not None and total != self.bar.total:
            self.bar.total = total
        self.bar.set_postfix_str(", ".join(f"{k}={_fmt(v)}" for k, v in values.items()),
                                 refresh=False)
        self.bar.update(advance)
        if not advance:
            self.bar.refresh()

    def busy(self, **values) -> None:
        """Show ``values`` while a unit is under way (EM steps, the motion being fitted),
        redrawing at most twice a second."""
        if self.bar is None:
            return
        now = time.monotonic()
        if now - self._drawn >= 0.5:
            self.bar.set_postfix_str(", ".join(f"{k}={_fmt(v)}" for k, v in values.items()),
                                     refresh=True)
            self._drawn = now

    def end_stage(self, finished: bool = True) -> None:
        """Close the current bar; a stage ``finished`` before its total (reduce stops
        at M = 1, path matching when nothing is left to do) shows what it did."""
        if self.bar is not None:
            if finished and self.bar.total is not None and self.bar.n < self.bar.total:
                self.bar.total = self.bar.n
            self.bar.refresh()
            self.bar.close()
        self.bar = None
        self._stage = None

    # ---- TensorBoard
    def scalar(self, tag: str, value, step: int) -> None:
        if self.writer is not None:
            self.writer.add_scalar(tag, float(value), step)

    def figure(self, tag: str, fig, step: int) -> None:
        """A matplotlib figure (left open for the caller)."""
        if self.writer is not None:
            self.writer.add_figure(tag, fig, step, close=False)

    def fields(self, M: int, step: int, K: Optional[torch.Tensor] = None, weights=None) -> None:
        """A model change: M, and histograms of the stiffness eigenvalues (of K,
        M×n×n) and of the weights (a MotionWeights)."""
        if self.writer is None:
            return
        self.scalar("0_overview/M", M, step)
        if K is not None and len(K):
            self.writer.add_histogram("stiffness/eigenvalues",
                                      torch.linalg.eigvalsh(K.detach()).flatten(), step)
        if weights is not None and weights.a.numel():
            self.writer.add_histogram("weights/a", weights.a.detach().flatten(), step)
            self.writer.add_histogram("weights/b", weights.b.detach().flatten(), step)
            if weights.P:
                self.writer.add_histogram("weights/c", weights.c.detach().flatten(), step)

    def model(self, basis, weights, step: int) -> None:
        """A change of the shared model (basis, weights)."""
        self.fields(basis.M, step, basis.K() if basis.M else None, weights)

    def scores(self, scores: Scores, tg, step: int, figures: bool = False,
               overview: bool = True) -> None:
        """Per-motion scores (``motion/NAME/...``), with ``overview`` the headline
        ``0_overview/`` scalars of the whole model, with ``figures`` the paths."""
        if self.writer is None:
            return
        for j, name in enumerate(tg.names):
            self.scalar(f"motion/{name}/rmse_rad", scores.rmse[j], step)
            self.scalar(f"motion/{name}/tip_cm", 100 * scores.tip[j], step)
            self.scalar(f"motion/{name}/torque_error_pct", 100 * scores.torque[j], step)
        if overview:
            self.scalar("0_overview/rmse_rad", pooled_rmse(scores.rmse, tg.mask.sum(-1).tolist()), step)
            self.scalar("0_overview/worst_tip_cm", 100 * max(scores.tip), step)
            self.scalar("0_overview/torque_cost", sum(t * t for t in scores.torque), step)
        if figures:
            from .plots import figures as plots
            for j in scores.worst(self.figures):
                name, k = tg.names[j], int(tg.mask[j].sum())
                fig = plots.motion_sheet(self.body, tg.t[j, :k],
                                         {"target": tg.q[j, :k], "simulated": scores.q_sim[j, :k]},
                                         title=name)
                self.writer.add_figure(f"paths/{name}", fig, step)

    def hparams(self, config: dict, metrics: dict) -> None:
        """The run's config (``Config.model_dump()``) as hyper-parameters, every key
        (:func:`flat_hparams`), with the final metrics (metrics.json's dict) in the same
        run: the HPARAMS tab reads the ``0_overview/`` scalars written here."""
        if self.writer is None:
            return
        from torch.utils.tensorboard.summary import hparams
        overall = metrics["overall"]
        final = {"0_overview/M": overall["M"], "0_overview/rmse_rad": overall["rmse"],
                 "0_overview/worst_tip_cm": 100 * overall["tip"],
                 "0_overview/torque_cost": sum(m["torque_rel_rms"] ** 2
                                               for m in metrics["motions"].values())}
        exp, ssi, sei = hparams(flat_hparams(config), final)
        for summary in (exp, ssi, sei):
            self.writer.file_writer.add_summary(summary)
        self.writer.flush()


def flat_hparams(config: dict, prefix: str = "") -> dict:
    """A nested config as TensorBoard hyper-parameters: one dotted key per leaf
    (``solver.em.steps``); booleans, numbers and strings as they are, anything else
    (lists, null) as its JSON text."""
    import json
    flat = {}
    for key, value in config.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict) and value:
            flat.update(flat_hparams(value, f"{name}."))
        elif isinstance(value, (bool, int, float, str)):
            flat[name] = value
        else:
            flat[name] = json.dumps(value)
    return flat


# ------------------------------------------------------------------ the summary

def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}h{m:02d}m{s:02d}s" if h else f"{m}m{s:02d}s" if m else f"{s}s"


def summary_table(metrics: dict, out=None) -> str:
    """The results of a run as a table (metrics.json's dict): per motion joint RMSE
    (rad), maximum tip error (cm), relative RMS torque error (%), the e-folds of error
    growth along its path and whether it was reproduced (if not, whether its simulation
    failed or its own fit failed too); then M, the overall figures, the
    most numbers per second of motion that describe a motion, the wall time, the method
    ``solver.method: auto`` chose (:func:`method_line`), the generating fields matched
    (:func:`identity_line`, for data that carries them), the bad data files skipped and,
    given ``out`` (the run folder), where the artefacts were written. No trailing newline."""
    rows = [("motion", "rmse (rad)", "tip (cm)", "torque err (%)", "growth (e-folds)", "reproduced")]
    alone = (metrics.get("history", {}).get("each") or {}).get("reproduced") or []
    for j, (name, m) in enumerate(metrics["motions"].items()):
        rows.append((name, f"{m['rmse']:.4f}", f"{100 * m['tip']:.2f}",
                     f"{100 * m['torque_rel_rms']:.2f}", f"{m['growth_efolds']:.2f}",
                     _verdict(m, alone[j] if j < len(alone) else None)))
    o = metrics["overall"]
    n_ok = sum(bool(m["success"]) for m in metrics["motions"].values())
    rows.append(("overall", f"{o['rmse']:.4f}", f"{100 * o['tip']:.2f}",
                 f"{100 * o['torque_rel_rms']:.2f}", f"{o['growth_efolds']:.2f}",
                 f"{n_ok}/{len(metrics['motions'])}"))
    width = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]

    def line(r):
        return "  ".join([r[0].ljust(width[0])] + [c.rjust(w) for c, w in zip(r[1:5], width[1:5])]
                         + [r[5]]).rstrip()
    rule = "-" * len(line(rows[0]))
    lines = [line(rows[0]), rule, *map(line, rows[1:-1]), rule, line(rows[-1]), ""]
    verdict = "every motion reproduced" if o["success"] else "not all motions reproduced"
    lines.append(f"M = {o['M']} fields, {verdict}, at most {o['numbers_per_s']:.0f} numbers per second of "
                 f"motion, wall time {_duration(o['wall_time_s'])}")
    if "method" in metrics.get("history", {}):
        lines.append(method_line(metrics["history"]["method"]))
    if "identity" in metrics:
        lines.append(identity_line(metrics["identity"]))
    for skip in metrics.get("skipped", []):
        lines.append(f"skipped {skip['file']}: {skip['reason']}")
    if out is not None:
        lines.append(f"artefacts in {out}: basis.json, metrics.json, config.yaml, figures/"
                     + (", tensorboard/" if (Path(out) / "tensorboard").is_dir() else ""))
    return "\n".join(lines)


def _verdict(motion: dict, alone: Optional[bool]) -> str:
    """A motion's "reproduced" cell, and why not: its simulation failed, or its own fit
    (``alone``: the ``each`` stage's verdict, None where no motion was fitted alone) did
    not reproduce it either."""
    if motion["success"]:
        return "yes"
    if motion.get("failure"):
        return "no: simulation failed"
    return "no: nor by its own fit" if alone is False else "no"


def method_line(decision: dict) -> str:
    """One line of what ``solver.method: auto`` chose (metrics.json's ``history.method``,
    :func:`tflearn.train.choice.choose`) and why: the probed motions' relative torque
    costs on a few fields of each stiffness kind probed."""
    spans = []
    for kind, costs in decision["probes"].items():
        c = list(costs.values())
        spans.append(f"{kind} {min(c):.1e}" + (f"–{max(c):.1e}" if len(c) > 1 else ""))
    why = (f"relative torque cost of the probed motions on a few fields: {', '.join(spans)}; "
           f"bar {decision['tol']:g}")
    if decision["method"] == "pipeline":
        return (f"method: the pipeline learned the shared basis, {decision['stiffness']} K "
                f"(solver.method auto; {why})")
    return (f"method: convergent fields held on the path (solver.method auto; {why}: "
            f"no few fields made these motions)")


def identity_line(identity: dict, listed: int = 3) -> str:
    """One line of metrics.json's ``identity`` block (:func:`tflearn.fit.identity.identify`):
    how many generating fields meet the bar, the worst centre distance and stiffness
    ratio among them, and the first ``listed`` that do not, each with its match."""
    fields = identity["fields"]
    ok = [f for f in fields if f["matched"]]
    line = f"generating fields matched: {identity['matched']}/{identity['G']}"
    if ok:
        worst = max((abs(f["stiffness_ratio"] - 1) for f in ok if f["stiffness_ratio"] is not None),
                    default=0.0)
        line += (f" (centre ≤ {max(f['centre_distance_rad'] for f in ok):.4f} rad, stiffness within "
                 f"{100 * worst:.2f}%)")
    missed = [f for f in fields if not f["matched"]]
    if missed:
        def one(f):
            if f["learned"] is None:
                return f"{f['field']} (none)"
            ratio = "" if f["stiffness_ratio"] is None else f", stiffness ×{f['stiffness_ratio']:.2f}"
            return f"{f['field']} (nearest field {f['learned']}: {f['centre_distance_rad']:.3f} rad{ratio})"
        more = f" and {len(missed) - listed} more" if len(missed) > listed else ""
        line += "; not: " + ", ".join(map(one, missed[:listed])) + more
    return line
