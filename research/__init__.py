"""Research tools: diagnostics of the rule, the simulators and the agents, outside the library.

Scripts run from the repository root (``python research/repair_breaks.py …``); their helper modules
(:mod:`research.counterexample_tools`) import the library and are imported by nothing in it. Their tests are
``tests/research/``.
"""
