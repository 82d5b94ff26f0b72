"""The one exception type a user is meant to see: the CLI prints its message on one line."""


class MCSplatError(Exception):
    """A problem with the user's input or options; the message says what is wrong and how to fix it."""


class DataError(MCSplatError):
    """A scene folder or one of its files cannot be used."""
