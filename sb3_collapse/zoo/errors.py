"""Errors of the rl_zoo3 launcher, each printed as ``error: ...`` with exit status 2 by the command line."""


class ZooNotInstalledError(ImportError):
    """rl_zoo3 (an optional dependency) or one of its own dependencies cannot be imported."""


class ZooConfigError(ValueError):
    """A configuration rl_zoo3 would run wrongly or fail on deep inside; the message says what to change."""


class LauncherError(ValueError):
    """A bad launcher command line; the message says what to pass."""
