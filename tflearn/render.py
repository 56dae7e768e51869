"""Animations of a run: one motion's target and its reproduction by the learned program.

:func:`render` re-simulates a motion of a run exactly as :func:`tflearn.evaluate.evaluate_run`
does (the run's basis.json and config.yaml, the motion from the config's ``data``, its
stored weights, the config's solver settings) and draws both arms side by side in 3-D as
stick figures (:func:`tflearn.plots.figures.joint_positions`) with their hand trails. Frame k
shows the sample nearest to t = k/fps, for k = 0 … ⌊λ·fps⌋ (λ the motion's duration).

In TensorBoard (RUN/tensorboard, the run's own events) the frames are images, through
the writer's image API (no video encoder needed): ``render/MOTION/frames`` one image
per frame at steps 0 … F−1 (scrub with the step slider; TensorBoard keeps all of them
with ``--samples_per_plugin images=F``), and ``render/MOTION/strip`` a contact sheet of
up to :data:`STRIP_FRAMES` evenly spaced frames.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Callable

import numpy as np

from .data.loading import named_motions, torsos
from .errors import InputError
from .evaluate import run_config, weights_for
from .fit.targets import prepare
from .io import basis as basis_io
from .io.files import replacing
from .metrics import score
from .plots import figures as plots

STRIP_FRAMES = 8          # frames in the TensorBoard contact sheet (4 per row)


def contact_sheet(frames: list, count: int = STRIP_FRAMES, columns: int = 4) -> np.ndarray:
    """Up to ``count`` evenly spaced frames (H×W×3 uint8 each) in a grid of ``columns``
    (the last row padded white): H·rows × W·columns × 3 uint8."""
    pick = np.unique(np.linspace(0, len(frames) - 1, min(count, len(frames))).round().astype(int))
    tiles = [frames[i] for i in pick]
    columns = min(columns, len(tiles))
    rows = -(-len(tiles) // columns)
    tiles += [np.full_like(tiles[0], 255)] * (rows * columns - len(tiles))
    return np.concatenate([np.concatenate(tiles[r * columns:(r + 1) * columns], 1)
                           for r in range(rows)], 0)


def frame_samples(t, fps: float) -> np.ndarray:
    """Sample index shown in each frame: the sample of t (T, from 0) nearest to k/fps for
    k = 0 … ⌊t[-1]·fps⌋."""
    t = np.asarray(t, dtype=float)
    n = int(math.floor(t[-1] * fps + 1e-9)) + 1
    return np.abs(t[:, None] - np.arange(n) / fps).argmin(0)


def render(run, motion: str, out=None, fps: int = 25, tensorboard: bool = True,
           log: Callable[[str], None] = print, progress: bool = True) -> Path:
    """Animate motion ``motion`` of the run folder ``run``: target and reproduced arm.

    Writes a GIF (default RUN/figures/MOTION.gif) and, with ``tensorboard``, the same
    frames as images in RUN/tensorboard (see the module); ``log`` receives a line
    saying what was logged. ``progress``: a bar on stderr
    (:func:`tflearn.log.progress_bar`): the simulation, then the frames drawn. Returns the
    GIF's path.

    Raises :class:`~tflearn.errors.InputError` for a motion name the basis does not hold
    (the message lists the names it holds) or one missing from the run's data, and for
    fps ≤ 0.
    """
    if fps <= 0:
        raise InputError(f"fps must be positive, got {fps}")
    run = Path(run)
    lb = basis_io.load(run / "basis.json")
    lb.index(motion)
    cfg, options = run_config(run)
    found = named_motions(cfg.data, lb.body, [motion], str(run / "basis.json"))
    from .log import progress_bar
    with progress_bar(None, f"render {motion}", "frames", progress) as bar:
        bar.set_postfix_str("simulating")
        tg = prepare(lb.body, found, base=torsos(cfg.data, found, cfg.torso))
        s = score(lb.body, lb.basis, weights_for(lb, tg), tg, options)
        T = int(tg.mask[0].sum())
        t = tg.t[0, :T].numpy()
        paths = {"target": plots.joint_positions(lb.body, tg.q[0, :T]),
                 "reproduced": plots.joint_positions(lb.body, s.q_sim[0, :T])}
        out = Path(out) if out is not None else run / "figures" / f"{motion}.gif"
        out.parent.mkdir(parents=True, exist_ok=True)
        samples = frame_samples(t, fps)
        bar.total = len(samples)
        bar.set_postfix_str("drawing")
        frames = write_gif(paths, t, samples, fps, out,
                           f"{motion}: rmse {s.rmse[0]:.4f} rad, tip error {100 * s.tip[0]:.2f} cm",
                           keep=tensorboard, tick=bar.update)
        if tensorboard:
            bar.set_postfix_str("logging the frames to TensorBoard")
            log_frames(run / "tensorboard", motion, frames)
    if tensorboard:
        log(f"tensorboard: logged {len(frames)} frames as images render/{motion}/frames "
            f"(steps 0-{len(frames) - 1}; see them all with tensorboard --samples_per_plugin "
            f"images={len(frames)}) and render/{motion}/strip to {run / 'tensorboard'}")
    return out


#: The smallest width (px) of an animation frame, and its fonts' smallest size (pt).
GIF_MIN_WIDTH = 900
GIF_FONT = 11


def log_frames(logdir, motion: str, frames: list) -> None:
    """Log animation frames (H×W×3 uint8) to the TensorBoard run ``logdir`` as images:
    ``render/MOTION/frames`` at steps 0 … F−1 and the contact sheet ``render/MOTION/strip``."""
    from torch.utils.tensorboard import SummaryWriter
    with SummaryWriter(str(logdir)) as writer:
        for k, frame in enumerate(frames):
            writer.add_image(f"render/{motion}/frames", frame, k, dataformats="HWC")
        writer.add_image(f"render/{motion}/strip", contact_sheet(frames), 0, dataformats="HWC")


def write_gif(paths: dict, t: np.ndarray, samples: np.ndarray, fps: int, out: Path,
              title: str, keep: bool, reference=None, window=None,
              tick: Callable[[], object] = lambda: None) -> list:
    """Draw one frame per entry of ``samples`` and write them to ``out`` with
    PillowWriter; ``paths``: label → joint positions (T×(L+1)×3), one 3-D panel each
    (axes x, y, z in m), the title above them with the time in s. ``reference`` (joint
    positions) is drawn as a dashed "target hand path" in every panel; without it the
    first path is, in the other panels. ``window`` (t₀, t₁): while t₀ ≤ t ≤ t₁ the hands
    are marked with a red star and the title says "push". Frames are at least
    :data:`GIF_MIN_WIDTH` px wide (560 px per panel), fonts at least :data:`GIF_FONT` pt.
    ``tick()`` follows each frame drawn (a progress bar's ``update``). Returns the frames
    as H×W×3 uint8 arrays when ``keep``, else []."""
    import matplotlib.pyplot as plt
    from matplotlib.animation import PillowWriter

    dpi = 100
    width = max(GIF_MIN_WIDTH / dpi, 5.6 * len(paths))
    fig = plt.figure(figsize=(width, 5.8), dpi=dpi)
    allpts = np.concatenate(list(paths.values()) + ([reference] if reference is not None else []), 0)
    artists = []
    for n, (label, P) in enumerate(paths.items()):
        color = f"C{n}"
        ax = fig.add_subplot(1, len(paths), n + 1, projection="3d")
        ax.computed_zorder = False               # the target's path stays on top of the trail
        ref = reference if reference is not None else (next(iter(paths.values())) if n else None)
        if ref is not None:
            ax.plot(ref[:, -1, 0], ref[:, -1, 1], ref[:, -1, 2], "--", color="0.3", lw=1.2,
                    label="target hand path", zorder=4)
        arm, = ax.plot([], [], [], "o-", color=color, ms=6, lw=3, label=f"{label} arm")
        trail, = ax.plot([], [], [], color=color, lw=1.6, label=f"{label} hand trail")
        star, = ax.plot([], [], [], "*", color="red", ms=16, zorder=5)
        plots._equal_3d(ax, allpts, fontsize=GIF_FONT)
        ax.view_init(elev=15, azim=-30)
        ax.set_title(label, fontsize=GIF_FONT + 2)
        ax.tick_params(labelsize=GIF_FONT - 1)
        ax.legend(fontsize=GIF_FONT - 1, loc="upper left")
        artists.append((P, arm, trail, star))
    head = fig.suptitle("", fontsize=GIF_FONT + 3)
    fig.subplots_adjust(left=0.02, right=0.95, bottom=0.04, top=0.86, wspace=0.12)
    frames = []
    writer = PillowWriter(fps=fps)
    with replacing(out) as tmp, writer.saving(fig, str(tmp), dpi=fig.dpi):
        for k in samples:
            pushing = window is not None and window[0] <= t[k] <= window[1]
            for P, arm, trail, star in artists:
                arm.set_data_3d(P[k, :, 0], P[k, :, 1], P[k, :, 2])
                trail.set_data_3d(P[:k + 1, -1, 0], P[:k + 1, -1, 1], P[:k + 1, -1, 2])
                star.set_data_3d(P[k:k + 1, -1, 0] if pushing else [], P[k:k + 1, -1, 1] if pushing else [],
                                 P[k:k + 1, -1, 2] if pushing else [])
            head.set_text(f"{title}\nt = {t[k]:.2f} s" + ("   (push)" if pushing else ""))
            writer.grab_frame()
            if keep:
                fig.canvas.draw()
                frames.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
            tick()
    plt.close(fig)
    return frames
