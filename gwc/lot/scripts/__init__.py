"""The lot scripts shipped with the cell (registered in sql/900_seed.sql's LOT_SCRIPTS)."""
