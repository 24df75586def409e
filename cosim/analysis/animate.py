"""Animation of the manipulator from any trace that holds a platform pose.

The pose columns ``<comp>.platform.x``, ``.y``, ``.phi`` [m, m, rad] place the platform; the
fixed joints come from the mechanism's geometry (:mod:`models.geometry`, with the scene's
``config`` option and geometry parameters), the platform joints from the inverse-kinematics map
of :mod:`models.kinematics` (``B_i = A_i + L_i (cos theta_i, sin theta_i)``).  Legs outside the
stroke ``[Lmin, Lmax]`` are drawn red.  Written with matplotlib's PillowWriter (GIF).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from models.geometry import Manipulator, preset

from ..errors import UserError
from ..trace.traces import Trace



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
    from matplotlib.animation import FuncAnimation, PillowWriter

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
    fig, ax = plt.subplots(figsize=(5.2, 5.2), dpi=80, layout="constrained")
    ax.set_aspect("equal")
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title or f"{comp}: platform and legs")
    ax.plot(*np.vstack([A, A[:1]]).T, ls=":", c="0.6", lw=1)
    ax.plot(A[:, 0], A[:, 1], "ks", ms=6)
    for i, a in enumerate(A):
        ax.annotate(f"A{i + 1}", a, textcoords="offset points", xytext=(4, 4), fontsize=8)
    path_line, = ax.plot([], [], c="tab:blue", lw=0.8, alpha=0.6)
    legs = [ax.plot([], [], lw=3, solid_capstyle="round")[0] for _ in range(3)]
    plat = plt.Polygon(B[0], closed=True, fc="tab:orange", ec="k", alpha=0.7)
    ax.add_patch(plat)
    centre, = ax.plot([], [], "k+", ms=8)
    text = ax.text(0.02, 0.98, "", transform=ax.transAxes, va="top", family="monospace", fontsize=8)

    def draw(k: int):
        for i, ln in enumerate(legs):
            ln.set_data([A[i, 0], B[k, i, 0]], [A[i, 1], B[k, i, 1]])
            ln.set_color("tab:red" if not (m.Lmin <= L[k, i] <= m.Lmax) else "tab:green")
        plat.set_xy(B[k])
        centre.set_data([q[0, k]], [q[1, k]])
        path_line.set_data(q[0, : k + 1], q[1, : k + 1])
        text.set_text(f"t = {t[idx[k]]:6.3f} s\n" + "\n".join(f"L{i + 1} = {L[k, i]:.4f} m" for i in range(3))
                      + f"\nphi = {q[2, k]:+.4f} rad")
        return [*legs, plat, centre, path_line, text]

    anim = FuncAnimation(fig, draw, frames=len(idx), blit=False)
    from ..outputs import staged

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with staged(path) as part:  # an interrupted animation never replaces a complete one
            try:
                anim.save(str(part), writer=PillowWriter(fps=fps))
            except Exception as exc:  # the writer's own clean-up fails after a signal: the signal counts
                if isinstance(exc.__context__, KeyboardInterrupt):
                    raise exc.__context__ from None
                raise
    finally:
        plt.close(fig)
    return path
