"""A scene as one self-contained HTML file, drawn by MeshCat's viewer (three.js; its script is
inlined from the meshcat package, so the page opens offline, without a server).

The scene is sent to the viewer as MeshCat's own commands (set_object, set_transform,
set_animation, msgpack-encoded, as meshcat's server would send them); its GUI has the
animation's play button and time slider.  `view.html#t=0.35` opens the arm at 0.35 s.
"""
from __future__ import annotations

import base64
import json
from pathlib import Path

import numpy as np

ARM = ("meshcat", "arm")
COLOURS = {"link": 0xB0B8C8, "rotor": 0x3060C0, "path": 0x20A020, "goal": 0x20C040, "obstacle": 0xC07030,
           "payload": 0xD0A020, "broken": 0xE02020}


def _path(*parts):
    from meshcat.path import Path as MeshcatPath
    return MeshcatPath(ARM + tuple(parts))


def _packed(command) -> str:
    import umsgpack
    return base64.b64encode(umsgpack.packb(command.lower())).decode()


def _align_y(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """4x4 placing MeshCat's cylinder (its axis y, centred) on the segment a-b."""
    d = b - a
    length = np.linalg.norm(d)
    y = d / length if length > 1e-12 else np.array([0.0, 1.0, 0.0])
    x = np.cross(y, [0.0, 0.0, 1.0])
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-9 else np.array([1.0, 0.0, 0.0])
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, np.cross(x, y)])
    T[:3, 3] = (a + b) / 2
    return T


def commands(scene) -> list:
    """MeshCat commands that build and animate the scene."""
    import meshcat.geometry as g
    from meshcat.animation import Animation
    from meshcat.commands import SetAnimation, SetObject, SetTransform
    out = []

    def put(geometry, colour, path, T=None, opacity=1.0):
        material = g.MeshLambertMaterial(color=colour, opacity=opacity, transparent=opacity < 1.0)
        out.append(SetObject(geometry, material, path))
        if T is not None:
            out.append(SetTransform(T, path))

    for body, shapes in scene.visuals.items():              # the URDF's visuals, where at hand
        for i, (kind, data, T) in enumerate(shapes):
            if kind == "mesh":
                suffix = data.rsplit(".", 1)[-1].lower()
                geometry = {"stl": g.StlMeshGeometry, "obj": g.ObjMeshGeometry, "dae": g.DaeMeshGeometry}[suffix].from_file(data)
            elif kind == "box":
                geometry = g.Box(data)
            elif kind == "cylinder":                         # MeshCat's axis is y, the URDF's z
                geometry, T = g.Cylinder(data[1], data[0]), T @ _align_y(np.array([0.0, 0.0, -1.0]), np.array([0.0, 0.0, 1.0]))
            else:
                geometry = g.Sphere(data[0])
            put(geometry, COLOURS["link"], _path(f"body{body}", f"visual{i}"), T)
    for body, capsules in scene.links.items():
        if not scene.draws_capsules(body):
            continue
        for i, (a, b, r) in enumerate(capsules):
            length = float(np.linalg.norm(b - a))
            put(g.Cylinder(max(length, 1e-4), r), COLOURS["link"], _path(f"body{body}", f"rod{i}"), _align_y(a, b))
            for k, end in enumerate((a, b)):
                T = np.eye(4)
                T[:3, 3] = end
                put(g.Sphere(r), COLOURS["link"], _path(f"body{body}", f"rod{i}", f"end{k}"),
                    np.linalg.inv(_align_y(a, b)) @ T)
    # the rotors stand out of the links' capsules on both sides
    half = max([0.03] + [r + 0.015 for capsules in scene.links.values() for _, _, r in capsules])
    for j, (parent, T) in enumerate(scene.rotors):
        axis = T @ np.array([[0.0, 0.0, -half, 1.0], [0.0, 0.0, half, 1.0]]).T
        put(g.Cylinder(2 * half, 0.045), COLOURS["rotor"], _path(f"body{parent}", f"rotor{j}"),
            _align_y(axis[:3, 0], axis[:3, 1]), opacity=0.8)
    if scene.payload is not None:
        body, T, size, kind = scene.payload
        shape = g.Sphere(size / 2) if kind == "sphere" else g.Box([size, size, size])
        put(shape, COLOURS["payload"], _path(f"body{body}", "payload"), T)
    if scene.path is not None and len(scene.path) > 1:
        out.append(SetObject(g.Line(g.PointsGeometry(scene.path.T), g.LineBasicMaterial(color=COLOURS["path"])),
                             path=_path("world", "tool_path")))
    if scene.target is not None:
        out.append(SetObject(g.Line(g.PointsGeometry(scene.target.T), g.LineBasicMaterial(color=COLOURS["goal"])),
                             path=_path("world", "target_path")))
    for i, where in enumerate(np.atleast_2d(scene.goal) if scene.goal is not None else []):
        T = np.eye(4)
        T[:3, 3] = where
        put(g.Sphere(0.015), COLOURS["goal"], _path("world", "goal" if i == 0 else f"goal{i}"), T)
    for i, ob in enumerate(scene.obstacles):
        T = np.eye(4)
        T[:3, 3] = ob["center"]
        shape = g.Sphere(ob["radius"]) if ob["kind"] == "sphere" else g.Box(ob["size"])
        put(shape, COLOURS["obstacle"], _path("world", f"obstacle{i}"), T, opacity=0.6)
    out.append(SetObject(g.LineSegments(g.PointsGeometry(floor_lines(scene).T), g.LineBasicMaterial(color=0xB8BEC8)),
                         path=_path("world", "floor")))
    # a red marker at the base, shown (scaled up) in the frames where a limit or clearance is broken
    put(g.Sphere(0.03), COLOURS["broken"], _path("world", "broken"), np.diag([1e-6, 1e-6, 1e-6, 1.0]))
    for body in range(scene.poses.shape[1]):
        out.append(SetTransform(scene.poses[0, body], _path(f"body{body}")))
    if len(scene.times) > 1:
        anim = Animation(default_framerate=1.0 / (scene.times[1] - scene.times[0]))
        frames = _Frames(_path())
        for k in range(len(scene.times)):
            frame = anim.at_frame(frames, k)
            for body in range(scene.poses.shape[1]):
                frame[f"body{body}"].set_transform(scene.poses[k, body])
            s = 1.0 if scene.broken[k] else 1e-6
            frame["world"]["broken"].set_property("scale", "vector3", [s, s, s])
        out.append(SetAnimation(anim, play=False))
    return out


