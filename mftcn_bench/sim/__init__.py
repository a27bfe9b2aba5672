"""Simulation: headless rendering of MuJoCo scenes and the dm_control suite's limits."""
