"""The committed shield's episode starts: each reset reports them, and can redraw an uncertified spawn.

The ``committed`` shield mode (:mod:`safelane.safety.committed`) promises nothing in an episode whose first state has no
verified plan (``info["uncertified_start"]``). :class:`RedrawUncertified` sits above the shield and adds to every
reset's ``info`` the number of spawns drawn again (``redraws``); with ``tries`` > 0 (``shield.redraw_uncertified``) it
resets again, without a seed — the environment's generator draws the next spawn, so the same seed still gives the same
episode — until the first state has a verified plan, at most ``tries`` times.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym


class RedrawUncertified(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Report (and with ``tries`` > 0, redraw) the committed shield's uncertified starts (module docstring).

    ``env``: an environment whose outermost shield is a committed :class:`safelane.safety.shield.SafetyShield`.
    ``tries``: the most spawns drawn again per episode (0: none, the traffic as it is)."""

    def __init__(self, env: gym.Env, tries: int = 0) -> None:
        if not isinstance(tries, int) or isinstance(tries, bool) or tries < 0:
            raise ValueError(f"shield.redraw_tries: must be a whole number >= 0 (got {tries!r})")
        gym.utils.RecordConstructorArgs.__init__(self, tries=tries)
        super().__init__(env)
        self.tries = tries

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(seed=seed, options=options)
        redraws = 0
        while info.get("uncertified_start", False) and redraws < self.tries:
            obs, info = self.env.reset(options=options)  # no seed: the generator's next spawn
            redraws += 1
        info["redraws"] = redraws
        return obs, info

    def action_masks(self) -> Any:
        """The shield's mask of the current state (sb3-contrib's convention, as the shield gives it)."""
        return self.env.get_wrapper_attr("action_masks")()
