"""The safety side: the pure safety model (:mod:`safelane.safety.model`) and the gymnasium shield
that applies it (:mod:`safelane.safety.shield`).
"""
