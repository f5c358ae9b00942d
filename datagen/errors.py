"""User-facing errors: the command line prints them as one line and exits non-zero."""


class UserError(Exception):
    """A mistake in the user's input or environment, stated in one line."""


class DatasetError(UserError):
    """A problem with a dataset on disk, stated in one line naming the file."""
