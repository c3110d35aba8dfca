"""The client layer: what the operator's tools do with the cell, written once.

The HI commands (gwc/hi), the demo, the soak driver, the benchmarks, the operator console and the
OPC UA gateway all enter orders, import and export lots, start and stop machines, cancel requests,
clear alarms, manage recipes and read the cell's tables. They do it through these functions, which
hold the conversations (or read the tables, which anyone may) and return data or raise GwcError with a
message saying what to do. Nothing here prints: the callers decide how to show the result.

    session   the HI's bus attachment and connection, waiting for a server, one-question conversations
    orders    work orders, lots (CREATE_LOT, IMPORT_LOT, EXPORT_LOT), customers, products, lot scripts
    machines  ME_START / ME_SHUT to a machine's WC, the machines' status
    alarms    ALARM_CLR_REQ, STATUS_LN, the alarm history
    requests  MSCHED's queue and reservations, CANCEL_RE
    recipes   RECIPE_PUT, RECIPE_APPR, the recipe library
"""
