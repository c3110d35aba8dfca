"""`gwc console`: the thesis's Human Interface screens (Figures 6 to 6.9) as one live terminal application.

link.py is the console's side of the cell (its bus attachment, a listener on the bus, one database
connection, the operator's actions as the `gwc` commands hold them), with no user interface in it;
app.py is the Textual application drawn over it; command.py the click command.
"""
