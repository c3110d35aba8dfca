"""The cell database: the embedded PostgreSQL cluster, connections with retry, one-transaction steps.

The thesis (3.2.2) asks every module to retry a failed database request and, when the failure is
fatal, to die cleanly; `connect` and `transaction` are those two rules, written once. The embedded
cluster is private to one cell: it lives in var/pg, listens on a unix socket in var/run and trusts
local connections. In a cell spread over several hosts it also listens on its host's address, where
each module's role logs in with its password (scram-sha-256) from the cell's subnet only, over TLS
when configured (docs/deploying.md).

Every module connects as the superuser of the cluster and then `SET ROLE gwc_<module>`, so the
table-ownership rule (thesis 5.1, GUIDE 4) is enforced by the server, not by convention.

Its parts: `names` (the database, its roles, its socket), `cluster` (the embedded cluster), `access`
(who logs in from where: passwords, pg_hba, TLS), `connect` (connections), `steps` (`transaction`,
`Statement`) and `schema` (sql/*.sql and the cell's machines). What the rest of the cell uses is
assembled here: `from gwc import db`, then `db.connect`, `db.transaction`, `db.Statement`.
"""

from gwc.db.access import lot_passwords_file, role_passwords, secrets_dir
from gwc.db.cluster import DEFAULT_SETTINGS, cluster_running, cluster_start, cluster_stop, find_pg_bin
from gwc.db.connect import CONNECT_TIMEOUT_S, SLOW_MEMBER_S, TCP_WATCH, connect, connect_async, database_url, probe
from gwc.db.names import DB_NAME, LOT_ROLE, SUPERUSER, socket_dir
from gwc.db.schema import KIND_RECIPES, SQL_DIR, get_new_max_value, init_schema, sql_files
from gwc.db.steps import ConnectionSource, Statement, transaction

__all__ = [
    "CONNECT_TIMEOUT_S",
    "DB_NAME",
    "DEFAULT_SETTINGS",
    "KIND_RECIPES",
    "LOT_ROLE",
    "SLOW_MEMBER_S",
    "SQL_DIR",
    "SUPERUSER",
    "TCP_WATCH",
    "ConnectionSource",
    "Statement",
    "cluster_running",
    "cluster_start",
    "cluster_stop",
    "connect",
    "connect_async",
    "database_url",
    "find_pg_bin",
    "get_new_max_value",
    "init_schema",
    "lot_passwords_file",
    "probe",
    "role_passwords",
    "secrets_dir",
    "socket_dir",
    "sql_files",
    "transaction",
]
