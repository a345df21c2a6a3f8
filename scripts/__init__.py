"""Benchmark, evaluation, comparison and reproduction scripts; run from the repository root as
``python -m scripts.<group>.<name>``. The library never imports them."""
