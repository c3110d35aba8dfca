-- One database role per module: "no module writes another's tables" (thesis 5.1), enforced by the
-- server. Modules connect as the cluster's user and SET ROLE gwc_<module> (gwc.db.connect).
-- Every role reads every table; each table has one writer. Idempotent: privileges are reset, then
-- granted, in the one transaction gwc.db.init_schema runs this in.

do $$
declare
    r text;
begin
    foreach r in array array['gwc_msched', 'gwc_ms', 'gwc_ls', 'gwc_cas', 'gwc_ers', 'gwc_sls',
                             'gwc_wc', 'gwc_hi', 'gwc_lot', 'gwc_opcua'] loop
        if not exists (select 1 from pg_roles where rolname = r) then
            begin
                execute format('create role %I nologin', r);
            exception when duplicate_object then
                null;  -- another database of this cluster created it meanwhile
            end;
        end if;
        if not pg_has_role(current_user, r, 'MEMBER') then
            execute format('grant %I to %I', r, current_user);
        end if;
    end loop;
end;
$$;

revoke all on all tables in schema public
    from gwc_msched, gwc_ms, gwc_ls, gwc_cas, gwc_ers, gwc_sls, gwc_wc, gwc_hi, gwc_lot, gwc_opcua;
revoke all on all sequences in schema public
    from gwc_msched, gwc_ms, gwc_ls, gwc_cas, gwc_ers, gwc_sls, gwc_wc, gwc_hi, gwc_lot, gwc_opcua;

grant usage on schema public
    to gwc_msched, gwc_ms, gwc_ls, gwc_cas, gwc_ers, gwc_sls, gwc_wc, gwc_hi, gwc_lot, gwc_opcua;
grant select on all tables in schema public
    to gwc_msched, gwc_ms, gwc_ls, gwc_cas, gwc_ers, gwc_sls, gwc_wc, gwc_hi, gwc_lot, gwc_opcua;
grant execute on function get_new_max_value(text), get_new_max_values(text, int)
    to gwc_msched, gwc_ms, gwc_ls, gwc_cas, gwc_ers, gwc_sls, gwc_wc, gwc_hi, gwc_lot;
grant execute on function msched_analyze(), msched_walk(text[], text[], int), msched_candidates(text[], text[], int)
    to gwc_msched;

-- MSCHED: the request queue, the reservations, what machines accept now.
grant insert, update, delete on request_machines, reserved_machines, accept_types, request_outcomes,
    satisfied_alt_groups to gwc_msched;
grant usage on sequence request_machines_seq_seq to gwc_msched;
-- Machine Server: machine status (rows for machines that join, never deleted) and their config.
grant insert, update on machine_status, me_config to gwc_ms;
-- WC: the results of its runs, and how each ended.
grant insert, update, delete on machine_run_result, machine_run_outcome to gwc_wc;
-- Lot Server: lots, their entities, where each entity is.
grant insert, update, delete on lots, lot_entities, lot_status to gwc_ls;
-- Cell Alarm Server: the alarm history and the known alarms.
grant insert, update, delete on alarms, alarm_description to gwc_cas;
-- Equipment Recipe Server: recipes, their versions, which machine runs which for what.
grant insert, update, delete on recipes, recipe_versions, op_machine_recipe, op_types to gwc_ers;
-- Human Interface: orders, customers, and the products and lot scripts it registers.
grant insert, update, delete on work_orders, work_order_items, customers, products, lot_scripts to gwc_hi;
-- SLS, lot scripts (gwc_lot) and the OPC UA gateway (gwc_opcua) only read; they ask the owners over the bus.
