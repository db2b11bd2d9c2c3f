"""Evaluation against ground truth: trajectory metrics, object metrics, the reference check."""
