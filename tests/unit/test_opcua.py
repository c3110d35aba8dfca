"""The OPC UA gateway's rules, in isolation: who may call, how passwords compare, the Machinery
states of the cell's statuses, the [opcua] settings (the gateway itself: tests/e2e/test_opcua.py)."""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path

import pytest
from asyncua import ua
from asyncua.common.utils import Buffer
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.ua.ua_binary import struct_to_binary

from gwc.errors import ConfigError
from gwc.opcua.security import (
    CALL,
    WRITE,
    ClearText,
    GatewayRules,
    GatewayUsers,
    hash_password,
    password_matches,
)
from gwc.opcua.settings import OpcuaSettings, load_settings
from gwc.opcua.space import machinery_state, operation_mode
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
