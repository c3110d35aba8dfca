-- Schema versions (issue 36, upgrades without stopping). Idempotent: safe to run again.
-- docs/schema.md (Versions) and docs/deploying.md (7) tell the rules.
--
-- SCHEMA_VERSION holds one row: the version of the schema this database holds, and the oldest schema
-- version whose builds still run on it (`compatible_from`). A migration that only adds (a table, a
-- nullable column, a function) keeps the builds of the version before running: it records its new
-- version with the same `compatible_from`. A module checks the row at start (gwc/schema.py): it runs
-- when its own version lies between `compatible_from` and `version`, and says what to do if not.
-- SCHEMA_MIGRATIONS keeps every version reached, when, and what it brought.
--
-- A later sql/ file that changes the schema ends with `select schema_version_reached(N, C, 'what')`,
-- and gwc/schema.py's SCHEMA_VERSION becomes N (tests/unit/test_schema_versions.py checks they agree).

create table if not exists schema_version (
    one             boolean primary key default true check (one),
    version         int not null check (version > 0),
    compatible_from int not null check (compatible_from > 0),
    updated_at      timestamptz not null default now(),
    check (compatible_from <= version)
);

create table if not exists schema_migrations (
    version         int primary key check (version > 0),
    compatible_from int not null check (compatible_from > 0),
    note            text not null,
    applied_at      timestamptz not null default now()
);

-- Record that the schema reached p_version (never lowers it: an older build's `gwc db init` run after
-- a newer one's leaves the newer version standing, and its additive files change nothing).
create or replace function schema_version_reached(p_version int, p_compatible_from int, p_note text)
returns void language plpgsql as $$
begin
    insert into schema_migrations (version, compatible_from, note)
    values (p_version, p_compatible_from, p_note)
    on conflict (version) do nothing;
    insert into schema_version (one, version, compatible_from)
    values (true, p_version, p_compatible_from)
    on conflict (one) do update
        set version = excluded.version, compatible_from = excluded.compatible_from, updated_at = now()
        where schema_version.version < excluded.version;
end;
$$;

select schema_version_reached(1, 1, 'sql/010..095: the first versioned schema');

grant select on schema_version, schema_migrations
    to gwc_msched, gwc_ms, gwc_ls, gwc_cas, gwc_ers, gwc_sls, gwc_wc, gwc_hi, gwc_lot, gwc_opcua;
revoke execute on function schema_version_reached(int, int, text) from public;
