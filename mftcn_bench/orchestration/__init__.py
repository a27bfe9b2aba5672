"""Sweeps: the (encoder, task, seed) grid, its jobs and the executors that run them (local pool, Ray)."""
