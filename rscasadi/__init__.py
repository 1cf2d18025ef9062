"""rscasadi: rotor-separated dynamics of FS-SEA arms (Chen & Li) in CasADi."""
from importlib.metadata import PackageNotFoundError, version as _version

from rscasadi.codegen import CodegenError, load_compiled
from rscasadi.dynamics.arm import Arm, Robot, load
from rscasadi.dynamics.floating import FloatingRobot, load_robot
from rscasadi.dynamics.inverse_kinematics import inverse_kinematics
from rscasadi.errors import Error
from rscasadi.model.modelfile import ArmModel, ModelFileError

try:
    __version__ = _version("rscasadi")
except PackageNotFoundError:                       # run from a source tree that is not installed
    __version__ = "unknown"

__all__ = ["Arm", "ArmModel", "CodegenError", "Error", "FloatingRobot", "ModelFileError", "Robot", "__version__",
           "inverse_kinematics", "load", "load_compiled", "load_robot"]
