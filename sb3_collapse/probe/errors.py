"""The error of the probe's bad inputs."""


from sb3_collapse.errors import InputError


class ProbeError(InputError):
    """Bad input to the probe (a file, a model, rollouts or a setting); the message says what to do."""
