"""The WC<->ME channel: a pair of POSIX message queues per machine carrying the thesis's struct (5.2).

The thesis's WC and ME shared one System V queue and told the directions apart by message type
(TO_ME, FROM_ME). We give each direction its own POSIX queue, named after the cell and the machine:

    <prefix>.<machine>.to_me     written by the WC, read by the ME
    <prefix>.<machine>.from_me   written by the ME, read by the WC

Each queue carries one fixed-size record: the thesis's file_name, recipe_id, message_id, ack_code
and alarm_text, plus a sequence number (an answer carries its request's, so a late answer is never
taken for the answer to the next request) and a CRC32 (so a garbled record is refused, not acted
on). The byte layout is in docs/machine-interface.md and in `LAYOUT` below.

Either half may start first: each creates a queue exclusively (O_CREAT|O_EXCL, mode 0600) or opens
the one the other half made, so the queues outlive the restart of either half, and a request sent
while the other half is down waits in its queue. Only `gwc stop` (remove_queues) deletes them. A
queue found already there must be the cell's: owned by the cell's user, open to nobody else (0600,
or 0660 with the cell's group); any other was made by someone else to talk to both halves, and is
refused (QueueNotOurs), never used. Nothing is ever truncated: a field too long for its slot, a full
queue or a garbled record is a QueueError that says which.
"""

from __future__ import annotations

import logging
import os
import stat
import struct
import zlib
from enum import IntEnum
from typing import Any, Literal, NamedTuple

import posix_ipc

from gwc.errors import QueueError, QueueFull, QueueNotOurs, QueueTimeout
from gwc.ipc.codes import AckCode

MAGIC = b"GWME"
VERSION = 1
FILE_NAME_SIZE = 256
RECIPE_ID_SIZE = 32
ACK_CODE_SIZE = 12
ALARM_TEXT_SIZE = 80
TRACE = 5  # gwc.log's Trace level: every record sent and received
# Records a queue holds. The WC asks one request at a time and the ME keeps what does not fit in its
# outbox, so a few suffice. The kernel charges each queue's whole capacity (about 2.6 kB at 5, 5.1 kB
# at 10) against the user's RLIMIT_MSGQUEUE (819,200 bytes by default): at 10 one user's cells stopped
# at about 150 queues (75 machines); at 5 the host's queues_max (256) binds first, 128 machines.
MAX_MESSAGES = 5

# Big-endian, no padding: magic, version, message_id, seq, ack_code, recipe_id, file_name, alarm_text.
_BODY = struct.Struct(f"!4sHHI{ACK_CODE_SIZE}s{RECIPE_ID_SIZE}s{FILE_NAME_SIZE}s{ALARM_TEXT_SIZE}s")
_CRC = struct.Struct("!I")
LAYOUT_SIZE = _BODY.size + _CRC.size  # 396 bytes

Side = Literal["wc", "me"]


class MessageId(IntEnum):
    """message_id of the queue record: the ids of Listings 3, 6 and 7."""

    NO_MESSAGE = 0  # "are you there?" from the WC; the ME answers it in kind (our liveness ping)
    ME_START = 1  # WC -> ME: home and get ready; answered ME_START with the ack code
    ME_SHUT = 2  # WC -> ME: shut down
    ME_SHUT_C = 3  # ME -> WC: the answer to ME_SHUT (shutdown complete)
    SETUP_RUN = 4  # WC -> ME: load the recipe in file_name, id recipe_id; answered SETUP_RUN
    START_RUN = 5  # WC -> ME: start the run set up; file_name = where to write the results
    DNLD_ME = 6  # WC -> ME: download the recipe in file_name to the machine
    UPLD_ME = 7  # WC -> ME: upload recipe_id from the machine; the answer's file_name holds it
    RUN_COMPL = 8  # ME -> WC: the run ended; file_name = its results file, ack_code ACK_OK or Run_Fail
    CELL_ALAR = 9  # ME -> WC: raise alarm alarm_text (an ALARM_DESCRIPTION id) and tell me when cleared
    ME_START_WAIT = 10  # WC -> ME: the alarm was cleared (ack ACK_OK) or could not be raised: go on
    ME_LOST = 11  # ME -> WC: the machine itself stopped answering (alarm_text: why); the ME looks for it
    ME_BACK = 12  # ME -> WC: the machine answers again


