"""Reporting: statistics, the reproduction report, plots, rendered episodes."""
