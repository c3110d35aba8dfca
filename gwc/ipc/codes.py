"""Ack codes and machine statuses, spelled as the thesis spells them on the wire and in the database."""

from __future__ import annotations

from enum import StrEnum


class AckCode(StrEnum):
    """The answer carried by every acknowledgement, on the bus and on the WC<->ME queues."""

    ACK_OK = "ACK_OK"
    NO_MACHINE = "NO_MACHINE"
    REQ_CANCEL = "REQ_CANCEL"
    REQ_KEY_U = "REQ_KEY_U"
    NOT_RESERVED = "Not_Reserv"
    NOTNOW = "Notnow"
    DB_BADREA = "DB_Badrea"
    DB_BADUPD = "DB_Badupd"
    REC_INVAL = "Rec_Inval"
    START_FAIL = "Start_Fail"
    RUN_FAIL = "Run_Fail"
    BAD_MESSAGE = "Bad_message"
    UNKNOWN = "Unknown"
    TIMEOUT = "Timeout"
    NOT_AUTH = "Not_Auth"

    @property
    def words(self) -> str:
        """What the code means, for a person (the console shows it beside the code)."""
        return _ACK_WORDS[self]


_ACK_WORDS = {
    AckCode.ACK_OK: "done",
    AckCode.NO_MACHINE: "a requested machine does not exist, is shut down, or MSCHED shut down",
    AckCode.REQ_CANCEL: "the request was cancelled (operator or entity)",
    AckCode.REQ_KEY_U: "no such request key: nothing to cancel",
    AckCode.NOT_RESERVED: "the machine is not reserved by that entity",
    AckCode.NOTNOW: "the module or machine is in a state that does not allow this now",
    AckCode.DB_BADREA: "a database read failed",
    AckCode.DB_BADUPD: "a database update failed",
    AckCode.REC_INVAL: "recipe unknown, not for this machine or op type, or its checksum is wrong",
    AckCode.START_FAIL: "the startup or the run could not be started",
    AckCode.RUN_FAIL: "the machine reported a failed run",
    AckCode.BAD_MESSAGE: "the message is malformed or does not fit its conversation",
    AckCode.UNKNOWN: "unknown entity, lot, alarm or machine",
    AckCode.TIMEOUT: "a peer (ME, server) did not answer in time",
    AckCode.NOT_AUTH: "the sender's key does not allow this conversation (a lot script outside its rights)",
}


class MachineStatus(StrEnum):
    """MACHINE_STATUS.status: the states 6.3.2 moves a machine through."""

    SHUTDOWN = "Shutdown"
    IDLE = "Idle"
    SETUP = "Setup"
    RUNNING = "Running"
    SETUP_SHUT = "Setup_Shut"  # shutdown asked while in Setup: shut down after the run
    RUN_SHUT = "Run_Shut"  # shutdown asked while Running: shut down when the run completes


class LotState(StrEnum):
    """LOT_STATUS.state: where each lot entity is."""

    CREATED = "created"
    WAITING_IMPORT = "waiting_import"
    IMPORTED = "imported"
    WAITING_MACHINE = "waiting_machine"
    RUNNING = "running"
    COMPLETED = "completed"
    WAITING_EXPORT = "waiting_export"
    EXPORTED = "exported"
    FAILED = "failed"
    HELD = "held"  # a run in doubt past its bound, held for the operator's release (retry, reroute, fail)
