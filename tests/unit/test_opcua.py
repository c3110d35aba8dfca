"""The OPC UA gateway's rules, in isolation: who may call, how passwords compare, the Machinery
states of the cell's statuses, the [opcua] settings (the gateway itself: tests/e2e/test_opcua.py)."""

from __future__ import annotations

import hashlib
import logging
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
from asyncua import ua
from asyncua.common.utils import Buffer
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.ua.ua_binary import struct_to_binary

from gwc.config import MachineSpec
from gwc.errors import ConfigError
from gwc.opcua.model import NODESET_FILES, identification, published_nodeset
from gwc.opcua.security import (
    CALL,
    WRITE,
    ClearText,
    GatewayRules,
    GatewayUsers,
    certificate_names,
    hash_password,
    password_matches,
    with_timestamps,
)
from gwc.opcua.settings import OpcuaSettings, load_settings
from gwc.opcua.space import check_arguments, data_value, machinery_state, operation_mode
from tests.conftest import make_config

READ = ua.NodeId(ua.ObjectIds.ReadRequest_Encoding_DefaultBinary)
OPERATOR = User(role=UserRole.User, name="operator")
ANONYMOUS = User(role=UserRole.Anonymous)


def calls(*methods: int) -> Buffer:
    params = ua.CallParameters(
        MethodsToCall=[ua.CallMethodRequest(ObjectId=ua.NodeId(2253), MethodId=ua.NodeId(m)) for m in methods]
    )
    return Buffer(struct_to_binary(params))


def test_methods_need_a_user_on_an_encrypted_channel_and_nobody_writes() -> None:
    secure, plain = GatewayRules(encrypted=True), GatewayRules(encrypted=False)
    some_method = calls(12345)
    assert secure.check_validity(OPERATOR, CALL, some_method)
    assert not plain.check_validity(OPERATOR, CALL, some_method)
    assert not secure.check_validity(ANONYMOUS, CALL, some_method)
    for rules in (secure, plain):
        assert rules.check_validity(ANONYMOUS, READ, Buffer(b""))
        assert not rules.check_validity(OPERATOR, WRITE, Buffer(b""))


def test_anyone_may_ask_for_the_active_alarms_again_but_not_with_another_call() -> None:
    refresh = ua.ObjectIds.ConditionType_ConditionRefresh
    body = calls(refresh)
    assert GatewayRules(encrypted=False).check_validity(ANONYMOUS, CALL, body)
    assert len(body) > 0, "the rule must not consume the request it looked at"
    assert not GatewayRules(encrypted=False).check_validity(ANONYMOUS, CALL, calls(refresh, 12345))


def test_passwords_are_salted_slow_hashes_and_never_taken_in_clear_off_an_unsecured_channel() -> None:
    stored = hash_password("pw")
    assert stored.startswith("scrypt$16384$8$1$") and stored != hash_password("pw")  # salted: never twice alike
    assert password_matches(stored, "pw") and not password_matches(stored, "px")
    digest = "sha256:" + hashlib.sha256(b"pw").hexdigest()
    assert not password_matches(digest, "pw") and not password_matches("pw", "pw")  # the old forms: no more
    users = GatewayUsers(OpcuaSettings(users={"op": stored}, anonymous=False), logging.getLogger("t"))
    cert = b"client certificate"  # asyncua passes the channel's: none on the None endpoint
    assert users.get_user(None, "op", "pw", cert) == User(role=UserRole.User, name="op")
    assert users.get_user(None, "op", ClearText("pw"), cert) == User(role=UserRole.User, name="op")  # channel encrypts
    assert users.get_user(None, "op", ClearText("pw"), None) is None  # in clear on the None endpoint
    assert users.get_user(None, "op", "pw", None) == User(role=UserRole.User, name="op")  # encrypted to our key
    assert users.get_user(None, "op", "bad", cert) is None
    assert users.get_user(None) is None  # anonymous not allowed
    allowed = GatewayUsers(OpcuaSettings(), logging.getLogger("t"))
    assert allowed.get_user(None, certificate=b"a client's certificate") == ANONYMOUS


