"""Robot programs as users keep them: read a program, find its motion targets, write it back
with the targets compensated and every other byte as it was (``urscript``: Universal Robots'
URScript; ``apply``: the compensation of a parsed program with a calibrated model)."""
