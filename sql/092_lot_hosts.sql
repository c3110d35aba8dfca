-- Lot scripts outlive their host (issue 36). Idempotent: safe to run again. docs/reliability.md
-- (*A lot script whose host dies*) tells the rules; gwc/lot/hosting.py is their Python side.
--
-- In a cell over several hosts every host's agent beats here once a second (LOT_HOSTS) and names
-- the lot scripts it runs or queues; each such entity's row in LOT_SCRIPT_HOSTS says which host runs
-- its script. When a host's beat is older than its ttl, a live host's agent claims that host's
-- unfinished entities (one more `epoch` each) and starts their scripts, which resume from the
-- record each script keeps here (LOT_TRAVELLERS) instead of on its host's disk. Writes go through
-- the functions below only: LOT_HOSTS and LOT_SCRIPT_HOSTS are the agents' (role gwc_agent),
-- LOT_TRAVELLERS the lot scripts' (gwc_lot), each row its own entity's.

do $$
begin
    if not exists (select 1 from pg_roles where rolname = 'gwc_agent') then
        begin
            create role gwc_agent nologin;
        exception when duplicate_object then
            null;  -- another database of this cluster created it meanwhile
        end;
    end if;
    if not pg_has_role(current_user, 'gwc_agent', 'MEMBER') then
        grant gwc_agent to current_user;
    end if;
end;
$$;

create table if not exists lot_hosts (
    host       text primary key check (host <> ''),
    ttl_s      real not null check (ttl_s > 0),       -- the beat's age after which its scripts are taken over
    renewed_at timestamptz not null default now()     -- the server's clock
);

create table if not exists lot_script_hosts (
    entity_id  bigint primary key,
    host       text not null,                          -- the host whose agent runs (or queues) its script
    epoch      bigint not null default 1 check (epoch > 0),  -- one more at every takeover
    previous   text,                                   -- the host it was taken from
    since      timestamptz not null default now()
);
create index if not exists lot_script_hosts_host on lot_script_hosts (host);

create table if not exists lot_travellers (
    entity_id  bigint primary key,
    host       text,                                   -- where the script that saved it ran
    pid        int,
    traveller  jsonb not null,                         -- var/lots/entity-E.json's text, as the script saved it
    saved_at   timestamptz not null default now()
);

-- One agent's beat: renew its host, name the scripts it runs or queues (p_mine), take up to p_room
-- scripts of dead hosts: hosts whose beat is older than their ttl and whose agents the caller does
-- not hear on the bus (p_heard: after a database outage every beat is stale, live hosts' too).
-- Answers ('take', E) for each entity this host must now start, ('lost', E) for each of p_mine
-- another host took over (the agent stops that script: it is fenced).
create or replace function lot_hosts_beat(p_host text, p_ttl real, p_mine bigint[], p_room int, p_heard text[])
returns table (what text, entity_id bigint)
language plpgsql security definer set search_path = public, pg_catalog as $$
declare
    r record;
begin
    insert into lot_hosts as h (host, ttl_s, renewed_at) values (p_host, p_ttl, now())
    on conflict (host) do update set ttl_s = excluded.ttl_s, renewed_at = now();
    -- Fenced: ours by the agent's list, another host's by the table.
    for r in select s.entity_id from lot_script_hosts s
             where s.entity_id = any(p_mine) and s.host <> p_host loop
        what := 'lost';
        entity_id := r.entity_id;
        return next;
    end loop;
    -- Ours: recorded (a script started since the last beat), or let go (its script ended).
    insert into lot_script_hosts (entity_id, host)
    select e, p_host from unnest(p_mine) e on conflict do nothing;
    delete from lot_script_hosts s where s.host = p_host and s.entity_id <> all(p_mine);
    -- Finished entities need no script anywhere.
    delete from lot_script_hosts s using lot_status l
    where l.entity_id = s.entity_id and l.state in ('exported', 'failed');
    delete from lot_travellers t using lot_status l
    where l.entity_id = t.entity_id and l.state in ('exported', 'failed')
      and l.updated_at < now() - interval '1 hour';
    -- Orphans: scripts of hosts whose beat is older than their ttl (or who never beat).
    for r in select s.entity_id, s.host from lot_script_hosts s
             left join lot_hosts h on h.host = s.host
             join lot_status l on l.entity_id = s.entity_id
             join lot_entities e on e.entity_id = s.entity_id
             where s.host <> p_host and s.host <> all(p_heard)
               and l.state not in ('exported', 'failed') and e.destroyed_at is null
               -- Only with a record to resume from, or with nothing done yet: a script that could not
               -- reach the database (gwc/lothosts.py) left none, and started anew it could run an
               -- operation twice; the Lot Server reaps such an entity instead.
               and (exists (select 1 from lot_travellers t where t.entity_id = s.entity_id)
                    or l.state in ('created', 'waiting_import'))
               and (h.host is null or now() - h.renewed_at > make_interval(secs => h.ttl_s))
             order by s.entity_id
             limit greatest(p_room, 0)
             for update of s skip locked loop
        update lot_script_hosts s set host = p_host, epoch = s.epoch + 1, previous = r.host, since = now()
        where s.entity_id = r.entity_id;
        what := 'take';
        entity_id := r.entity_id;
        return next;
    end loop;
end;
$$;

-- A lot script saves its traveller. Refused (false) when another host's agent runs the entity's
-- script now: this one was taken over (its host was thought dead) and must stop.
create or replace function lot_traveller_save(p_entity bigint, p_host text, p_pid int, p_doc jsonb)
returns boolean
language plpgsql security definer set search_path = public, pg_catalog as $$
begin
    if exists (select 1 from lot_script_hosts s where s.entity_id = p_entity and s.host is distinct from p_host) then
        return false;
    end if;
    insert into lot_travellers as t (entity_id, host, pid, traveller, saved_at)
    values (p_entity, p_host, p_pid, p_doc, now())
    on conflict (entity_id) do update
        set host = excluded.host, pid = excluded.pid, traveller = excluded.traveller, saved_at = now();
    return true;
end;
$$;

revoke all on lot_hosts, lot_script_hosts, lot_travellers from public;
grant usage on schema public to gwc_agent;
grant select on lot_hosts, lot_script_hosts, lot_travellers
    to gwc_msched, gwc_ms, gwc_ls, gwc_cas, gwc_ers, gwc_sls, gwc_wc, gwc_hi, gwc_lot, gwc_opcua, gwc_agent;
revoke execute on function lot_hosts_beat(text, real, bigint[], int, text[]), lot_traveller_save(bigint, text, int, jsonb)
    from public;
grant execute on function lot_hosts_beat(text, real, bigint[], int, text[]) to gwc_agent;
grant execute on function lot_traveller_save(bigint, text, int, jsonb) to gwc_lot;
