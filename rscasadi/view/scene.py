"""What `rscasadi view` draws, as plain geometry: the arm's links (their capsules, or a rod from
each joint to the next), its rotors at the joints, the tool path, a goal, obstacles and the
payload, and for every frame of the animation each link's pose and whether a limit or a
clearance is broken."""
from __future__ import annotations

import json
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rscasadi.dynamics.arm import Arm, load
from rscasadi.dynamics.collision import exact_clearance
from rscasadi.dynamics.kinematics import body_poses, frame_pose
from rscasadi.model.meshes import mesh_file
from rscasadi.model.types import ModelFileError
from rscasadi.task.objects import goals_of

FPS = 30


@dataclass
class Scene:
    """Everything to draw: `links` per body (1..n) a list of capsules (a, b in the body frame,
    radius), `rotors` per joint (its origin and axis in its parent body's frame), `poses` per
    animation frame per body (4x4 in the world), `broken` per frame (a limit or clearance),
    `path` (k x 3 tool positions), `goal`, `obstacles`, `payload` (body, 4x4 in it, size, "sphere" or "box");
    `visuals` per body its URDF visual geometries (kind, data, 4x4 in the body frame): a body
    that has any is drawn with them instead of its capsules, unless one of its meshes was
    skipped (`incomplete`: then its capsules are drawn too, so nothing is missing); `skipped`:
    the meshes not read (file name, why: only files inside the robot's package are)."""
    title: str
    times: np.ndarray
    poses: np.ndarray                          # (frames, n + 1, 4, 4)
    links: dict
    rotors: list
    broken: np.ndarray
    path: np.ndarray | None = None
    goal: np.ndarray | None = None            # (k x 3) the goals' positions
    obstacles: list = field(default_factory=list)
    payload: tuple | None = None
    target: np.ndarray | None = None
    visuals: dict = field(default_factory=dict)
    skipped: list = field(default_factory=list)
    incomplete: set = field(default_factory=set)

    def draws_capsules(self, body: int) -> bool:
        """Whether `body` is drawn by its capsules: it has no visuals, or some were skipped."""
        return body not in self.visuals or body in self.incomplete


def _homogeneous(R, p) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = np.asarray(R, float), np.asarray(p, float).ravel()
    return T


def _links(arm: Arm) -> dict:
    """Per body its capsules: the model's collision capsules, else a rod from the joint to each
    joint it carries (a leaf link: to its farthest frame), 2.5 cm thick."""
    model = arm.model
    shapes: dict[int, list] = {b: [] for b in range(1, model.n + 1)}
    if model.collision is not None:
        for c in model.collision.capsules:
            shapes[c.body].append((np.asarray(c.a, float), np.asarray(c.b, float), c.radius))
    for b in range(1, model.n + 1):
        if shapes[b]:
            continue
        carried = model.children(b - 1)
        if carried:
            ends = [np.asarray(model.joints[c].origin_xyz, float) for c in carried]
        else:
            ends = [np.asarray(f.p, float) for f in model.frames if f.body == b]
            ends.append(2 * np.asarray(model.joints[b - 1].link.com, float))     # or as far again as its centre
            ends = [max(ends, key=np.linalg.norm)]
        shapes[b] += [(np.zeros(3), end, 0.025) for end in ends]
    return shapes


def _visuals(arm: Arm) -> tuple[dict, list]:
    """Per body the URDF's visual geometries (a URDF model): meshes found inside the robot's
    package (STL, OBJ, DAE) and boxes, cylinders and spheres, each with its pose in the body
    frame; and the meshes skipped, with the reason."""
    urdf = arm.model.extra.get("urdf") if isinstance(arm.model.extra, dict) else None
    if not urdf or not Path(urdf).is_file():
        return {}, []
    import yourdfpy
    robot = yourdfpy.URDF.load(urdf, load_meshes=False, build_scene_graph=False,
                               load_collision_meshes=False, build_collision_scene_graph=False)
    links = {lk.name: lk for lk in robot.robot.links}
    frames = {f.name: f for f in arm.model.frames}
    out: dict = {}
    skipped: list = []
    for name, frame in frames.items():
        if frame.body == 0 or name not in links:
            continue
        for v in links[name].visuals or ():
            T = _homogeneous(frame.R, frame.p) @ np.asarray(v.origin if v.origin is not None else np.eye(4), float)
            g = v.geometry
            if g is None:
                continue
            if g.mesh is not None:
                path, why = mesh_file(Path(urdf), g.mesh.filename)
                if path is None:
                    skipped.append((g.mesh.filename, why, frame.body))
                    continue
                scale = np.ones(3) if g.mesh.scale is None else np.broadcast_to(np.asarray(g.mesh.scale, float), 3)
                shape: tuple = ("mesh", str(path), T @ np.diag([*scale, 1.0]))
            elif g.box is not None:
                shape = ("box", np.asarray(g.box.size, float).tolist(), T)
            elif g.cylinder is not None:
                shape = ("cylinder", [float(g.cylinder.radius), float(g.cylinder.length)], T)
            elif g.sphere is not None:
                shape = ("sphere", [float(g.sphere.radius)], T)
            else:
                continue
            out.setdefault(frame.body, []).append(shape)
    return out, skipped


