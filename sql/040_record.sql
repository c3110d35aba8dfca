-- The production record (issue 34, docs/record.md): every machine state in time, downtime with its
-- reasons, each entity's states and the operator's actions on it. Append-only, written in the same
-- statement as the change it records, by the owner of that change; pruned by the same owner after
-- cell.toml [record] keep_days. Idempotent: safe to run again.

-- Machine Server: one row per change of machine_status (and one per MAINT_DONE). cause: what made
-- the change (setup, setup_end, run, run_end, operator_stop, start, liveness, agent_death, alarm,
-- maintenance). entity_id, recipe_version and recipe_checksum are those of the run, read when the
-- machine went Setup or Running (the reservation and the recipe version approved then).
create table if not exists machine_state_history (
    id              bigserial primary key,
    machine_id      text not null,
    status          text not null,
    previous        text,
    cause           text not null,
    recipe_id       text,
    recipe_version  int,
    recipe_checksum text,
    machine_run_id  bigint,
    entity_id       bigint,
    note            text,
    at              timestamptz not null default clock_timestamp()
);
create index if not exists machine_state_history_machine_at on machine_state_history (machine_id, at);
-- Each index is paid by every status change: only those a reader needs. Time ranges (pruning, reports)
-- use a BRIN index (rows come in time order), tiny and nearly free to keep; `trace where --recipe` scans.
create index if not exists machine_state_history_at_brin on machine_state_history using brin (at);
create index if not exists machine_state_history_entity on machine_state_history (entity_id)
    where entity_id is not null;

-- Machine Server: a stop that was not planned (the machine went Shutdown). Open while ended_at is
-- null: at most one per machine. reason: the alarm that caused it, or the one the operator gave from
-- cell.toml's reason tree. e10_state: SEMI E10's state of the time lost.
create table if not exists downtime_events (
    event_id   bigserial primary key,
    machine_id text not null,
    started_at timestamptz not null default clock_timestamp(),
    ended_at   timestamptz,
    cause      text not null,
    reason     text,
    e10_state  text not null check (e10_state in ('scheduled_downtime', 'unscheduled_downtime', 'engineering',
                                                  'non_scheduled')),
    note       text,
    reason_by  text,
    reason_at  timestamptz,
    check (ended_at is null or ended_at >= started_at)
);
create unique index if not exists downtime_events_open on downtime_events (machine_id) where ended_at is null;
create index if not exists downtime_events_machine_started on downtime_events (machine_id, started_at);
create index if not exists downtime_events_ended on downtime_events (ended_at);

-- Lot Server: every change of an entity's state (a trigger on lot_status, so no path that moves an
-- entity can forget it: it runs in the Lot Server's own transaction, as its role).
create table if not exists entity_state_history (
    id        bigserial,  -- the order of changes within one instant; no key: nothing refers to a row
    entity_id bigint not null,
    lot_id    bigint not null,
    state     text not null,
    reason    text,
    at        timestamptz not null default clock_timestamp()
);
create index if not exists entity_state_history_entity on entity_state_history (entity_id, at);
create index if not exists entity_state_history_at_brin on entity_state_history using brin (at);

-- Lot Server: the operator's actions on an entity (import, export, release, cancel) and who did it
-- (today the unix user of the HI: user@hi.pid).
create table if not exists operator_actions (
    id        bigserial primary key,
    entity_id bigint not null,
    lot_id    bigint,
    action    text not null check (action <> ''),
    by        text not null,
    note      text,
    at        timestamptz not null default clock_timestamp()
);
create index if not exists operator_actions_entity on operator_actions (entity_id, at);
create index if not exists operator_actions_at on operator_actions (at);

-- The trigger: a state that changed (or a new row) is one insert more in the same transaction.
-- gwc.record_entities = 'off' (set by a Lot Server whose cell.toml turns the history off) skips it.
-- No SET clause (search_path): a function with one saves and restores the setting at every call, on
-- the Lot Server's hot path; the table is named with its schema instead.
create or replace function record_entity_state() returns trigger
language plpgsql
as $$
begin
    if coalesce(current_setting('gwc.record_entities', true), '') = 'off' then
        return null;
    end if;
    if tg_op = 'INSERT' or new.state is distinct from old.state then
        insert into public.entity_state_history (entity_id, lot_id, state, reason) values
            (new.entity_id, new.lot_id, new.state, new.reason);
    end if;
    return null;
end;
$$;

drop trigger if exists lot_status_record on lot_status;
create trigger lot_status_record after insert or update of state on lot_status
    for each row execute function record_entity_state();

-- prune_record(owner, days): the owner's history older than `days` days goes (an open downtime
-- event never); returns the rows deleted.
create or replace function prune_record(p_owner text, p_days double precision) returns bigint
language plpgsql
set search_path = public, pg_temp
as $$
declare
    n bigint := 0;
    k bigint;
    cutoff timestamptz := now() - make_interval(secs => p_days * 86400);
begin
    if p_owner = 'ms' then
        delete from machine_state_history h where h.at < cutoff
            -- keep each machine's last row before the cutoff: the state it was in when the kept time began
            and h.id <> (select max(id) from machine_state_history l where l.machine_id = h.machine_id and l.at < cutoff);
        get diagnostics k = row_count; n := n + k;
        delete from downtime_events where ended_at < cutoff;
        get diagnostics k = row_count; n := n + k;
    elsif p_owner = 'ls' then
        delete from entity_state_history where at < cutoff;
        get diagnostics k = row_count; n := n + k;
        delete from operator_actions where at < cutoff;
        get diagnostics k = row_count; n := n + k;
    else
        raise exception 'prune_record: owner must be ms or ls, not %', p_owner using errcode = 'invalid_parameter_value';
    end if;
    return n;
end;
$$;

-- Owners (030_roles.sql grants every role select on every table; these tables may be new since).
grant select on machine_state_history, downtime_events, entity_state_history, operator_actions
    to gwc_msched, gwc_ms, gwc_ls, gwc_cas, gwc_ers, gwc_sls, gwc_wc, gwc_hi, gwc_lot, gwc_opcua;
grant insert, update, delete on machine_state_history, downtime_events to gwc_ms;
grant usage on sequence machine_state_history_id_seq, downtime_events_event_id_seq to gwc_ms;
grant insert, delete on entity_state_history, operator_actions to gwc_ls;
grant usage on sequence entity_state_history_id_seq, operator_actions_id_seq to gwc_ls;
revoke all on function prune_record(text, double precision) from public;
grant execute on function prune_record(text, double precision) to gwc_ms, gwc_ls;
