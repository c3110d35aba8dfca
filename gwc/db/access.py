"""Who may reach the cell database, and how: from other hosts each module role by its own password
(var/secrets/database, made on the database host and copied by the operator), over TLS when configured
(a self-signed certificate whose public half goes to var/secrets/); on the host, by the kernel's word
on who connects once the lot user's scripts reach the socket (pg_hba.conf, pg_ident.conf).
docs/deploying.md, docs/security.md."""

from __future__ import annotations

import contextlib
import grp
import os
import pwd
import secrets
import subprocess
from pathlib import Path
from typing import Any

import psycopg
from psycopg import sql

from gwc import hostuser
from gwc.config import Config, HostSpec
from gwc.db.names import DB_NAME, LOT_ROLE, SUPERUSER
from gwc.errors import DatabaseError


def uses_tls(cfg: Config) -> bool:
    return bool(cfg.raw.get("database", {}).get("tls", False))


def secrets_dir(cfg: Config) -> Path:
    """What every host of the cell needs and no one else may read: copied to each host by the operator."""
    return cfg.var / "secrets"


def passwords_file(cfg: Config) -> Path:
    return secrets_dir(cfg) / "database"


def ca_file(cfg: Config) -> Path:
    return secrets_dir(cfg) / "database.crt"


def role_passwords(cfg: Config) -> dict[str, str]:
    """Each module role's password ("role password" lines, mode 0600), made on the database host."""
    try:
        lines = passwords_file(cfg).read_text().splitlines()
    except FileNotFoundError:
        raise DatabaseError(
            f"no database passwords at {passwords_file(cfg)}: copy var/secrets/ from the database host "
            "(docs/deploying.md, Keys)"
        ) from None
    return dict(line.split(" ", 1) for line in lines if " " in line)


def _write_secret(path: Path, text: str) -> None:
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)


def set_role_passwords(cur: psycopg.Cursor[Any], cfg: Config) -> None:
    """Let every module role log in from other hosts, each with its own password (made once, kept)."""
    roles = [r for (r,) in cur.execute("select rolname from pg_roles where rolname like 'gwc\\_%' order by 1")]
    try:
        known = role_passwords(cfg)
    except DatabaseError:
        known = {}
    passwords = {r: known.get(r) or secrets.token_urlsafe(24) for r in roles}
    for role, password in passwords.items():
        cur.execute(sql.SQL("alter role {} login password {}").format(sql.Identifier(role), sql.Literal(password)))
    if passwords != known:
        _write_secret(passwords_file(cfg), "".join(f"{r} {p}\n" for r, p in passwords.items()))
    lot_role = f"gwc_{LOT_ROLE}"
    if lot_role in passwords and lot_password(cfg) != passwords[lot_role]:
        _write_secret(lot_passwords_file(cfg), f"{lot_role} {passwords[lot_role]}\n")


def lot_passwords_file(cfg: Config) -> Path:
    """The lot scripts' own role's password alone (var/secrets/lot.database): shared with the lot user's
    group as lot.key is (gwc.private), so that a lot script on a host other than the database's can log
    in as gwc_lot (reads, and its own traveller) without reading the other roles' passwords."""
    return secrets_dir(cfg) / "lot.database"


def lot_password(cfg: Config) -> str | None:
    with contextlib.suppress(OSError, ValueError):
        for line in lot_passwords_file(cfg).read_text().splitlines():
            role, _, password = line.partition(" ")
            if role == f"gwc_{LOT_ROLE}" and password:
                return password
    return None


def lot_access(cfg: Config) -> tuple[str, str] | None:
    """(group, user) of the lot scripts' OS user when they run as one (gwc.hostuser) and so must reach
    the socket; None when only the cell's user does."""
    gid = hostuser.lot_group(cfg)
    if gid is None:
        return None
    return grp.getgrgid(gid).gr_name, hostuser.lot_user_name(cfg)


def write_hba(
    cfg: Config, host: HostSpec | None, owner: pwd.struct_passwd | None, lots: tuple[str, str] | None = None
) -> None:
    """Local connections: trusted while only the cell's user can reach the socket; once the lot user
    can, by the kernel's word on who connects (peer): the cell's user and root as the cell's superuser
    or the lots' role, the lot user as the lots' role alone. From the network only the cell's subnet,
    each role by password."""
    lines = ["# Written by gwc.db at every start; edit etc/cell.toml [database] allow/tls instead."]
    lines.append("local all all peer map=cell" if lots else "local all all trust")
    if host is not None:
        allow = cfg.raw.get("database", {}).get("allow") or f"{host.address.rsplit('.', 1)[0]}.0/24"
        lines.append(f"{'hostssl' if uses_tls(cfg) else 'host'} {DB_NAME} all {allow} scram-sha-256")
    hba = cfg.pg_dir / "pg_hba.conf"
    hba.write_text("\n".join(lines) + "\n")
    if lots is not None:
        me = pwd.getpwuid(os.geteuid()).pw_name
        pairs = [(who, role) for who in dict.fromkeys((me, "root")) for role in (SUPERUSER, f"gwc_{LOT_ROLE}")]
        pairs.append((lots[1], f"gwc_{LOT_ROLE}"))
        (cfg.pg_dir / "pg_ident.conf").write_text("".join(f"cell {who} {role}\n" for who, role in pairs))
    if owner is not None:
        os.chown(hba, owner.pw_uid, owner.pw_gid)


def make_certificate(cfg: Config, host: HostSpec, owner: pwd.struct_passwd | None) -> None:
    """A self-signed certificate for the host's address, made once; its public half goes to
    var/secrets/, so the other hosts can verify the server they talk to (sslmode=verify-ca)."""
    crt, key = cfg.pg_dir / "server.crt", cfg.pg_dir / "server.key"
    if not crt.exists():
        r = subprocess.run(
            ["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "3650", "-subj",
             f"/CN={host.address}", "-addext", f"subjectAltName=IP:{host.address}",
             "-keyout", str(key), "-out", str(crt)],
            capture_output=True, text=True,
        )  # fmt: skip
        if r.returncode != 0:
            raise DatabaseError(f"cannot make the database's TLS certificate: {r.stderr.strip()[-300:]}")
        key.chmod(0o600)
        if owner is not None:
            for f in (crt, key):
                os.chown(f, owner.pw_uid, owner.pw_gid)
    _write_secret(ca_file(cfg), crt.read_text())
