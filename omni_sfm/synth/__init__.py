"""Synthetic data with exact ground truth: simulated line observations and rendered video."""
