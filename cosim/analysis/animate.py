"""Animation of the manipulator from any trace that holds a platform pose.

The pose columns ``<comp>.platform.x``, ``.y``, ``.phi`` [m, m, rad] place the platform; the
fixed joints come from the mechanism's geometry (:mod:`models.geometry`, with the scene's
``config`` option and geometry parameters), the platform joints from the inverse-kinematics map
of :mod:`models.kinematics` (``B_i = A_i + L_i (cos theta_i, sin theta_i)``).  Legs outside the
stroke ``[Lmin, Lmax]`` are drawn red.

Speed: matplotlib renders the figure once (axes, labels, fixed joints); each frame then restores
that background and draws only the moving artists (blitting), and Pillow encodes the frames with
one palette taken from a few of them: no layout or full render per frame (pid_step's 101 frames
took 11 s redrawn whole through ``FuncAnimation`` and ``PillowWriter``).
"""
from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from models.geometry import Manipulator, preset

from ..errors import UserError
from ..trace.traces import Trace
from ..outputs import staged



def pose_component(trace: Trace) -> str:
    """The first component whose ``platform.x``, ``platform.y`` and ``platform.phi`` are recorded."""
    for name in trace.names:
        if name.endswith(".platform.x"):
            comp = name[: -len(".platform.x")]
            if f"{comp}.platform.y" in trace and f"{comp}.platform.phi" in trace:
                return comp
    raise UserError("the trace has no platform pose (columns <component>.platform.x, .y, .phi); "
                    "add e.g. 'mech.platform.*' to the scene's outputs")


def joints(m: Manipulator, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For poses ``q`` of shape (3, N): fixed joints A (3, 2), platform joints B (N, 3, 2) and
    leg lengths L (N, 3)."""
    from models import kinematics

    L, th = kinematics.ik(m, q)
    A = np.asarray(m.base, dtype=float)
    B = A[None, :, :] + (L.T[:, :, None] * np.stack([np.cos(th.T), np.sin(th.T)], axis=-1))
    return A, B, L.T


def animate(trace: Trace, path: Path, *, manipulator: Manipulator | None = None, component: str | None = None,
            fps: int = 20, max_frames: int = 150, title: str = "") -> Path:
    """Write a GIF of the platform and legs over the trace to ``path``; returns the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    comp = component or pose_component(trace)
    m = manipulator or preset("cross_leg")
    t = trace.time
    if len(t) < 2:
        raise UserError("the trace has fewer than two rows; nothing to animate")
    n = int(min(max_frames, max(2, round((t[-1] - t[0]) * fps)) + 1))
    idx = np.unique(np.searchsorted(t, np.linspace(t[0], t[-1], n)).clip(0, len(t) - 1))
    q = np.vstack([trace[f"{comp}.platform.{k}"][idx] for k in ("x", "y", "phi")])
    A, B, L = joints(m, q)
    pts = np.vstack([A, B.reshape(-1, 2)])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = 0.08 * float(np.max(hi - lo))
    fig, ax = plt.subplots(figsize=(5.2, 5.2), dpi=80)
    fig.subplots_adjust(left=0.8 / 5.2, right=1 - 0.15 / 5.2, bottom=0.55 / 5.2, top=1 - 0.35 / 5.2)
    ax.set_aspect("equal")
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title or f"{comp}: platform and legs", y=1.0)
    ax.plot(*np.vstack([A, A[:1]]).T, ls=":", c="0.6", lw=1)
    ax.plot(A[:, 0], A[:, 1], "ks", ms=6)
    for i, a in enumerate(A):
        ax.annotate(f"A{i + 1}", a, textcoords="offset points", xytext=(4, 4), fontsize=8)
    path_line, = ax.plot([], [], c="tab:blue", lw=0.8, alpha=0.6, animated=True)
    legs = [ax.plot([], [], lw=3, solid_capstyle="round", animated=True)[0] for _ in range(3)]
    plat = plt.Polygon(B[0], closed=True, fc="tab:orange", ec="k", alpha=0.7, animated=True)
    ax.add_patch(plat)
    centre, = ax.plot([], [], "k+", ms=8, animated=True)
    moving = [path_line, *legs, plat, centre]

    def draw(k: int) -> None:
        for i, ln in enumerate(legs):
            ln.set_data([A[i, 0], B[k, i, 0]], [A[i, 1], B[k, i, 1]])
            ln.set_color("tab:red" if not (m.Lmin <= L[k, i] <= m.Lmax) else "tab:green")
        plat.set_xy(B[k])
        centre.set_data([q[0, k]], [q[1, k]])
        path_line.set_data(q[0, : k + 1], q[1, : k + 1])

    def caption(k: int) -> str:
        return (f"t = {t[idx[k]]:6.3f} s\n" + "\n".join(f"L{i + 1} = {L[k, i]:.4f} m" for i in range(3))
                + f"\nphi = {q[2, k]:+.4f} rad")


    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        frames = _frames(fig, ax, moving, draw, len(idx))
        _captions(frames, fig, ax, [caption(k) for k in range(len(idx))])
        with staged(path) as part:  # an interrupted animation never replaces a complete one
            _write_gif(frames, part, fps)
    finally:
        plt.close(fig)
    return path


