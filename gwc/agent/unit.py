"""The systemd unit of a host's agent (`gwc agent --systemd-unit`, docs/deploying.md)."""

from __future__ import annotations

import socket
import sys

from gwc.config import Config
from gwc.hostuser import cell_user_name


def systemd_unit(cfg: Config) -> str:
    """A unit for this host's agent (docs/deploying.md): the agent is supervised by systemd, the modules
    by the agent; KillMode=process, so restarting the unit does not take the modules with it. It runs
    as the cell's user with the few capabilities the agent keeps (gwc.hostuser: it starts lot scripts
    as their user and stops them), none of which it passes on."""
    env = {"GWC_CONFIG": cfg.path.resolve(), "GWC_VAR": cfg.var.resolve(), "GWC_HOST": cfg.host}
    user = cell_user_name(cfg)
    caps = "CAP_SETUID CAP_SETGID CAP_KILL CAP_SYS_NICE"
    run_as = [f"User={user}", f"Group={user}", f"AmbientCapabilities={caps}"] if user and user != "root" else []
    lines = [
        "[Unit]",
        f"Description=GWC cell {cfg.cell_name}: the agent of host {cfg.host or socket.gethostname()}",
        "After=network-online.target",
        "Wants=network-online.target",
        "",
        "[Service]",
        "Type=simple",
        *(f"Environment={k}={v}" for k, v in env.items() if v),
        f"ExecStart={sys.executable} -m gwc agent",
        *run_as,
        f"CapabilityBoundingSet={caps}",
        "NoNewPrivileges=yes",
        "UMask=0027",
        "ProtectSystem=full",
        "Restart=always",
        "RestartSec=2",
        "KillMode=process",
        "",
        "[Install]",
        "WantedBy=multi-user.target",
    ]
    return "\n".join(lines) + "\n"


__all__ = ["systemd_unit"]
