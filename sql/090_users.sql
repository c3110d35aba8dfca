-- Issue 39: the cell's people (users and their roles) and the audit trail of what they did, through
-- whichever door (web, console, gwc, opcua). docs/users.md says who may do what (gwc/users/roles.py);
-- docs/schema.md describes the tables. Idempotent: safe to run again.

-- A person: a name, one role, a salted slow hash of the password (argon2id, gwc/users/passwords.py),
-- and the unix login a `gwc` command on a cell host is mapped from (docs/users.md, *Who runs a gwc command*).
create table if not exists cell_users (
    user_name     text primary key check (user_name ~ '^[a-z][a-z0-9_.-]{0,31}$'),
    role          text not null check (role in ('viewer', 'operator', 'engineer', 'admin')),
    password_hash text not null check (password_hash like '$argon2%'),
    unix_user     text unique check (unix_user <> ''),
    created_at    timestamptz not null default now(),
    created_by    text not null,
    changed_at    timestamptz not null default now()
);

-- Every act of a person, allowed or refused: appended, never changed. No role of the cell may
-- update, delete or truncate it (grants below), and a trigger refuses it to anyone, the cluster's
-- superuser too (short of dropping the trigger: docs/security.md, *The audit trail*).
create table if not exists audit_trail (
    audit_no  bigint generated always as identity primary key,
    at        timestamptz not null default clock_timestamp(),
    user_name text not null,
    role      text not null,
    door      text not null check (door in ('web', 'console', 'gwc', 'opcua')),
    address   text not null default '',
    action    text not null,
    target    text not null default '',
    outcome   text not null check (outcome in ('ok', 'refused', 'failed')),
    note      text not null default ''
);
create index if not exists audit_trail_at_brin on audit_trail using brin (at);
create index if not exists audit_trail_user on audit_trail (user_name, at);

create or replace function audit_trail_append_only() returns trigger
language plpgsql as $$
begin
    raise exception 'audit_trail is append-only: % refused', tg_op
        using errcode = 'insufficient_privilege';
end;
$$;
drop trigger if exists audit_trail_no_change on audit_trail;
create trigger audit_trail_no_change before update or delete on audit_trail
    for each row execute function audit_trail_append_only();
drop trigger if exists audit_trail_no_truncate on audit_trail;
create trigger audit_trail_no_truncate before truncate on audit_trail
    for each statement execute function audit_trail_append_only();

-- Who reads and writes: the Human Interface (gwc commands, the console, the web module, which acts as
-- gwc_hi) owns cell_users; the doors (gwc_hi, and the OPC UA gateway as gwc_opcua) read it and append
-- to audit_trail, and none may change that. No other role reads either: password hashes are for the
-- doors alone (a lot script, gwc_lot, is user code). 030_roles.sql grants every role select on every
-- table when it runs again, so it is taken back here each time.
revoke all on cell_users, audit_trail
    from gwc_msched, gwc_ms, gwc_ls, gwc_cas, gwc_ers, gwc_sls, gwc_wc, gwc_hi, gwc_lot, gwc_opcua;
grant select, insert, update, delete on cell_users to gwc_hi;
grant select on cell_users to gwc_opcua;
grant select, insert on audit_trail to gwc_hi, gwc_opcua;
revoke update, delete, truncate on audit_trail from public;
