"""Errors the command line reports as one line (no traceback)."""


class UserError(Exception):
    """Bad input from the user: a file, an option, a record. The message is the whole story."""
