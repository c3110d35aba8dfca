-- MSCHED's scheduling pass as one server-side function (issue 38, item 5). Idempotent.
--
-- A step of MSCHED (gwc/msched/store.py) was five to seven round trips to PostgreSQL: BEGIN, the
-- frees, forgetting acknowledged outcomes, then per round of the pass one msched_candidates and one
-- bind, and a last msched_candidates that found nothing, then COMMIT. On two cores shared by MSCHED,
-- PostgreSQL and the lots, each round trip is two process wake-ups and a statement's parse, bind and
-- executor start on the server. Here the whole greedy pass is one function (msched_pass), and the
-- step of the scheduler under load - frees, acknowledged outcomes, the pass - one statement
-- (msched_step), run alone in autocommit: PostgreSQL makes it atomic, so a decision is still
-- committed before MSCHED announces it, and a step costs one round trip. docs/performance.md (The
-- scheduler) has the figures.

-- msched_pass(machines, up, per): bind every queued request that can be bound now, touching one of
-- `machines` (null: every machine), greedily in the policy's order (rank, seq) - the order the
-- policy's rank_sql() stores with each request (gwc/msched/policy.py). Each round takes, per
-- machine still to look at, the first `per` requests whose every 'machine:op_type' slot is usable
-- (msched_walk, sql/020_procedures.sql: the one walk), binds greedily (a request whose machine an
-- earlier one took, or whose entity was served, is skipped), and repeats while a round binds
-- something, for the machines not taken whose walk stopped at `per`: a machine that gave fewer
-- reached the end of its queue, and nothing it did not give can become bindable within the pass
-- (machines are only taken in it, and a served entity's requests leave the queue), so walking it
-- again would only read its whole queue once more. Per request ended, the outcome MSCHED must tell
-- (bound ACK_OK, an alternative of a bound entity REQ_CANCEL, a held outcome of a bound entity
-- REQ_CANCEL). The pass's own statements (the candidates in order, the binding) keep the walk's
-- planner settings: the queue is read by its indexes whatever the statistics say. jit = off: the
-- one sort of the candidates (rank, seq) is priced at 10^10 by enable_sort = off, which took the
-- plan past jit_above_cost, and PostgreSQL JIT-compiled the query at each call (0.7 s).
create or replace function msched_pass(p_machines text[], p_up text[], p_per int)
returns table (request_key bigint, entity_id bigint, ack_code text, machines text[], machine_run_id bigint,
               note text, reply_to text, reply_conv text)
language plpgsql
volatile
set enable_sort = off
set enable_bitmapscan = off
set enable_seqscan = off
set jit = off
set plan_cache_mode = force_generic_plan
as $$
#variable_conflict use_column
declare
    v_trig text[] := p_machines;  -- null: every machine (the first round only)
    v_more text[];
    v_taken text[];
    v_ents bigint[];
    v_keys bigint[];
    v_mach text[];
    v_midx bigint[];
    v_ms text[];
    n int;
    c record;
begin
    loop
        exit when v_trig is not null and cardinality(v_trig) = 0;
        v_taken := '{}'; v_ents := '{}'; v_keys := '{}'; v_mach := '{}'; v_midx := '{}'; v_more := '{}'; n := 0;
        for c in
            select w.request_key, w.entity_id, w.found_on, w.found,
                   -- the request's machines, in the order it named them ('machine:op_type' slots)
                   array(select left(u.s, -length(w.op_type) - 1) from unnest(w.slots) with ordinality u (s, i)
                         order by u.i) as machines
            from msched_walk(v_trig, p_up, p_per) w
            order by w.rank, w.seq
        loop
            if c.found >= p_per then
                v_more := v_more || c.found_on;  -- its walk stopped at `per`: it may have more
            end if;
            continue when c.entity_id = any (v_ents);
            v_ms := c.machines;
            continue when v_ms && v_taken;
            n := n + 1;
            v_keys := v_keys || c.request_key;
            v_ents := v_ents || c.entity_id;
            v_taken := v_taken || v_ms;
            v_mach := v_mach || v_ms;
            v_midx := v_midx || array_fill(n::bigint, array[cardinality(v_ms)]);
        end loop;
        exit when n = 0;
        -- Bind the chosen ones in one statement (as gwc/msched/store.py did from the client): the
        -- machine_run_ids (one counter update for all); reserve; the bound request ends ACK_OK, the
        -- entity's other requests (its alternatives) REQ_CANCEL, and so do its held outcomes; a bound
        -- request's alt_group is remembered as satisfied. The CTEs share one snapshot, so the update
        -- sees only outcomes held before this statement.
        return query
        with ids (last) as materialized (select get_new_max_values('MACH_R_ID', n)),
        b (i, entity_id, bound_key, run_id) as (
            select u.i, u.entity_id, u.bound_key, ids.last - n + u.i
            from ids, unnest(v_ents, v_keys) with ordinality as u (entity_id, bound_key, i)),
        reserve as (
            insert into reserved_machines (machine_id, entity_id, machine_run_id, request_key)
            select m.machine_id, b.entity_id, b.run_id, b.bound_key
            from unnest(v_mach, v_midx) as m (machine_id, i) join b on b.i = m.i),
        gone as (
            delete from request_machines q using b where q.entity_id = b.entity_id
            returning q.request_key, q.entity_id, q.op_type, q.machine_id, q.seq, q.alt_group, q.reply_to,
                      q.reply_conv, b.bound_key, b.run_id),
        satisfied as (
            insert into satisfied_alt_groups (entity_id, alt_group, request_key)
            select distinct g.entity_id, g.alt_group, g.bound_key from gone g
            where g.request_key = g.bound_key and g.alt_group is not null
            on conflict do nothing),
        ended as (
            insert into request_outcomes (request_key, entity_id, op_type, machines, ack_code, machine_run_id,
                                          note, reply_to, reply_conv)
            select g.request_key, min(g.entity_id), min(g.op_type), array_agg(g.machine_id order by g.seq),
                   case when g.request_key = min(g.bound_key) then 'ACK_OK' else 'REQ_CANCEL' end,
                   case when g.request_key = min(g.bound_key) then min(g.run_id) end,
                   case when g.request_key = min(g.bound_key) then null
                        else 'alternative ' || min(g.bound_key) || ' satisfied' end,
                   min(g.reply_to), min(g.reply_conv)
            from gone g group by g.request_key
            returning request_outcomes.request_key, request_outcomes.entity_id, request_outcomes.ack_code,
                      request_outcomes.machines, request_outcomes.machine_run_id, request_outcomes.note,
                      request_outcomes.reply_to, request_outcomes.reply_conv),
        released as (
            update request_outcomes o set ack_code = 'REQ_CANCEL', held = false,
                   note = 'alternative ' || b.bound_key || ' satisfied'
            from b where o.held and o.entity_id = b.entity_id
            returning o.request_key, o.entity_id, o.ack_code, o.machines, o.machine_run_id, o.note, o.reply_to,
                      o.reply_conv)
        select * from ended union all select * from released;
        v_trig := array(select unnest(v_more) except select unnest(v_taken));
    end loop;
end
$$;

-- msched_step(free_entities, free_machines, finished, triggers, full, up, per): the step of MSCHED
-- under load in one statement. First the Unreserve_Me of the step (entity i frees free_machines[i],
-- or all its machines when that is null; a machine two frees name goes to the first, as one by
-- one), then the acknowledged outcomes `finished` are forgotten, then msched_pass over `triggers`
-- and the machines freed that someone waits for (every machine when `full`). Rows: one per machine
-- freed (kind 'freed', i = the free's 1-based index, machine_id), then one per outcome (kind 'outcome').
create or replace function msched_step(p_free_entities bigint[], p_free_machines text[], p_finished bigint[],
                                       p_triggers text[], p_full boolean, p_up text[], p_per int)
returns table (kind text, i int, machine_id text, request_key bigint, entity_id bigint, ack_code text,
               machines text[], machine_run_id bigint, note text, reply_to text, reply_conv text)
language plpgsql
volatile
set jit = off
set plan_cache_mode = force_generic_plan
as $$
#variable_conflict use_column
declare
    v_trig text[] := coalesce(p_triggers, '{}');
    r record;
begin
    if cardinality(p_finished) > 0 then
        delete from request_outcomes o where o.request_key = any (p_finished) and not o.held;
    end if;
    if cardinality(p_free_entities) > 0 then
        for r in
            with f (i, entity_id, machine_id) as (
                select u.i, u.entity_id, u.machine_id
                from unnest(p_free_entities, p_free_machines) with ordinality as u (entity_id, machine_id, i)),
            d as (
                select distinct on (rm.machine_id) rm.machine_id, f.i from reserved_machines rm join f
                on rm.entity_id = f.entity_id and (f.machine_id is null or rm.machine_id = f.machine_id)
                order by rm.machine_id, f.i)
            delete from reserved_machines rm using d where rm.machine_id = d.machine_id
            returning d.i, rm.machine_id,
                      exists (select 1 from request_machines q where q.machine_id = rm.machine_id) as waited_for
        loop
            kind := 'freed'; i := r.i; machine_id := r.machine_id;
            return next;
            if r.waited_for then
                v_trig := v_trig || r.machine_id;
            end if;
        end loop;
    end if;
    if p_full or cardinality(v_trig) > 0 then
        return query select 'outcome', null::int, null::text, p.*
            from msched_pass(case when p_full then null else v_trig end, p_up, p_per) p;
    end if;
end
$$;

revoke all on function msched_pass(text[], text[], int) from public;
revoke all on function msched_step(bigint[], text[], bigint[], text[], boolean, text[], int) from public;
grant execute on function msched_pass(text[], text[], int),
    msched_step(bigint[], text[], bigint[], text[], boolean, text[], int) to gwc_msched;

select schema_version_reached(2, 1, 'sql/096: msched_pass and msched_step, the scheduling pass in one call');