class MeMessage(NamedTuple):
    """One record of the queue. Empty strings stand for the listings' "NULL".

    A named tuple: made and unpacked on every round trip, where a frozen dataclass's construction
    and dataclasses.replace() cost more than the rest of the record's handling together.
    """

    message_id: MessageId
    file_name: str = ""
    recipe_id: str = ""
    ack_code: AckCode | None = None
    alarm_text: str = ""
    seq: int = 0

    def reply(
        self, ack_code: AckCode | None = AckCode.ACK_OK, message_id: MessageId | None = None, **fields: Any
    ) -> MeMessage:
        """The answer to this request: same seq, same id unless told otherwise (Listing 7)."""
        return MeMessage(
            self.message_id if message_id is None else message_id,
            fields.get("file_name", self.file_name),
            fields.get("recipe_id", self.recipe_id),
            ack_code,
            fields.get("alarm_text", self.alarm_text),
            self.seq,
        )

    def with_seq(self, seq: int) -> MeMessage:
        """The same record under another sequence number."""
        return MeMessage(self.message_id, self.file_name, self.recipe_id, self.ack_code, self.alarm_text, seq)

    def describe(self) -> str:
        parts = [self.message_id.name, f"seq {self.seq}"]
        if self.ack_code:
            parts.append(str(self.ack_code))
        for name in ("recipe_id", "file_name", "alarm_text"):
            value = getattr(self, name)
            if value:
                parts.append(f"{name}={value}")
        return " ".join(parts)


# Lookup tables: packing and unpacking a record is on every round trip, so no enum calls there.
_IDS = {m.value: m for m in MessageId}
_ACK_OUT: dict[object, bytes] = {None: b"", **{c: c.value.encode("ascii") for c in AckCode}}
_ACK_IN: dict[bytes, AckCode | None] = {
    b"\0" * ACK_CODE_SIZE: None,
    **{c.value.encode("ascii").ljust(ACK_CODE_SIZE, b"\0"): c for c in AckCode},
}


def _field(name: str, value: str, size: int) -> bytes:
    if not isinstance(value, str):
        raise QueueError(f"queue field {name} must be text, got {type(value).__name__}")
    data = value.encode("utf-8")
    if len(data) > size:
        raise QueueError(
            f"queue field {name} is {len(data)} bytes, its slot holds {size}: refused "
            f"(nothing is truncated): {value[:60]!r}..."
        )
    if b"\0" in data:
        raise QueueError(f"queue field {name} contains a NUL byte: refused")
    return data


def pack(msg: MeMessage) -> bytes:
    """The record's bytes (LAYOUT_SIZE of them); QueueError if a field does not fit."""
    mid = _IDS.get(msg.message_id)
    if mid is None:
        raise QueueError(f"unknown message id {msg.message_id!r}")
    ack = _ACK_OUT.get(msg.ack_code)
    if ack is None:
        raise QueueError(f"unknown ack code {msg.ack_code!r}")
    if not 0 <= msg.seq < 2**32:
        raise QueueError(f"sequence number {msg.seq} does not fit 32 bits")
    body = _BODY.pack(
        MAGIC,
        VERSION,
        mid,
        msg.seq,
        ack,
        _field("recipe_id", msg.recipe_id, RECIPE_ID_SIZE) if msg.recipe_id else b"",
        _field("file_name", msg.file_name, FILE_NAME_SIZE) if msg.file_name else b"",
        _field("alarm_text", msg.alarm_text, ALARM_TEXT_SIZE) if msg.alarm_text else b"",
    )
    return body + _CRC.pack(zlib.crc32(body))


def _text(name: str, raw: bytes) -> str:
    data = raw.rstrip(b"\0")
    if not data:
        return ""
    if b"\0" in data:
        raise QueueError(f"garbled record: field {name} has a NUL inside its text")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise QueueError(f"garbled record: field {name} is not UTF-8") from None


_RECORD = struct.Struct(_BODY.format + "I")  # the body and its CRC, read in one call
_EMPTY = {size: bytes(size) for size in (FILE_NAME_SIZE, RECIPE_ID_SIZE, ALARM_TEXT_SIZE)}


def unpack(data: bytes) -> MeMessage:
    """A record back from its bytes; QueueError naming what is wrong with a garbled one."""
    if len(data) != LAYOUT_SIZE:
        raise QueueError(f"garbled record: {len(data)} bytes, expected {LAYOUT_SIZE}")
    magic, version, mid, seq, ack, recipe, file_name, alarm, crc = _RECORD.unpack(data)
    if magic != MAGIC:
        raise QueueError(f"garbled record: magic {magic!r}, expected {MAGIC!r}")
    if version != VERSION:
        raise QueueError(
            f"record of layout version {version}, this program speaks {VERSION}: "
            "run the same GWC version on both halves"
        )
    if zlib.crc32(data[: _BODY.size]) != crc:
        raise QueueError("garbled record: CRC mismatch")
    message_id = _IDS.get(mid)
    if message_id is None:
        raise QueueError(f"garbled record: unknown message id {mid}")
    if ack not in _ACK_IN:
        raise QueueError(f"garbled record: unknown ack code {ack.rstrip(bytes(1))!r}")
    return MeMessage(
        message_id,
        "" if file_name == _EMPTY[FILE_NAME_SIZE] else _text("file_name", file_name),
        "" if recipe == _EMPTY[RECIPE_ID_SIZE] else _text("recipe_id", recipe),
        _ACK_IN[ack],
        "" if alarm == _EMPTY[ALARM_TEXT_SIZE] else _text("alarm_text", alarm),
        seq,
    )


