"""A scene as an animated GIF for documents: the links as rods and the joints as dots, drawn by
matplotlib in 3D, one frame per animation frame."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def write_gif(scene, out: Path, fps: int = 15):
    """The animation of `scene` at `fps` into `out` (written whole)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.animation import FuncAnimation, PillowWriter
    fig = plt.figure(figsize=(4.8, 4.2), dpi=90)
    ax = fig.add_subplot(projection="3d")
    points_seen = [scene.poses[:, :, :3, 3].reshape(-1, 3)] + ([scene.path] if scene.path is not None else [])
    reach = max(float(np.max(np.abs(np.vstack(points_seen)))), 0.2) * 1.15
    step = max(1, int(round((len(scene.times) - 1) / max(scene.times[-1] * fps, 1))))
    frames = list(range(0, len(scene.times), step)) or [0]

    def points(k):
        P = []
        for body, capsules in scene.links.items():
            for a, b, _ in capsules:
                T = scene.poses[k, body]
                P.append([(T @ np.r_[a, 1.0])[:3], (T @ np.r_[b, 1.0])[:3]])
        return P

    def draw(k):
        ax.cla()
        ax.set(xlim=(-reach, reach), ylim=(-reach, reach), zlim=(0, reach), xlabel="x (m)", ylabel="y (m)",
               zlabel="z (m)")
        ax.set_title(f"{scene.title}  t = {scene.times[k]:.2f} s", fontsize=9)
        for a, b in points(k):
            ax.plot(*zip(a, b), color="red" if scene.broken[k] else "0.35", lw=5, solid_capstyle="round")
            ax.scatter(*a, color="tab:blue", s=25)
        if scene.path is not None:
            ax.plot(*scene.path.T, color="tab:green", lw=1)
        for ob in scene.obstacles:
            ax.scatter(*ob["center"], color="tab:orange", s=200, alpha=0.5)
        return []

    tmp = Path(out).with_name(f".{Path(out).name}.part.gif")
    try:
        FuncAnimation(fig, draw, frames=frames).save(tmp, writer=PillowWriter(fps=fps))
        tmp.replace(out)
    finally:
        tmp.unlink(missing_ok=True)
        plt.close(fig)
