-- The cell's tables, named as the thesis names them (lowercase). Idempotent: safe to run again.
-- Statuses and states are spelled exactly as gwc/ipc/codes.py (MachineStatus, LotState) spells them.
-- Owners (who may write) are set in 030_roles.sql; docs/schema.md describes every table.

-- Machines ------------------------------------------------------------------------------------

create table if not exists me_config (
    machine_id  text primary key check (machine_id <> ''),
    kind        text not null check (kind in ('dummy', 'cmm')),
    description text,
    liveness_s  real not null default 3 check (liveness_s > 0)
);

create table if not exists op_types (
    op_type     text primary key check (op_type <> ''),
    description text
);

create table if not exists machine_status (
    machine_id             text primary key references me_config,
    status                 text not null check (status in ('Shutdown', 'Idle', 'Setup', 'Running',
                                                           'Setup_Shut', 'Run_Shut')),
    recipe_id              text,
    machine_run_id         bigint,
    start_time             timestamptz,
    end_time               timestamptz,
    note                   text,
    updated_at             timestamptz not null default now(),
    runs_since_maintenance int not null default 0 check (runs_since_maintenance >= 0),
    scrap_count            int not null default 0 check (scrap_count >= 0),
    maintenance_every      int check (maintenance_every > 0)
);

-- What each machine accepts right now (its WC tells MSCHED; MSCHED writes it).
create table if not exists accept_types (
    machine_id text not null references me_config,
    op_type    text not null references op_types,
    primary key (machine_id, op_type)
);

-- Recipes -------------------------------------------------------------------------------------

create table if not exists recipes (
    recipe_id   text primary key check (recipe_id <> ''),
    description text
);

create table if not exists recipe_versions (
    recipe_id  text not null references recipes,
    version    int not null check (version > 0),
    content    bytea not null,
    checksum   text not null check (checksum ~ '^[0-9a-f]{64}$'),  -- sha256 of content, hex
    approved   boolean not null default false,
    created_at timestamptz not null default now(),
    created_by text,
    note       text,
    primary key (recipe_id, version)
);
-- At most one approved version per recipe.
create unique index if not exists recipe_versions_one_approved on recipe_versions (recipe_id) where approved;

create table if not exists op_machine_recipe (
    machine_id text not null references me_config,
    recipe_id  text not null references recipes,
    op_type    text not null references op_types,
    primary key (machine_id, recipe_id, op_type)
);

-- Orders and lots -----------------------------------------------------------------------------

create table if not exists customers (
    customer_id text primary key check (customer_id <> ''),
    name        text
);

create table if not exists lot_scripts (
    script_id   text primary key check (script_id <> ''),
    path        text not null check (path <> ''),
    description text
);

create table if not exists products (
    product_id  text primary key check (product_id <> ''),
    description text,
    script_id   text references lot_scripts,
    lot_type    text
);

create table if not exists work_orders (
    work_order_id bigint primary key,
    customer_id   text references customers,
    created_at    timestamptz not null default now(),
    note          text
);

create table if not exists work_order_items (
    work_order_id bigint not null references work_orders,
    product_id    text not null references products,
    quantity      int not null check (quantity > 0),
    primary key (work_order_id, product_id)
);

create table if not exists lots (
    lot_id        bigint primary key,
    lot_type      text,
    work_order_id bigint references work_orders,
    product_id    text references products,
    quantity      int not null default 1 check (quantity > 0),
    priority      int not null default 20,
    owner         text,
    script_id     text references lot_scripts,
    result_params text[],
    created_at    timestamptz not null default now()
);

create table if not exists lot_entities (
    entity_id        bigint primary key,
    lot_id           bigint not null references lots,
    unit             int check (unit > 0),
    parent_entity_id bigint references lot_entities check (parent_entity_id <> entity_id),
    created_at       timestamptz not null default now(),
    destroyed_at     timestamptz,
    unique (entity_id, lot_id)  -- target of lot_status's consistency key
);
create index if not exists lot_entities_lot on lot_entities (lot_id);

-- The CREATE_LOT request (its request_id) that made each entity: a repeated request finds them.
alter table lot_entities add column if not exists create_request text;
create index if not exists lot_entities_create_request on lot_entities (create_request)
    where create_request is not null;

create table if not exists lot_status (
    entity_id  bigint primary key,
    lot_id     bigint not null,
    state      text not null check (state in ('created', 'waiting_import', 'imported', 'waiting_machine',
                                              'running', 'completed', 'waiting_export', 'exported', 'failed')),
    reason     text,
    script_pid int check (script_pid > 0),
    updated_at timestamptz not null default now(),
    -- the entity exists and belongs to this lot
    foreign key (entity_id, lot_id) references lot_entities (entity_id, lot_id)
);
create index if not exists lot_status_lot on lot_status (lot_id);
-- 'held': a run in doubt past its bound, the entity held for the operator's release (issue 22).
alter table lot_status drop constraint if exists lot_status_state_check;
alter table lot_status add constraint lot_status_state_check check (state in (
    'created', 'waiting_import', 'imported', 'waiting_machine', 'running', 'held', 'completed', 'waiting_export',
    'exported', 'failed'));

-- The entities that may still use a machine: not destroyed, with a lot status that is not finished.
-- MSCHED never binds a request of any other, and its sweep ends their queued requests.
create or replace view live_entities as
    select s.entity_id from lot_status s join lot_entities e on e.entity_id = s.entity_id
    where e.destroyed_at is null and s.state not in ('completed', 'waiting_export', 'exported', 'failed');

-- Scheduling ----------------------------------------------------------------------------------

