"""A scene as an animated GIF for documents, drawn like the HTML page: the links' capsules (or
the URDF's visuals) as shaded solids, the rotors as blue drums at the joints, obstacles and the
payload to scale, the tool path, a floor grid, seen from the page's camera and framed on
everything the scene shows at any instant (nothing clipped).  matplotlib in 3D, one frame per
animation frame, 800 x 600 pixels."""
from __future__ import annotations

from pathlib import Path

from typing import Any
import numpy as np

LINK, ROTOR, OBSTACLE, PAYLOAD, BROKEN, PATH, FLOOR = "#b0b8c8", "#3060c0", "#c07030", "#d0a020", "#e02020", \
    "#20a020", "#c8ccd4"
ROTOR_RADIUS = 0.045
MAX_MESH_FACES = 1500


def _tube(a, b, r, k=14):
    """A cylinder's side from a to b of radius r: three (2, k) grids of x, y, z."""
    d = b - a
    length = np.linalg.norm(d)
    z = d / length if length > 1e-12 else np.array([0.0, 0.0, 1.0])
    x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    u = np.linspace(0, 2 * np.pi, k)
    ring = np.outer(np.cos(u), x) + np.outer(np.sin(u), y)                 # (k, 3)
    pts = np.stack([a + r * ring, b + r * ring])                          # (2, k, 3)
    return pts[..., 0], pts[..., 1], pts[..., 2]


