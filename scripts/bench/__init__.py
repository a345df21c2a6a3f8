"""Benchmarks: time and memory of the stages and of whole commands."""
