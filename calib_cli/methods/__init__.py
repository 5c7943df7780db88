"""Estimators: arrays and a model description in, result objects out. No I/O."""
