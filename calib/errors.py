"""The one error of configuration and calibration input."""


class ConfigError(ValueError):
    """A configuration file is unreadable or invalid. The message is one line naming the file
    and the key; CLIs turn it into that line on stderr and exit code 2."""