@pytest.mark.parametrize(
    ("status", "on_bus", "state", "mode"),
    [
        ("Idle", True, "NotExecuting", "None"),
        ("Setup", True, "Executing", "Setup"),
        ("Running", True, "Executing", "Processing"),
        ("Run_Shut", True, "Executing", "Processing"),
        ("Shutdown", True, "OutOfService", "None"),
        ("Shutdown", False, "NotAvailable", "None"),
        (None, False, "NotAvailable", "None"),
    ],
)
def test_machinery_states_of_the_cells_statuses(status: str | None, on_bus: bool, state: str, mode: str) -> None:
    assert machinery_state(status, on_bus) == state
    assert operation_mode(status) == mode


def test_settings_are_checked_and_certificates_go_under_var(tmp_path: Path) -> None:
    stored = hash_password("pw")
    cfg = make_config(tmp_path, None, opcua={"endpoint": "opc.tcp://127.0.0.1:4999/x/", "users": {"op": stored}})
    s = load_settings(cfg)
    assert s.endpoint.endswith(":4999/x/") and s.users == {"op": stored}
    assert s.cert_dir == cfg.var / "opcua"
    for plain in ("pw", "sha256:" + hashlib.sha256(b"pw").hexdigest(), "scrypt$3$8$1$AAAAAAAAAAA=$AAAA"):
        with pytest.raises(ConfigError, match=r"users.op: .* never in clear"):
            load_settings(make_config(tmp_path, None, opcua={"users": {"op": plain}}))
    for bad in ({"endpoint": "http://x"}, {"refresh": 0}, {"colour": "red"}):
        with pytest.raises(ConfigError, match=r"\[opcua\]"):
            load_settings(make_config(tmp_path, None, opcua=bad))


def test_bench_pairs_each_status_change_with_its_notification_in_order() -> None:
    from gwc.bench.opcua import latencies

    heard = [(1.0, "wc1", "Setup"), (1.1, "wc1", "Running"), (1.2, "wc2", "Idle"), (1.3, "wc1", "Idle")]
    seen = [
        (0.5, "machines/wc1/status", "Idle"),  # the initial value
        (1.01, "machines/wc1/status", "Setup"),
        (1.02, "machines/wc1/machine_run_id", 7),
        (1.15, "machines/wc1/status", "Running"),
        (1.35, "machines/wc1/status", "Idle"),
    ]
    lat, missed = latencies(heard, seen)
    assert [(t, round(x, 3)) for t, x in lat] == [(1.0, 0.01), (1.1, 0.05), (1.3, 0.05)]
    assert missed == 1  # wc2's change was never notified


def test_bench_counts_two_changes_shown_as_one_without_losing_the_next() -> None:
    from gwc.bench.opcua import latencies

    heard = [(1.0, "wc1", "Setup"), (1.001, "wc1", "Running"), (1.2, "wc1", "Idle")]
    seen = [(1.05, "machines/wc1/status", "Running"), (1.25, "machines/wc1/status", "Idle")]
    lat, missed = latencies(heard, seen)
    assert missed == 1 and [round(x, 3) for _, x in lat] == [0.049, 0.05]


V = ua.VariantType
S = ua.StatusCodes
DECLARED = [("entity_id", V.Int64, "the lot entity"), ("note", V.String, "a note")]


def test_method_arguments_are_checked_for_count_and_type_without_conversion() -> None:
    good = [ua.Variant(5, V.Int64), ua.Variant("x", V.String)]
    assert check_arguments(good, DECLARED) is None
    assert check_arguments([ua.Variant(5, V.Int32), good[1]], DECLARED) is None  # an integer that fits
    assert check_arguments(good[:1], DECLARED).StatusCode.value == S.BadArgumentsMissing
    assert check_arguments([*good, good[1]], DECLARED).StatusCode.value == S.BadTooManyArguments
    for wrong in (ua.Variant(1.5, V.Double), ua.Variant(True, V.Boolean), ua.Variant("1", V.String)):
        refused = check_arguments([wrong, good[1]], DECLARED)
        assert refused is not None and refused.StatusCode.value == S.BadInvalidArgument
        assert [r.value for r in refused.InputArgumentResults] == [S.BadTypeMismatch, S.Good]
    too_big = check_arguments([ua.Variant(2**40, V.Int64)], [("priority", V.Int32, "")])
    assert too_big is not None and too_big.InputArgumentResults[0].value == S.BadTypeMismatch