def _ball(c, r, k=10):
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, k + 2), np.linspace(0, np.pi, k // 2 + 2))
    return c[0] + r * np.cos(u) * np.sin(v), c[1] + r * np.sin(u) * np.sin(v), c[2] + r * np.cos(v)


def _box_faces(T, size):
    h = np.asarray(size, float) / 2
    c = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * h
    c = c @ T[:3, :3].T + T[:3, 3]
    quads = [(0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5)]
    return [c[list(q)] for q in quads]


def _mesh_faces(path: str, T):
    """A mesh file's triangles placed by T (its scale folded in), at most MAX_MESH_FACES of them."""
    import trimesh
    mesh: Any = trimesh.load(path, force="mesh", process=False)       # a Trimesh (force="mesh")
    tri = np.asarray(mesh.vertices, float)[np.asarray(mesh.faces)]
    if len(tri) > MAX_MESH_FACES:
        tri = tri[np.argsort(-mesh.area_faces)[:MAX_MESH_FACES]]             # the largest faces shape it
    return tri @ T[:3, :3].T + T[:3, 3]


def _solids(scene):
    """Per body the solids that ride on it, in its frame: ("tube"/"ball"/"faces", data)."""
    out = {}
    for body, capsules in scene.links.items():
        if not scene.draws_capsules(body):
            continue
        for a, b, r in capsules:
            out.setdefault(body, []).append(("tube", (np.asarray(a, float), np.asarray(b, float), r)))
            out[body] += [("ball", (np.asarray(e, float), r)) for e in (a, b)]
    for body, shapes in scene.visuals.items():
        for kind, data, T in shapes:
            try:
                if kind == "mesh":
                    out.setdefault(body, []).append(("faces", _mesh_faces(data, T)))
                elif kind == "box":
                    out.setdefault(body, []).append(("faces", np.array(_box_faces(T, data))))
                elif kind == "cylinder":
                    r, length = data
                    ends = T @ np.array([[0, 0, -length / 2, 1.0], [0, 0, length / 2, 1.0]]).T
                    out.setdefault(body, []).append(("tube", (ends[:3, 0], ends[:3, 1], r)))
                else:
                    out.setdefault(body, []).append(("ball", (T[:3, 3], data[0])))
            except (OSError, ValueError):
                continue
    return out


def write_gif(scene, out: Path, fps: int = 15):
    """The animation of `scene` at `fps` into `out` (written whole)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.animation import FuncAnimation, PillowWriter
    from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

    from rscasadi.view.html import VIEW_DIRECTION, floor_lines
    from rscasadi.view.scene import bounds
    fig = plt.figure(figsize=(8, 6), dpi=100)
    ax = fig.add_axes((0, 0, 1, 1), projection="3d")
    lo, hi = bounds(scene)
    lo, hi = np.minimum(lo, [np.inf, np.inf, 0.0]) - 0.05, hi + 0.05
    centre, half = (lo + hi) / 2, np.max(hi - lo) / 2
    elev = np.degrees(np.arcsin(VIEW_DIRECTION[2]))
    azim = np.degrees(np.arctan2(VIEW_DIRECTION[1], VIEW_DIRECTION[0]))
    solids, floor = _solids(scene), floor_lines(scene).reshape(-1, 2, 3)
    half_rotor = max([0.03] + [r + 0.015 for capsules in scene.links.values() for _, _, r in capsules])
    slow = max(1.0, 2.0 / max(float(scene.times[-1]), 1e-9))   # a short motion plays slowed to 2 s
    step = max(1, int(round((len(scene.times) - 1) / max(scene.times[-1] * slow * fps, 1))))
    motion = list(range(0, len(scene.times), step)) or [0]
    if motion[-1] != len(scene.times) - 1:              # the motion to its last instant
        motion.append(len(scene.times) - 1)
    rate = max(1, round((len(motion) - 1) / max(float(scene.times[-1]) * slow, 1e-9))) if len(motion) > 1 else fps
    frames = motion + [len(scene.times) - 1] * (rate // 2)       # and its end held for half a second

    def place(T, p):
        return np.asarray(p, float) @ T[:3, :3].T + T[:3, 3]

    def draw(k):
        ax.cla()
        ax.set_axis_off()
        ax.set_box_aspect((1, 1, 1), zoom=1.35)
        ax.set(xlim=(centre[0] - half, centre[0] + half), ylim=(centre[1] - half, centre[1] + half),
               zlim=(centre[2] - half, centre[2] + half))
        ax.view_init(elev=elev, azim=azim)
        ax.add_collection3d(Line3DCollection(floor, colors=FLOOR, linewidths=0.6))
        colour = BROKEN if scene.broken[k] else LINK
        for body, items in solids.items():
            T = scene.poses[k, body]
            for kind, data in items:
                if kind == "tube":
                    a, b, r = data
                    ax.plot_surface(*_tube(place(T, a), place(T, b), r), color=colour, shade=True, lw=0)
                elif kind == "ball":
                    ax.plot_surface(*_ball(place(T, data[0]), data[1]), color=colour, shade=True, lw=0)
                else:
                    ax.add_collection3d(Poly3DCollection(place(T, data.reshape(-1, 3)).reshape(data.shape),
                                                         facecolors=colour, shade=True))
        for parent, J in scene.rotors:
            T = scene.poses[k, parent] @ J
            ends = place(T, [[0, 0, -half_rotor], [0, 0, half_rotor]])
            ax.plot_surface(*_tube(ends[0], ends[1], ROTOR_RADIUS), color=ROTOR, shade=True, lw=0, alpha=0.9)
        if scene.payload is not None:
            body, T0, size, kind = scene.payload
            T = scene.poses[k, body] @ T0
            if kind == "sphere":
                ax.plot_surface(*_ball(T[:3, 3], size / 2), color=PAYLOAD, shade=True, lw=0)
            else:
                ax.add_collection3d(Poly3DCollection(_box_faces(T, [size] * 3), facecolors=PAYLOAD, shade=True))
        for ob in scene.obstacles:
            c = np.asarray(ob["center"], float)
            if ob["kind"] == "sphere":
                ax.plot_surface(*_ball(c, ob["radius"], 16), color=OBSTACLE, shade=True, lw=0, alpha=0.6)
            else:
                T = np.eye(4)
                T[:3, 3] = c
                ax.add_collection3d(Poly3DCollection(_box_faces(T, ob["size"]), facecolor=OBSTACLE, alpha=0.35,
                                                     edgecolor=OBSTACLE))
        for line in (scene.path, scene.target):
            if line is not None and len(line) > 1:
                ax.plot(*np.asarray(line).T, color=PATH, lw=1.2)
        ax.text2D(0.02, 0.03, f"{scene.title}, t = {scene.times[k]:.3f} s of {scene.times[-1]:.3f} s"
                  + (f" (slowed x{slow:.1f})" if slow > 1 else ""), transform=ax.transAxes, fontsize=11)
        return []

    from rscasadi.files import replacing
    try:
        with replacing(out) as tmp:
            FuncAnimation(fig, draw, frames=frames).save(tmp, writer=PillowWriter(fps=rate))
    finally:
        plt.close(fig)