def _rotors(arm: Arm) -> list:
    """Per joint: (parent body, 4x4 of the joint frame in it): the rotors sit at the joint."""
    return [(p + 1, _homogeneous(jt.R, jt.origin_xyz)) for jt, p in zip(arm.model.joints, arm.model.parent)]


def _poses(arm: Arm, thetas: np.ndarray) -> np.ndarray:
    """(frames, n + 1, 4, 4): every body's pose at every frame."""
    import casadi as ca
    th = ca.SX.sym("theta", arm.n)
    parts = body_poses(arm.model, th)
    f = ca.Function("poses", [th], [ca.vertcat(*[ca.vec(ca.horzcat(R, o)) for R, o in parts])])
    out = np.array(f.map(thetas.shape[1])(thetas)).T.reshape(thetas.shape[1], arm.n + 1, 4, 3)
    T = np.zeros((thetas.shape[1], arm.n + 1, 4, 4))
    T[:, :, :3, :] = out.transpose(0, 1, 3, 2)
    T[:, :, 3, 3] = 1.0
    return T


def scene_of(path, model=None) -> Scene:
    """The scene of a solution.json, or of a model file alone (the arm at theta = 0)."""
    from rscasadi.files import check_input_size
    path = Path(path)
    check_input_size(path, "result")
    text = path.read_text() if path.suffix == ".json" else None
    if text is None:
        arm = load(path)
        thetas, times, data = np.zeros((arm.n, 1)), np.zeros(1), {}
    else:
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ModelFileError(f"{path}: not a solution.json ({exc})") from None
        if isinstance(data, dict) and not {"t", "theta"} <= set(data):     # an MPC closed_loop.json: its MPC's run
            cases = [data] + [case for case in data.values() if isinstance(case, dict)]   # one plant, or several
            runs = [case["MPC (C)"] for case in cases
                    if isinstance(case.get("MPC (C)"), dict) and "theta" in case["MPC (C)"]]
            if runs:                                    # with the task's path, obstacles and payload
                with _field(path, "MPC (C)"):
                    data = {"t": runs[0]["t"], "theta": runs[0]["theta"], "model": runs[0]["model"],
                            **{k: v for k, v in {**data, **runs[0]}.items() if k in ("path", "obstacles", "payload")}}
        if not isinstance(data, dict) or not {"t", "theta", "model"} <= set(data):
            raise ModelFileError(f"{path}: not a solution.json or closed_loop.json (no t, theta, model)")
        t, theta = _checked_motion(path, data)
        arm = _checked_arm(path, data, model)
        if theta.shape[0] != arm.n:
            raise ModelFileError(f"{path}: field 'theta': {theta.shape[0]} rows for the {arm.n}-joint arm of {arm.model.path}")
        times = np.linspace(0.0, t[-1], int(np.ceil(t[-1] * FPS - 1e-9)) + 1)     # FPS or a little more, to the end
        thetas = np.vstack([np.interp(times, t, row) for row in theta])
    visuals, skipped = _visuals(arm)
    scene = Scene(f"{path.parent.name}/{path.name}" if text is not None else path.name, times, _poses(arm, thetas),
                  _links(arm), _rotors(arm), _broken(arm, thetas, data), visuals=visuals,
                  skipped=[(name, why) for name, why, _ in skipped], incomplete={body for *_, body in skipped})
    if data:                                            # the tool's path: the (first) goal's frame, else the arm's tip
        goals = goals_of(data)
        if goals:
            import casadi as ca
            th = ca.SX.sym("theta", arm.n)
            place = ca.Function("p", [th], [frame_pose(arm.model, arm.model.frame(goals[0]["frame"]), th)[1]])
            scene.path = np.array(place.map(thetas.shape[1])(thetas)).T
            scene.goal = np.array([g["position"] for g in goals], float)
        else:
            tip = np.r_[scene.links[arm.n][-1][1], 1.0]
            scene.path = (scene.poses[:, arm.n] @ tip)[:, :3]
    scene.obstacles = list(data.get("obstacles") or []) if data else []
    if data and data.get("path"):                       # the path asked for, beside the one flown
        from rscasadi.task.toolpath import ToolPath
        with _field(path, "path"):
            scene.target = ToolPath.from_dict(data["path"]).sample()
    if arm.model.payload is not None:
        f = arm.model.frame(arm.model.payload.frame)
        body = arm.model.payload.body
        radius = arm.model.payload.radius                # its collision sphere, else a cube of aluminium
        size = (2 * radius, "sphere") if radius else (float(np.cbrt(body.mass / 2700.0)), "box")
        scene.payload = (f.body, _homogeneous(f.R, f.p + f.R @ body.com), *size)
    return scene