def queue_names(prefix: str, machine_id: str) -> tuple[str, str]:
    """(to_me, from_me): the POSIX names of one machine's queues."""
    if not machine_id or "/" in machine_id or "\0" in machine_id:
        raise QueueError(f"machine id {machine_id!r} cannot name a queue")
    return f"{prefix}.{machine_id}.to_me", f"{prefix}.{machine_id}.from_me"


def queue_exists(name: str) -> bool:
    """Whether a queue of this name exists (for leak checks: opening it creates nothing)."""
    try:
        posix_ipc.MessageQueue(name).close()
    except posix_ipc.ExistentialError:
        return False
    return True


def remove_queues(prefix: str, machine_ids: list[str]) -> list[str]:
    """Unlink the queues of these machines (gwc stop); returns the names that existed."""
    removed = []
    for mid in machine_ids:
        for name in queue_names(prefix, mid):
            try:
                posix_ipc.unlink_message_queue(name)
                removed.append(name)
            except posix_ipc.ExistentialError:
                pass
    return removed


def open_queue(name: str, max_messages: int = MAX_MESSAGES) -> posix_ipc.MessageQueue:
    """Create the queue exclusively or open the one the other half created; refuse one of another
    layout, and one the cell did not make (QueueNotOurs)."""
    for _ in range(3):  # made, or removed, by the other half between our two calls: once more
        try:
            q = posix_ipc.MessageQueue(
                name, posix_ipc.O_CREX, mode=0o600, max_messages=max_messages, max_message_size=LAYOUT_SIZE
            )
            break
        except posix_ipc.ExistentialError:
            pass
        except (posix_ipc.Error, OSError, ValueError) as e:
            raise QueueError(f"cannot create message queue {name}: {e} (queue limits: /proc/sys/fs/mqueue)") from e
        try:
            q = posix_ipc.MessageQueue(name)
        except posix_ipc.ExistentialError:
            continue
        except (posix_ipc.Error, OSError, ValueError) as e:
            raise QueueError(
                f"cannot open message queue {name}: {e}: the queue is not the cell's (made by another user?)"
            ) from e
        try:
            check_ours(q, name)
        except QueueError:
            q.close()
            raise
        break
    else:
        raise QueueError(f"message queue {name} keeps coming and going: is another cell on this var/?")
    if q.max_message_size != LAYOUT_SIZE:
        size = q.max_message_size
        q.close()
        raise QueueError(
            f"message queue {name} exists with messages of {size} bytes, not {LAYOUT_SIZE}: "
            "left by another GWC version; remove it with `gwc stop`"
        )
    return q


def check_ours(q: posix_ipc.MessageQueue, name: str) -> None:
    """Refuse a queue this process's user did not make, or that others may open (QueueNotOurs)."""
    st = os.fstat(q.mqd)  # on Linux a queue descriptor is a file's: its owner and mode
    mode = stat.S_IMODE(st.st_mode)
    uid, gid = os.geteuid(), os.getegid()
    if st.st_uid == uid and not mode & 0o007 and (not mode & 0o070 or st.st_gid == gid):
        return
    raise QueueNotOurs(
        f"message queue {name} exists but is not the cell's: owner uid {st.st_uid}, group {st.st_gid}, "
        f"mode {mode:04o} (the cell runs as uid {uid} and makes its queues 0600): refused, not used. "
        "Find who made it; `gwc stop` removes it"
    )


