"""Kinematic identification: the measurement model, the geometric fit, pose design, ISO 9283."""
