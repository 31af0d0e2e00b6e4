"""Opening robot recordings in the forms ROS 2 leaves them: one MCAP file, a rosbag2 directory (MCAP or
SQLite storage) or a bare SQLite ``.db3`` file.

Each form is opened into a :class:`Bag`: its topics and their message types, its metadata records, the
topics that cannot be decoded (and why), and its messages in file order, decoded. Message definitions
come from the bag itself (MCAP schemas, the rosbag2 ``message_definitions`` table) and else from the
stock ROS 2 (Humble) types; a single MCAP file is read with its CRCs checked, as before.
"""
from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from protocol.errors import InputError
from protocol.ros2 import JOINT_STATE, read_joint_state, same_joint_state

log = logging.getLogger("twin.source")

SQLITE_MAGIC = b"SQLite format 3\x00"
MCAP_MAGIC = b"\x89MCAP0\r\n"

Decoder = Callable[[bytes], Any]
# (topic, log time in ns, sequence number, decoded message or None if it could not be decoded)
Message = tuple[str, int, int, Any]


@dataclass
class Bag:
    path: str
    storage: str  # "mcap", "rosbag2-mcap", "rosbag2-sqlite3" or "sqlite3"
    types: dict[str, str] | None  # topic -> message type; None when the file has no summary to tell
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    undecodable: dict[str, str] = field(default_factory=dict)  # topic -> why it cannot be decoded
    # the messages of some topics, in the order of the file (not of their log times: the reader sorts them, once)
    messages: Callable[[list[str]], Iterator[Message]] = lambda topics: iter(())
    # topics in an encoding other than CDR (JSON, protobuf...: a twin run log's own channels): not ROS 2 messages
    foreign: frozenset[str] = frozenset()
    cut: str = ""  # why the messages end before the file's did (an MCAP file cut short), once they were read
    # chunks of an MCAP file that could not be read (a CRC that fails, data that does not decompress): (first and
    # last log time in ns of their messages, why), once the messages were read; their messages are left out
    damaged: list[tuple[int, int, str]] = field(default_factory=list)


def ros2_type(name: str) -> str:
    """``sensor_msgs/JointState`` (ROS 1 / short spelling) as ``sensor_msgs/msg/JointState``."""
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else name


_STOCK: Any = None


def _stock_decoder(msgtype: str) -> Decoder | None:
    """A decoder of ``msgtype`` from the stock ROS 2 Humble types, or None if it is not one of them."""
    global _STOCK
    from rosbags.typesys import Stores, get_typestore

    if _STOCK is None:
        _STOCK = get_typestore(Stores.ROS2_HUMBLE)
    store, typ = _STOCK, ros2_type(msgtype)
    if typ not in store.fielddefs:
        return None
    return lambda raw: store.deserialize_cdr(raw, typ)


def _embedded_decoder(msgtype: str, fmt: str, text: str) -> Decoder:
    """A decoder from a definition carried by the bag (``msg`` or ``idl`` text); raises if it does not parse."""
    from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

    typs = get_types_from_msg(text, msgtype) if fmt == "msg" else get_types_from_idl(text)
    store = get_typestore(Stores.EMPTY)  # one per definition: two bags may define a type differently
    store.register(typs)
    if msgtype not in store.fielddefs:
        raise ValueError(f"the definition does not define {msgtype}")
    store.get_msgdef(msgtype)  # resolves the nested types now: a missing one is a KeyError here, not per message
    return lambda raw: store.deserialize_cdr(raw, msgtype)


def _decoder(msgtype: str, fmt: str, text: str) -> tuple[Decoder | None, str]:
    """The bag's own definition first, then the stock ROS 2 types; else None and why."""
    why = "no definition in the bag and not a stock ROS 2 type"
    if text and fmt in ("msg", "idl"):
        try:
            return _embedded_decoder(msgtype, fmt, text), ""
        except Exception as e:  # a definition that does not parse: the stock type may still do
            why = f"its definition in the bag does not parse ({type(e).__name__}: {e}), not a stock ROS 2 type"
    stock = _stock_decoder(msgtype)
    return (stock, "") if stock is not None else (None, why)


