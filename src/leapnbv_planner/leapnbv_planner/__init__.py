"""Next-best-view candidate ring, S_v/S_a/S_o scoring and the nbv node."""
