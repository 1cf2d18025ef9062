"""Independent oracles for the tests: a numpy implementation of the recursions and a Pinocchio route."""
