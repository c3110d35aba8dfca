-- Issue 42, the rest of the thesis. Idempotent: safe to run again (docs/schema.md describes each).

-- 1.4.5: "taking the appropriate actions necessary for the given alarm". What the Cell Alarm Server
-- does when an alarm is raised, besides recording it: shut the alarm's machine down, page the operator.
alter table alarm_description add column if not exists actions text[] not null default '{}';
alter table alarm_description drop constraint if exists alarm_description_actions_check;
alter table alarm_description add constraint alarm_description_actions_check
    check (actions <@ array['shutdown', 'page']::text[]);
-- What it did for each alarm, as it did it (null: nothing to do).
alter table alarms add column if not exists actions_taken text;

-- Listing 3's MESTRT_FAIL ("See Error Log"): a machine that refuses to start raises it (3.2.2).
insert into alarm_description (alarm_id, alarm_text, severity, actions) values
    ('MESTRT_FAIL', 'A machine refused to start (homing failed, the machine silent): see its error log',
     'error', '{page}')
on conflict do nothing;

-- 1.4.2: the Machine Server keeps track of scraps. A part is scrap by its lot's verdict (a lot script
-- decides: mill_and_measure after three millings), not by a failed run: each report, once per
-- (run, machine, entity), adds its parts to machine_status.scrap_count. Owned by the MS.
create table if not exists scrap_reports (
    machine_run_id bigint not null,
    machine_id     text not null references me_config,
    entity_id      bigint not null,
    parts          int not null check (parts > 0),
    reason         text,
    reported_at    timestamptz not null default now(),
    primary key (machine_run_id, machine_id, entity_id)
);
-- (030_roles.sql made the roles and granted reads of the tables it saw; this table is newer.)
grant select on scrap_reports
    to gwc_msched, gwc_ms, gwc_ls, gwc_cas, gwc_ers, gwc_sls, gwc_wc, gwc_hi, gwc_lot, gwc_opcua;
grant insert, update, delete on scrap_reports to gwc_ms;

-- Figures 6.2 and 6.3: a customer's address (Customer Entry) and a work order's due date (Work Order
-- Entry), shown as the Due Time of Work Order Status (Figure 6.6). Owned by the HI.
alter table customers add column if not exists address text;
alter table customers add column if not exists city text;
alter table customers add column if not exists state text;
alter table customers add column if not exists zip text;
alter table work_orders add column if not exists due_at timestamptz;
