-- The NJIT cell: its machines, operation types, alarms, recipes, customer, lot scripts, products.
-- Idempotent: existing rows are left alone (on conflict do nothing), so an operator's changes survive.
-- Names follow the thesis's listings: cmm_wc and op type alum_chess (Listing 1), lot type CMM_LOT,
-- the homing alarm "Push the start button on the CMM" (Listing 3).

insert into me_config (machine_id, kind, description, liveness_s) values
    ('cmm_wc', 'cmm',   'Coordinate Measuring Machine on RS-232 (Listing 3, CMM_WC)', 3),
    ('wc1',    'dummy', 'dummy machine 1', 3),
    ('wc2',    'dummy', 'dummy machine 2', 3),
    ('wc3',    'dummy', 'dummy machine 3', 3),
    ('wc4',    'dummy', 'dummy machine 4', 3),
    ('wc5',    'dummy', 'dummy machine 5', 3),
    ('wc6',    'dummy', 'dummy machine 6', 3),
    ('mazak',  'dummy', 'the Mazak mill (simulated by a dummy machine)', 3)
on conflict do nothing;

insert into machine_status (machine_id, status)
    select machine_id, 'Shutdown' from me_config
on conflict do nothing;

insert into op_types (op_type, description) values
    ('alum_chess',  'measure the aluminium chess pieces on the CMM (Listing 1)'),
    ('brass_chess', 'measure the brass chess pieces on the CMM'),
    ('mill_chess',  'mill a chess piece'),
    ('measure',     'measure a part'),
    ('dummy_op',    'an operation of a dummy machine')
on conflict do nothing;

insert into alarm_description (alarm_id, alarm_text, severity) values
    ('HOME_CMM',  'Push the start button on the CMM', 'warning'),
    ('ME_DIED',   'The machine side (ME) stopped answering its WC', 'error'),
    ('MACH_LOST', 'The machine stopped answering its ME (line lost, hung or powered off): Shutdown until it answers again', 'error'),
    ('WC_SILENT', 'The machine''s WC has gone silent (liveness): machine marked Shutdown', 'error'),
    ('MAINT_DUE', 'Maintenance is due on the machine', 'warning'),
    ('RUN_FAIL',  'The machine reported a failed run', 'error'),
    ('REC_INVAL', 'Recipe unknown, not for this machine or op type, or its checksum is wrong', 'error'),
    ('MODULE_FATAL', 'A module failed at every start: its host''s agent left it down', 'error'),
    ('DB_DOWN',   'The cell database was away longer than the cell rides out unnoticed', 'error')
on conflict do nothing;

insert into recipes (recipe_id, description) values
    ('alum_chess_set', 'CMM program: measure an aluminium chess set'),
    ('mill_pawn',      'mill a pawn'),
    ('dummy_recipe',   'what a dummy machine runs')
on conflict do nothing;

-- Version 1 of each, approved, with the sha256 of its content computed here so it is right.
insert into recipe_versions (recipe_id, version, content, checksum, approved, created_by, note)
    select recipe_id, 1, c, encode(sha256(c), 'hex'), true, 'seed', 'shipped with the cell'
    from (values
        ('alum_chess_set', convert_to(E'# alum_chess_set v1: CMM part program\n'
                                      || E'PART alum_chess_set\nHOME\n'
                                      || E'MEASURE king queen bishop knight rook pawn\n'
                                      || E'TOLERANCE 0.05 mm\nREPORT PASS_FAIL\n', 'UTF8')),
        ('mill_pawn',      convert_to(E'# mill_pawn v1\nSTOCK alum_bar 25mm\nPROFILE pawn\nFEED 120\n', 'UTF8')),
        ('dummy_recipe',   convert_to(E'# dummy_recipe v1\nRUN\n', 'UTF8'))
    ) as v (recipe_id, c)
on conflict do nothing;

insert into op_machine_recipe (machine_id, recipe_id, op_type)
    select 'cmm_wc', 'alum_chess_set', 'alum_chess'
    union all
    select machine_id, 'mill_pawn', 'mill_chess' from me_config
        where machine_id in ('mazak', 'wc1', 'wc2', 'wc3', 'wc4', 'wc5', 'wc6')
    union all
    select machine_id, 'dummy_recipe', op from me_config, (values ('dummy_op'), ('measure')) as o (op)
        where kind = 'dummy'
on conflict do nothing;

insert into customers (customer_id, name) values
    ('NJIT', 'New Jersey Institute of Technology')
on conflict do nothing;

insert into lot_scripts (script_id, path, description) values
    ('chess',            'gwc/lot/scripts/chess.py',            'measure a chess set on the CMM (Listing 1)'),
    ('mill_and_measure', 'gwc/lot/scripts/mill_and_measure.py', 'mill a part, then measure it')
on conflict do nothing;

insert into products (product_id, description, script_id, lot_type) values
    ('alum_chess_set', 'aluminium chess set, measured on the CMM', 'chess',            'CMM_LOT'),
    ('milled_pawn',    'a milled and measured pawn',              'mill_and_measure', null)
on conflict do nothing;

insert into max_values (type, value) values
    ('MACH_R_KEY', 0), ('MACH_R_ID', 0), ('ENTITY_ID', 0), ('LOT_ID', 0), ('WORK_ORDER', 0), ('ALARM_NO', 0)
on conflict do nothing;
