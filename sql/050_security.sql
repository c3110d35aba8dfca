-- Issue 40 (least privilege on the host): the alarms the cell raises when something on its host is
-- not its own. Idempotent like the seed: present rows are left as they are.

insert into alarm_description (alarm_id, alarm_text, severity) values
    ('IPC_FOREIGN', 'A WC<->ME message queue of the cell''s name exists that the cell did not make (another user''s, or open to others): refused, not used; the machine stays down until it is removed (gwc stop)', 'error')
on conflict do nothing;
