"""Evaluation: the comparison with other methods (compare, pattern), the paper's metrics against
ground truth (evaluate) and the consistency of two results in sigmas (consistency).

Above the solver and io, below the report and the CLI."""
