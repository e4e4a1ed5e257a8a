"""The one error type for bad input, shared by every layer.

:class:`ConfigError` is raised, before any simulation, for a configuration value that cannot work
(the config schema, the course geometry, a checkpoint that does not fit the run). It lives at the
bottom of the package so that the pure rooms (``march.world``) can raise it without importing the
config framework; ``march.config`` re-exports it.
"""


class ConfigError(ValueError):
    """A configuration value that cannot work; the message says how to fix it."""
