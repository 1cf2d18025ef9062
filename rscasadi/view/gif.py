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
    # a motion shorter than 2 s plays slowed down to 2 s, and its end is held for half a second
    slow = max(1.0, 2.0 / max(float(scene.times[-1]), 1e-9))
    step = max(1, int(round((len(scene.times) - 1) / max(scene.times[-1] * slow * fps, 1))))
    motion = list(range(0, len(scene.times), step)) or [0]
    if motion[-1] != len(scene.times) - 1:              # the motion to its last instant
        motion.append(len(scene.times) - 1)
    rate = max(1, round((len(motion) - 1) / max(float(scene.times[-1]) * slow, 1e-9))) if len(motion) > 1 else fps
    frames = motion + [len(scene.times) - 1] * (rate // 2)

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
        ax.set_title(f"{scene.title}  t = {scene.times[k]:.2f} s" + (f" (slowed x{slow:.1f})" if slow > 1 else ""),
                     fontsize=9)
        for a, b in points(k):
            ax.plot(*zip(a, b), color="red" if scene.broken[k] else "0.35", lw=5, solid_capstyle="round")
            ax.scatter(*a, color="tab:blue", s=25)
        if scene.path is not None:
            ax.plot(*scene.path.T, color="tab:green", lw=1)
        for ob in scene.obstacles:
            _obstacle(ax, ob)
        return []

    tmp = Path(out).with_name(f".{Path(out).name}.part.gif")
    try:
        FuncAnimation(fig, draw, frames=frames).save(tmp, writer=PillowWriter(fps=rate))
        tmp.replace(out)
    finally:
        tmp.unlink(missing_ok=True)
        plt.close(fig)


def _obstacle(ax, ob):
    """A sphere as a wireframe of its radius, a box as its twelve edges."""
    c = np.asarray(ob["center"], float)
    if ob["kind"] == "sphere":
        u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 13), np.linspace(0, np.pi, 7))
        r = ob["radius"]
        ax.plot_wireframe(c[0] + r * np.cos(u) * np.sin(v), c[1] + r * np.sin(u) * np.sin(v), c[2] + r * np.cos(v),
                          color="tab:orange", lw=0.6, alpha=0.8)
        return
    h = np.asarray(ob["size"], float) / 2
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * h + c
    for i in range(8):
        for j in range(i + 1, 8):
            if np.sum(np.abs(corners[i] - corners[j]) > 1e-12) == 1:      # an edge: one coordinate differs
                ax.plot(*zip(corners[i], corners[j]), color="tab:orange", lw=0.8)
