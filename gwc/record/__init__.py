"""The production record (issue 34, docs/record.md): planned time, timelines, downtime, OEE, genealogy."""
