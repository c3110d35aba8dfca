-- Redundant modules (issue 36): which instance of a singleton module is the active one.
-- Idempotent: safe to run again. docs/reliability.md (Active and standby modules) tells the rules.
--
-- A module that runs with standbys holds a session advisory lock (classid 36036, objid the hash of
-- its name) on the connection it does all its work through, and a row here. The lock says that the
-- holder's session is alive; the row says who holds it (`holder`), since when (`epoch`, one more at
-- every takeover) and how recently it proved itself alive (`renewed_at`, the server's clock). A
-- standby takes the lease when the lock is free, or, when the row has not been renewed for the
-- lease's `ttl`, after terminating the holder's backend: the deposed instance's session is then gone,
-- and with it every write it could still make.

create table if not exists module_leases (
    name        text primary key check (name <> ''),
    epoch       bigint not null default 1 check (epoch > 0),
    holder      text not null,                  -- host:pid:token of the active instance
    host        text,                           -- the cell host it runs on (null in a one-host cell)
    backend_pid int,                            -- its database session, terminated on a takeover
    ttl_s       real not null check (ttl_s > 0),
    server      timestamptz,                    -- pg_postmaster_start_time() of the server it renewed on
    taken_at    timestamptz not null default now(),
    renewed_at  timestamptz not null default now()
);

-- Every takeover, kept for the operator (gwc lease, docs/operating.md) and the failover benchmark.
create table if not exists lease_takeovers (
    takeover_no bigint generated always as identity primary key,
    name        text not null,
    epoch       bigint not null,
    holder      text not null,
    host        text,
    previous    text,                           -- the holder it took over from, null for the first
    how         text not null check (how in ('first', 'free', 'expired', 'again')),
    at          timestamptz not null default now()
);
create index if not exists lease_takeovers_name on lease_takeovers (name, takeover_no);

-- The lease's lock key: (36036, hashtext(name)), shown in pg_locks as classid, objid, objsubid 2.
create or replace function lease_key(p_name text) returns oid
language sql immutable as $$ select (hashtext(p_name)::bigint & 4294967295)::oid $$;

-- Terminate the session holding an EXPIRED lease's lock (a holder cut off, or stalled, with its TCP
-- connection still open): the only way to take a lease from a live session. Security definer, so a
-- module's role may end another session of the cell, but only this one and only once its lease is
-- past its ttl. Returns the sessions ended.
create or replace function lease_fence(p_name text) returns int
language plpgsql security definer set search_path = public, pg_catalog as $$
declare
    r record;
    n int := 0;
begin
    if not exists (select 1 from module_leases m
                   where m.name = p_name and now() - m.renewed_at > make_interval(secs => m.ttl_s)) then
        return 0;
    end if;
    for r in select l.pid from pg_locks l
             where l.locktype = 'advisory' and l.classid = 36036 and l.objid = lease_key(p_name)
               and l.objsubid = 2 and l.granted and l.pid <> pg_backend_pid() loop
        perform pg_terminate_backend(r.pid, 5000);  -- waits (up to 5 s) until the session is gone
        n := n + 1;
    end loop;
    return n;
end;
$$;

