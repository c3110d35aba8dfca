-- Issue 35, quality: measured features, statistical process control, run-to-run feedback
-- (docs/quality.md). Idempotent: safe to run again.

-- A recipe's features, read from its content: one line `FEATURE <name> <nominal> <tolerance>` each
-- (nominal +/- tolerance), and its feedback, `FEEDBACK EWMA <weight> STEP <limit> LIMIT <limit>`
-- (docs/quality.md). A view, so a feature is versioned and approved with the recipe that carries it
-- and nobody writes it but the ERS, which owns the content.
create or replace view recipe_features as
    select v.recipe_id, v.version, v.approved, m[1] as feature,
           m[2]::double precision as nominal, m[3]::double precision as tol
    from recipe_versions v,
         regexp_matches(encode(v.content, 'escape'),
                        '^FEATURE[ \t]+([A-Za-z][A-Za-z0-9_]*)[ \t]+([-+]?[0-9]+(?:\.[0-9]*)?)[ \t]+([0-9]+(?:\.[0-9]*)?)[ \t\r]*$',
                        'gn') as m;

create or replace view recipe_feedback as
    select v.recipe_id, v.version, v.approved,
           m[1]::double precision as weight, m[2]::double precision as step_limit,
           m[3]::double precision as total_limit
    from recipe_versions v,
         regexp_matches(encode(v.content, 'escape'),
                        '^FEEDBACK[ \t]+EWMA[ \t]+([0-9]*\.?[0-9]+)[ \t]+STEP[ \t]+([0-9]*\.?[0-9]+)[ \t]+LIMIT[ \t]+([0-9]*\.?[0-9]+)[ \t\r]*$',
                        'gn') as m;

-- One feature of one run: what a measuring run measured (measured), and what offset a making run
-- was given (offset_used, the run-to-run feedback's, stored with the run it was used in). workpiece:
-- the run that made the part (a measuring run's part, a re-milling's earlier milling). Written by the
-- WC of the machine with its results and outcome (the trigger below, in the WC's own statement).
create table if not exists run_features (
    machine_run_id bigint not null,
    machine_id     text not null references me_config,
    recipe_id      text not null,
    feature        text not null,
    measured       double precision,
    nominal        double precision not null,
    tol            double precision not null check (tol >= 0),
    offset_used    double precision,
    workpiece      bigint,
    in_tol         boolean generated always as (abs(measured - nominal) <= tol) stored,
    at             timestamptz not null default clock_timestamp(),
    primary key (machine_run_id, machine_id, feature)
);
create index if not exists run_features_chart on run_features (machine_id, recipe_id, feature, at);
create index if not exists run_features_workpiece on run_features (workpiece) where workpiece is not null;

-- A run's features from its results (param = feature name, `OFFSET.<feature>`, `WORKPIECE`), for the
-- features its recipe's approved version declares. A value that is not a number is left out (and the
-- results keep it as text): a bad value never costs the WC its results.
create or replace function quality_record_run() returns trigger language plpgsql as $$
declare
    rec text;
    piece bigint;
    num constant text := '^[-+]?[0-9]+(\.[0-9]*)?([eE][-+]?[0-9]+)?$';
begin
    select value into rec from machine_run_result
        where machine_run_id = new.machine_run_id and machine_id = new.machine_id and param = 'RECIPE';
    if rec is null or not exists (select 1 from recipe_versions where recipe_id = rec and approved) then
        return null;
    end if;
    select case when value ~ '^[0-9]{1,18}$' then value::bigint end into piece from machine_run_result
        where machine_run_id = new.machine_run_id and machine_id = new.machine_id and param = 'WORKPIECE';
    insert into run_features (machine_run_id, machine_id, recipe_id, feature, measured, nominal, tol,
                              offset_used, workpiece)
        select new.machine_run_id, new.machine_id, rec, f.feature, m.v, f.nominal, f.tol, o.v, piece
        from recipe_features f
        left join lateral (select case when r.value ~ num then r.value::double precision end as v
                           from machine_run_result r
                           where r.machine_run_id = new.machine_run_id and r.machine_id = new.machine_id
                             and r.param = f.feature) m on true
        left join lateral (select case when r.value ~ num then r.value::double precision end as v
                           from machine_run_result r
                           where r.machine_run_id = new.machine_run_id and r.machine_id = new.machine_id
                             and r.param = 'OFFSET.' || f.feature) o on true
        where f.recipe_id = rec and f.approved and (m.v is not null or o.v is not null)
    on conflict (machine_run_id, machine_id, feature) do update
        set measured = excluded.measured, offset_used = excluded.offset_used, workpiece = excluded.workpiece;
    return null;
exception when others then
    raise warning 'run % on %: features not recorded: %', new.machine_run_id, new.machine_id, sqlerrm;
    return null;
end;
$$;

drop trigger if exists machine_run_outcome_quality on machine_run_outcome;
create trigger machine_run_outcome_quality after insert or update on machine_run_outcome
    for each row when (new.ack_code = 'ACK_OK') execute function quality_record_run();

-- The operator's confirmation that a machine's tool was changed (`gwc tool change M`): the feedback's
-- offsets start again from zero after it, and the simulated mill's wear with it. Owned by the HI.
create table if not exists tool_changes (
    id           bigserial primary key,
    machine_id   text not null references me_config,
    changed_at   timestamptz not null default clock_timestamp(),
    confirmed_by text,
    note         text
);
create index if not exists tool_changes_machine on tool_changes (machine_id, changed_at);

-- The alarms quality raises: a control chart's rule broken (SPC_RULE), a tool worn out (TOOL_CHANGE:
-- the machine is shut down until the operator confirms the change).
insert into alarm_description (alarm_id, alarm_text, severity, actions) values
    ('SPC_RULE', 'A control chart broke a Western Electric rule: the process has moved', 'warning', '{page}'),
    ('TOOL_CHANGE', 'The tool is worn out (the feedback reached its limit): change it, then `gwc tool change`',
     'error', '{shutdown,page}')
on conflict do nothing;

grant select on recipe_features, recipe_feedback, run_features, tool_changes
    to gwc_msched, gwc_ms, gwc_ls, gwc_cas, gwc_ers, gwc_sls, gwc_wc, gwc_hi, gwc_lot, gwc_opcua;
grant insert, update on run_features to gwc_wc;
grant insert, update, delete on tool_changes to gwc_hi;
grant usage on sequence tool_changes_id_seq to gwc_hi;
