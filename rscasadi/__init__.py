"""rscasadi: rotor-separated dynamics of FS-SEA arms (Chen & Li) in CasADi."""
from .dynamics.arm import Arm, load
from .codegen import CodegenError, load_compiled
from .model.modelfile import ArmModel, ModelFileError

__all__ = ["Arm", "ArmModel", "CodegenError", "ModelFileError", "load", "load_compiled"]
