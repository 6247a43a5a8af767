"""One exception type for every problem a user can fix, so the CLI can print it without a traceback."""


class RMError(ValueError):
    """Bad input to rm_torchrl: a malformed spec, wrong shapes, NaNs, empty data, bad options."""
