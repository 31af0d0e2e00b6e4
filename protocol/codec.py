"""msgpack codec of the twin's messages.

Every message is a msgpack map ``{"v": PROTOCOL_VERSION, "type": <name>, ...fields}``. numpy arrays
travel as a msgpack extension (dtype, shape, raw bytes) and come back as arrays; numpy scalars become
plain numbers. :func:`decode` validates the envelope and the fields of the message type against
:mod:`protocol.messages` and raises :class:`~protocol.errors.ProtocolError` naming the key and the
problem; it never returns a half-checked message.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol

import msgpack
import numpy as np
import numpy.typing as npt

from .errors import ProtocolError
from .messages import PROTOCOL_VERSION, SCHEMAS, Message, check_fields

__all__ = ["EXT_NDARRAY", "MAX_PAYLOAD", "SupportsToBytes", "pack", "unpack", "encode", "encode_unchecked",
           "encode_error", "to_bytes", "decode", "decode_hot", "ZENOH_TIMEOUT", "differs"]

EXT_NDARRAY = 1
"""The msgpack extension code of a numpy array: ``[dtype.str, shape, raw bytes]`` packed inside."""
MAX_PAYLOAD = 64 * 1024 * 1024
"""The largest payload :func:`decode` accepts (bytes)."""
ZENOH_TIMEOUT = b"Timeout"
"""The error reply Zenoh itself gives a query that timed out (a reply of ours is msgpack, never these bytes)."""


class SupportsToBytes(Protocol):
    """A payload that gives its bytes, as ``zenoh.ZBytes`` does."""

    def to_bytes(self) -> bytes:
        """The payload's bytes."""
        ...


def _default(obj: object) -> object:
    if isinstance(obj, np.ndarray):
        if obj.ndim == 0 and obj.dtype.kind in "biuf" and not obj.dtype.hasobject:
            return obj.item()  # (a number: ascontiguousarray would make it a list of one)
        arr = np.ascontiguousarray(obj)
        if arr.dtype.kind not in "biuf c" or arr.dtype.hasobject:
            raise TypeError(f"cannot encode numpy array of dtype {arr.dtype}")
        return msgpack.ExtType(EXT_NDARRAY, msgpack.packb([arr.dtype.str, list(arr.shape), arr.tobytes()]))
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, (set, frozenset)):
        return sorted(obj)
    raise TypeError(f"cannot encode {type(obj).__name__}")


def _ext_hook(code: int, data: bytes) -> npt.NDArray[Any]:
    if code != EXT_NDARRAY:
        raise ValueError(f"unknown msgpack extension type {code}")
    dtype, shape, raw = msgpack.unpackb(data, raw=False)
    dt = np.dtype(dtype)
    if dt.hasobject:
        raise ValueError("object arrays are not allowed")
    arr = np.frombuffer(raw, dtype=dt)
    n = 1
    for s in shape:
        if not isinstance(s, int) or s < 0:
            raise ValueError(f"bad array shape {shape!r}")
        n *= s
    if n != arr.size:
        raise ValueError(f"array of shape {shape} needs {n} items, got {arr.size}")
    return arr.reshape(shape)


_packer_opts = dict(default=_default, use_bin_type=True)


def pack(obj: Any) -> bytes:
    """Pack any msgpack-able structure (numpy included) without an envelope.

    Raises TypeError for a value msgpack cannot carry (an object array, an arbitrary object)."""
    data: bytes = msgpack.packb(obj, **_packer_opts)
    return data


def unpack(data: bytes) -> Any:
    """The inverse of :func:`pack` (no envelope, no validation): numpy arrays come back as read-only arrays.

    Raises what msgpack raises on malformed data, ValueError for a malformed array extension."""
    return msgpack.unpackb(data, raw=False, ext_hook=_ext_hook, strict_map_key=False)


def encode(mtype: str, fields: Mapping[str, Any] | None = None, **kw: Any) -> bytes:
    """Encode a message of type ``mtype`` from ``fields`` and ``kw`` (``kw`` wins).

    The fields are validated first and a ProtocolError on key ``<encode>`` means the caller built a
    malformed message (a bug here is ours); TypeError for a value msgpack cannot carry."""
    body = dict(fields) if fields else {}
    body.update(kw)
    schema = SCHEMAS.get(mtype)
    if schema is None:
        raise ProtocolError("<encode>", f"unknown message type {mtype!r}")
    check_fields("<encode>", mtype, body)
    body["v"] = PROTOCOL_VERSION
    body["type"] = mtype
    data: bytes = msgpack.packb(body, **_packer_opts)
    return data


