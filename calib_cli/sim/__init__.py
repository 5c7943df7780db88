"""Turns a plan, a truth model and noise into raw samples, through model/ only."""
