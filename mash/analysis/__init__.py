"""Evaluation rollouts, the paper's metrics and the comparison's statistics."""
