"""Building blocks shared by the learned baselines (one copy each, never per network)."""
