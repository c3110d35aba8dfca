"""People in the cell: users and their roles, the one table of who may do what, and the audit trail
(docs/users.md).

* roles.py: the roles, the actions and the table (`check`), consulted at every door.
* passwords.py: argon2id hashes.
* store.py: the SQL of users and the audit trail (sql/090_users.sql).
* doors.py: who a person is at a door (`Person`, a unix login mapped to a user, a login), and `act`,
  which checks, runs and audits one act.
"""

from gwc.users.doors import Person, act, identify_unix, login, refuse_unless
from gwc.users.roles import LOWEST, Action, Role, check

__all__ = ["LOWEST", "Action", "Person", "Role", "act", "check", "identify_unix", "login", "refuse_unless"]
