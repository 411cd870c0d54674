"""Errors a user can act on. The CLI prints them as one line, without a traceback."""


class AvatarPerfectError(Exception):
    """An expected failure caused by the input (bad file, missing stage, wrong size)."""


class InputFileError(AvatarPerfectError):
    """A file that cannot be used; the message names the file and the problem."""

    def __init__(self, path: object, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path = path
        self.problem = problem