MAX_SECONDS = 3600.0          # the longest motion view animates (30 frames a second)


@contextmanager
def _field(path: Path, name: str):
    """A malformed part of a result file as a ModelFileError naming the file and the field."""
    try:
        yield
    except (TypeError, KeyError, ValueError, IndexError, AttributeError) as exc:
        raise ModelFileError(f"{path}: field '{name}': malformed ({exc})") from None


def _checked_motion(path: Path, data: dict) -> tuple[np.ndarray, np.ndarray]:
    """t (K, finite, non-decreasing, from 0 to at most MAX_SECONDS) and theta (rows x K, finite)."""
    def numbers(name, v, dims):
        with _field(path, name):
            a = np.asarray(v, dtype=float)
        if a.ndim != dims or a.size == 0 or not np.all(np.isfinite(a)):
            raise ModelFileError(f"{path}: field '{name}': expected {'a list' if dims == 1 else 'lists'} of finite "
                                 f"numbers{'' if dims == 1 else ', one list per joint'}")
        return a
    t, theta = numbers("t", data["t"], 1), numbers("theta", data["theta"], 2)
    if np.any(np.diff(t) < 0) or t[-1] - t[0] > MAX_SECONDS:
        raise ModelFileError(f"{path}: field 't': expected times that do not decrease, at most {MAX_SECONDS:g} s long")
    if theta.shape[1] != t.size:
        raise ModelFileError(f"{path}: field 'theta': {theta.shape[1]} samples for {t.size} times")
    return t - t[0], theta


def _checked_arm(path: Path, data: dict, model) -> Arm:
    """The arm of a result file (its model, payload and parameters), or `model`'s; its goal and
    obstacles checked against it."""
    from rscasadi.ocp.solution import solution_arm
    if model is None and (not isinstance(data["model"], str) or not Path(data["model"]).is_file()):
        raise ModelFileError(f"{path}: field 'model': expected the path of a model file, got {data['model']!r}")
    if model is not None:
        arm = Arm(load(model).model)
    else:
        with _field(path, "payload"):
            arm = solution_arm(data)
    goal = data.get("goal")
    if goal:
        if not (isinstance(goal, dict) or isinstance(goal, list) and all(isinstance(g, dict) for g in goal)) or any(
                g.get("frame") not in [f.name for f in arm.model.frames] or np.shape(g.get("position")) != (3,)
                for g in goals_of(data)):
            raise ModelFileError(f"{path}: field 'goal': expected a frame of {arm.model.path} and a position (3), "
                                 "or a list of them")
    with _field(path, "obstacles"):
        from rscasadi.task.objects import Obstacle
        for o in data.get("obstacles") or []:
            Obstacle.from_dict(o)
    return arm


def _broken(arm: Arm, thetas: np.ndarray, data: dict) -> np.ndarray:
    """Per frame: a joint beyond its angle limit, or a clearance short (obstacles of the solution)."""
    broken = np.zeros(thetas.shape[1], bool)
    for j, jt in enumerate(arm.model.joints):
        if "theta" in jt.limits:
            lo, hi = jt.limits["theta"]
            broken |= (thetas[j] < lo - 1e-9) | (thetas[j] > hi + 1e-9)
    if data and data.get("obstacles") and arm.model.collision is not None:
        from rscasadi.task.objects import Obstacle
        obstacles = [Obstacle.from_dict(o) for o in data["obstacles"]]
        gap = np.array(exact_clearance(arm.model, obstacles).map(thetas.shape[1])(thetas)).ravel()
        broken |= gap < -1e-4
    return broken


def bounds(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """The box (lowest, highest corner, world frame) holding everything the scene shows at any
    instant: every capsule of every link (its radius included), the rotors, the obstacles, the
    payload, the paths and the goal; what a view must frame and must not clip."""
    pts, pad = [], []
    for body, capsules in scene.links.items():
        for a, b, r in capsules:
            ends = scene.poses[:, body] @ np.array([[*a, 1.0], [*b, 1.0]]).T      # (frames, 4, 2)
            pts.append(ends[:, :3].transpose(0, 2, 1).reshape(-1, 3))
            pad.append(np.full(len(pts[-1]), r))
    for ob in scene.obstacles:
        c = np.asarray(ob["center"], float)
        h = np.full(3, ob["radius"]) if ob["kind"] == "sphere" else np.asarray(ob["size"], float) / 2
        pts.append(np.array([c - h, c + h]))
        pad.append(np.zeros(2))
    for extra in (scene.path, scene.target, None if scene.goal is None else np.atleast_2d(scene.goal)):
        if extra is not None:
            pts.append(np.asarray(extra, float).reshape(-1, 3))
            pad.append(np.zeros(len(pts[-1])))
    P, R = np.vstack(pts), np.concatenate(pad)[:, None]
    return np.min(P - R, axis=0), np.max(P + R, axis=0)

