"""Why a lot script stops: each failure of an operation entity, as one exception with a clear message.

All of them are GwcErrors, so `python -m gwc.lot.run` turns them into one log line, the entity's
failure reason, and a non-zero exit code.
"""

from __future__ import annotations

from gwc.errors import GwcError


class LotError(GwcError):
    """An operation entity could not go on: the message says which step and why."""

    exit_code = 7


class LotTimeout(LotError, TimeoutError):
    """A step of the lot did not finish within its deadline (thesis 3.2.3)."""


class RequestRefused(LotError):
    """MSCHED could not give the machines asked for (NO_MACHINE), on every try."""


class RequestCancelled(LotError):
    """A machine request of the entity was cancelled (REQ_CANCEL), e.g. by the operator (Listing 8)."""


class MachineLost(LotError):
    """A machine reserved by the entity shut down (or its WC went silent) before the run completed."""


class MachineDied(MachineLost):
    """A reserved machine's ME died (its agent said so): the run is lost for certain, not in doubt."""


class RunInDoubt(LotError):
    """A machine's run could not be heard of within its bound, and the lot script holds the entity."""


class RunFailed(LotError):
    """A machine refused to set up or start a run."""


class ScriptStopped(LotError):
    """The lot script was asked to stop (SIGTERM, e.g. by `gwc stop`)."""


class StepRefused(LotError):
    """A server refused a step of the entity's: `ack_code` says why (Not_Auth: the entity does not hold
    the machine or recipe it asked about)."""

    def __init__(self, cls: str, ack_code: str, text: str) -> None:
        super().__init__(text)
        self.cls, self.ack_code = cls, ack_code
