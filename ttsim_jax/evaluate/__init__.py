"""Metrics and summaries of simulated or measured rallies."""
