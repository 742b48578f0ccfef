"""Vocabulary shared by every tier: action and observation sizes, the road snapshot, errors, atomic files.

Imports no simulator and no torch.
"""
