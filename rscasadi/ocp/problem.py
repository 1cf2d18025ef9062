"""The optimal-control problem file (TOML), every field checked and named in errors:

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
                                         # for older files; docs/design/fatrop.md)
    [design]                             # parameters the optimiser chooses, constant over time
    "elbow_pitch.sea.k1" = [300.0, 3000.0]

Names in [design] are the model's parameter names (docs/user-guide/model.md, "Parameters") or gear ratios
("elbow_pitch.gear_ratio", bounds > 0).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rscasadi.model.modelfile import ModelFileError, field_checker, read_toml

OBJECTIVES = ("min_time", "min_effort", "tracking")
METHODS = ("radau", "legendre", "hermite-simpson")
SOLVERS = ("fatrop", "ipopt")
INTERFACES = ("direct", "casadi")
BARRIERS = ("monotone",)                     # fatrop's barrier rule (docs/design/fatrop.md)
HESSIANS = ("exact", "limited-memory")
TOP = {"model", "objective", "theta_start", "theta_end", "duration", "max_duration", "trajectory",
       "effort_weight", "transcription", "verification", "solver", "refinement", "design"}
TABLES = {"transcription": {"method", "degree", "intervals", "dynamics", "compiled", "condense"},
          "verification": {"final_angle_tol", "final_speed_tol", "tracking_tol", "limit_tol"},
          "refinement": {"rounds"},
          "solver": {"name", "hessian", "interface", "threads", "barrier"}}
# problem fields a sweep may vary without rebuilding the NLP (they are its parameters or bounds)
SWEEPABLE = ("theta_start", "theta_end", "duration", "max_duration", "effort_weight")


@dataclass
class Problem:
    path: Path
    model_path: Path
    objective: str
    duration: float
    theta_start: np.ndarray | None = None
    theta_end: np.ndarray | None = None
    max_duration: float = 10.0
    trajectory: Path | None = None
    effort_weight: float = 1e-3
    method: str = "radau"
    degree: int = 3
    intervals: int = 100
    dynamics: str = "explicit"
    compiled: bool = True
    condense: bool = True
    solver: str = "fatrop"
    hessian: str = "exact"
    interface: str = "direct"
    threads: int = 1                                 # 0: one per available core
    final_angle_tol: float = 1e-4
    final_speed_tol: float = 1e-3
    tracking_tol: float = 1e-3
    limit_tol: float = 1e-3
    rounds: int = 4
    design: dict = field(default_factory=dict)       # name -> (lo, hi): decision variables
    parameters: dict = field(default_factory=dict)   # name -> value: NLP inputs (sweeps)


def load_problem(path) -> Problem:
    path = Path(path)
    d = read_toml(path, "problem")
    fail = field_checker(path, d, TOP)

    def number(fld, v, positive=True):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or (positive and v <= 0):
            fail(fld, f"must be a{' positive' if positive else ''} number, got {v!r}")
        return float(v)

    def table(name):
        t = d.get(name, {})
        if not isinstance(t, dict):
            fail(name, "expected a table")
        for key in t:
            if name in TABLES and key not in TABLES[name]:
                fail(f"{name}.{key}", f"unknown key (allowed: {', '.join(sorted(TABLES[name]))})")
        return t

    for key in ("model", "objective", "duration"):
        if key not in d:
            fail(key, "missing required field")
    for key in ("model", "trajectory"):
        if key in d and (not isinstance(d[key], str) or not d[key].strip()):
            fail(key, f"expected the path of a file, got {d[key]!r}")
    if d["objective"] not in OBJECTIVES:
        fail("objective", f"must be one of {', '.join(OBJECTIVES)}, got {d['objective']!r}")
    tr = table("transcription")
    p = Problem(path=path, model_path=(path.parent / str(d["model"])).resolve(), objective=d["objective"],
                duration=number("duration", d["duration"]))
    if d["objective"] == "tracking":
        if "trajectory" not in d:
            fail("trajectory", "missing required field (objective tracking)")
        p.trajectory = (path.parent / str(d["trajectory"])).resolve()
    else:
        for key in ("theta_start", "theta_end"):
            v = d.get(key)
            if v is None:
                fail(key, f"missing required field (objective {d['objective']})")
            if not isinstance(v, list) or not v:
                fail(key, f"expected a list of numbers, got {v!r}")
            setattr(p, key, np.array([number(f"{key}[{i}]", x, positive=False) for i, x in enumerate(v)]))
    if "max_duration" in d:
        p.max_duration = number("max_duration", d["max_duration"])
    if "effort_weight" in d:
        p.effort_weight = number("effort_weight", d["effort_weight"], positive=False)
    p.method = tr.get("method", "radau")
    if p.method not in METHODS:
        fail("transcription.method", f"must be one of {', '.join(METHODS)}, got {p.method!r}")
    for fld, lo, value in (("transcription.degree", 1, tr.get("degree", p.degree)),
                           ("transcription.intervals", 2, tr.get("intervals", p.intervals)),
                           ("refinement.rounds", 0, table("refinement").get("rounds", p.rounds)),
                           ("solver.threads", 0, table("solver").get("threads", p.threads))):
        if isinstance(value, bool) or not isinstance(value, int) or value < lo:
            fail(fld, f"must be an integer >= {lo}, got {value!r}")
        setattr(p, fld.split(".")[1], value)
    p.dynamics = tr.get("dynamics", "explicit")
    if p.dynamics not in ("explicit", "implicit"):
        fail("transcription.dynamics", f"must be explicit or implicit, got {p.dynamics!r}")
    for key, value in table("verification").items():
        setattr(p, key, number(f"verification.{key}", value))
    solver = table("solver")
    p.solver, p.hessian = solver.get("name", p.solver), solver.get("hessian", p.hessian)
    if p.solver not in SOLVERS:
        fail("solver.name", f"must be one of {', '.join(SOLVERS)}, got {p.solver!r}")
    if p.hessian not in HESSIANS:
        fail("solver.hessian", f"must be one of {', '.join(HESSIANS)}, got {p.hessian!r}")
    p.interface = solver.get("interface", p.interface)
    if p.interface not in INTERFACES:
        fail("solver.interface", f"must be one of {', '.join(INTERFACES)}, got {p.interface!r}")
    if p.hessian != "exact" and p.solver == "fatrop":
        fail("solver.hessian", "fatrop needs the exact Hessian; use name = \"ipopt\" for limited-memory")
    p.compiled = tr.get("compiled", True)
    if not isinstance(p.compiled, bool):
        fail("transcription.compiled", f"must be true or false, got {p.compiled!r}")
    p.condense = tr.get("condense", p.compiled)
    if not isinstance(p.condense, bool):
        fail("transcription.condense", f"must be true or false, got {p.condense!r}")
    if solver.get("barrier", "monotone") not in BARRIERS:
        fail("solver.barrier", f"must be \"monotone\" (fatrop's rule; the adaptive rule was removed, "
                               f"docs/design/fatrop.md), got {solver['barrier']!r}")
    if solver.get("interface") == "direct" and not p.compiled:
        fail("solver.interface", "the direct fatrop interface calls the compiled NLP: needs compiled = true")
    if p.condense and not p.compiled:
        fail("transcription.condense", "the condensing kernel is C: needs compiled = true (or condense = false)")
    for name, bounds in table("design").items():
        if (not isinstance(bounds, list) or len(bounds) != 2
                or any(isinstance(b, bool) or not isinstance(b, (int, float)) for b in bounds)
                or not bounds[0] < bounds[1]):
            fail(f"design.{name}", f"expected [lower, upper] with lower < upper, got {bounds!r}")
        p.design[name] = (float(bounds[0]), float(bounds[1]))
    return p


def check_against_model(problem: Problem, model):
    """The problem's poses and parameter names fit the arm (errors name the problem file)."""
    from rscasadi.model.parameters import check_names
    for key in ("theta_start", "theta_end"):
        v = getattr(problem, key)
        if v is not None and len(v) != model.n:
            raise ModelFileError(f"{problem.path}: field '{key}': {len(v)} entries for a {model.n}-joint arm")
    try:
        check_names(model, problem.design, f"{problem.path}: field 'design'")
        check_names(model, problem.parameters, f"{problem.path}: parameters")
    except ValueError as exc:
        raise ModelFileError(str(exc)) from None
    for name, (lo, _) in problem.design.items():
        if name.endswith(".gear_ratio") and lo <= 0:
            raise ModelFileError(f"{problem.path}: field 'design.{name}': a gear ratio stays positive "
                                 f"(lower bound {lo:g})")
    for name, v in problem.parameters.items():
        if name.endswith(".gear_ratio") and v <= 0:
            raise ModelFileError(f"{problem.path}: parameter '{name}' = {v:g}: a gear ratio is positive")
    both = set(problem.design) & set(problem.parameters)
    if both:
        raise ModelFileError(f"{problem.path}: field 'design': {sorted(both)} cannot be both designed and swept")
