"""Interaction: estimating and controlling the forces between the arm and the world."""
from rscasadi.interaction.generate import CompiledImpedance, CompiledObserver, generate_impedance, generate_observer
from rscasadi.interaction.impedance import ImpedanceController, impedance_law
from rscasadi.interaction.observer import MomentumObserver, observer_terms, tool_wrench

__all__ = ["CompiledImpedance", "CompiledObserver", "ImpedanceController", "generate_impedance", "MomentumObserver", "generate_observer", "impedance_law",
           "observer_terms", "tool_wrench"]
