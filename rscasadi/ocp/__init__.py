"""Optimal control of the motor torques: problem files, a stage-wise direct collocation, fatrop
or IPOPT, verification on the complete model with mesh refinement, co-design and sweeps."""
from rscasadi.ocp.problem import Problem, load_problem
from rscasadi.ocp.solving import rest_state, run, solve, solve_once, verify
from rscasadi.ocp.transcription import Transcription

__all__ = ["Problem", "Transcription", "load_problem", "rest_state", "run", "solve", "solve_once", "verify"]
