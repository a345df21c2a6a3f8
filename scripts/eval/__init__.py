"""Evaluations: accuracy against ground truth on rendered and simulated sequences."""