def _fast_joint_states(msgtype: str, general: Decoder | None) -> Decoder | None:
    """For a JointState channel: the bag's own decoder until :func:`~protocol.ros2.read_joint_state` has read its
    first decodable message the same, then that reader (several times faster; a message it cannot read still goes
    to the bag's decoder). A bag whose JointState reads otherwise keeps its own decoder throughout."""
    if general is None or ros2_type(msgtype) != JOINT_STATE:
        return general
    fast: bool | None = None  # not yet known

    def decode(raw: bytes) -> Any:
        nonlocal fast
        if fast:
            try:
                return read_joint_state(raw)
            except ValueError:
                return general(raw)
        msg = general(raw)  # raises on a message it cannot decode: the next one is compared then
        if fast is None:
            try:
                fast = same_joint_state(read_joint_state(raw), msg)
            except ValueError:
                fast = False
        return msg
    return decode


# ------------------------------------------------------------------ a single MCAP file
def _mcap_decoder(channel, schema) -> tuple[Decoder | None, str]:
    from mcap_ros2.decoder import DecoderFactory

    if channel.message_encoding != "cdr":
        return None, f"its messages are encoded as {channel.message_encoding!r}, not CDR"
    name = schema.name if schema is not None else ""
    if schema is not None and schema.encoding == "ros2msg":
        try:
            dec = DecoderFactory().decoder_for("cdr", schema)
            if dec is not None:
                return dec, ""
        except Exception:  # the stock type may still do
            pass
    stock = _stock_decoder(name) if name else None
    return (stock, "") if stock is not None else (None, "no usable definition in the file and not a stock ROS 2 type")


def _open_mcap(path: str, f) -> Bag:
    from mcap.reader import make_reader

    from ..runlog.reader import ends_early

    if ends_early(f):  # the recorder was killed, or the copy stopped: what was written up to the cut
        return _open_cut_mcap(path, f)
    f.seek(0)
    reader = make_reader(f, validate_crcs=True)  # seeks as needed
    meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    try:
        summary = reader.get_summary()
    except Exception:
        summary = None
    types: dict[str, str] | None = None
    bad: dict[str, str] = {}
    if summary is not None and summary.chunk_indexes and not summary.channels:
        _channels_in_chunks(f, summary)  # (a summary that does not repeat them, as the format allows)
    if summary is not None:  # without one the topics are known only as messages come
        types = {}
        for ch in summary.channels.values():
            sch = summary.schemas.get(ch.schema_id)
            types[ch.topic] = ros2_type(sch.name) if sch is not None else ""
            dec, why = _mcap_decoder(ch, sch)
            if dec is None:
                bad[ch.topic] = f"{types[ch.topic] or 'no schema'}: {why}"

    def messages(topics: list[str]) -> Iterator[Message]:
        # in the file's order: ordering them by log time here is a heap of Python comparisons, a fifth of the
        # reading; load_recording sorts them by log time (a stable sort: the same order for equal times)
        if summary is None or not summary.chunk_indexes:  # (no index of chunks: read straight through)
            yield from _decoded(reader.iter_messages(topics=topics, log_time_order=False))
        else:
            yield from _decoded(_chunk_by_chunk(f, summary, set(topics), bag.damaged))

    foreign = frozenset(ch.topic for ch in summary.channels.values() if ch.message_encoding != "cdr") \
        if summary is not None else frozenset()
    bag = Bag(path, "mcap", types, meta, bad, messages, foreign)
    return bag