def _frames(fig, ax, moving, draw, n: int) -> list:
    """The ``n`` frames as RGB images: the figure rendered once without the ``moving`` artists
    (its layout then frozen), each frame that background with the moving artists drawn on it."""
    from PIL import Image

    canvas = fig.canvas
    canvas.draw()  # everything that does not move, once
    background = canvas.copy_from_bbox(fig.bbox)
    frames = []
    for k in range(n):
        draw(k)
        canvas.restore_region(background)
        for artist in moving:
            ax.draw_artist(artist)
        canvas.blit(fig.bbox)
        frames.append(Image.fromarray(np.asarray(canvas.buffer_rgba())).convert("RGB"))  # Pillow copies fastest
    return frames


def _captions(frames: list, fig, ax, texts: list[str]) -> None:
    """Each frame's caption (time, leg lengths, angle) written by Pillow in matplotlib's monospace
    font at the axes' top left: text is the costly part of an Agg render (three quarters of it)."""
    from PIL import ImageDraw

    font = caption_font(round(8 * fig.dpi / 72))
    x, y = ax.transAxes.transform((0.02, 0.98))
    height = frames[0].size[1]
    for im, caption in zip(frames, texts):
        ImageDraw.Draw(im).multiline_text((round(x), round(height - y)), caption, fill=(0, 0, 0), font=font,
                                          spacing=2)


@functools.lru_cache(maxsize=4)
def caption_font(size: int):
    """matplotlib's monospace font as a Pillow font of ``size`` pixels."""
    from matplotlib import font_manager
    from PIL import ImageFont

    return ImageFont.truetype(font_manager.findfont(font_manager.FontProperties(family="monospace")), size)


def _write_gif(frames: list, path: Path, fps: int) -> None:
    """``frames`` (RGB images) as an endlessly looping GIF at ``fps``, with one palette of at most
    128 colours taken from the first, middle and last frames (no dithering: flat colours)."""
    from PIL import Image

    pick = [frames[0], frames[len(frames) // 2], frames[-1]]
    w, h = pick[0].size
    sample = Image.new("RGB", (w, h * len(pick)))
    for i, im in enumerate(pick):
        sample.paste(im, (0, i * h))
    palette = sample.quantize(colors=128, method=Image.Quantize.MEDIANCUT)
    images = [im.quantize(palette=palette, dither=Image.Dither.NONE) for im in frames]
    images[0].save(path, format="GIF", save_all=True, append_images=images[1:], duration=round(1000 / fps),
                   loop=0, optimize=False)
