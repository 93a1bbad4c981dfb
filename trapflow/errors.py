"""The exception hierarchy: every error trapflow raises on purpose derives from TrapflowError."""


class TrapflowError(Exception):
    """Base of every error trapflow raises on purpose."""


class ConfigError(TrapflowError):
    """A configuration value, file or command-line option is invalid."""


class ProtocolError(TrapflowError):
    """A message on a socket does not match the wire format."""


class WorkerError(TrapflowError):
    """An algorithm plugin cannot be loaded, configured or run."""


class StartupError(TrapflowError):
    """A pipeline piece cannot start (socket in use, run directory locked...)."""
