"""The one exception type tnf raises for problems a user can fix (bad input, bad config, missing data)."""


class TnfError(Exception):
    """A user-facing error. The ``tnf`` command prints its message as one line and exits non-zero."""


class NonFiniteLoss(TnfError):
    """A training loss became NaN or infinite; training stopped before any checkpoint was overwritten."""