def _read_chunk(f, index) -> list[Any]:
    """The records of the chunk ``index`` points at, its CRC checked (raises whatever a damaged chunk makes the
    reader raise)."""
    from mcap.data_stream import ReadDataStream
    from mcap.reader import breakup_chunk
    from mcap.records import Chunk

    f.seek(index.chunk_start_offset + 1 + 8)  # (past the record's opcode and length)
    return list(breakup_chunk(Chunk.read(ReadDataStream(f)), validate_crc=True))


def _channels_in_chunks(f, summary) -> None:
    """Gather into ``summary`` the schemas and channels its chunks declare: a writer need not repeat them in the
    summary, and without them no message of the file was matched to a topic (it read as holding nothing)."""
    from mcap.records import Channel, Schema

    for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        try:
            records = _read_chunk(f, ci)
        except Exception:  # noqa: BLE001 (a damaged chunk: said when its messages are read)
            continue
        for r in records:
            if isinstance(r, Schema):
                summary.schemas.setdefault(r.id, r)
            elif isinstance(r, Channel):
                summary.channels.setdefault(r.id, r)


def _chunk_by_chunk(f, summary, topics: set[str],
                    damaged: list[tuple[int, int, str]]) -> Iterator[tuple[Any, Any, Any]]:
    """(schema, channel, message) of the topics' messages, chunk by chunk in the file's order; a chunk that cannot
    be read (its CRC fails, its data does not decompress: a bad disk block, a copy gone wrong) is left out and noted
    in ``damaged``, the rest of the file still read."""
    from mcap.records import Message as McapMessage

    wanted = {cid: ch for cid, ch in summary.channels.items() if ch.topic in topics}
    for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        if not wanted.keys() & ci.message_index_offsets.keys():
            continue
        try:
            records = _read_chunk(f, ci)
        except Exception as e:  # noqa: BLE001 (whatever a damaged chunk makes the reader raise)
            why = str(e).splitlines()[0] if str(e) else ""
            damaged.append((ci.message_start_time, ci.message_end_time, f"{type(e).__name__}: {why}".rstrip(": ")))
            continue
        for r in records:
            ch = wanted.get(r.channel_id) if isinstance(r, McapMessage) else None
            if ch is not None:
                yield summary.schemas.get(ch.schema_id), ch, r


def _decoded(items: Iterator[tuple[Any, Any, Any]]) -> Iterator[Message]:
    """(topic, log time, sequence, decoded message) of an MCAP reader's (schema, channel, message)."""
    decoders: dict[int, Decoder | None] = {}
    for schema, channel, message in items:
        if channel.id not in decoders:
            decoders[channel.id] = _fast_joint_states(schema.name if schema is not None else "",
                                                      _mcap_decoder(channel, schema)[0])
        yield channel.topic, message.log_time, message.sequence, _decode(decoders[channel.id], message.data)


def _open_cut_mcap(path: str, f) -> Bag:
    """An MCAP file cut short (no summary, no end): its topics, metadata and messages up to the cut
    (:mod:`.salvage`); ``cut`` says where it stopped once the messages were read."""
    from mcap.records import Channel, Metadata, Schema

    from . import salvage

    cut = salvage.Cut()
    meta: dict[str, dict[str, str]] = {}
    schemas: dict[int, Any] = {}
    types: dict[str, str] = {}
    bad: dict[str, str] = {}
    foreign = set()
    for rec in salvage.salvage(f, cut):  # what it holds, before any message is decoded
        if isinstance(rec, Metadata):
            meta[rec.name] = dict(rec.metadata)
        elif isinstance(rec, Schema):
            schemas[rec.id] = rec
        elif isinstance(rec, Channel) and rec.topic not in types:
            sch = schemas.get(rec.schema_id)
            types[rec.topic] = ros2_type(sch.name) if sch is not None else ""
            dec, why = _mcap_decoder(rec, sch)
            if dec is None:
                bad[rec.topic] = f"{types[rec.topic] or 'no schema'}: {why}"
            if rec.message_encoding != "cdr":
                foreign.add(rec.topic)
    if not types and cut.offset < 0:
        raise InputError(f"{path}: an MCAP file without its end that holds no channel")

    def messages(topics: list[str]) -> Iterator[Message]:
        yield from _decoded(salvage.messages(f, cut, set(topics)))
        part = f" ({cut.from_partial_chunk} messages of the file from a chunk written in part)" \
            if cut.from_partial_chunk else ""
        lost = "" if meta else ("; what a recorder writes at its end is lost with it (its metadata: a twin "
                                "recording's perception and ground truth)")
        bag.cut = ("the recording is cut short (no end: its recorder was killed, or the copy stopped): its messages "
                   f"up to the last whole one are replayed{part}{lost}")

    bag = Bag(path, "mcap", types, meta, bad, messages, frozenset(foreign))
    return bag


