-- get_new_max_value: the thesis's id generator over MAX_VALUES, one counter per type
-- (MACH_R_KEY, MACH_R_ID, ENTITY_ID, LOT_ID, WORK_ORDER, ALARM_NO).
--
-- The upsert takes the counter row's lock, so concurrent callers queue on it and each gets the
-- next value; the lock is held until the caller's transaction ends, so values are strictly
-- increasing in commit order and a rolled-back caller gives its value back (no gaps, unlike a
-- sequence). Keep transactions that call it short. SECURITY DEFINER: module roles have no write
-- privilege on max_values and need none.

create or replace function get_new_max_values(p_type text, p_count int) returns bigint
language plpgsql
security definer
set search_path = public, pg_temp
as $$
declare
    v bigint;
begin
    if p_type is null or p_type = '' then
        raise exception 'get_new_max_value: type must be given' using errcode = 'invalid_parameter_value';
    end if;
    if p_count is null or p_count < 1 then
        raise exception 'get_new_max_values: count must be at least 1' using errcode = 'invalid_parameter_value';
    end if;
    insert into max_values as m (type, value) values (p_type, p_count)
        on conflict (type) do update set value = m.value + p_count
        returning m.value into v;
    return v;
end;
$$;

-- get_new_max_values(type, n): n values at once (MSCHED's machine_run_ids of one pass), one row
-- update; the caller's are last - n + 1 .. last, where last is what it returns.
create or replace function get_new_max_value(p_type text) returns bigint
language plpgsql
security definer
set search_path = public, pg_temp
as $$ begin return get_new_max_values(p_type, 1); end $$;

revoke all on function get_new_max_value(text) from public;
revoke all on function get_new_max_values(text, int) from public;

-- msched_analyze(): MSCHED's scheduling pass walks an index and stops after a few matches; the
-- planner takes that path only when it knows how many requests a machine has. A queue that grew
-- from nothing to thousands within autovacuum's minute was planned as if empty (a pass read every
-- request of each machine: 105 ms instead of 4 for 100 freed machines). MSCHED calls this at start
-- and in its periodic sweep; it analyzes the queue only when much of it changed since the last time.
-- SECURITY DEFINER: only a table's owner may analyze it.
create or replace function msched_analyze() returns boolean
language plpgsql
security definer
set search_path = public, pg_temp
as $$
declare
    stale boolean;
begin
    select n_mod_since_analyze > 200 + 0.2 * greatest(n_live_tup, 0) into stale
        from pg_stat_user_tables where relid = 'request_machines'::regclass;
    if coalesce(stale, true) then
        analyze request_machines;
        return true;
    end if;
    return false;
end;
$$;
revoke all on function msched_analyze() from public;

-- msched_walk(machines, up, per): the scheduling pass's index walk, the one both msched_pass
-- (sql/096_sched_pass.sql, each of its rounds) and msched_candidates read. For each of the machines
-- (null: all), the first `per` queued requests in the policy's order (request_machines (machine_id,
-- rank, seq)) whose every 'machine:op_type' slot is usable (the machine's status is in `up`, it is
-- not reserved and it accepts the op type), of live entities; each row names the machine it was
-- found under (`found_on`, a request of two machines may be found under both) and how many that
-- machine gave (`found`: fewer than `per` means its walk reached the end of its queue). The walk of
-- the index stops after `per` matches, so a freed machine costs a few index probes however long the
-- queue. The SET clauses make that walk the plan whatever the statistics say: with a queue grown
-- faster than autovacuum analyzes it, PostgreSQL sorted every request of each machine instead (105
-- ms for 100 freed machines with 10,000 queued, against about 4). PL/pgSQL and a generic plan, so
-- that a session plans the query once: a LANGUAGE sql function with SET clauses is planned at every
-- call, which cost 0.55 ms of each 0.63 ms call.
create or replace function msched_walk(p_machines text[], p_up text[], p_per int)
returns table (request_key bigint, entity_id bigint, op_type text, priority int, seq bigint,
               requested_at timestamptz, slots text[], rank double precision, found_on text, found bigint)
language plpgsql
stable
set enable_sort = off
set enable_bitmapscan = off
set enable_seqscan = off
set jit = off
set plan_cache_mode = force_generic_plan
as $$
#variable_conflict use_column
begin
    return query
    with usable (slots) as materialized (
        select coalesce(array_agg(s.machine_id || ':' || a.op_type), '{}')
        from machine_status s join accept_types a on a.machine_id = s.machine_id
        where s.status = any (p_up)
          and not exists (select 1 from reserved_machines r where r.machine_id = s.machine_id)
    )
    select c.request_key, c.entity_id, c.op_type, c.priority, c.seq, c.requested_at, c.slots, c.rank,
           t.machine_id, count(*) over (partition by t.i)
    from usable, unnest(coalesce(p_machines, array(select machine_id from me_config)))
         with ordinality as t (machine_id, i)
    cross join lateral (
        select q.request_key, q.entity_id, q.op_type, q.priority, q.seq, q.requested_at, q.slots, q.rank
        from request_machines q
        where q.machine_id = t.machine_id
          and q.slots <@ usable.slots
          and exists (select 1 from live_entities l where l.entity_id = q.entity_id)
        order by q.rank, q.seq
        limit p_per
    ) c;
end
$$;
revoke all on function msched_walk(text[], text[], int) from public;

-- msched_candidates(machines, up, per): one round of the pass's walk (msched_walk), for the store's
-- Store.candidates() and tools; the scheduler itself runs msched_pass.
drop function if exists msched_candidates(text[], text[], int);  -- its parameters were renamed
create function msched_candidates(p_machines text[], p_up text[], p_per int)
returns table (request_key bigint, entity_id bigint, op_type text, priority int, seq bigint,
               requested_at timestamptz, slots text[])
language sql
stable
as $$
    select w.request_key, w.entity_id, w.op_type, w.priority, w.seq, w.requested_at, w.slots
    from msched_walk(p_machines, p_up, p_per) w
$$;
