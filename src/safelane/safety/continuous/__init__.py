"""The committed rule for an ego under continuous controls (acceleration and steering).

Plans that end stopped in one lane (:mod:`~safelane.safety.continuous.plans`, over the ego's exact motion,
:mod:`~safelane.safety.continuous.controls`), verified against the committed rule's reachable sets; the compiled
engine (:mod:`~safelane.safety.continuous.compiled`, the same bits); the verified action nearest the agent's
(:mod:`~safelane.safety.continuous.search`); the memory between decisions
(:mod:`~safelane.safety.continuous.family`). Pure maths: no simulator, no highway-env, no torch.
"""