class Channel:
    """One half's end of a machine's queue pair: send to the other half, receive from it.

    `side` is "wc" or "me". Safe to use from two threads at once when one only sends and the
    other only receives (the WC's reader thread does exactly that).
    """

    def __init__(
        self, prefix: str, machine_id: str, side: Side, log: logging.Logger, max_messages: int = MAX_MESSAGES
    ) -> None:
        if side not in ("wc", "me"):
            raise QueueError(f"a channel side is 'wc' or 'me', not {side!r}")
        self.machine_id = machine_id
        self.side = side
        self.log = log
        self.max_messages = max_messages
        to_me, from_me = queue_names(prefix, machine_id)
        self.out_name, self.in_name = (to_me, from_me) if side == "wc" else (from_me, to_me)
        self._out: posix_ipc.MessageQueue | None = None
        self._in: posix_ipc.MessageQueue | None = None
        self._peer = "ME" if side == "wc" else "WC"

    def open(self) -> Channel:
        """Open (creating if needed) both queues. Safe to call twice."""
        if self._out is None:
            self._out = open_queue(self.out_name, self.max_messages)
        if self._in is None:
            try:
                self._in = open_queue(self.in_name, self.max_messages)
            except QueueError:
                self.close()
                raise
        return self

    def close(self) -> None:
        """Close our descriptors; the queues themselves stay for the other half. Safe to call twice."""
        for q in (self._out, self._in):
            if q is not None:
                try:
                    q.close()
                except posix_ipc.Error:
                    pass
        self._out = self._in = None

    def __enter__(self) -> Channel:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _queue(self, q: posix_ipc.MessageQueue | None) -> posix_ipc.MessageQueue:
        if q is None:
            raise QueueError(f"the {self.side} channel of {self.machine_id} is not open")
        return q

    def send(self, msg: MeMessage, timeout: float = 0.0) -> None:
        """Queue one record for the other half; QueueError if it is refused or the queue stays full."""
        data = pack(msg)
        q = self._queue(self._out)
        try:
            q.send(data, timeout=max(0.0, timeout))
        except posix_ipc.BusyError:
            raise QueueFull(
                f"queue {self.out_name} is full ({q.max_messages} records waiting): "
                f"the {self._peer} is not reading; {msg.message_id.name} not sent"
            ) from None
        except posix_ipc.Error as e:
            raise QueueError(f"sending {msg.message_id.name} on {self.out_name} failed: {e}") from e
        if self.log.isEnabledFor(TRACE):
            self.log.log(TRACE, "to %s: %s", self._peer, msg.describe())

    def receive(self, timeout: float | None = None) -> MeMessage:
        """The next record from the other half, waiting up to `timeout` s (None: for ever, 0: not at all).

        QueueTimeout if none came (or a signal interrupted the wait); QueueError if it is garbled.
        """
        q = self._queue(self._in)
        try:
            data, _ = q.receive(timeout=None if timeout is None else max(0.0, timeout))
        except posix_ipc.BusyError:
            raise QueueTimeout(f"nothing from the {self._peer} on {self.in_name} within {timeout}s") from None
        except posix_ipc.SignalError:
            raise QueueTimeout(f"wait on {self.in_name} interrupted by a signal") from None
        except posix_ipc.Error as e:
            raise QueueError(f"receiving on {self.in_name} failed: {e}") from e
        return self._received(data)

    def _received(self, data: bytes) -> MeMessage:
        msg = unpack(data)
        if self.log.isEnabledFor(TRACE):
            self.log.log(TRACE, "from %s: %s", self._peer, msg.describe())
        return msg

    def poll(self) -> MeMessage | None:
        """The next record if one is waiting, else None (the listings' mq_read_nowait)."""
        q = self._queue(self._in)
        try:
            data, _ = q.receive(0)
        except posix_ipc.BusyError:
            return None  # the usual answer when the queue is empty: no QueueTimeout made for it
        except posix_ipc.SignalError:
            return None
        except posix_ipc.Error as e:
            raise QueueError(f"receiving on {self.in_name} failed: {e}") from e
        return self._received(data)

    def drain(self) -> int:
        """Throw away every record waiting for us (stale ones from before a restart); how many."""
        n = 0
        while True:
            try:
                if self.poll() is None:
                    return n
            except QueueError as e:
                self.log.warning("dropped a garbled record while draining: %s", e)
            n += 1

    def withdraw(self) -> list[MeMessage]:
        """Take back what we sent and the other half has not read (it is dead or hung): a request
        left in the queue would be served, out of its time, by the next incarnation."""
        taken: list[MeMessage] = []
        q = self._queue(self._out)
        while True:
            try:
                data, _ = q.receive(timeout=0)
            except posix_ipc.BusyError:
                return taken
            except posix_ipc.Error as e:
                raise QueueError(f"withdrawing from {self.out_name} failed: {e}") from e
            try:
                taken.append(unpack(data))
            except QueueError as e:
                self.log.warning("dropped a garbled record while withdrawing: %s", e)

    def fileno(self) -> int:
        """The descriptor of the queue we read: on Linux a queue is a file that select/epoll can watch."""
        return int(self._queue(self._in).mqd)

    def pending(self) -> tuple[int, int]:
        """(records waiting for the other half, records waiting for us)."""
        return self._queue(self._out).current_messages, self._queue(self._in).current_messages
