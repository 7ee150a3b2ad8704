"""The one exception type that the command line turns into a one-line message and exit code 2."""


class CubecloudError(Exception):
    """A problem with the user's input or work directory, stated with its fix.

    The message is a single line meant for the terminal: what is wrong, then what to do. Text
    quoted from a library's exception may span lines, so white space is folded here.
    """

    def __init__(self, message: str) -> None:
        super().__init__(" ".join(str(message).split()))
