"""Every error the twin raises on purpose, in one tree.

::

    TwinError                         anything the twin raises on purpose
     ├── ProtocolError                a message that breaks the protocol (key, problem); counted, never fatal
     ├── SetupError                   the run cannot start
     │    ├── SceneError              a scene file's problems, all of them (also a ValueError)
     │    ├── InputError              an input file that cannot be read or does not fit the scene (also a ValueError)
     │    └── RegistrationError       an agent was refused, never registered, or declares what the scene cannot use
     ├── RunError                     something went wrong while a run was going
     │    ├── AgentError              a model answered with an error (agent, key, tick, remote type and traceback)
     │    │    ├── AgentTimeout       ... or did not answer within its timeout
     │    │    └── AgentLost          ... or is gone (nothing served the key of a query to it)
     │    └── RunAborted              the run cannot go on (the main model died, stopped while waiting, ...)
     ├── ExprError                    a scene expression that does not parse or evaluate (also a ValueError)
     ├── ViewerError                  the Rerun stream could not be opened (never stops a run)
     └── SynthError                   a synthetic recording could not be planned or played

Set-up errors (:class:`SetupError`) are raised before any agent is initialised: the scene is checked
whole, statically and against what the agents declare, and every problem is reported at once. Run errors
name the agent and the tick, the way mosaik's "Simulator X aborted ... with error ..." does; an error that
crossed a process boundary keeps the remote exception's type name and traceback as data.

A model signals a recoverable problem of one step with :class:`agents.StepWarning` (the step's status is
``warning``; the run goes on); that is a signal to the runtime, not an error of the twin.
"""
from __future__ import annotations

from dataclasses import dataclass

__all__ = ["TwinError", "ProtocolError", "SetupError", "Problem", "SceneError", "InputError", "RegistrationError",
           "RunError", "AgentError", "AgentTimeout", "AgentLost", "RunAborted", "ExprError", "ViewerError",
           "SynthError"]


class TwinError(Exception):
    """Base class of every error the twin raises on purpose."""


class ProtocolError(TwinError):
    """A message that does not follow the protocol.

    ``key`` is the Zenoh key expression the message arrived on (or was meant for), ``problem`` says what
    is wrong with it in words a person can act on.
    """

    def __init__(self, key: object, problem: str) -> None:
        self.key = str(key)
        self.problem = problem
        super().__init__(f"{self.key}: {problem}")


# ------------------------------------------------------------------------------------------- set-up
class SetupError(TwinError):
    """The run cannot start: nothing has been initialised."""


@dataclass(frozen=True)
class Problem:
    """One problem of a scene: ``file:line: key: problem``."""

    file: str
    line: int | None
    key: str
    problem: str

    def __str__(self) -> str:
        where = f"{self.file}:{self.line}" if self.line is not None else self.file
        return f"{where}: {self.key}: {self.problem}" if self.key else f"{where}: {self.problem}"


class SceneError(SetupError, ValueError):
    """A scene's problems, every one of them, each naming the file, line and key path.

    ``SceneError(file, line, key, problem)`` is one problem; :meth:`of` gathers several. ``file``,
    ``line``, ``key`` and ``problem`` are those of the first problem; :attr:`problems` holds them all.
    """

    def __init__(self, file: str, line: int | None, key: str, problem: str) -> None:
        self.problems: list[Problem] = [Problem(file, line, key, problem)]
        self.file, self.line, self.key, self.problem = file, line, key, problem
        super().__init__(str(self.problems[0]))

    @classmethod
    def of(cls, problems: list[Problem]) -> SceneError:
        """One error for ``problems`` (at least one), listed one per line when there are several."""
        first = problems[0]
        err = cls(first.file, first.line, first.key, first.problem)
        err.problems = list(problems)
        if len(problems) > 1:
            err.args = (f"{len(problems)} problems:\n" + "\n".join(f"  {p}" for p in problems),)
        return err


class InputError(SetupError, ValueError):
    """An input file the command was given (a recording, a perception, a run log) that cannot be read, or that
    does not fit the scene (none of the recording's joints is the robot's): the message names the file and, where
    there is one, the key. Like a scene's problems it is bad input (exit 2), not a run that failed."""


class RegistrationError(SetupError):
    """An agent was refused, never registered, or its declarations do not fit the scene."""


# --------------------------------------------------------------------------------------------- run
class RunError(TwinError):
    """Something went wrong while a run was going."""


class AgentError(RunError):
    """A model answered a query with an error.

    ``agent`` is the model's name, ``key`` the key expression of the query, ``tick`` the conductor's tick
    when it was asked (None outside the tick loop), ``remote_type`` the exception's type name in the
    agent's process, ``message`` its message and ``remote_traceback`` its formatted traceback (may be
    empty).
    """

    def __init__(self, agent: str, key: str, tick: int | None, remote_type: str, message: str,
                 remote_traceback: str = "") -> None:
        self.agent, self.key, self.tick = agent, key, tick
        self.remote_type, self.message, self.remote_traceback = remote_type, message, remote_traceback
        at = f" at tick {tick}" if tick is not None else ""
        super().__init__(f"model {agent}{at}: {key}: {remote_type}: {message}")


class AgentTimeout(AgentError):
    """A model did not answer a query within its timeout."""

    def __init__(self, agent: str, key: str, tick: int | None, timeout: float) -> None:
        self.timeout = timeout
        super().__init__(agent, key, tick, "Timeout", f"no answer within {timeout:g} s (agent gone or too slow)")


class AgentLost(AgentError):
    """A model's agent is gone: nothing served the key of a query to it (its process or link is gone)."""

    def __init__(self, agent: str, key: str, tick: int | None) -> None:
        super().__init__(agent, key, tick, "Lost", "no agent answers on this key (the agent is gone)")


class RunAborted(RunError):
    """The run cannot go on (the main model died, a stop while waiting for agents, ...)."""


# --------------------------------------------------------------------------------------- elsewhere
class ExprError(TwinError, ValueError):
    """A scene expression that does not parse or cannot be evaluated; ``pos`` is the character offset."""

    def __init__(self, message: str, pos: int | None = None) -> None:
        self.pos = pos
        super().__init__(message if pos is None else f"{message} (at column {pos + 1})")


class ViewerError(TwinError):
    """The Rerun stream could not be opened or written (a viewer problem never stops a run)."""


class SynthError(TwinError):
    """A synthetic recording could not be planned or executed (unreachable pose, time limit)."""