def encode_unchecked(mtype: str, body: dict[str, Any]) -> bytes:
    """Hot-path encoder for messages whose fields the caller builds itself: no validation, and ``body``
    gains the envelope (``v``, ``type``) in place."""
    body["v"] = PROTOCOL_VERSION
    body["type"] = mtype
    data: bytes = msgpack.packb(body, **_packer_opts)
    return data


def to_bytes(payload: object) -> bytes:
    """The bytes of a payload: ``bytes``-like, anything with ``to_bytes()`` (``zenoh.ZBytes``), or None
    (empty). Raises TypeError for anything else."""
    if payload is None:
        return b""
    if isinstance(payload, (bytes, bytearray, memoryview)):
        return bytes(payload)
    tb = getattr(payload, "to_bytes", None)
    if tb is not None:
        data: bytes = tb()
        return data
    raise TypeError(f"not a payload: {type(payload).__name__}")


_unpackb = msgpack.unpackb


def decode_hot(key: object, payload: SupportsToBytes | bytes, mtype: str) -> dict[str, Any]:
    """Hot-path decoder for one expected message type (step, step_reply): the same checks as
    :func:`decode`, fewer Python calls, and a plain dict back. ``payload`` is a ``zenoh.ZBytes`` or the bytes
    already taken from one. Raises ProtocolError as :func:`decode` does."""
    try:
        data = payload if isinstance(payload, bytes) else payload.to_bytes()
        obj = _unpackb(data, raw=False, ext_hook=_ext_hook, strict_map_key=False) if len(data) <= MAX_PAYLOAD \
            else None  # (refused below, by decode, with its size)
    except Exception:
        return decode(key, payload, mtype)  # slow path produces the precise error
    if obj.__class__ is not dict or obj.get("v") != PROTOCOL_VERSION or obj.get("type") != mtype:
        return decode(key, payload, mtype)
    check_fields(key, mtype, obj)
    msg: dict[str, Any] = obj  # a typed local, not cast(): no call on the hot path
    return msg


def decode(key: object, payload: Any, expect: str | tuple[str, ...] | None = None) -> Message:
    """Decode and validate one message that arrived on ``key`` (a key expression, or anything whose
    ``str()`` is one).

    ``payload`` is ``zenoh.ZBytes``, ``bytes``-like or anything :func:`to_bytes` takes. ``expect`` restricts
    the accepted message types. Raises ProtocolError on anything malformed, never a half-checked message.
    """
    try:
        data = payload.to_bytes() if payload.__class__.__name__ == "ZBytes" else to_bytes(payload)
    except (TypeError, AttributeError) as e:
        raise ProtocolError(str(key), str(e)) from None
    if not data:
        key = str(key)
        raise ProtocolError(key, "empty payload")
    if len(data) > MAX_PAYLOAD:
        raise ProtocolError(key, f"payload of {len(data)} bytes exceeds {MAX_PAYLOAD}")
    try:
        obj = msgpack.unpackb(data, raw=False, ext_hook=_ext_hook, strict_map_key=False)
    except Exception as e:  # msgpack raises many kinds
        raise ProtocolError(key, f"not a msgpack message ({type(e).__name__}: {e})") from None
    if not isinstance(obj, dict):
        raise ProtocolError(key, f"message must be a map, got {type(obj).__name__}")
    v = obj.get("v")
    if v != PROTOCOL_VERSION:
        raise ProtocolError(key, f"protocol version {v!r} is not supported (this process speaks {PROTOCOL_VERSION})")
    mtype = obj.get("type")
    if not isinstance(mtype, str):
        raise ProtocolError(key, "message has no 'type' string")
    if expect is not None:
        ok = mtype == expect if isinstance(expect, str) else mtype in expect
        if not ok:
            raise ProtocolError(key, f"expected a {expect!r} message, got {mtype!r}")
    schema = SCHEMAS.get(mtype)
    if schema is None:
        raise ProtocolError(key, f"unknown message type {mtype!r}")
    check_fields(key, mtype, obj)
    return Message(obj)


def encode_error(exc: BaseException, traceback: str = "") -> bytes:
    """The one error reply: the exception's type name, its message and (optionally) its traceback."""
    fields: dict[str, Any] = {"kind": type(exc).__name__, "message": str(exc)}
    if traceback:
        fields["traceback"] = traceback
    return encode("error", fields)


def differs(old: Any, new: Any) -> bool:
    """Whether an output took another value, as topic triggers judge it (the conductor's map) and as an agent judges
    where ``tick.until`` stops it: numpy arrays element-wise; values that cannot be compared count as changed."""
    try:
        r = old != new
        return bool(r.any()) if hasattr(r, "any") else bool(r)
    except Exception:
        return True