class _Frames:
    """What Animation.at_frame needs of a visualiser: its path."""

    def __init__(self, path):
        self.path = path


PAGE = """<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>{title}</title>
<style>body {{ margin: 0; }} #meshcat-pane {{ width: 100vw; height: 100vh; overflow: hidden; }}
#clock {{ position: absolute; left: 12px; bottom: 10px; font: 14px sans-serif; color: #222; }}</style></head>
<body><div id="meshcat-pane"></div><div id="clock"></div>
<script>{viewer}</script>
<script>
var viewer = new MeshCat.Viewer(document.getElementById("meshcat-pane"));
function run(b64) {{
  var raw = atob(b64), bytes = new Uint8Array(raw.length);
  for (var i = 0; i < raw.length; ++i) bytes[i] = raw.charCodeAt(i);
  viewer.handle_command_bytearray(bytes);
}}
{commands}
viewer.set_property(["Background"], "top_color", [1.0, 1.0, 1.0]);
viewer.set_property(["Background"], "bottom_color", [0.85, 0.88, 0.92]);
viewer.set_property(["Cameras", "default", "rotated", "<object>"], "position", {camera});
viewer.controls.target.set({target});                 // the orbit turns about the scene's centre
viewer.controls.update();
viewer.set_property(["Grid"], "visible", false);      // the scene's own floor grid instead
function at_hash() {{
  var m = /t=([0-9.eE+-]+)/.exec(location.hash);
  var t = m ? parseFloat(m[1]) : 0.0;
  if (viewer.animator.actions.length) {{          // actions take effect once played: play, hold, seek
    viewer.animator.play(); viewer.animator.pause(); viewer.animator.seek(t); viewer.animator.display_progress(t);
  }}
  document.getElementById("clock").textContent = "{title}, t = " + t.toFixed(3) + " s of {duration:.3f} s";
}}
window.addEventListener("hashchange", at_hash);
at_hash();
</script></body></html>
"""


def write_html(scene, out: Path):
    """The scene as one HTML file at `out` (written whole)."""
    import meshcat
    from rscasadi.files import write_text
    viewer = (Path(meshcat.__file__).parent / "viewer" / "dist" / "main.min.js").read_text()
    calls = "\n".join(f'run("{_packed(c)}");' for c in commands(scene))
    title = "".join(ch for ch in scene.title if ch.isalnum() or ch in "._-/ ")
    position, target, _ = framing(scene)
    write_text(out, PAGE.format(title=title, viewer=viewer, commands=calls, duration=float(scene.times[-1]),
                                camera=json.dumps(_rotated(position)), target=", ".join(map(repr, _rotated(target)))))


FOV_DEG = 75.0                          # MeshCat's camera's vertical field of view
VIEW_DIRECTION = np.array([1.0, -1.0, 0.75]) / np.linalg.norm([1.0, -1.0, 0.75])   # front, right, above


def floor_lines(scene, spacing: float = 0.1) -> np.ndarray:
    """Segments (2k x 3) of a floor grid under the scene: just below everything shown (and no
    higher than z = 0), reaching a little beyond it, every `spacing` m."""
    from rscasadi.view.scene import bounds
    lo, hi = bounds(scene)
    z = float(min(lo[2], 0.0)) - 1e-3
    x0, y0 = np.floor((lo[:2] - 0.2) / spacing) * spacing
    x1, y1 = np.ceil((hi[:2] + 0.2) / spacing) * spacing
    xs, ys = np.arange(x0, x1 + spacing / 2, spacing), np.arange(y0, y1 + spacing / 2, spacing)
    seg = [[(x, y0, z), (x, y1, z)] for x in xs] + [[(x0, y, z), (x1, y, z)] for y in ys]
    return np.array(seg, float).reshape(-1, 3)


def framing(scene) -> tuple[np.ndarray, np.ndarray, float]:
    """Where the camera stands and what it looks at (world frame) so that everything the scene
    shows at any instant fits the view (bounds), and the floor's height: just under all of it."""
    from rscasadi.view.scene import bounds
    lo, hi = bounds(scene)
    centre, radius = (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 0.2)
    distance = 1.1 * radius / np.sin(np.radians(FOV_DEG) / 2)
    return centre + distance * VIEW_DIRECTION, centre, float(min(lo[2], 0.0)) - 1e-3


def _rotated(p) -> list:
    """A world point in MeshCat's rotated (y up) frame."""
    x, y, z = (float(v) for v in p)
    return [x, z, -y]
