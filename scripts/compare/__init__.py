"""Comparisons: line-based against point-based initializers, tracking variants."""
