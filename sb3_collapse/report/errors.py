"""The error of the report's bad inputs."""

from sb3_collapse.errors import InputError


class ReportError(InputError):
    """Bad input to the report (a sweep folder, a trial file or a setting); the message says what to do."""
