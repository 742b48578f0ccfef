"""Every DQN method's agent class by name: the paper's four (:mod:`safelane.agents.dqn`) and the recurrent one
(:mod:`safelane.agents.recurrent`). The recurrent module builds on :mod:`~safelane.agents.dqn`, so this module, not
that one, knows both: the import graph keeps no cycle."""

from __future__ import annotations

from safelane.agents.dqn import AGENT_CLASSES, METHODS, RECURRENT_METHODS, AgentConfig, DQNAgent
from safelane.agents.recurrent import RecurrentRobustAgent
from safelane.core.spaces import OBS_SIZE

ALL_AGENT_CLASSES: dict[str, type[DQNAgent]] = {**AGENT_CLASSES, RecurrentRobustAgent.method: RecurrentRobustAgent}
"""The agent class of every method: :data:`~safelane.agents.dqn.METHODS`, then
:data:`~safelane.agents.dqn.RECURRENT_METHODS`."""
assert tuple(ALL_AGENT_CLASSES) == (*METHODS, *RECURRENT_METHODS)


def agent_class(method: str) -> type[DQNAgent]:
    """The agent class of ``method`` (any of :data:`ALL_AGENT_CLASSES`)."""
    return ALL_AGENT_CLASSES[method]


def make_agent(cfg: AgentConfig, seed: int = 0, obs_size: int = OBS_SIZE) -> DQNAgent:
    """The agent for ``cfg.method``, recurrent or not, networks initialised from ``seed``."""
    return agent_class(cfg.method)(cfg, seed, obs_size)
