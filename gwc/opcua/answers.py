"""How a gateway method answers (docs/opcua.md, Methods): the cell's ack code as the call's OPC UA
status, and the code and the cell's note as its first two outputs."""

from __future__ import annotations

from asyncua import ua

from gwc.ipc.codes import AckCode

V = ua.VariantType
S = ua.StatusCodes
# The cell's ack codes as OPC UA statuses (docs/opcua.md, Methods).
STATUS_OF: dict[str, int] = {
    AckCode.ACK_OK: S.Good,
    AckCode.NOTNOW: S.BadInvalidState,
    AckCode.UNKNOWN: S.BadNotFound,
    AckCode.REQ_KEY_U: S.BadNotFound,
    AckCode.BAD_MESSAGE: S.BadInvalidArgument,
    AckCode.DB_BADREA: S.BadResourceUnavailable,
    AckCode.DB_BADUPD: S.BadResourceUnavailable,
    AckCode.TIMEOUT: S.BadTimeout,
}
OUT = [("ack_code", V.String, "the cell's ack code"), ("note", V.String, "what the cell said")]


def result(code: str | int, note: str = "", *more: ua.Variant) -> ua.CallMethodResult:
    """A method's answer: the ack code as a status, the code and the note as outputs."""
    status = code if isinstance(code, int) else STATUS_OF.get(code, S.BadUnexpectedError)
    name = code if isinstance(code, str) else ua.StatusCode(ua.UInt32(code)).name
    return ua.CallMethodResult(
        StatusCode=ua.StatusCode(ua.UInt32(status)),
        OutputArguments=[ua.Variant(name, V.String), ua.Variant(note[:500], V.String), *more],
    )
