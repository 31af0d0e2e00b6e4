"""Exception hierarchy shared by every process of the twin."""


class TwinError(Exception):
    """Base class of every error the twin raises on purpose."""


class ProtocolError(TwinError):
    """A message that does not follow the protocol.

    ``key`` is the Zenoh key expression the message arrived on (or was meant for),
    ``problem`` says what is wrong with it in words a person can act on.
    """

    def __init__(self, key, problem: str):
        key = str(key)
        self.key = key
        self.problem = problem
        super().__init__(f"{key}: {problem}")


class RemoteError(TwinError):
    """A model answered a query with an error reply."""

    def __init__(self, key: str, kind: str, message: str, traceback: str = ""):
        self.key = key
        self.kind = kind
        self.message = message
        self.traceback = traceback
        super().__init__(f"{key}: {kind}: {message}")


class SceneError(TwinError):
    """A scene file problem: names file, line and key path."""

    def __init__(self, file: str, line: int | None, key: str, problem: str):
        self.file = file
        self.line = line
        self.key = key
        self.problem = problem
        where = f"{file}:{line}" if line is not None else file
        super().__init__(f"{where}: {key}: {problem}" if key else f"{where}: {problem}")
