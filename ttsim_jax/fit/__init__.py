"""Identification of each physics stage's parameters from data (one module per stage)."""
