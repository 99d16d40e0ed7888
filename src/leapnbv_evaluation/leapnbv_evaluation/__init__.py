"""Closed-loop evaluation on synthetic scenes: evaluator, metrics, benchmark sets, reports, demo."""
