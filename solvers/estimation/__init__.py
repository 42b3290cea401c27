"""Estimation that knows no robot: least squares in chunks, fit results, identifiability, grouped cross-validation."""
