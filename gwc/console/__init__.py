"""`gwc console`: the thesis's Human Interface screens (Figures 6 to 6.9) as one live terminal application.

link.py is the console's side of the cell (its bus attachment, a listener on the bus, one database
connection, the operator's actions as the `gwc` commands hold them), with no user interface in it;
views.py the screens, app.py the Textual application that holds them; command.py the click command.
"""
