"""The arm as CasADi Functions: the recursions, kinematics, statics, feedforward and collision distances."""
