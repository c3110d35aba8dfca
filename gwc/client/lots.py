"""The Lot Server's divide, merge and destroy (thesis 1.4.4: "the creation of entities, division of
entities, merger of entities, and the destruction of entities"), for the HI and any tool: DIV_MERGE
and ENTITY_REQ destroy, asked of the Lot Server, the one writer of the lots' tables. The
conversations are the lot library's (gwc/lot/holdings.py), as create_lot is; the rules are the Lot
Server's (docs/servers.md, *Lot Server*)."""

from __future__ import annotations

from gwc.lot.holdings import destroy_entity, divide_entity, merge_entities

__all__ = ["destroy_entity", "divide_entity", "merge_entities"]