-- One row per machine a request asks for; seq is the arrival order FIFO scheduling follows.
create table if not exists request_machines (
    request_key  bigint not null,
    entity_id    bigint not null references lot_entities,
    machine_id   text not null references me_config,
    op_type      text not null references op_types,
    priority     int not null default 20,
    requested_at timestamptz not null default clock_timestamp(),
    seq          bigserial,
    reply_to     text,   -- the bus module to answer when the request is filled
    reply_conv   text,   -- the bus conversation to answer in
    primary key (request_key, machine_id)
);
create index if not exists request_machines_seq on request_machines (seq);
create index if not exists request_machines_machine on request_machines (machine_id);
create index if not exists request_machines_entity on request_machines (entity_id);

-- machine_id is the key: a machine can never be reserved twice.
create table if not exists reserved_machines (
    machine_id     text primary key references me_config,
    entity_id      bigint not null references lot_entities,
    machine_run_id bigint not null,
    request_key    bigint not null,
    reserved_at    timestamptz not null default now()
);
create index if not exists reserved_machines_entity on reserved_machines (entity_id);
-- MSCHED finds a repeated Machine_Request (a step retried after a lost commit) by its conversation,
-- and walks the requests of a freed machine oldest first (the FIFO scheduling pass).
create index if not exists request_machines_conv on request_machines (reply_conv);
-- The policy's order of a request, set when it is queued (MSCHED sets it again at start when the
-- policy or its ageing changed): FIFO 0 (so seq decides), priority its priority plus its arrival
-- time in ageing steps (gwc/msched/policy.py). The scheduling pass walks (machine_id, rank, seq)
-- in order and stops after a few matches, for both policies.
alter table request_machines add column if not exists rank double precision not null default 0;
create index if not exists request_machines_machine_rank on request_machines (machine_id, rank, seq);
-- (machine_id) and (machine_id, seq) are prefixes or orders the index above serves.
drop index if exists request_machines_machine_seq;
drop index if exists request_machines_machine;
-- Every row carries its request's 'machine:op_type' pairs, so the scheduling pass tells whether a
-- request can be bound from one row (slots <@ the free, accepting pairs) instead of joining its rows.
alter table request_machines add column if not exists slots text[];
update request_machines q set slots = (select array_agg(u.machine_id || ':' || u.op_type order by u.seq)
                                       from request_machines u where u.request_key = q.request_key)
    where q.slots is null;

-- MSCHED's decided requests whose Machine_Req_Comp the entity has not acknowledged yet. A request
-- leaves request_machines in the transaction that writes its row here, so after a crash MSCHED
-- resends exactly these answers and never decides a request twice. held: NO_MACHINE (a machine of
-- the request shut down) not told yet, because the entity still has a live alternative queued.
create table if not exists request_outcomes (
    request_key    bigint primary key,
    entity_id      bigint not null,
    op_type        text not null,
    machines       text[] not null,
    ack_code       text not null check (ack_code in ('ACK_OK', 'NO_MACHINE', 'REQ_CANCEL')),
    machine_run_id bigint,
    note           text,
    held           boolean not null default false check (not held or ack_code = 'NO_MACHINE'),
    reply_to       text,
    reply_conv     text,
    decided_at     timestamptz not null default clock_timestamp(),
    check ((ack_code = 'ACK_OK') = (machine_run_id is not null))
);
create index if not exists request_outcomes_entity on request_outcomes (entity_id);
-- Machine_Request.alt_group: an entity's requests with the same alt_group are alternatives of one
-- need. MSCHED remembers each group it bound until the entity finishes, so an alternative arriving
-- after its group was served is answered REQ_CANCEL instead of queued (BUG-6).
alter table request_machines add column if not exists alt_group text;
create table if not exists satisfied_alt_groups (
    entity_id   bigint not null,
    alt_group   text not null,
    request_key bigint not null,  -- the request of the group that was bound
    bound_at    timestamptz not null default clock_timestamp(),
    primary key (entity_id, alt_group)
);

create table if not exists machine_run_result (
    machine_run_id bigint not null,
    machine_id     text not null references me_config,
    param          text not null,
    value          text,
    recorded_at    timestamptz not null default now(),
    primary key (machine_run_id, machine_id, param)
);

-- How each run ended on each machine, written by its WC with the results and before it goes Idle:
-- a lot that missed the Run_Complete broadcast (the WC died before sending it) reads it here.
create table if not exists machine_run_outcome (
    machine_run_id bigint not null,
    machine_id     text not null references me_config,
    ack_code       text not null check (ack_code <> ''),
    note           text,
    ended_at       timestamptz not null default clock_timestamp(),
    primary key (machine_run_id, machine_id)
);

-- Alarms --------------------------------------------------------------------------------------

create table if not exists alarm_description (
    alarm_id   text primary key check (alarm_id <> ''),
    alarm_text text not null,
    severity   text not null default 'warning' check (severity in ('note', 'warning', 'error'))
);

-- The alarm history; pending = cleared_at is null. alarm_id is not a foreign key: alarms the
-- ALARM_DESCRIPTION table does not know are recorded too (known = false).
create table if not exists alarms (
    alarm_no   bigint primary key,
    alarm_id   text,
    known      boolean not null,
    machine_id text,
    alarm_text text not null,
    raised_by  text not null,
    raised_at  timestamptz not null default now(),
    cleared_by text,
    cleared_at timestamptz,
    check ((cleared_at is null) = (cleared_by is null)),
    check (not known or alarm_id is not null)
);
create index if not exists alarms_pending on alarms (alarm_no) where cleared_at is null;

-- Ids -----------------------------------------------------------------------------------------

create table if not exists max_values (
    type  text primary key,
    value bigint not null
);
