"""An optimal-control problem, stated in four parts, as rockit and acados state theirs:

- `Task`: what the arm must do (model, objective, boundary conditions, limits from the model,
  parameters, design variables);
- `TranscriptionOptions`: how time is discretised;
- `SolverOptions`: which NLP solver and how;
- `Verification`: what the replay on the complete model must meet, and how many mesh
  refinements it may ask for.

`Problem(task, transcription, solver, verification)` in Python, or `load_problem(path)` from a
TOML file; both are checked by `Problem.check()`, whose errors name the field (and the file).
`problem.replace(intervals=200, solver="ipopt")` gives a changed copy by the fields' names.

The TOML file, every field checked and named in errors:

    model = "arm3.toml"                  # relative to the problem file
    objective = "min_effort"             # min_time | min_effort | tracking
    theta_start = [0.0, 0.3, -0.5]       # rest poses (not for tracking); the arm starts and
    theta_end = [0.8, 0.9, -1.2]         # ends at rest in the SEA's static equilibrium
    duration = 1.5                       # s: fixed (min_effort, tracking) or the initial guess (min_time)
    max_duration = 5.0                   # min_time only (default 10 s)
    trajectory = "trajectory_arm3.toml"  # tracking only
    effort_weight = 1e-3                 # min_time and tracking: weight of the integral of tau^2
    [transcription]
    method = "radau"                     # radau | legendre | hermite-simpson
    degree = 3                           # collocation points per interval (radau, legendre)
    intervals = 100                      # of the first round; refinement adds where needed
    dynamics = "explicit"                # explicit (forward dynamics) | implicit (inverse-dynamics residual)
    compiled = true                      # generate the NLP's functions to C, compile once, cache
    condense = true                      # solve each interval's collocation equations inside the
                                         # NLP's functions (a C kernel; needs compiled): the solver
                                         # sees (x_k, tau_k) only, 2-3x faster; false: the lifted NLP
    parametric = "none"                  # "family": the model's nonzero parameters are NLP parameters,
                                         # one compiled NLP for every arm with the same zeros
    [verification]                       # the replay on the complete model must meet these
    final_angle_tol = 1e-4               # theta, phi at the end (rad)
    final_speed_tol = 1e-3               # dtheta, dphi at the end (rad/s)
    tracking_tol = 1e-3                  # tracking: largest |theta - theta_ref| on the replay (rad)
    limit_tol = 1e-3                     # largest violation between grid points, relative to the limit
    [refinement]
    rounds = 4                           # at most this many re-solves on a refined mesh (0: none)
    [solver]
    name = "fatrop"                      # fatrop (stage-structured interior point; the default:
                                         # faster than ipopt on every benchmark problem) | ipopt
    hessian = "exact"                    # exact | limited-memory (ipopt only: no second
                                         # derivatives to generate, for large arms)
    interface = "direct"                 # fatrop: direct (its C interface, stage by stage, on the
                                         # compiled NLP; needs compiled) | casadi (casadi.nlpsol)
    threads = 1                          # the compiled NLP's loops over the intervals on this many
                                         # threads (OpenMP); 0: one per core this process may use.
                                         # Above 1, a process forked after the solve hangs if
                                         # it solves on more than 1 too (libgomp): spawn them
    barrier = "monotone"                 # fatrop's barrier rule: monotone, its only one (accepted
                                         # for older files)
    [design]                             # parameters the optimiser chooses, constant over time
    "elbow_pitch.sea.k1" = [300.0, 3000.0]

Names in [design] are the model's parameter names (docs/user-guide/model.md, "Parameters") or gear ratios
("elbow_pitch.gear_ratio", bounds > 0).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rscasadi.model.checks import field_checker, read_toml
from rscasadi.model.parameters import PROBLEM_PARAMETRIC
from rscasadi.model.types import ModelFileError
from rscasadi.task.objects import Goal, Obstacle, holding_payload  # noqa: F401  (the task's objects)
from rscasadi.task.read import number, read_goal, read_obstacles, read_path, read_payload
from rscasadi.task.toolpath import ToolPath
from rscasadi.errors import WrongType

OBJECTIVES = ("min_time", "min_effort", "tracking")
METHODS = ("radau", "legendre", "hermite-simpson")
DYNAMICS = ("explicit", "implicit")
SOLVERS = ("fatrop", "ipopt")
INTERFACES = ("direct", "casadi")
BARRIERS = ("monotone",)                     # fatrop's barrier rule (docs/design/condensing.md)
HESSIANS = ("exact", "limited-memory")
TOP = {"model", "objective", "theta_start", "theta_end", "duration", "max_duration", "trajectory",
       "effort_weight", "transcription", "verification", "solver", "refinement", "design", "goal", "obstacles",
       "payload", "path", "collision"}
# sizes refused before the work: a 1e8-interval NLP takes tens of GB and is killed by the kernel
MAX_INTERVALS, MAX_DEGREE, MAX_ROUNDS = 5000, 9, 20
SIZES_WHY = "5000 intervals of degree 3 on 7 joints already take minutes and gigabytes; refine instead"
TABLES = {"transcription": {"method", "degree", "intervals", "dynamics", "compiled", "condense", "parametric",
                             "limit_margin"},
          "verification": {"final_angle_tol", "final_speed_tol", "tracking_tol", "limit_tol", "clearance_tol"},
          "refinement": {"rounds"},
          "solver": {"name", "hessian", "interface", "threads", "barrier"}}
# problem fields a sweep may vary without rebuilding the NLP (they are its parameters or bounds)
SWEEPABLE = ("theta_start", "theta_end", "duration", "max_duration", "effort_weight")


@dataclass
class Task:
    """What the arm must do.  `model`: the model file; `objective`: min_time | min_effort |
    tracking; `duration` (s): fixed, or min_time's first guess; the rest poses `theta_start`,
    `theta_end` (not for tracking) or the `trajectory` file to track; `goal`: a `Goal` for a
    frame instead of theta_end, or a tuple of them for several frames at once (`goals`); `design`: parameter name -> (lower, upper), chosen by the
    optimiser; `parameters`: name -> value, set (sweeps); `terms`: more costs and constraints
    (`rscasadi.task.terms.Term` objects, Python only: docs/user-guide/problems.md, "Terms")."""
    model: Path
    objective: str
    duration: float
    theta_start: np.ndarray | None = None
    theta_end: np.ndarray | None = None
    max_duration: float = 10.0                      # min_time's upper bound (s)
    trajectory: Path | None = None
    effort_weight: float = 1e-3                     # min_time, tracking: weight of the integral of tau^2
    design: dict = field(default_factory=dict)
    parameters: dict = field(default_factory=dict)
    goal: Goal | tuple | None = None
    obstacles: tuple = ()
    payload: dict | None = None                     # frame, mass, com, inertia: the model's payload set or changed
    path: ToolPath | None = None
    collision: dict | None = None                   # the model's [collision] replaced for this task
    terms: tuple = ()                               # more costs and constraints (rscasadi.task.terms.Term)

    def __post_init__(self):
        self.model = Path(self.model)
        self.trajectory = None if self.trajectory is None else Path(self.trajectory)
        for key in ("theta_start", "theta_end"):
            if getattr(self, key) is not None:
                setattr(self, key, np.asarray(getattr(self, key), float))
        self.design = {k: (float(lo), float(hi)) for k, (lo, hi) in self.design.items()}
        self.terms = tuple(self.terms)
        if isinstance(self.goal, (list, tuple)):
            self.goal = tuple(self.goal) or None

    @property
    def goals(self) -> tuple:
        """The goals: none, the one `goal`, or the several."""
        return () if self.goal is None else self.goal if isinstance(self.goal, tuple) else (self.goal,)


@dataclass
class TranscriptionOptions:
    """Direct collocation: `method` radau | legendre | hermite-simpson with `degree` points on
    each of `intervals` intervals; `dynamics` explicit (forward dynamics) | implicit
    (inverse-dynamics residual); `compiled`: the NLP's functions as C; `condense`: each
    interval's collocation solved inside the NLP's functions (needs compiled; default: wherever
    it can be, i.e. when compiled); `parametric`
    none | family: the model's nonzero parameters (model.parameters.family) enter the compiled
    NLP as parameters, so every arm with the same zeros (an identified one, another payload's)
    reuses it.  `limit_margin`: the fraction of each psi and dphi limit, and of each link-angle
    range, the NLP holds in reserve at its collocation points, so that the motion between them
    (what the replay checks) stays inside the true limits; the motor torques keep theirs."""
    method: str = "radau"
    degree: int = 3
    intervals: int = 100
    dynamics: str = "explicit"
    compiled: bool = True
    condense: bool | None = None
    parametric: str = "none"
    limit_margin: float = 0.0

    def __post_init__(self):
        if self.condense is None:
            self.condense = bool(self.compiled)


@dataclass
class SolverOptions:
    """`name` fatrop | ipopt; `hessian` exact | limited-memory (ipopt); `interface` direct
    (fatrop's C interface, needs compiled) | casadi; `threads` for the NLP's loops over the
    intervals (0: one per core)."""
    name: str = "fatrop"
    hessian: str = "exact"
    interface: str = "direct"
    threads: int = 1


@dataclass
class Verification:
    """What the replay on the complete model must meet (angles rad, speeds rad/s, limits
    relative), and at most how many re-solves on a refined mesh it may ask for."""
    final_angle_tol: float = 1e-4
    final_speed_tol: float = 1e-3
    tracking_tol: float = 1e-3
    limit_tol: float = 1e-3
    clearance_tol: float = 1e-4                     # m: how far into an obstacle's margin the replay may go
    rounds: int = 4


PARTS = {"task": Task, "transcription": TranscriptionOptions, "solver": SolverOptions, "verification": Verification}
# a field's flat name (as sweeps and `Problem.replace` use it) -> (part, attribute)
FIELDS = {**{f.name: (part, f.name) for part, cls in PARTS.items() for f in dataclasses.fields(cls)},
          "solver": ("solver", "name"), "tool_path": ("task", "path")}
del FIELDS["path"]                           # `path` names the problem's file; the task's is `tool_path`


@dataclass
class Problem:
    """An optimal-control problem: the task, and how it is transcribed, solved and verified.
    `path`: the file it was read from (errors name it), if any."""
    task: Task
    transcription: TranscriptionOptions = field(default_factory=TranscriptionOptions)
    solver: SolverOptions = field(default_factory=SolverOptions)
    verification: Verification = field(default_factory=Verification)
    path: Path | None = None

    def replace(self, **changes) -> "Problem":
        """A copy with fields changed by their names (`intervals=200`, `solver="ipopt"`,
        `theta_end=...`, `tool_path=...` for the task's path, `path=` for the file's); a part may
        also be replaced whole (`solver=SolverOptions(...)`)."""
        parts = {name: getattr(self, name) for name in PARTS}
        for key, value in changes.items():
            if key in PARTS and isinstance(value, PARTS[key]):
                parts[key] = value
            elif key in FIELDS:
                part, attr = FIELDS[key]
                parts[part] = dataclasses.replace(parts[part], **{attr: value})
            elif key == "path":
                continue
            else:
                raise WrongType(f"Problem has no field {key!r} (fields: {', '.join(sorted(FIELDS))})")
        return Problem(**parts, path=changes.get("path", self.path))

    def check(self) -> "Problem":
        """Every rule of the problem file, on the objects; a `ModelFileError` names the field."""
        where = str(self.path) if self.path is not None else "<Problem>"

        def fail(fld, msg):
            raise ModelFileError(f"{where}: field '{fld}': {msg}")
        t, tr, s, v = self.task, self.transcription, self.solver, self.verification
        if t.objective not in OBJECTIVES:
            fail("objective", f"must be one of {', '.join(OBJECTIVES)}, got {t.objective!r}")
        for fld, value, positive in (("duration", t.duration, True), ("max_duration", t.max_duration, True),
                                     ("effort_weight", t.effort_weight, False)):
            number(fail, fld, value, positive)
        if t.objective == "tracking":
            if t.trajectory is None:
                fail("trajectory", "missing required field (objective tracking)")
            if t.goal is not None:
                fail("goal", "a tracking problem follows its trajectory: no goal")
        else:
            if t.goal is not None and t.theta_end is not None:
                fail("goal", "give theta_end or a goal, not both")
            for key in ("theta_start",) + (("theta_end",) if t.goal is None and t.path is None else ()):
                if getattr(t, key) is None:
                    fail(key, f"missing required field (objective {t.objective})"
                         + (" (or a [goal])" if key == "theta_end" else ""))
                if np.size(getattr(t, key)) == 0 or not np.all(np.isfinite(getattr(t, key))):
                    fail(key, f"expected a list of finite numbers, got {getattr(t, key)!r}")
        for i, ob in enumerate(t.obstacles):
            fld = f"obstacles[{i}].{ob.kind}"
            if ob.kind not in ("sphere", "box"):
                fail(f"obstacles[{i}]", f"expected a sphere or a box, got {ob.kind!r}")
            if ob.center.shape != (3,) or not np.all(np.isfinite(ob.center)):
                fail(f"{fld}.center", f"expected 3 finite numbers, got {ob.center!r}")
            if ob.kind == "sphere":
                number(fail, f"{fld}.radius", ob.radius, True)
            elif ob.size is None or ob.size.shape != (3,) or not np.all(np.isfinite(ob.size)) or np.any(ob.size <= 0):
                fail(f"{fld}.size", f"expected 3 positive numbers, got {ob.size!r}")
        if t.path is not None:
            pa = t.path
            if t.objective not in ("min_effort", "min_time"):
                fail("path", "a path is followed at its speed (min_effort) or as fast as it can be (min_time)")
            if t.goal is not None or t.theta_end is not None:
                fail("path", "the path's end is where the arm ends: no theta_end or goal")
            if pa.kind == "polyline":
                if pa.points.shape[0] < 2 or not np.all(np.isfinite(pa.points)) or pa.length <= 0:
                    fail("path.points", "expected at least two distinct points of 3 numbers")
            else:
                for key in ("center", "normal"):
                    vec = getattr(pa, key)
                    if vec.shape != (3,) or not np.all(np.isfinite(vec)) or (key == "normal" and not np.any(vec)):
                        fail(f"path.circle.{key}", f"expected 3 finite numbers{' not all 0' if key == 'normal' else ''}, got {vec!r}")
                number(fail, "path.circle.radius", pa.radius, True)
                number(fail, "path.circle.turns", pa.turns, True)
            number(fail, "path.tolerance", pa.tolerance, True)
            if t.objective == "min_time":
                if pa.speed is not None:
                    fail("path.speed", "min_time chooses the timing along the path: no speed (duration is the guess)")
            else:
                if pa.speed is None:
                    fail("path.speed", "missing required field (objective min_effort: the mean speed along the path)")
                number(fail, "path.speed", pa.speed, True)
                if abs(t.duration - pa.duration) > 1e-9 * pa.duration:
                    fail("duration", f"the path's length and speed make it {pa.duration:.6g} s (leave duration out)")
        for i, g in enumerate(t.goals):
            fld = "goal" if len(t.goals) == 1 else f"goal[{i}]"
            if g.position.shape != (3,) or not np.all(np.isfinite(g.position)):
                fail(f"{fld}.position", f"expected 3 finite numbers, got {g.position!r}")
            if g.R is not None and (g.R.shape != (3, 3) or not np.allclose(g.R.T @ g.R, np.eye(3), atol=1e-9)):
                fail(f"{fld}.rpy", "not a rotation")
            for key in ("position_tol", "angle_tol"):
                number(fail, f"{fld}.tolerance.{key.split('_')[0]}", getattr(g, key), True)
        frames = [g.frame for g in t.goals]
        if len(set(frames)) != len(frames):
            fail("goal", f"a frame has two goals: {frames}")
        for name, bounds in t.design.items():
            if len(bounds) != 2 or not bounds[0] < bounds[1]:
                fail(f"design.{name}", f"expected [lower, upper] with lower < upper, got {bounds!r}")
        for fld, chosen, allowed in (("transcription.method", tr.method, METHODS),
                                    ("transcription.dynamics", tr.dynamics, DYNAMICS),
                                    ("transcription.parametric", tr.parametric, PROBLEM_PARAMETRIC),
                                    ("solver.name", s.name, SOLVERS), ("solver.hessian", s.hessian, HESSIANS),
                                    ("solver.interface", s.interface, INTERFACES)):
            if chosen not in allowed:
                fail(fld, f"must be one of {', '.join(allowed)}, got {chosen!r}")
        for fld, value, lo, hi in (("transcription.degree", tr.degree, 1, MAX_DEGREE),
                                   ("transcription.intervals", tr.intervals, 2, MAX_INTERVALS),
                                   ("refinement.rounds", v.rounds, 0, MAX_ROUNDS), ("solver.threads", s.threads, 0, 1024)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < lo:
                fail(fld, f"must be an integer >= {lo}, got {value!r}")
            if value > hi:
                fail(fld, f"{value} is more than this machine's solver can hold: at most {hi} ({SIZES_WHY})")
        for fld in ("compiled", "condense"):
            if not isinstance(getattr(tr, fld), bool):
                fail(f"transcription.{fld}", f"must be true or false, got {getattr(tr, fld)!r}")
        for fld in ("final_angle_tol", "final_speed_tol", "tracking_tol", "limit_tol", "clearance_tol"):
            number(fail, f"verification.{fld}", getattr(v, fld), True)
        if number(fail, "transcription.limit_margin", tr.limit_margin, False) < 0 or tr.limit_margin >= 0.5:
            fail("transcription.limit_margin", f"must be in [0, 0.5), got {tr.limit_margin!r}")
        if s.hessian != "exact" and s.name == "fatrop":
            fail("solver.hessian", "fatrop needs the exact Hessian; use name = \"ipopt\" for limited-memory")
        if tr.condense and not tr.compiled:
            fail("transcription.condense", "the condensing kernel is C: needs compiled = true (or condense = false)")
        return self


def load_problem(path) -> Problem:
    """Read a problem file (the format above) into a checked `Problem`."""
    path = Path(path)
    d = read_toml(path, "problem")
    fail = field_checker(path, d, TOP)

    def table(name):
        t = d.get(name, {})
        if not isinstance(t, dict):
            fail(name, "expected a table")
        for key in t:
            if name in TABLES and key not in TABLES[name]:
                fail(f"{name}.{key}", f"unknown key (allowed: {', '.join(sorted(TABLES[name]))})")
        return t

    timed_path = "path" in d and d.get("objective") != "min_time"      # the path's speed sets the duration
    for key in ("model", "objective") + (("duration",) if not timed_path else ()):
        if key not in d:
            fail(key, "missing required field" + (" (the guess of min_time along a path)" if "path" in d else ""))
    if timed_path and "duration" in d:
        fail("duration", "a path's length and speed set the duration: leave it out")
    tool_path = read_path(fail, table("path")) if "path" in d else None
    for key in ("model", "trajectory"):
        if key in d and (not isinstance(d[key], str) or not d[key].strip() or "\0" in d[key]):
            fail(key, f"expected the path of a file, got {d[key]!r}")
    if timed_path and tool_path.speed is None:
        fail("path.speed", "missing required field (objective min_effort: the mean speed along the path)")
    task = {"model": (path.parent / str(d["model"])).resolve(), "objective": d["objective"],
            "duration": number(fail, "duration", d["duration"], True) if not timed_path else tool_path.duration,
            "path": tool_path}
    if "goal" in d and not isinstance(d["goal"], dict) and not (
            isinstance(d["goal"], list) and d["goal"] and all(isinstance(g, dict) for g in d["goal"])):
        fail("goal", "expected a table ([goal]), or tables ([[goal]]) for several frames")
    if "trajectory" in d and d["objective"] == "tracking":
        task["trajectory"] = (path.parent / str(d["trajectory"])).resolve()
    for key in ("theta_start", "theta_end"):
        if key in d and d["objective"] != "tracking":
            v = d[key]
            if not isinstance(v, list) or not v:
                fail(key, f"expected a list of numbers, got {v!r}")
            task[key] = np.array([number(fail, f"{key}[{i}]", x, False) for i, x in enumerate(v)])
    if "max_duration" in d:
        task["max_duration"] = number(fail, "max_duration", d["max_duration"], True)
    if "effort_weight" in d:
        task["effort_weight"] = number(fail, "effort_weight", d["effort_weight"], False)
    if isinstance(d.get("goal"), dict):
        task["goal"] = read_goal(fail, table("goal"))
    elif "goal" in d:
        task["goal"] = tuple(read_goal(fail, g, f"goal[{i}]") for i, g in enumerate(d["goal"]))
    if "obstacles" in d:
        task["obstacles"] = read_obstacles(fail, d["obstacles"])
    if "collision" in d:
        if not isinstance(d["collision"], dict):
            fail("collision", f"expected a table like the model file's [collision], got {d['collision']!r}")
        task["collision"] = dict(d["collision"])
    if "payload" in d:
        task["payload"] = read_payload(fail, d["payload"])
    design = {}
    for name, bounds in table("design").items():
        if (not isinstance(bounds, list) or len(bounds) != 2
                or any(isinstance(b, bool) or not isinstance(b, (int, float)) for b in bounds)):
            fail(f"design.{name}", f"expected [lower, upper] with lower < upper, got {bounds!r}")
        design[name] = (float(bounds[0]), float(bounds[1]))
    tr = dict(table("transcription"))
    solver = dict(table("solver"))
    if solver.pop("barrier", "monotone") not in BARRIERS:
        fail("solver.barrier", f"must be \"monotone\" (fatrop's rule; the adaptive rule was removed, "
                               f"docs/design/condensing.md), got {table('solver')['barrier']!r}")
    if solver.get("interface") == "direct" and not tr.get("compiled", True):
        fail("solver.interface", "the direct fatrop interface calls the compiled NLP: needs compiled = true")
    verification = {**table("verification"), **table("refinement")}
    return Problem(Task(**task, design=design), TranscriptionOptions(**tr), SolverOptions(**solver),
                   Verification(**verification), path=path).check()


def check_against_model(problem: Problem, model):
    """The problem's poses and parameter names fit the arm (errors name the problem file)."""
    from rscasadi.model.parameters import check_names
    t = problem.task
    where = problem.path
    model = holding_payload(model, t.payload, where)          # its parameters (payload.*) named too
    if t.collision is not None:
        from rscasadi.model.collision import with_collision
        model = with_collision(model, t.collision, where if where is not None else "<Problem>")
    for ob in t.obstacles:
        ob.check(model, where)
    for i, g in enumerate(t.goals):
        g.check(model, where, "goal" if len(t.goals) == 1 else f"goal[{i}]")
    rows = sum(3 if g.R is None else 6 for g in t.goals)
    if len(t.goals) > 1 and rows > model.n:
        raise ModelFileError(f"{where}: field 'goal': the goals are {rows} conditions, more than the {model.n} "
                             "joints can meet in general")
    if t.terms:
        from rscasadi.dynamics.arm import Arm
        from rscasadi.task.terms import check_terms
        check_terms(Arm(model), t.terms, str(where if where is not None else "<Problem>"))
    for key in ("theta_start", "theta_end"):
        v = getattr(t, key)
        if v is not None and len(v) != model.n:
            raise ModelFileError(f"{problem.path}: field '{key}': {len(v)} entries for a {model.n}-joint arm")
    try:
        check_names(model, t.design, f"{problem.path}: field 'design'")
        check_names(model, t.parameters, f"{problem.path}: parameters")
    except ValueError as exc:
        raise ModelFileError(str(exc)) from None
    if t.path is not None:
        t.path.check(model, where)
    for name, (lo, _) in t.design.items():
        if name.endswith(".gear_ratio") and lo <= 0:
            raise ModelFileError(f"{problem.path}: field 'design.{name}': a gear ratio stays positive "
                                 f"(lower bound {lo:g})")
    for name, v in t.parameters.items():
        if name.endswith(".gear_ratio") and v <= 0:
            raise ModelFileError(f"{problem.path}: parameter '{name}' = {v:g}: a gear ratio is positive")
    both = set(t.design) & set(t.parameters)
    if both:
        raise ModelFileError(f"{problem.path}: field 'design': {sorted(both)} cannot be both designed and swept")
