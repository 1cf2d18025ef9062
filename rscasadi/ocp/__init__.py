"""Optimal control of the motor torques: a problem stated in parts (task, transcription, solver,
verification), a stage-wise direct collocation, fatrop or IPOPT, every solution replayed on the
complete model with mesh refinement, co-design and sweeps.

    from rscasadi.ocp import Problem, Task, TranscriptionOptions, solve
    problem = Problem(Task("problems/arm3.toml", "min_effort", duration=1.5,
                           theta_start=[0, 0.3, -0.5], theta_end=[0.8, 0.9, -1.2]),
                      TranscriptionOptions(intervals=50))
    sol = solve(problem)                    # a Solution: sol.theta, sol.tau, sol.verify(), sol.plot(dir)
"""
from rscasadi.ocp.problem import (Problem, SolverOptions, Task, TranscriptionOptions, Verification,  # noqa: F401
                                  load_problem)
from rscasadi.ocp.solution import Solution, verify
from rscasadi.ocp.solving import rest_state, run, solve, solve_once
from rscasadi.ocp.transcription import Transcription

__all__ = ["Problem", "Solution", "SolverOptions", "Task", "Transcription", "TranscriptionOptions", "Verification",
           "load_problem", "rest_state", "run", "solve", "solve_once", "verify"]
