"""One exception hierarchy for the whole cell; the CLI turns each into one line and an exit code."""

from __future__ import annotations


class GwcError(Exception):
    """Base of every error the cell raises on purpose. Its message says what to do."""

    exit_code = 1


class ConfigError(GwcError):
    """etc/cell.toml (or an override) is missing or wrong."""

    exit_code = 2


class DatabaseError(GwcError):
    """The cell database cannot be reached or refused a statement."""

    exit_code = 3


class DatabaseUnavailable(DatabaseError):
    """No connection could be made after the retries 3.2.2 asks for."""


class BusError(GwcError):
    """The conversation bus could not send or receive."""

    exit_code = 4


class ConversationTimeout(BusError, TimeoutError):
    """The answer to a conversation did not come in time (thesis 3.2.3)."""


class MessageError(BusError, ValueError):
    """A message does not fit its class in the catalogue, or a datagram is malformed."""


class QueueError(GwcError):
    """The WC<->ME message-queue channel failed (full queue, garbled message, oversize field)."""

    exit_code = 5


class QueueTimeout(QueueError, TimeoutError):
    """Nothing arrived on a WC<->ME queue before the deadline."""


class QueueFull(QueueError):
    """A WC<->ME queue is full: the other half is not reading (down, or stuck)."""


class QueueNotOurs(QueueError):
    """A queue of the cell's name exists that the cell did not make (another user's, or open to other
    users): refused, never used (docs/security.md, Local users)."""


class LineError(GwcError):
    """The RS-232 line to a machine failed: port gone, no answer in time, or a garbled record."""

    exit_code = 7


class ModuleError(GwcError):
    """A cell module could not be started, stopped or found."""

    exit_code = 6


class Refused(GwcError):
    """A conversation was answered with an ack code other than ACK_OK; or, raised by a server's
    handler or store, is to be (the module runtime answers it, with `fields` beside the code)."""

    def __init__(self, ack_code: str, detail: str = "", **fields: object) -> None:
        self.ack_code = ack_code
        self.detail = detail
        self.fields = fields
        super().__init__(f"refused with {ack_code}" + (f": {detail}" if detail else ""))


class Forbidden(GwcError):
    """A person's role may not do what they asked (gwc/users/roles.py; docs/users.md)."""

    exit_code = 8


class NotAuthenticated(GwcError):
    """A person could not be identified: no such user, a wrong password, or a door locked for a while."""

    exit_code = 8
