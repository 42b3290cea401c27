"""Tool-frame fits: pivots, crossed-beam sweeps, stylus contacts, checks and handshakes between two robots."""
