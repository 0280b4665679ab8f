"""User-facing errors: the CLI prints these as one line, without a traceback."""


class TwohrError(Exception):
    """An error caused by the user's input or environment, with a message that says how to fix it."""


class DatasetError(TwohrError):
    """A sequence folder, file or frame that cannot be read."""


class ModelError(TwohrError):
    """A model that is unknown, missing or fails its checksum."""


class ConfigError(TwohrError):
    """A configuration value that does not validate."""
