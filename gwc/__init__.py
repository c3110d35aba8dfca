"""GWC: a Python re-creation of the Generic WorkCell (Siemens/NJIT, 1991)."""

__version__ = "0.1.0"
