"""Rigid-body geometry: SE(3), kinematic chains and robot models, inverse kinematics, gravity regressors."""
