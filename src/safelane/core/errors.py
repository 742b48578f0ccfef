"""The one error type of bad input: a :class:`ConfigError` says, in one line, which key is wrong and what is
allowed. The CLI prints it without a traceback and exits with code 2."""

from __future__ import annotations


class ConfigError(ValueError):
    """A configuration problem, described in one line (key, value, what is allowed)."""


class NotSupported(ConfigError):
    """A valid configuration that this particular combination cannot run: a simulator without a traffic
    option, a trained policy in an environment it was not trained for. Suites skip it and say why."""
