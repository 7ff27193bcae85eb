"""The error of the probe's bad inputs."""


class ProbeError(Exception):
    """Bad input to the probe (a file, a model, rollouts or a setting); the message says what to do."""