-- One try at the lease, by the instance `p_holder`, which holds epoch `p_epoch` (0: none yet, a
-- standby). Answers the epoch, the holder and how: 'first', 'free' (its holder's session is gone),
-- 'expired' (its holder was fenced), 'again' (the same instance after a reconnect: its epoch is
-- unchanged), 'held' (someone else holds it: stand by) or 'deposed' (p_epoch was taken over).
-- The session lock it takes is the caller's session's, on the caller's connection. Security definer:
-- MODULE_LEASES and LEASE_TAKEOVERS are written only through these functions (no role may write
-- them directly: one writer per table, thesis 5.1).
create or replace function lease_claim(p_name text, p_holder text, p_host text, p_ttl real, p_epoch bigint)
returns table (epoch bigint, holder text, how text)
language plpgsql security definer set search_path = public, pg_catalog as $$
declare
    cur module_leases;
    key int := hashtext(p_name);
    fresh boolean;
    outcome text;
begin
    if not pg_try_advisory_lock(36036, key) then
        perform lease_fence(p_name);  -- ends the holder's session if its lease expired: next try takes it
        select * into cur from module_leases m where m.name = p_name;
        return query select coalesce(cur.epoch, 0::bigint), coalesce(cur.holder, ''),
                            (case when p_epoch > 0 then 'deposed' else 'held' end)::text;
        return;
    end if;
    select * into cur from module_leases m where m.name = p_name for update;
    if found and p_epoch > 0 and (cur.holder <> p_holder or cur.epoch <> p_epoch) then
        perform pg_advisory_unlock(36036, key);
        return query select cur.epoch, cur.holder, 'deposed'::text;
        return;
    end if;
    fresh := found and now() - cur.renewed_at <= make_interval(secs => cur.ttl_s);
    if found and cur.holder <> p_holder and fresh
       and cur.server is distinct from pg_postmaster_start_time() then
        -- Renewed on another server (the database failed over since): the lock here says nothing
        -- about its holder, who may be reconnecting. Wait for it, or for the lease to expire.
        perform pg_advisory_unlock(36036, key);
        return query select cur.epoch, cur.holder, 'held'::text;
        return;
    end if;
    if not found then
        outcome := 'first';
        insert into module_leases (name, epoch, holder, host, backend_pid, ttl_s, server)
        values (p_name, 1, p_holder, p_host, pg_backend_pid(), p_ttl, pg_postmaster_start_time())
        returning * into cur;
    elsif cur.holder = p_holder and cur.epoch = p_epoch then
        outcome := 'again';
        update module_leases m set backend_pid = pg_backend_pid(), ttl_s = p_ttl, renewed_at = now(),
                                   server = pg_postmaster_start_time()
        where m.name = p_name returning * into cur;
    else
        outcome := case when fresh then 'free' else 'expired' end;
        insert into lease_takeovers (name, epoch, holder, host, previous, how)
        values (p_name, cur.epoch + 1, p_holder, p_host, cur.holder, outcome);
        update module_leases m set epoch = cur.epoch + 1, holder = p_holder, host = p_host,
                                   backend_pid = pg_backend_pid(), ttl_s = p_ttl, taken_at = now(),
                                   renewed_at = now(), server = pg_postmaster_start_time()
        where m.name = p_name returning * into cur;
        return query select cur.epoch, cur.holder, outcome;
        return;
    end if;
    if outcome = 'first' then
        insert into lease_takeovers (name, epoch, holder, host, previous, how)
        values (p_name, 1, p_holder, p_host, null, 'first');
    end if;
    return query select cur.epoch, cur.holder, outcome;
end;
$$;

-- The holder proves itself alive, through the session that holds the lock. No row: deposed.
create or replace function lease_renew(p_name text, p_holder text, p_epoch bigint) returns boolean
language sql security definer set search_path = public, pg_catalog as $$
    update module_leases set renewed_at = now(), server = pg_postmaster_start_time()
    where name = p_name and holder = p_holder and epoch = p_epoch and backend_pid = pg_backend_pid()
    returning true
$$;

grant select on module_leases, lease_takeovers
    to gwc_msched, gwc_ms, gwc_ls, gwc_cas, gwc_ers, gwc_sls, gwc_wc, gwc_hi, gwc_lot, gwc_opcua;
grant execute on function lease_key(text), lease_fence(text), lease_claim(text, text, text, real, bigint),
    lease_renew(text, text, bigint)
    to gwc_msched, gwc_ms, gwc_ls, gwc_cas, gwc_ers, gwc_sls, gwc_opcua;
revoke execute on function lease_fence(text), lease_claim(text, text, text, real, bigint),
    lease_renew(text, text, bigint) from public;
