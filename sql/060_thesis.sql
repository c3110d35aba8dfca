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
