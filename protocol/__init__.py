"""The contract every process of the twin shares.

Submodules: :mod:`~protocol.keys` (key expressions), :mod:`~protocol.messages` (one typed definition per
message), :mod:`~protocol.codec` (msgpack encoding and validation), :mod:`~protocol.config` (Zenoh session
options), :mod:`~protocol.geometry` (shapes and poses), :mod:`~protocol.ros2` (the rmw_zenoh wire format),
:mod:`~protocol.security` (certificates and access control), :mod:`~protocol.robot` (a robot as data: the
scene's robot block and the shipped descriptions), :mod:`~protocol.joints` (joint states that name some joints,
merged into the latest of every joint) and :mod:`~protocol.errors` (the error tree).

The names below are re-exported for convenience, and loaded on first use: ``import protocol.keys`` still
imports neither numpy, msgpack, mcap nor cryptography.
"""
from __future__ import annotations

import importlib

TYPE_CHECKING = False  # typing.TYPE_CHECKING without importing typing; type checkers take it as True
if TYPE_CHECKING:
    from . import codec, config, errors, geometry, joints, keys, messages, robot, ros2, security
    from .config import ZenohOptions, add_zenoh_args, options_from_args
    from .errors import (
        AgentError,
        AgentLost,
        AgentTimeout,
        ExprError,
        InputError,
        Problem,
        ProtocolError,
        RegistrationError,
        RunAborted,
        RunError,
        SceneError,
        SetupError,
        SynthError,
        TwinError,
        ViewerError,
    )
    from .joints import LatestJoints
    from .keys import CONDUCTOR, Keys, check_name
    from .messages import PROTOCOL_VERSION, Message

__all__ = [
    # submodules
    "codec", "config", "errors", "geometry", "joints", "keys", "messages", "robot", "ros2", "security",
    # keys
    "CONDUCTOR", "Keys", "check_name",
    # messages
    "PROTOCOL_VERSION", "Message", "LatestJoints",
    # session options
    "ZenohOptions", "add_zenoh_args", "options_from_args",
    # errors
    "TwinError", "ProtocolError", "SetupError", "Problem", "SceneError", "InputError", "RegistrationError",
    "RunError", "AgentError", "AgentTimeout", "AgentLost", "RunAborted", "ExprError", "ViewerError", "SynthError",
]

_SUBMODULES = frozenset({"codec", "config", "errors", "geometry", "joints", "keys", "messages", "robot", "ros2",
                         "security"})
_HOME = {
    "CONDUCTOR": "keys", "Keys": "keys", "check_name": "keys",
    "PROTOCOL_VERSION": "messages", "Message": "messages", "LatestJoints": "joints",
    "ZenohOptions": "config", "add_zenoh_args": "config", "options_from_args": "config",
    "TwinError": "errors", "ProtocolError": "errors", "SetupError": "errors", "Problem": "errors",
    "SceneError": "errors", "InputError": "errors", "RegistrationError": "errors", "RunError": "errors",
    "AgentError": "errors", "AgentTimeout": "errors", "AgentLost": "errors", "RunAborted": "errors",
    "ExprError": "errors", "ViewerError": "errors", "SynthError": "errors",
}
"""The submodule each re-exported name lives in."""

if not TYPE_CHECKING:  # hidden from type checkers, which see the imports above and flag any other name

    def __getattr__(name: str) -> object:
        """Import a submodule or a re-exported name on first use (PEP 562)."""
        if name in _SUBMODULES:
            return importlib.import_module(f"{__name__}.{name}")
        home = _HOME.get(name)
        if home is None:
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{__name__}.{home}"), name)
        globals()[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted({*globals(), *__all__})