def test_a_null_is_a_value_less_data_value_with_both_timestamps() -> None:
    at = datetime(2026, 1, 2, tzinfo=UTC)
    null = data_value(None, V.String, at, at)
    assert null.Value is None and null.SourceTimestamp == at and null.ServerTimestamp == at
    text = data_value("Idle", V.String, at, at)
    assert text.Value == ua.Variant("Idle", V.String)
    assert data_value("x", V.LocalizedText, at, at).Value.Value == ua.LocalizedText("x")


def test_read_returns_the_timestamps_asked_for() -> None:
    at = datetime(2026, 1, 2, tzinfo=UTC)
    stored = [
        data_value("Idle", V.String, at, at),
        ua.DataValue(ua.Variant(1, V.Int32)),
        data_value(None, V.String, at, at),
    ]
    items = [ua.ReadValueId(NodeId=ua.NodeId(i), AttributeId=ua.AttributeIds.Value) for i in (1, 2, 3)]
    both = with_timestamps(ua.ReadParameters(NodesToRead=items, TimestampsToReturn=ua.TimestampsToReturn.Both), stored)
    assert both[0].SourceTimestamp == at and both[0].ServerTimestamp == at
    assert both[1].SourceTimestamp is None and both[1].ServerTimestamp is not None  # the server's own: now
    assert both[2].Value is None and both[2].ServerTimestamp == at
    neither = with_timestamps(
        ua.ReadParameters(NodesToRead=items, TimestampsToReturn=ua.TimestampsToReturn.Neither), stored
    )
    assert all(dv.SourceTimestamp is None and dv.ServerTimestamp is None for dv in neither)


def test_identification_comes_from_cell_toml_checked_with_defaults_for_the_mandatory() -> None:
    spec = MachineSpec(id="cmm_wc", kind="cmm", options={"identification": {"manufacturer": "Zeiss"}})
    ident = identification("c1", spec)
    assert ident["manufacturer"] == "Zeiss" and ident["serial_number"] == "cmm_wc"
    assert ident["product_instance_uri"] == "urn:gwc:c1:machine:cmm_wc" and ident["model"] == "cmm"
    for bad in ({"colour": "red"}, {"year_of_construction": 1e3}, {"serial_number": 7}):
        with pytest.raises(ConfigError, match="cmm_wc"):
            identification("c1", MachineSpec(id="cmm_wc", options={"identification": bad}))


def test_the_published_nodesets_are_read_less_their_design_tool_only_nodes() -> None:
    for name in NODESET_FILES:
        text = published_nodeset(name)
        assert "<UANodeSet" in text and 'DesignToolOnly="true"' not in text
    assert "OPC Foundation MIT License" in published_nodeset("Opc.Ua.Machinery.NodeSet2.xml")


def test_the_certificate_names_the_host_by_name_and_by_address() -> None:
    dns, ips = certificate_names("opc.tcp://192.0.2.7:4840/gwc/")
    assert "localhost" in dns and "127.0.0.1" in ips and "192.0.2.7" in ips
    dns, ips = certificate_names("opc.tcp://cell.example:4840/gwc/")
    assert "cell.example" in dns and "0.0.0.0" not in certificate_names("opc.tcp://0.0.0.0:4840/")[1]


class FakeHiBus:
    """hi_bus's context manager, attaching to nothing."""

    def __enter__(self) -> FakeHiBus:
        return self

    def __exit__(self, *exc: object) -> None:
        return None


def gateway_with(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, **client: Any) -> Any:
    """A gateway (not started: nothing listens, nothing attaches) whose HI client calls are `client`."""
    from gwc.opcua import gateway, hi_methods

    monkeypatch.setattr(hi_methods, "hi_bus", lambda cfg, log: FakeHiBus())
    for name, fake in client.items():
        monkeypatch.setattr(hi_methods, name, fake)
    cfg = make_config(tmp_path, None, machine=[{"id": "wc1", "kind": "dummy"}])
    return gateway.Gateway(cfg, "opcua", logging.getLogger("t"))


