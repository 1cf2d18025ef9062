"""Nonlinear MPC on the complete model, generated to C (`rscasadi mpc PROBLEM.toml --out DIR`).

problem: the problem file; formulation: the shooting, the condensed Gauss-Newton QP and its
box-constrained interior point, as CasADi Functions; generate: the C (templates/) and its
library; compiled: the library through ctypes; study: the closed loop on a plant that differs.
"""
from rscasadi.mpc.compiled import CompiledMPC
from rscasadi.mpc.formulation import (_Linearisation, box_qp, hold_function, interval_functions,  # noqa: F401
                                      limit_arrays, rti_function, stage_residual)
from rscasadi.mpc.generate import generate_mpc
from rscasadi.mpc.problem import MPCProblem, load_mpc_problem
from rscasadi.mpc.study import (closed_loop, heavier_tip, plot_closed_loop, plot_task_study, reach_pose, study,
                                task_closed_loop, task_study)

__all__ = ["CompiledMPC", "MPCProblem", "box_qp", "closed_loop", "generate_mpc", "heavier_tip", "hold_function",
           "interval_functions", "limit_arrays", "load_mpc_problem", "plot_closed_loop", "reach_pose",
           "rti_function", "stage_residual", "study", "task_closed_loop", "task_study", "plot_task_study"]
