"""Ack codes and machine statuses, spelled as the thesis spells them on the wire and in the database."""

from __future__ import annotations

from enum import StrEnum


class AckCode(StrEnum):
    """The answer carried by every acknowledgement, on the bus and on the WC<->ME queues."""

    ACK_OK = "ACK_OK"  # done
    NO_MACHINE = "NO_MACHINE"  # a requested machine does not exist, is shut down, or MSCHED shut down
    REQ_CANCEL = "REQ_CANCEL"  # the request was cancelled (operator or entity)
    REQ_KEY_U = "REQ_KEY_U"  # cancel: no such request_key (nothing to cancel)
    NOT_RESERVED = "Not_Reserv"  # unreserve: the machine is not reserved by that entity
    NOTNOW = "Notnow"  # the module or machine is in a state that does not allow this now
    DB_BADREA = "DB_Badrea"  # a database read failed
    DB_BADUPD = "DB_Badupd"  # a database update failed
    REC_INVAL = "Rec_Inval"  # recipe unknown, not for this machine/op type, or its checksum is wrong
    START_FAIL = "Start_Fail"  # startup or a run could not be started
    RUN_FAIL = "Run_Fail"  # the machine reported a failed run
    BAD_MESSAGE = "Bad_message"  # the message is malformed or does not fit its conversation
    UNKNOWN = "Unknown"  # unknown entity, lot, alarm, machine ...
    TIMEOUT = "Timeout"  # a peer (ME, server) did not answer in time


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
