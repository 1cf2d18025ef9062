"""Simulation: the plant, trajectories, sensors and contacts."""
