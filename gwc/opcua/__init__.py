"""The OPC UA gateway (`gwc run opcua`): the cell as an OPC UA server any MES, SCADA or client can
browse, subscribe to and command. docs/opcua.md describes the address space, the methods and security.

* settings.py: the [opcua] section of cell.toml.
* security.py: users, the rule that methods need a user on a SignAndEncrypt channel, certificates,
  BadSessionIdInvalid for a session the server does not know, Read's timestamps.
* space.py: the address space (string node ids in the cell's namespace, stable across restarts),
  values with their timestamps, methods with their arguments checked.
* model.py: the DI, IA and Machinery nodesets (nodesets/, as published), the cell's own types, and
  one machine's node tree (build_machine).
* answers.py: how a method answers: the cell's ack code as its status, the code and note as outputs.
* hi_methods.py: the methods done by the `gwc` command's own client code (Unreserve, MaintenanceDone).
* gateway.py: the cell module: what it hears on the bus and reads in the tables, and the methods.
"""
