"""The error of the report's bad inputs."""


class ReportError(Exception):
    """Bad input to the report (a sweep folder, a trial file or a setting); the message says what to do."""
