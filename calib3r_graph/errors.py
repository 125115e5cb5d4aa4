"""Domain exceptions. The CLI turns each into one line on stderr and its exit code.

Exit codes (documented in the README):
    0  success
    1  unexpected internal error (a bug: please report it with --debug output)
    2  bad command line (argparse)
    3  invalid input: a dataset, predictions or candidates file breaks the contract
    4  the data cannot be solved (too few poses, degenerate motion, no overlap)
    5  output could not be written
"""


class Calib3rError(Exception):
    exit_code = 1


class InputError(Calib3rError):
    """A file breaks the contract. ``str(e)`` is ``"<path>[: <where>]: <what>"``."""

    exit_code = 3

    def __init__(self, path, what: str, where: str | None = None):
        self.path, self.what, self.where = str(path), what, where
        loc = f"{self.path}: {where}" if where else self.path
        super().__init__(f"{loc}: {what}")


class SolveError(Calib3rError):
    exit_code = 4


class OutputError(Calib3rError):
    exit_code = 5
