"""The web HMI (`gwc run web`; docs/web.md): the cell in a browser, live, for people with a role.

* settings.py: the [web] section of cell.toml.
* tls.py: the HTTPS certificate (the plant's, or one the cell makes).
* sessions.py: sessions (cookie and CSRF token) and the login's lockout.
* cellview.py: what the pages show (read as gwc_hi with the HI's own read functions).
* actions.py: what the pages do (the `gwc` commands' conversations, in the person's name).
* app.py: the pages, the HTTP API and the server-sent events (Starlette).
* module.py: the cell module that runs it all beside its bus attachment.
"""
