"""Scenarios, dataset validation and test-archive generators: the code that checks
calib against known truth (tests, ``make validate``, docs figures). It may import
any layer; nothing in the package imports it (tests/test_layers.py)."""
