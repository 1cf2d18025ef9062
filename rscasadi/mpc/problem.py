"""The MPC problem file (docs/user-guide/mpc.md): the model, the reference (link angles, or a
frame's position in task space), horizon, sampling, weights, soft obstacles and the payload
whose mass the controller takes at run time, checked field by field."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rscasadi.model.checks import field_checker, read_toml
from rscasadi.model.parameters import PROBLEM_PARAMETRIC
from rscasadi.model.types import ModelFileError
from rscasadi.task.objects import holding_payload
from rscasadi.task.read import read_obstacles, read_path, read_payload
from rscasadi.task.toolpath import ToolPath

TOP = {"model", "trajectory", "sample_time", "horizon", "interval", "substeps", "integrator", "qp", "sqp_iterations",
       "qp_iterations", "threads", "weights", "frame", "orientation", "path", "obstacles", "payload", "theta_start", "solution", "parametric", "angle_limits"}
ANGLE_LIMITS = ("soft", "hard")
WEIGHTS = {"theta": 1e5, "dtheta": 1.0, "tau": 1e-3, "limits": 1e5, "angle_limits": 1e8,
           "position": 1e6, "velocity": 10.0, "orientation": 1e3, "posture": 1.0, "obstacles": 1e8}
JOINT_WEIGHTS, TASK_WEIGHTS = ("theta", "dtheta"), ("position", "velocity", "orientation", "posture")
SOFT = 0.9                   # penalties start at this fraction of the psi and dphi limits (and of
                             # the link-angle range's half-width, about its middle, or in joint space
                             # at the reference where that is farther out: task.terms.AngleBand)
AUTO = "auto"               # integrator and substeps chosen from the arm's spring modes (with_integrator)
INTEGRATORS = ("auto", "rk4", "ros2")
QPS = ("auto", "condensed", "riccati")
# qp = auto: the Riccati recursion from this many torques in the horizon on (N n: 10 intervals of a
# 7-joint arm). The condensed QP's C grows as (N n)^2: on the Panda at N = 10 it built in 90 s from
# 5.1 MB and stepped in 2.5 ms, HPIPM's in 8 s from 0.7 MB and 1.5 ms; at N = 5 the condensed
# one was the faster (0.9 against 1.1 ms)
RICCATI_FROM = 70
RK4_MOST = 4                # integrator = auto: RK4 where this many substeps hold every spring mode, else ROS2
ROS2_STEP = 0.01            # s: the longest ROS2 substep substeps = auto takes (its error on the rigid motion)
LINE_SEARCH = (1.0, 0.5, 0.25, 0.125)   # step sizes tried when sqp_iterations > 1
# sizes refused before the work: the condensed QP's C grows as N^2 (20 intervals on 7 joints are
# 30 MB of C, 6 CPU-minutes to compile), and every unrolled iteration adds to it
MAX_SIZES = {"horizon": (50, "the condensed QP's C grows as horizon^2: 20 intervals on 7 joints are 30 MB of C"),
             "substeps": (20, "each substep is unrolled into the C"),
             "sqp_iterations": (10, "each SQP iteration is unrolled into the C"),
             "qp_iterations": (100, "each interior-point iteration is unrolled into the C"),
             "threads": (64, "each thread's work arrays are in the controller's struct")}


@dataclass
class MPCProblem:
    """An MPC problem: the `model` and the reference `trajectory`, the controller's `sample_time`,
    a horizon of `horizon` intervals of `interval` s, each `substeps` steps of `integrator` ("rk4"
    or "ros2"; "auto", the default for both: RK4 with the fewest substeps that amplify none of the
    arm's spring modes where RK4_MOST do, else the L-stable ROS2, `with_integrator`), the QP
    (`qp_of`: "condensed", "riccati" or "auto"), the SQP iterations per sample (1: the real-time
    iteration) and the QP's interior-point iterations, the threads the Riccati QP's preparation
    runs its loops over the intervals on (`threads`, OpenMP), and the cost `weights` (theta, dtheta, tau,
    limits, angle_limits; in task space position, velocity, orientation, posture; obstacles).  Task space: `frame`, one frame or a list (their positions,
    and rotations if `orientation`, are the reference, a block per frame), `tool_path` (a `ToolPath` at a speed: the study's
    reference, from rest at `theta_start`) or `solution` (an optimal-control solution.json: the
    frame's motion in it is the study's reference).  `obstacles` are soft (the model's [collision]
    capsules); `payload` sets or changes the model's payload, whose mass is a run-time parameter;
    `parametric` "family": every nonzero parameter of the model is one too (mpc_set_parameters:
    an identified arm of the family without recompiling).  `angle_limits` "hard": the plan's link
    angles also stay inside their ranges at every interval end, as rows of the QP with an exact
    penalty (when the arm cannot stop in time, the least excess); "soft": the penalty alone.  Build it in Python or read it with `load_mpc_problem`; `check()` applies the file's rules.
    `path`: the file it came from."""
    model: Path
    trajectory: Path | None = None
    sample_time: float = 1e-3
    horizon: int = 10
    interval: float = 0.01
    substeps: int | str = AUTO
    integrator: str = AUTO
    qp: str = AUTO
    sqp_iterations: int = 1
    qp_iterations: int = 16
    threads: int = 1
    weights: dict = field(default_factory=lambda: dict(WEIGHTS))
    path: Path | None = None
    frame: str | None = None
    orientation: bool = False
    tool_path: ToolPath | None = None
    obstacles: tuple = ()
    payload: dict | None = None
    theta_start: np.ndarray | None = None
    solution: Path | None = None
    parametric: str = "none"
    angle_limits: str = "soft"
    terms: tuple = ()


    def __post_init__(self):
        self.model = Path(self.model)
        self.trajectory = None if self.trajectory is None else Path(self.trajectory)
        self.weights = {**WEIGHTS, **self.weights}
        self.obstacles = tuple(self.obstacles)
        self.terms = tuple(self.terms)
        self.solution = None if self.solution is None else Path(self.solution)
        if self.theta_start is not None:
            self.theta_start = np.asarray(self.theta_start, float).ravel()

    def __eq__(self, other):
        if not isinstance(other, MPCProblem):
            return NotImplemented
        mine, theirs = self.__dict__, other.__dict__
        return all(np.array_equal(mine[k], theirs[k]) if isinstance(mine[k], np.ndarray) else mine[k] == theirs[k]
                   for k in mine)

    @property
    def task_space(self) -> bool:
        """The reference is the frame's position (and rotation), not link angles."""
        return self.frame is not None

    @property
    def frames(self) -> tuple:
        """The frames whose motion is the reference: `frame`, one name or a list of them."""
        return () if self.frame is None else (self.frame,) if isinstance(self.frame, str) else tuple(self.frame)

    @property
    def reference_rows(self) -> int:
        """Rows of a reference column in task space: per frame p, v (6) and vec(R) (9)."""
        return (15 if self.orientation else 6) * len(self.frames) if self.task_space else None

    def check(self) -> "MPCProblem":
        """The problem file's rules on the object; a `ModelFileError` names the field."""
        where = str(self.path) if self.path is not None else "<MPCProblem>"

        def fail(fld, msg):
            raise ModelFileError(f"{where}: field '{fld}': {msg}")
        for key in ("sample_time", "interval"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v <= 0:
                fail(key, f"must be a positive number, got {v!r}")
        for key in ("horizon", "substeps", "sqp_iterations", "qp_iterations", "threads"):
            v = getattr(self, key)
            if key == "substeps" and v == AUTO:
                continue
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                fail(key, f"must be an integer >= 1, got {v!r}")
            if v > MAX_SIZES[key][0]:
                fail(key, f"at most {MAX_SIZES[key][0]}, got {v} ({MAX_SIZES[key][1]})")
        for key, v in self.weights.items():
            if key not in WEIGHTS:
                fail(f"weights.{key}", f"unknown weight (allowed: {', '.join(WEIGHTS)})")
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v < 0:
                fail(f"weights.{key}", f"must be a number >= 0, got {v!r}")
        names = [self.frame] if isinstance(self.frame, str) else self.frame
        if self.frame is not None and (not isinstance(names, (list, tuple)) or not names
                                       or not all(isinstance(f, str) and f for f in names)
                                       or len(set(names)) != len(names)):
            fail("frame", f"expected the name of a frame, or a list of distinct names, got {self.frame!r}")
        if not isinstance(self.orientation, bool):
            fail("orientation", f"must be true or false, got {self.orientation!r}")
        if self.orientation and self.frame is None:
            fail("orientation", "needs a frame (task space)")
        if self.tool_path is not None:
            if self.frame is None:
                fail("path", "a path is a task-space reference: give frame too")
            if len(self.frames) != 1:
                fail("path", f"a path is one frame's; the controller follows {len(self.frames)} frames (give them a "
                             "solution whose motion they follow)")
            if self.tool_path.frame != self.frames[0]:
                fail("path.frame", f"the path is for {self.tool_path.frame!r}, the controller's frame is {self.frame!r}")
            if self.tool_path.speed is None:
                fail("path.speed", "missing required field (the reference's mean speed along the path)")
            if self.trajectory is not None:
                fail("path", "give a trajectory (link angles) or a path (task space), not both")
            if self.theta_start is None:
                fail("theta_start", "missing required field (where the path's run starts, at rest)")
        if self.solution is not None:
            if self.frame is None:
                fail("solution", "a solution's frame motion is a task-space reference: give frame too")
            if self.tool_path is not None or self.trajectory is not None:
                fail("solution", "give one reference: a trajectory, a path or a solution")
            if not self.solution.is_file():
                fail("solution", f"no file {self.solution}")
        if self.parametric not in PROBLEM_PARAMETRIC:
            fail("parametric", f"must be one of {', '.join(PROBLEM_PARAMETRIC)}, got {self.parametric!r}")
        if self.qp not in QPS:
            fail("qp", f"must be one of {', '.join(QPS)}, got {self.qp!r}")
        if self.qp == "riccati" and self.sqp_iterations != 1:
            fail("qp", "riccati: the real-time iteration only (sqp_iterations = 1)")
        if self.qp == "riccati" and self.angle_limits == "hard":
            fail("qp", "riccati: hard link-angle rows are the condensed QP's (angle_limits = \"soft\", or qp = "
                       "\"condensed\")")
        if self.integrator not in INTEGRATORS:
            fail("integrator", f"must be one of {', '.join(INTEGRATORS)}, got {self.integrator!r}")
        if self.angle_limits not in ANGLE_LIMITS:
            fail("angle_limits", f"must be one of {', '.join(ANGLE_LIMITS)}, got {self.angle_limits!r}")
        if self.theta_start is not None and not np.all(np.isfinite(self.theta_start)):
            fail("theta_start", f"expected finite numbers, got {self.theta_start!r}")
        return self


def load_mpc_problem(path) -> MPCProblem:
    """Read and check an MPC problem file (docs/user-guide/mpc.md); errors name the field."""
    path = Path(path)
    d = read_toml(path, "MPC problem")
    fail = field_checker(path, d, TOP)
    if not isinstance(d.get("model"), str) or "\0" in d["model"]:
        fail("model", "missing, or not the path of a model file")
    if "trajectory" in d and (not isinstance(d["trajectory"], str) or "\0" in d["trajectory"]):
        fail("trajectory", "expected the path of a trajectory file")
    if not isinstance(d.get("weights", {}), dict):
        fail("weights", "expected a table")
    special = {"model", "trajectory", "weights", "path", "obstacles", "payload", "theta_start", "solution"}
    fields = {k: d[k] for k in TOP - special if k in d}
    if "path" in d:
        if not isinstance(d["path"], dict):
            fail("path", "expected a table")
        fields["tool_path"] = read_path(fail, d["path"])
    if "obstacles" in d:
        fields["obstacles"] = read_obstacles(fail, d["obstacles"])
    if "payload" in d:
        fields["payload"] = read_payload(fail, d["payload"])
    if "solution" in d:
        if not isinstance(d["solution"], str) or not d["solution"].strip() or "\0" in d["solution"]:
            fail("solution", f"expected the path of a solution.json, got {d['solution']!r}")
        fields["solution"] = (path.parent / d["solution"]).resolve()
    if "theta_start" in d:
        v = d["theta_start"]
        if not isinstance(v, list) or not v or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in v):
            fail("theta_start", f"expected a list of numbers, got {v!r}")
        fields["theta_start"] = np.array(v, float)
    return MPCProblem((path.parent / d["model"]).resolve(),
                      (path.parent / d["trajectory"]).resolve() if "trajectory" in d else None,
                      weights=dict(d.get("weights", {})), path=path, **fields).check()


def mpc_model(p: MPCProblem):
    """The controller's model: the problem's model file with its payload set or changed, checked
    against the problem (frame, obstacles, theta_start); errors name the problem file."""
    from rscasadi.model.modelfile import read
    where = p.path if p.path is not None else "<MPCProblem>"
    model = holding_payload(read(p.model), p.payload, where)
    unlimited = [model.joints[j].name for j in model.actuated if not np.isfinite(model.joints[j].limits.get("tau", np.inf))]
    if unlimited:
        raise ModelFileError(f"{model.path}: joint {unlimited[0]!r}: limits.tau missing: the MPC commands motor "
                             f"torques within their limits (no limit would let it command any torque); give "
                             f"limits.tau for {', '.join(repr(j) for j in unlimited)}")
    frames = [f.name for f in model.frames]
    missing = [f for f in p.frames if f not in frames]
    if missing:
        raise ModelFileError(f"{where}: field 'frame': {model.path} has no frame {', '.join(map(repr, missing))} "
                             f"(frames: {', '.join(frames)})")
    if p.orientation and model.n < 6 * len(p.frames):
        raise ModelFileError(f"{where}: field 'orientation': a position and a rotation per frame are "
                             f"{6 * len(p.frames)} conditions, more than the {model.n} joints can follow")
    for ob in p.obstacles:
        ob.check(model, where)
    if p.terms:
        from rscasadi.dynamics.arm import Arm
        from rscasadi.task.terms import check_terms
        check_terms(Arm(model), p.terms, str(where))
    if p.theta_start is not None and len(p.theta_start) != model.n:
        raise ModelFileError(f"{where}: field 'theta_start': {len(p.theta_start)} entries for a {model.n}-joint arm")
    return model


def mpc_problem(problem) -> MPCProblem:
    """`problem` itself (checked) if an MPCProblem, else the problem file it names."""
    return problem.check() if isinstance(problem, MPCProblem) else load_mpc_problem(problem)


def problem_poses(p, n: int, count: int = 5) -> list[np.ndarray]:
    """Where the arm will be: `count` poses along the reference trajectory or the solution's
    motion, else theta_start, else zero."""
    import json
    from rscasadi.sim.trajectory import load_trajectory
    if p.trajectory is not None:
        traj = load_trajectory(p.trajectory)
        return list(traj(np.linspace(0.0, traj.duration, count))[0].T)
    if p.solution is not None and Path(p.solution).is_file():
        theta = np.asarray(json.loads(Path(p.solution).read_text())["theta"], float)
        return list(theta[:, np.linspace(0, theta.shape[1] - 1, count).astype(int)].T)
    return [np.asarray(p.theta_start, float) if p.theta_start is not None else np.zeros(n)]


def qp_of(p: MPCProblem, n: int) -> str:
    """The QP the controller of an n-joint arm solves: "condensed" (onto the torques, a dense
    interior-point method in straight-line C: fastest at short horizons, its C growing as
    (N n)^2) or "riccati" (HPIPM's interior-point method on the stage structure, its C the same
    size at any N and its step growing far slower with N); "auto": riccati from RICCATI_FROM
    torques in the horizon (N n) on, where the real-time iteration allows it."""
    if p.qp != AUTO:
        return p.qp
    return ("riccati" if p.horizon * n >= RICCATI_FROM and p.sqp_iterations == 1 and p.angle_limits == "soft"
            else "condensed")


def with_integrator(p: MPCProblem, arm) -> MPCProblem:
    """`p` with its integrator and substeps settled (`p` itself if both are given).  From the
    arm's spring modes at the problem's poses (`problem_poses`; rscasadi.dynamics.modes):
    RK4's substeps = "auto" are the fewest that amplify none of them (refused, naming the mode,
    where more than MAX_SIZES allows would be needed: ROS2 holds any mode); ROS2's are the fewest
    of at most ROS2_STEP s (its accuracy on the rigid motion: it damps every mode, fast or not);
    integrator = "auto" is RK4 where RK4_MOST substeps (or the given number) hold every mode, else
    ROS2, whose stability does not depend on the step."""
    import dataclasses
    from rscasadi.dynamics.modes import linear_modes, rk4_spurious, rk4_substeps
    if p.substeps != AUTO and p.integrator != AUTO:
        return p
    most = MAX_SIZES["substeps"][0]
    need, hardest = 1, None                            # RK4's fewest substeps over the poses
    for theta in problem_poses(p, arm.n):
        modes = linear_modes(arm, theta)
        s = rk4_substeps(modes, p.interval, most)
        if s is None:
            hardest = max(rk4_spurious(modes, p.interval / most), key=lambda m: m.hz)
            need = None
            break
        need = max(need, s)
    integrator = p.integrator
    if integrator == AUTO:
        enough = RK4_MOST if p.substeps == AUTO else int(p.substeps)
        integrator = "rk4" if need is not None and need <= enough else "ros2"
    if p.substeps != AUTO:
        return dataclasses.replace(p, integrator=integrator)
    if integrator == "ros2":
        return dataclasses.replace(p, integrator=integrator, substeps=max(1, int(np.ceil(p.interval / ROS2_STEP - 1e-9))))
    if need is None:
        where = p.path if p.path is not None else "<MPCProblem>"
        raise ModelFileError(f"{where}: field 'substeps': auto: even {most} RK4 steps of the {p.interval:g} s interval "
                             f"amplify the {hardest.hz:.0f} Hz spring mode of {hardest.joint} (damping ratio "
                             f"{hardest.damping_ratio:.2f}); shorten the interval, or integrator = \"ros2\" (or "
                             f"\"auto\"), stable at any step")
    return dataclasses.replace(p, integrator=integrator, substeps=need)
