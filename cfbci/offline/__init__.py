"""Offline simulation: closed-loop sessions with a simulated user, presets, sweeps and their
figures, on one machine or a Dask cluster."""