def test_unreserve_and_maintenance_done_declare_their_arguments_and_are_checked() -> None:
    from gwc.opcua.hi_methods import MAINTENANCE_OUT, UNRESERVE_ARGS, UNRESERVE_OUT

    assert [(n, t) for n, t, _ in UNRESERVE_ARGS] == [("force", V.Boolean)]
    assert [n for n, _, _ in UNRESERVE_OUT] == ["ack_code", "note", "entity_id"]
    assert [n for n, _, _ in MAINTENANCE_OUT] == ["ack_code", "note", "runs"]
    assert check_arguments([ua.Variant(False, V.Boolean)], UNRESERVE_ARGS) is None
    assert check_arguments([], UNRESERVE_ARGS).StatusCode.value == S.BadArgumentsMissing
    for wrong in (ua.Variant(1, V.Int64), ua.Variant("true", V.String)):  # not converted to a Boolean
        refused = check_arguments([wrong], UNRESERVE_ARGS)
        assert refused is not None and refused.StatusCode.value == S.BadInvalidArgument
        assert [r.value for r in refused.InputArgumentResults] == [S.BadTypeMismatch]
    assert check_arguments([ua.Variant(1, V.Int64)], []).StatusCode.value == S.BadTooManyArguments  # MaintenanceDone


def test_unreserve_goes_through_the_clis_client_call_and_maps_its_answers(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import asyncio

    from gwc.errors import ConversationTimeout, GwcError, Refused

    asked: list[tuple[Any, ...]] = []
    answers: list[Any] = [
        17,
        GwcError("wc1 is held by entity 17, whose lot script runs (pid 4): it frees it itself"),
        GwcError("wc1 is not reserved (see `gwc requests`)"),
        Refused("Unknown", "MSCHED did not free wc1"),
        ConversationTimeout("msched did not answer"),
    ]

    def unreserve_machine(cfg: Any, bus: Any, machine: str, force: bool, by: str | None = None) -> int:
        asked.append((machine, force, by))
        answer = answers.pop(0)
        if isinstance(answer, Exception):
            raise answer
        return int(answer)

    gw = gateway_with(tmp_path, monkeypatch, unreserve_machine=unreserve_machine)
    freed = asyncio.run(gw.hi.unreserve("wc1", True))
    assert freed.StatusCode.is_good()
    assert [v.Value for v in freed.OutputArguments] == ["ACK_OK", "wc1 freed (it was reserved to entity 17)", 17]
    assert asked == [("wc1", True, "opcua:test")]
    expected = [
        (S.BadInvalidState, "lot script runs"),  # refused while the script runs: nothing was sent
        (S.BadInvalidState, "not reserved"),
        (S.BadNotFound, "MSCHED did not free wc1"),
        (S.BadTimeout, "did not answer"),
    ]
    for status_code, why in expected:
        out = asyncio.run(gw.hi.unreserve("wc1", False))
        assert out.StatusCode.value == status_code and why in out.OutputArguments[1].Value


def test_maintenance_done_goes_through_the_clis_client_call_and_maps_its_answers(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import asyncio

    from gwc.errors import GwcError

    answers: list[Any] = [6, GwcError("unknown machine 'wc1' (see `gwc machine status`)")]

    def maintenance_done(bus: Any, machine: str, by: str | None = None) -> int:
        assert machine == "wc1" and by == "opcua:test"
        answer = answers.pop(0)
        if isinstance(answer, Exception):
            raise answer
        return int(answer)

    gw = gateway_with(tmp_path, monkeypatch, maintenance_done=maintenance_done)
    done = asyncio.run(gw.hi.maintenance_done("wc1"))
    assert done.StatusCode.is_good() and done.OutputArguments[2] == ua.Variant(6, V.Int64)
    assert "after 6 run(s)" in done.OutputArguments[1].Value
    unknown = asyncio.run(gw.hi.maintenance_done("wc1"))
    assert unknown.StatusCode.value == S.BadNotFound and "unknown machine" in unknown.OutputArguments[1].Value
