"""The per-host agent (`gwc agent`): it starts this host's modules, watches them and restarts the dead.

states.py holds the process states and the one function that changes them; child.py one
supervised process; agent.py the agent itself; control.py the local socket `gwc start`, `gwc
stop`, `gwc status` and `gwc restart` talk to it through. docs/operating.md and
docs/reliability.md describe the policy.
"""
