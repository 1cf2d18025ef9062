"""What the arm must do, below both the optimal-control problem and the MPC.

objects: `Goal`, `Obstacle`, `Payload`, `Limits`, each checked against the arm and written as a
dict; toolpath: `ToolPath`, a frame's path and its timing; read: the problem files' shared
fields parsed once; terms: what the arm must do on a stage as **terms** (Crocoddyl's cost and
constraint models, rockit's `add_objective` / `subject_to`), each a residual or constraint rows
of (x, u, p) with its replay metric, which the OCP's transcription, the MPC's stage cost and the
verification loop over.
"""
from rscasadi.task.objects import Goal, Limits, Obstacle, Payload
from rscasadi.task.toolpath import ToolPath

__all__ = ["Goal", "Limits", "Obstacle", "Payload", "ToolPath"]
