"""Errors a user can act on. Stages print them as one line and exit non-zero (see `pipeline.cli`)."""


class PipelineError(Exception):
    """Base class: an error caused by the user's input, reported without a traceback."""


class ConfigError(PipelineError, ValueError):
    """An invalid configuration value. `field` is the config key (e.g. `controller.chi`)."""

    def __init__(self, field: str, reason: str):
        self.field = field
        self.reason = reason
        super().__init__(f"{field}: {reason}")


class DatasetError(PipelineError):
    """A dataset that is unknown, incomplete or fails verification."""


class ModelError(PipelineError):
    """A perception map that is unknown or does not fit its input."""
