"""Evaluation: metrics, Monte Carlo consistency study, plotting, textbook exercises."""
