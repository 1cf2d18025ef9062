"""rscasadi: rotor-separated dynamics of FS-SEA arms (Chen & Li) in CasADi."""
from .arm import Arm, load
from .modelfile import ArmModel, ModelFileError

__all__ = ["Arm", "ArmModel", "ModelFileError", "load"]
