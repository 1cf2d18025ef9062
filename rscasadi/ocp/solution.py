"""A solved optimal-control problem: the record `solution.json` holds, and what to do with it.

`Solution` is that record, read-only (a dict: `sol["theta"]`, as written to JSON; `replace(...)`
gives a changed copy) with its main fields as numpy attributes (`sol.t`, `sol.theta`,
`sol.tau`, ...), what it claims (`solved`: the solver converged; `verified`: the torques replayed
on the complete model did what the collocation promised; `success`: both where a replay was
done, else `solved`), `sample(quantity, times)` over that replay, `verify()`, `plot(directory)`,
`to_json(path)`; `Solution.from_json(path)` reads one back.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from rscasadi.dynamics.arm import Arm
from rscasadi.dynamics.collision import exact_clearance
from rscasadi.errors import InvalidArgument, WrongType
from rscasadi.files import write_json
from rscasadi.model.collision import with_collision
from rscasadi.task.objects import holding_payload
from rscasadi.model.modelfile import read
from rscasadi.model.parameters import with_values
from rscasadi.sim.simulation import simulate_held
from rscasadi.sim.trajectory import load_trajectory
from rscasadi.model.limits import slow_sides, violation
from rscasadi.task.objects import goals_of

STATE = ("theta", "phi", "dtheta", "dphi")


SAMPLED = STATE + ("psi", "tau")


class Solution(dict):
    """The record of a solve (the keys of solution.json, docs/user-guide/problems.md), read-only."""

    def _read_only(self, *args, **kwargs):
        raise WrongType("a Solution is read-only: sol.replace(key=value) returns a changed copy")

    __setitem__ = __delitem__ = update = pop = popitem = setdefault = clear = __ior__ = _read_only  # type: ignore

    def __reduce__(self):                     # pickled and copied as a whole, not item by item
        return type(self), (dict(self),)

    def replace(self, **changes) -> "Solution":
        """A copy with `changes` to its fields."""
        return type(self)({**self, **changes})

    def _array(self, key):
        return np.asarray(self[key], float)

    t = property(lambda self: self._array("t"), doc="the mesh's times (s)")
    theta = property(lambda self: self._array("theta"), doc="link angles at the mesh (n x N+1, rad)")
    phi = property(lambda self: self._array("phi"), doc="the SEAs' motor angles at the slow side (m x N+1, rad)")
    dtheta = property(lambda self: self._array("dtheta"), doc="link speeds (rad/s)")
    dphi = property(lambda self: self._array("dphi"), doc="the SEAs' motor speeds at the slow side (rad/s)")
    tau = property(lambda self: self._array("tau"), doc="the actuated joints' torques, held on each interval (u x N+1, N m)")
    success = property(lambda self: bool(self["success"]), doc="solved and, where a replay was done, verified")
    solved = property(lambda self: bool(self.get("solver_success", self["success"])), doc="the solver converged")
    verified = property(lambda self: bool((self.get("verification") or {}).get("passed", False)),
                        doc="the torques replayed on the complete model kept every promise (solve() replays)")
    status = property(lambda self: self["status"], doc="the solver's return status")
    objective = property(lambda self: float(self["objective"]), doc="the objective's value")
    design = property(lambda self: dict(self.get("design", {})), doc="the designed parameters' values")

    @classmethod
    def from_json(cls, path) -> "Solution":
        """A solution.json read back."""
        return cls(json.loads(Path(path).read_text()))

    def arm(self) -> Arm:
        """The arm the torques are for: the model file with the swept and designed parameters."""
        return solution_arm(self)

    def verify(self, substeps: int = 20, tol: float = 1e-10) -> dict:
        """The torques replayed on the complete model (see `verify`)."""
        return verify(self, substeps, tol)

    def sample(self, quantity: str, times, substeps: int = 20) -> np.ndarray:
        """`quantity` (theta, phi, dtheta, dphi, psi = phi - theta, or tau) at `times` (s) of the
        torques replayed on the complete model (CVODES, `substeps` per interval, interpolated
        linearly between its samples; tau as held over each interval): a row per joint (theta,
        dtheta), per SEA (phi, dphi, psi) or per input (tau), a column per time."""
        if quantity not in SAMPLED:
            raise InvalidArgument(f"sample: quantity {quantity!r} is not one of {', '.join(SAMPLED)}")
        times = np.atleast_1d(np.asarray(times, float))
        t = self.t
        if times.size and (times.min() < t[0] or times.max() > t[-1]):
            raise InvalidArgument(f"sample: times must lie in the motion's [{t[0]:g}, {t[-1]:g}] s")
        if quantity == "tau":
            k = np.clip(np.searchsorted(t, times, side="right") - 1, 0, len(t) - 2)
            return self.tau[:, k]
        sim = self._replay(substeps)
        return np.vstack([np.interp(times, sim["t"], row) for row in sim[quantity]])

    def _replay(self, substeps: int) -> dict:
        cache = self.__dict__.setdefault("_replays", {})
        if substeps not in cache:
            x0 = np.concatenate([np.asarray(self[k], float)[:, 0] for k in STATE])
            cache[substeps] = simulate_held(self.arm(), x0, self.t, self.tau, substeps, 1e-10)
        return cache[substeps]

    def to_json(self, path):
        """Write the record as JSON (whole or not at all; no NaN)."""
        write_json(path, dict(self), indent=1)

    def plot(self, directory):
        """Write solution.png and solution.pdf into `directory`: angles, deflections, torques,
        speeds, with the limits dotted."""
        plot_solution(self, self.arm(), Path(directory))


def solution_arm(solution: dict) -> Arm:
    """The arm the solution is for: the model file with the task's payload and its swept and
    designed parameters."""
    model = read(solution["model"])
    model = holding_payload(model, solution.get("payload") or None, solution["model"])
    if solution.get("collision") is not None:
        model = with_collision(model, solution["collision"], solution["model"])
    return Arm(with_values(model, {**solution.get("parameters", {}), **solution.get("design", {})}))


def verify(solution: dict, substeps: int = 20, tol: float = 1e-10, terms=()) -> dict:
    """Replay the torques on the complete model with CVODES, on a grid `substeps` times finer than
    the collocation grid; report the final-state error and the largest limit violation anywhere,
    and each of `terms` (the task's own, rscasadi.task.terms) as `term.<name>`: its replay
    metric on every sample (a constraint's largest violation)."""
    arm = solution_arm(solution)
    q, t, tau = arm.nq, np.asarray(solution["t"]), np.asarray(solution["tau"])
    x0 = np.concatenate([np.asarray(solution[k])[:, 0] for k in ("theta", "phi", "dtheta", "dphi")])
    sim = simulate_held(arm, x0, t, tau, substeps, tol, energy=False)
    per_interval = violation(arm.model, sim["theta"], sim["phi"], sim["dphi"], sim["dtheta"]
                             ).reshape(-1)[1:].reshape(len(t) - 1, substeps).max(axis=1)
    report = {"max_limit_violation": max(float(per_interval.max()), 0.0), "substeps": substeps}
    if solution.get("target_state") is not None:
        err = np.abs(sim["x"][:, -1] - np.asarray(solution["target_state"]))
        report["final_angle_error"] = float(np.max(err[:q]))
        report["final_speed_error"] = float(np.max(err[q:]))
    if solution.get("trajectory"):                                     # between the nodes too
        ref = load_trajectory(solution["trajectory"])(sim["t"])[0]
        report["tracking_error"] = float(np.max(np.abs(sim["theta"] - ref)))
    for g in goals_of(solution):                                       # the replay's end at the goals
        R, p = (np.array(v) for v in arm.frame_placement(g["frame"])(sim["theta"][:, -1]))
        error = float(np.linalg.norm(p.ravel() - np.asarray(g["position"])))
        report["goal_position_error"] = max(report.get("goal_position_error", 0.0), error)
        if g["R"] is not None:
            c = (np.trace(np.asarray(g["R"]).T @ R) - 1) / 2
            angle = float(np.arccos(np.clip(c, -1.0, 1.0)))
            report["goal_angle_error"] = max(report.get("goal_angle_error", 0.0), angle)
    from rscasadi.model.collision import capsule_pairs
    if solution.get("obstacles") or capsule_pairs(arm.model):         # clear of them and of each other, between
        from rscasadi.task.objects import Obstacle                      # the nodes too
        obstacles = [Obstacle.from_dict(o) for o in solution.get("obstacles") or []]
        gap = np.array(exact_clearance(arm.model, obstacles).map(sim["theta"].shape[1])(sim["theta"])).ravel()
        report["min_clearance"] = float(gap.min())
        report["interval_clearance"] = gap[1:].reshape(len(t) - 1, substeps).min(axis=1).tolist()
    if solution.get("obstacles"):                                      # the URDF's own shapes, by coal
        from rscasadi.dynamics.shapes_clearance import shapes_clearance
        from rscasadi.model.collision import margin
        urdf_gap = shapes_clearance(arm.model, obstacles, sim["theta"]) - margin(arm.model)
        if np.all(np.isfinite(urdf_gap)):                             # the URDF's own shapes, by coal
            report["urdf_min_clearance"] = float(urdf_gap.min())
            report["interval_urdf_clearance"] = urdf_gap[1:].reshape(len(t) - 1, substeps).min(axis=1).tolist()
    if solution.get("path"):                                          # on the path, between the nodes too
        from rscasadi.task.toolpath import ToolPath
        path = ToolPath.from_dict(solution["path"])
        place = arm.frame_placement(path.frame).map(sim["theta"].shape[1])
        where = np.array(place(sim["theta"])[1]).T
        # a fixed timing: from the point of its time; a free one: from the path itself
        gap = np.linalg.norm(where - path(sim["t"]), axis=1) if path.speed is not None else path.distance(where)
        report["path_error"] = float(gap.max())
        report["interval_path_error"] = gap[1:].reshape(len(t) - 1, substeps).max(axis=1).tolist()
    if terms:
        held = tau[:, np.maximum(np.arange(sim["x"].shape[1]) - 1, 0) // substeps]     # what led to each sample
        for term in terms:
            report[f"term.{term.name}"] = term.replay_metric(arm, sim["x"], held)
    report["max_collocation_deviation"] = float(np.max(np.abs(sim["theta"][:, ::substeps] - np.asarray(solution["theta"]))))
    report["interval_violation"] = per_interval.tolist()
    return report


def plot_solution(sol: dict, arm: Arm, out: Path):
    """out.png and out.pdf: angles, deflections, torques and speeds of a solution over time."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    t, model = np.asarray(sol["t"]), arm.model
    th, ph, dth, dph, tau = (np.asarray(sol[k]) for k in ("theta", "phi", "dtheta", "dphi", "tau"))
    ph, dph = slow_sides(model, th, ph, dth, dph)             # a row per joint: the link's own without a motor
    tau = np.vstack([tau[model.input_of[j]] if j in model.input_of else np.full(len(t), np.nan)
                     for j in range(arm.n)])
    panels = [("theta", th, "link angle theta (rad)", "theta"), ("psi", ph - th, "SEA deflection psi (rad)", "psi"),
              ("tau", tau, "motor torque tau (N m)", "tau"), ("dphi", dph, "slow-side speed dphi (rad/s)", "dphi")]
    fig, axes = plt.subplots(2, 2, figsize=(11, 7), sharex=True)
    for ax, (key, data, label, lim) in zip(axes.ravel(), panels):
        for j, jt in enumerate(arm.model.joints):
            line = ax.step(t, data[j], where="post", label=jt.name)[0] if key == "tau" else ax.plot(t, data[j], label=jt.name)[0]
            bound = jt.limits.get(lim)
            if bound is not None:
                lo, hi = bound if isinstance(bound, tuple) else (-bound, bound)
                for b in (lo, hi):
                    ax.axhline(b, color=line.get_color(), ls=":", lw=1)
        ax.set(ylabel=label)
    for ax in axes[1]:
        ax.set(xlabel="t (s)")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(f"{Path(sol['model']).name}: {sol['status']}, {sol['intervals']} intervals, "
                 f"success {sol['success']} (dotted: limits)")
    fig.tight_layout()
    for ext in ("png", "pdf"):
        fig.savefig(out / f"solution.{ext}", dpi=120)
    plt.close(fig)
