"""rscasadi: rotor-separated dynamics of FS-SEA arms (Chen & Li) in CasADi."""
from .arm import Arm, load
from .codegen import CodegenError, load_compiled
from .modelfile import ArmModel, ModelFileError

__all__ = ["Arm", "ArmModel", "CodegenError", "ModelFileError", "load", "load_compiled"]
