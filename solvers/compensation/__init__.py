"""From an identified or extended model back to commands: compensated targets and the calibrated model."""
