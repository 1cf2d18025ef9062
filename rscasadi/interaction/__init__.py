"""Interaction: estimating and controlling the forces between the arm and the world."""
from rscasadi.interaction.observer import MomentumObserver, observer_terms, tool_wrench

__all__ = ["MomentumObserver", "observer_terms", "tool_wrench"]
