"""The arm for other simulators: the complete rotor-separated model as MuJoCo's MJCF (`mujoco`)."""
from rscasadi.export.mujoco import export_mujoco, mujoco_xml

__all__ = ["export_mujoco", "mujoco_xml"]
