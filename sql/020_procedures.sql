-- get_new_max_value: the thesis's id generator over MAX_VALUES, one counter per type
-- (MACH_R_KEY, MACH_R_ID, ENTITY_ID, LOT_ID, WORK_ORDER, ALARM_NO).
--
-- The upsert takes the counter row's lock, so concurrent callers queue on it and each gets the
-- next value; the lock is held until the caller's transaction ends, so values are strictly
-- increasing in commit order and a rolled-back caller gives its value back (no gaps, unlike a
-- sequence). Keep transactions that call it short. SECURITY DEFINER: module roles have no write
-- privilege on max_values and need none.

create or replace function get_new_max_value(p_type text) returns bigint
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
    insert into max_values as m (type, value) values (p_type, 1)
        on conflict (type) do update set value = m.value + 1
        returning m.value into v;
    return v;
end;
$$;

revoke all on function get_new_max_value(text) from public;
