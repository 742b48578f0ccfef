"""The simulator side: the highway-env adapter (road snapshots), its neighbour-search patch, traffic
layout and scripted adversaries.
"""