def _decode(decoder: Decoder | None, raw: bytes) -> Any:
    if decoder is None:
        return None
    try:
        return decoder(raw)
    except Exception:  # counted by the caller as a message that cannot be decoded
        return None


# ------------------------------------------------------------------ rosbag2 directories and .db3 files
def _rosbags_bag(path: str, reader, storage: str, meta: dict[str, dict[str, str]]) -> Bag:
    from rosbags.interfaces import MessageDefinitionFormat

    fmts = {MessageDefinitionFormat.MSG: "msg", MessageDefinitionFormat.IDL: "idl"}
    types: dict[str, str] = {}
    decoders: dict[int, Decoder | None] = {}
    bad: dict[str, str] = {}
    for conn in reader.connections:
        types[conn.topic] = ros2_type(conn.msgtype)
        dec, why = _decoder(conn.msgtype, fmts.get(conn.msgdef.format, ""), conn.msgdef.data)
        decoders[conn.id] = _fast_joint_states(conn.msgtype, dec)
        if dec is None:
            bad[conn.topic] = f"{conn.msgtype}: {why}"

    def messages(topics: list[str]) -> Iterator[Message]:
        conns = [c for c in reader.connections if c.topic in topics]
        if not conns:
            return
        for seq, (conn, t, raw) in enumerate(reader.messages(connections=conns)):
            yield conn.topic, t, seq, _decode(decoders[conn.id], raw)

    return Bag(path, storage, types, meta, bad, messages)


def _mcap_metadata(files: list[Path]) -> dict[str, dict[str, str]]:
    """The metadata records of a rosbag2 directory's MCAP files (``twin.scene``, ...), if any."""
    from mcap.reader import make_reader

    meta: dict[str, dict[str, str]] = {}
    for p in files:
        try:
            with open(p, "rb") as f:
                meta.update({m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()
                             if m.name != "rosbag2"})
        except Exception as e:  # the messages are what matter; rosbags reports an unreadable file
            log.info("%s: metadata not read: %s", p, e)
    return meta


@contextmanager
def _opened(path: str, make: Callable[[], Any], kind: str) -> Iterator[Any]:
    """A rosbags reader made by ``make``, open for the block; InputError naming the file if it cannot open."""
    try:
        reader = make()
        reader.open()
    except Exception as e:
        blank = _blank_definitions(path) if isinstance(e, KeyError) and e.args == ("",) else []
        if blank:  # (rosbags cannot open such a file, though the topics may be ones nobody needs)
            raise InputError(f"{path}: rosbag2 stored no message definition for {', '.join(blank)} (their packages "
                             "were not sourced when it recorded), and the reader this twin uses cannot open such "
                             "a SQLite bag: record with the packages sourced, or in the MCAP storage (ros2 bag "
                             "record -s mcap), whose files it reads, skipping such topics") from None
        raise InputError(f"{path}: not a readable {kind} ({type(e).__name__}: {e})") from None
    try:
        yield reader
    finally:
        reader.close()


