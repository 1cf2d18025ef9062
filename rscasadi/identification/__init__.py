"""Fitting the model to logs: the regressor, excitation design, log reading, the fit, payloads."""
