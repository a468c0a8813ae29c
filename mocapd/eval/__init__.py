"""The accuracy harness (issue 3): real recorded motion, simulated sensors, the real solver, seed-003 metrics."""