def _blank_definitions(path: str) -> list[str]:
    """The message types a SQLite rosbag2 recording (a .db3, or a folder of them) stores with an empty definition
    format (a type rosbag2 could not find while recording); [] if there are none or it cannot tell."""
    import sqlite3

    p = Path(path)
    found: set[str] = set()
    for db in (sorted(p.glob("*.db3")) if p.is_dir() else [p]):
        try:
            with contextlib.closing(sqlite3.connect(f"file:{db}?mode=ro", uri=True)) as con:
                rows = con.execute("SELECT topic_type FROM message_definitions WHERE encoding = ''")
                found.update(r[0] for r in rows)
        except sqlite3.Error:
            continue
    return sorted(found)


def _storage_of(path: str, directory: Path) -> str:
    import yaml

    meta = directory / "metadata.yaml"
    try:
        data = yaml.safe_load(meta.read_text())
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"{meta}:{mark.line + 1}" if mark is not None else str(meta)
        raise InputError(f"{where}: not valid YAML ({getattr(e, 'problem', None) or e}), so this rosbag2 recording "
                        "cannot be read") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{meta}: cannot be read ({type(e).__name__}: {e})") from None
    try:
        info = data["rosbag2_bagfile_information"]
        plugin = str(info["storage_identifier"])
    except Exception as e:
        raise InputError(f"{path}: a rosbag2 metadata.yaml without a storage_identifier "
                        f"({type(e).__name__}: {e})") from None
    return f"rosbag2-{plugin}"


@contextmanager
def open_bag(path: str | Path) -> Iterator[Bag]:
    """Open any of the recording forms; a :class:`InputError` naming the file if it is none of them."""
    path = str(path)
    p = Path(path)
    if p.is_dir() or (p.suffix == ".db3" and (p.parent / "metadata.yaml").is_file()):
        directory = p if p.is_dir() else p.parent
        if not (directory / "metadata.yaml").is_file():
            files = sorted([*directory.glob("*.mcap"), *directory.glob("*.db3")])
            kind = "MCAP" if files and files[0].suffix == ".mcap" else "SQLite"
            hint = (f" (rosbag2 writes it when it stops: a recorder killed before that leaves none; give its {kind} "
                    f"file itself, e.g. {files[0]})") if files else ""
            raise InputError(f"{path}: a directory without metadata.yaml, not a rosbag2 recording{hint}")
        storage = _storage_of(path, directory)
        meta = _mcap_metadata(sorted(directory.glob("*.mcap"))) if storage == "rosbag2-mcap" else {}
        from rosbags.rosbag2 import Reader

        with _opened(path, lambda: Reader(directory), "rosbag2 directory") as reader:
            yield _rosbags_bag(path, reader, storage, meta)
        return
    try:
        f = open(path, "rb")
    except OSError as e:
        raise InputError(f"{path}: cannot open recording: {e.strerror}") from None
    with f:
        if f.read(len(SQLITE_MAGIC)) == SQLITE_MAGIC:
            f.close()
            from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader

            with _opened(path, lambda: Sqlite3Reader(Path(path)), "SQLite rosbag2 file") as reader:
                yield _rosbags_bag(path, reader, "sqlite3", {})
            return
        size = f.seek(0, 2)
        if size < 2 * len(MCAP_MAGIC):  # (an MCAP file begins and ends with its magic)
            raise InputError(f"{path}: {size} bytes: too short to be an MCAP recording (an empty or cut file?)")
        f.seek(0)
        if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:  # (said so, not as the MCAP reader's tuple of the first bytes)
            raise InputError(f"{path}: not a recording: neither an MCAP file nor an SQLite rosbag2 file (.db3) by "
                             "its first bytes; a recording is one of those, or a rosbag2 folder")
        f.seek(0)
        try:
            bag = _open_mcap(path, f)
        except InputError:
            raise
        except Exception as e:
            raise InputError(f"{path}: not a readable MCAP recording ({type(e).__name__}: {e})") from None
        yield bag
