"""The model (constant): types, model files, URDF import, frames, parameters, limits, collision geometry."""
