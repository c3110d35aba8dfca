"""Placeholder: filled in by its issue."""

commands: list = []
