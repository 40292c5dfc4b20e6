"""Batch evaluation of controllers: seeded rollouts, results files, reports."""
