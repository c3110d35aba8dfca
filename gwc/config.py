"""The cell's configuration: etc/cell.toml, with the few environment overrides tests and operators need.

Configuration lives in etc/, state in var/ (GUIDE 4). Overrides, in order of strength:
GWC_CONFIG (the file), GWC_VAR (the state folder), GWC_DATABASE_URL (use that server, not the
embedded cluster), GWC_HOST (which of the cell's [[host]]s this is, when it cannot be found from the
machine's own addresses).

Run from a checkout, etc/ and sql/ are the checkout's and state defaults to its var/ (ignored by git).
Installed (`pip install .`), etc/ and sql/ are the copies shipped in the package (gwc/data/), and state
defaults to the user's state folder, never the package: $XDG_STATE_HOME/gwc, ~/.local/state/gwc, or
/var/lib/gwc for root (docs/operating.md).
"""

from __future__ import annotations

import hashlib
import os
import re
import socket
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gwc.errors import ConfigError

PROJECT_ROOT = Path(__file__).resolve().parent.parent  # the checkout; installed, the folder holding gwc/
PACKAGE_DATA = Path(__file__).resolve().parent / "data"  # sql/ and etc/ as shipped in the package (setup.py)
SERVER_MODULES = ("cas", "ers", "ms", "ls", "sls", "msched")
OPTIONAL_MODULES = ("opcua", "web")  # modules a cell may list, not part of every cell (private cells leave them out)
LEVELS = ("trace", "note", "warning", "error")


@dataclass(frozen=True)
class Faults:
    """The bus fault injector: rates in [0, 1] applied to every datagram a module receives."""

    drop: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    seed: int | None = None

    @property
    def active(self) -> bool:
        return bool(self.drop or self.duplicate or self.reorder)


@dataclass(frozen=True)
class BusConfig:
    name: str = "CELL"
    group: str = "239.255.71.1"
    port: int = 47100
    interface: str = "127.0.0.1"
    ttl: int = 1  # multicast hops: 1 keeps the bus on its LAN segment; more only through multicast routers
    heartbeat: float = 0.75  # peer_timeout / 3: each beat costs every module that reads it (docs/performance.md)
    peer_timeout: float = 2.25
    ack_timeout: float = 0.02
    retry_deadline: float = 5.0
    reply_timeout: float = 10.0
    kernel_filter: bool = True  # the kernel drops datagrams a module would drop unread (docs/protocol.md)
    key_file: str | None = None  # the cell key file (module and lot keys); default var/secrets/cell.key
    lot_key_file: str | None = None  # the lot keys alone, for lot scripts; default var/secrets/lot.key
    replay_window: float = 10.0  # s: a datagram sealed longer ago (or that far ahead) is refused as a replay
    max_skew: float = 1.0  # s: how far apart the clocks of the cell's hosts may be (docs/protocol.md, Replay)
    faults: Faults = field(default_factory=Faults)

    @property
    def beat_port(self) -> int:
        """Where periodic hellos go: the next port, on the same group (docs/protocol.md, Membership)."""
        return self.port + 1


# The ME kinds a machine may be: kind -> its machine side, "module:Class" (loaded by gwc.me.make_machine
# only in that machine's ME process). A new kind of machine is one entry here.
ME_KINDS = {"dummy": "gwc.me.dummy:DummyMachine", "cmm": "gwc.me.cmm:CmmMachine"}


@dataclass(frozen=True)
class MachineSpec:
    """One machine: its WC and ME processes, and for a CMM its serial line."""

    id: str
    kind: str = "dummy"  # one of ME_KINDS
    liveness: float = 3.0  # the Machine Server marks it Shutdown after this much WC silence
    level: str = "note"
    options: dict[str, Any] = field(default_factory=dict)  # kind-specific: run_time, serial, sim, ...
    host: str | None = None  # the [[host]] it runs on; None: every host's (a one-host cell)


@dataclass(frozen=True)
class ModuleSpec:
    name: str
    level: str = "note"
    host: str | None = None
    # Redundancy (issue 36, docs/deploying.md): the hosts that run a standby of this module. A module
    # with standbys, or with `lease = true`, decides which instance is active through a database lease.
    standby: tuple[str, ...] = ()
    lease: bool = False


@dataclass(frozen=True)
class HostSpec:
    """One computer of a cell spread over several (docs/deploying.md)."""

    name: str
    address: str  # its address on the cell's LAN: the bus sends and joins the group there


@dataclass(frozen=True)
class Config:
    path: Path
    var: Path
    cell_name: str
    policy: str
    bus: BusConfig
    database_url: str | None
    modules: tuple[ModuleSpec, ...]
    machines: tuple[MachineSpec, ...]
    raw: dict[str, Any]
    hosts: tuple[HostSpec, ...] = ()
    host: str | None = None  # which of `hosts` this process runs on (None in a one-host cell)
    database_host: HostSpec | None = None  # where the embedded cluster runs, in a cell over several hosts
    record: RecordConfig = field(default_factory=lambda: RecordConfig())  # [record]: the production record

    @property
    def log_dir(self) -> Path:
        return self.var / "log"

    @property
    def run_dir(self) -> Path:
        """Pid files, the embedded cluster's unix socket, pty links."""
        return self.var / "run"

    @property
    def pg_dir(self) -> Path:
        return self.var / "pg"

    @property
    def results_dir(self) -> Path:
        """Where ME processes write run results files for their WC to load."""
        return self.var / "results"

    @property
    def ipc_prefix(self) -> str:
        """Prefix of this cell's POSIX queue names, unique per var/ so two cells never share a queue."""
        digest = hashlib.sha1(str(self.var.resolve()).encode()).hexdigest()[:8]
        return f"/gwc.{digest}"

    @property
    def embedded(self) -> bool:
        """Whether this host runs the cell's embedded cluster (not an external one, nor another host's)."""
        return self.database_url is None and (self.database_host is None or self.database_host.name == self.host)

    def placed_here(self, spec: ModuleSpec | MachineSpec) -> bool:
        """Whether a module or machine runs on this host (everything does in a one-host cell)."""
        return self.host is None or spec.host == self.host

    def standby_here(self, spec: ModuleSpec) -> bool:
        """Whether this host runs a standby of the module (a host of a cell with [[host]] tables)."""
        return self.host is not None and self.host in spec.standby and spec.host != self.host

    def leased(self, name: str) -> bool:
        """Whether the module decides through a database lease which instance is active (gwc.lease)."""
        return any(m.name == name and m.lease for m in self.modules)

    def machine(self, machine_id: str) -> MachineSpec:
        for m in self.machines:
            if m.id == machine_id:
                return m
        known = ", ".join(m.id for m in self.machines) or "none"
        raise ConfigError(f"unknown machine {machine_id!r} in {self.path} (known: {known})")

    def level_of(self, module: str) -> str:
        """The log level a module starts with (Listing 4 set it per module in its start script)."""
        for m in self.modules:
            if m.name == module:
                return m.level
        kind, _, mid = module.partition(":")
        if mid:
            for machine in self.machines:
                if machine.id == mid:
                    return machine.level
        return str(self.raw.get("log", {}).get("level", "note"))


def _check_level(level: str, where: str) -> str:
    if level not in LEVELS:
        raise ConfigError(f"{where}: log level {level!r} is not one of {', '.join(LEVELS)}")
    return level


def from_checkout() -> bool:
    """Whether gwc runs from a checkout (editable install, `python -m gwc` in it), not an installed copy."""
    return (PROJECT_ROOT / "pyproject.toml").is_file() and (PROJECT_ROOT / "sql").is_dir()


def shipped(folder: str) -> Path:
    """sql/ or etc/: the checkout's when running from one, else the copy installed with the package."""
    return PROJECT_ROOT / folder if from_checkout() else PACKAGE_DATA / folder


def cell_home() -> Path:
    """What a relative or missing [cell] var is under: the checkout, or the user's state folder."""
    if from_checkout():
        return PROJECT_ROOT
    if os.environ.get("XDG_STATE_HOME"):
        return Path(os.environ["XDG_STATE_HOME"]) / "gwc"
    return Path("/var/lib/gwc") if os.geteuid() == 0 else Path.home() / ".local" / "state" / "gwc"


def default_config_path() -> Path:
    return Path(os.environ.get("GWC_CONFIG") or shipped("etc") / "cell.toml")


def load_config(path: Path | str | None = None) -> Config:
    """Read the cell configuration, raising ConfigError with the file and the key that is wrong."""
    cfg_path = Path(path) if path else default_config_path()
    try:
        raw = tomllib.loads(cfg_path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"no cell configuration at {cfg_path} (set GWC_CONFIG or create etc/cell.toml)") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{cfg_path}: {e}") from None
    try:
        return _build(cfg_path, raw)
    except (TypeError, ValueError, KeyError) as e:
        raise ConfigError(f"{cfg_path}: {e}") from None


def _build(cfg_path: Path, raw: dict[str, Any]) -> Config:
    cell = raw.get("cell", {})
    var = Path(os.environ.get("GWC_VAR") or cell.get("var") or cell_home() / "var")
    if not var.is_absolute():  # under the cell's folder (etc/..); the configuration shipped in the package: its home
        home = cell_home() if PACKAGE_DATA in cfg_path.resolve().parents else cfg_path.resolve().parent.parent
        var = home / var  # absolute: the database socket's folder is named by it
    bus_raw = dict(raw.get("bus", {}))
    for name, default in (("key_file", "cell.key"), ("lot_key_file", "lot.key")):
        where = Path(bus_raw.get(name) or var / "secrets" / default)
        bus_raw[name] = str(where if where.is_absolute() else cfg_path.parent.parent / where)
    faults = Faults(**bus_raw.pop("faults", {}))
    hosts = tuple(HostSpec(name=h["name"], address=h["address"]) for h in raw.get("host", []))
    if len({h.name for h in hosts}) != len(hosts):
        raise ValueError("host names must be unique")
    host = _this_host(hosts)
    if host is not None:  # the bus lives on this host's LAN address, whatever [bus] says
        bus_raw["interface"] = next(h.address for h in hosts if h.name == host)
    bus = BusConfig(**bus_raw, faults=faults)
    if not 1 <= bus.ttl <= 255:
        raise ValueError(f"bus.ttl must be 1..255, got {bus.ttl}")
    for rate in (faults.drop, faults.duplicate, faults.reorder):
        if not 0.0 <= rate < 1.0:
            raise ValueError(f"bus.faults rates must be in [0, 1), got {rate}")
    url = os.environ.get("GWC_DATABASE_URL") or raw.get("database", {}).get("url") or None
    default_level = _check_level(raw.get("log", {}).get("level", "note"), "log.level")
    modules = tuple(
        ModuleSpec(
            name=m["name"],
            level=_check_level(m.get("level", default_level), f"module {m['name']}"),
            host=_placed(m.get("host"), hosts, f"module {m['name']}"),
            standby=tuple(_placed(h, hosts, f"module {m['name']}'s standby") or h for h in m.get("standby", ())),
            lease=bool(m.get("lease", False) or m.get("standby")),
        )
        for m in raw.get("module", [])
    )
    for m in modules:
        if m.name not in SERVER_MODULES + OPTIONAL_MODULES:
            raise ValueError(f"module {m.name!r} is not one of {', '.join(SERVER_MODULES + OPTIONAL_MODULES)}")
    machines = []
    for entry in raw.get("machine", []):
        options = dict(entry)  # what is left once the common keys are taken: the kind's own
        mid = options.pop("id")
        kind = options.pop("kind", "dummy")
        if kind not in ME_KINDS:
            raise ValueError(f"machine {mid}: kind {kind!r} is not one of {', '.join(ME_KINDS)}")
        machines.append(
            MachineSpec(
                id=mid,
                kind=kind,
                liveness=float(options.pop("liveness", 3.0)),
                level=_check_level(options.pop("level", default_level), f"machine {mid}"),
                host=_placed(options.pop("host", None), hosts, f"machine {mid}"),
                options=options,
            )
        )
    ids = [m.id for m in machines]
    if len(set(ids)) != len(ids):
        raise ValueError("machine ids must be unique")
    policy = cell.get("policy", "fifo")
    if policy not in ("fifo", "priority"):
        raise ValueError(f"cell.policy {policy!r} is not fifo or priority")
    return Config(
        path=cfg_path,
        var=var,
        cell_name=cell.get("name", "GWC"),
        policy=policy,
        bus=bus,
        database_url=url,
        modules=modules,
        machines=tuple(machines),
        raw=raw,
        hosts=hosts,
        host=host,
        database_host=_database_host(raw.get("database", {}).get("host"), hosts, url),
        record=parse_record(raw.get("record", {}), machines),
    )


# ----------------------------------------------------------------------------- [record]

DAYS = ("mon", "tue", "wed", "thu", "fri", "sat", "sun")
E10_STATES = ("productive", "standby", "engineering", "scheduled_downtime", "unscheduled_downtime", "non_scheduled")
DOWN_STATES = ("scheduled_downtime", "unscheduled_downtime", "engineering")  # what a downtime reason may be
ALWAYS = "always"  # the built-in calendar: every hour of every day planned


@dataclass(frozen=True)
class Shift:
    """Planned production time on some weekdays, start..end local time in minutes (end <= start: overnight)."""

    days: tuple[int, ...]  # 0 = Monday
    start: int
    end: int


@dataclass(frozen=True)
class Calendar:
    """A shift calendar: planned time is the union of its shifts; none at all: never planned."""

    name: str
    shifts: tuple[Shift, ...]
    always: bool = False


DEFAULT_REASONS: dict[str, dict[str, Any]] = {
    "planned": {"e10": "scheduled_downtime", "reasons": ["tool change", "preventive maintenance", "cleaning"]},
    "breakdown": {"e10": "unscheduled_downtime", "reasons": ["mechanical", "electrical", "controller", "tool broken"]},
    "material": {"e10": "unscheduled_downtime", "reasons": ["no material", "wrong material"]},
    "engineering": {"e10": "engineering", "reasons": ["trial run", "process engineering"]},
}
DEFAULT_REASON_INDEX = {r: (c, str(v["e10"])) for c, v in DEFAULT_REASONS.items() for r in v["reasons"]}


@dataclass(frozen=True)
class RecordConfig:
    """cell.toml [record] (docs/record.md): history on or off, retention, calendars, reason tree, cycles."""

    history: bool = True
    keep_days: float = 90.0
    prune_every_s: float = 3600.0
    timezone: str = "UTC"
    calendar: str = ALWAYS  # the cell's; a machine's `calendar` option names another
    calendars: dict[str, Calendar] = field(default_factory=lambda: {ALWAYS: Calendar(ALWAYS, (), always=True)})
    # reason -> (category, E10 state); the tree's categories in order, each with its reasons
    reasons: dict[str, tuple[str, str]] = field(default_factory=lambda: dict(DEFAULT_REASON_INDEX))
    ideal_cycle_s: dict[str, float] = field(default_factory=dict)  # recipe_id -> ideal seconds per part
    machine_calendars: dict[str, str] = field(default_factory=dict)  # machine_id -> calendar name

    def calendar_of(self, machine_id: str) -> Calendar:
        return self.calendars[self.machine_calendars.get(machine_id, self.calendar)]

    def tree(self) -> dict[str, list[str]]:
        """The reason tree: category -> its reasons."""
        out: dict[str, list[str]] = {}
        for reason, (category, _) in self.reasons.items():
            out.setdefault(category, []).append(reason)
        return out


def _hhmm(value: Any, where: str) -> int:
    if not isinstance(value, str) or not re.fullmatch(r"\d{1,2}:\d{2}", value):
        raise ValueError(f"{where}: {value!r} is not a time of day HH:MM")
    h, m = (int(x) for x in value.split(":"))
    if not (0 <= h <= 24 and 0 <= m < 60) or (h == 24 and m):
        raise ValueError(f"{where}: {value!r} is not a time of day 00:00..24:00")
    return h * 60 + m


def _calendar(name: str, entry: Any) -> Calendar:
    where = f"record.calendars.{name}"
    if not isinstance(entry, dict) or set(entry) - {"shifts"}:
        raise ValueError(f"{where} must be a table with one key, shifts = [{{days, start, end}}, ...]")
    shifts = entry.get("shifts", [])
    if not isinstance(shifts, list):
        raise ValueError(f'{where}.shifts must be a list of {{days = [...], start = "HH:MM", end = "HH:MM"}}')
    out = []
    for i, s in enumerate(shifts):
        w = f"{where}.shifts[{i}]"
        if not isinstance(s, dict) or set(s) != {"days", "start", "end"}:
            raise ValueError(f"{w} must have exactly days, start and end")
        days = s["days"]
        if days == "all":
            days = list(DAYS)
        if not isinstance(days, list) or not days or any(d not in DAYS for d in days):
            raise ValueError(f'{w}.days must be "all" or a list of {", ".join(DAYS)}; got {s["days"]!r}')
        start, end = _hhmm(s["start"], f"{w}.start"), _hhmm(s["end"], f"{w}.end")
        if start == end:
            raise ValueError(f"{w}: start and end are both {s['start']} (use 00:00 to 24:00 for a whole day)")
        out.append(Shift(tuple(sorted({DAYS.index(d) for d in days})), start, end))
    return Calendar(name, tuple(out))


def parse_record(raw: Any, machines: list[MachineSpec]) -> RecordConfig:
    """[record], checked: every error names its key and what it should be."""
    if not isinstance(raw, dict):
        raise ValueError("[record] must be a table")
    known = {"history", "keep_days", "prune_every_s", "timezone", "calendar", "calendars", "reasons", "ideal_cycle_s"}
    if set(raw) - known:
        unknown = ", ".join(sorted(set(raw) - known))
        raise ValueError(f"[record]: unknown key(s) {unknown} (known: {', '.join(sorted(known))})")
    history = raw.get("history", True)
    if not isinstance(history, bool):
        raise ValueError(f"record.history must be true or false, not {history!r}")
    numbers = {}
    for key, default in (("keep_days", 90.0), ("prune_every_s", 3600.0)):
        v = raw.get(key, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or v <= 0:
            raise ValueError(f"record.{key} must be a positive number, not {v!r}")
        numbers[key] = float(v)
    tz = raw.get("timezone", "UTC")
    try:
        from zoneinfo import ZoneInfo

        ZoneInfo(str(tz))
    except (KeyError, ValueError, OSError):
        raise ValueError(f'record.timezone {tz!r} is not a time zone (e.g. "UTC", "Europe/Berlin")') from None
    calendars = {ALWAYS: Calendar(ALWAYS, (), always=True)}
    cal_raw = raw.get("calendars", {})
    if not isinstance(cal_raw, dict):
        raise ValueError("record.calendars must be a table of calendars, each shifts = [...]")
    for name, entry in cal_raw.items():
        if name == ALWAYS:
            raise ValueError(f"record.calendars.{ALWAYS} is built in (every hour planned): name yours otherwise")
        calendars[name] = _calendar(name, entry)
    default = raw.get("calendar", ALWAYS)
    if default not in calendars:
        raise ValueError(f"record.calendar {default!r} is not a calendar (known: {', '.join(calendars)})")
    per_machine = {}
    for m in machines:
        name = m.options.get("calendar")
        if name is not None:
            if name not in calendars:
                names = ", ".join(calendars)
                raise ValueError(f"machine {m.id}: calendar {name!r} is not in record.calendars ({names})")
            per_machine[m.id] = str(name)
    reasons: dict[str, tuple[str, str]] = {}
    tree = raw.get("reasons", DEFAULT_REASONS)
    if not isinstance(tree, dict) or not tree:
        raise ValueError('record.reasons must be a table: category = {e10 = "...", reasons = ["...", ...]}')
    for category, entry in tree.items():
        where = f"record.reasons.{category}"
        if not isinstance(entry, dict) or set(entry) != {"e10", "reasons"}:
            raise ValueError(f'{where} must be {{e10 = "<state>", reasons = ["..."]}}')
        if entry["e10"] not in DOWN_STATES:
            raise ValueError(f"{where}.e10 {entry['e10']!r} is not one of {', '.join(DOWN_STATES)}")
        if not isinstance(entry["reasons"], list) or not entry["reasons"]:
            raise ValueError(f"{where}.reasons must be a list of reasons (text)")
        for r in entry["reasons"]:
            if not isinstance(r, str) or not r.strip():
                raise ValueError(f"{where}.reasons: {r!r} is not a reason (non-empty text)")
            if r in reasons:
                raise ValueError(f"{where}: reason {r!r} is also under {reasons[r][0]}: a reason has one place")
            reasons[r] = (str(category), str(entry["e10"]))
    cycles_raw = raw.get("ideal_cycle_s", {})
    if not isinstance(cycles_raw, dict):
        raise ValueError("record.ideal_cycle_s must be a table: recipe_id = seconds")
    cycles = {}
    for recipe, v in cycles_raw.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or v <= 0:
            raise ValueError(f"record.ideal_cycle_s.{recipe} must be a positive number of seconds, not {v!r}")
        cycles[str(recipe)] = float(v)
    return RecordConfig(
        history=history,
        keep_days=numbers["keep_days"],
        prune_every_s=numbers["prune_every_s"],
        timezone=str(tz),
        calendar=str(default),
        calendars=calendars,
        reasons=reasons,
        ideal_cycle_s=cycles,
        machine_calendars=per_machine,
    )


def _database_host(name: str | None, hosts: tuple[HostSpec, ...], url: str | None) -> HostSpec | None:
    if not hosts or url:
        return None
    for h in hosts:
        if h.name == name:
            return h
    raise ValueError(
        f"[database] host must name the host that runs the embedded cluster "
        f"(one of {', '.join(h.name for h in hosts)}), got {name!r}"
    )


def _placed(host: str | None, hosts: tuple[HostSpec, ...], what: str) -> str | None:
    """A module's or machine's host, checked: a cell with [[host]]s places everything on one of them."""
    if not hosts:
        if host is not None:
            raise ValueError(f"{what} names host {host!r} but the cell has no [[host]] tables")
        return None
    names = [h.name for h in hosts]
    if host not in names:
        raise ValueError(f"{what} must name its host, one of {', '.join(names)} (got {host!r})")
    return host


def _is_local(address: str) -> bool:
    """Whether this machine owns an address: binding to it succeeds only then."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind((address, 0))
        except OSError:
            return False
    return True


def _this_host(hosts: tuple[HostSpec, ...]) -> str | None:
    """Which [[host]] this is: GWC_HOST, else the one whose name is this machine's host name, else the one
    whose address is this machine's. None in a one-host cell; an error if it cannot be told."""
    if not hosts:
        return None
    names = [h.name for h in hosts]
    chosen = os.environ.get("GWC_HOST")
    if chosen:
        if chosen not in names:
            raise ValueError(f"GWC_HOST={chosen!r} is not one of the cell's hosts ({', '.join(names)})")
        return chosen
    hostname = socket.gethostname().split(".")[0]
    if hostname in names:
        return hostname
    local = [h.name for h in hosts if _is_local(h.address)]
    if len(local) == 1:
        return local[0]
    raise ValueError(
        f"cannot tell which of the cell's hosts ({', '.join(names)}) this is: "
        + ("several of their addresses are local" if local else "none has this host name or a local address")
        + "; set GWC_HOST (or `gwc --host NAME`)"
    )


def toml_value(v: Any) -> str:
    """One TOML value: strings quoted, dicts as inline tables, lists as arrays."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (str, Path)):
        return '"' + str(v).replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items()) + " }"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    return repr(v)


def dump_toml(doc: dict[str, Any]) -> str:
    """A cell.toml document: a dict value is a [table] (its dict values [table.sub]), a list an [[array]]."""
    lines: list[str] = []
    for key, value in doc.items():
        if isinstance(value, list):
            for item in value:
                lines += ["", f"[[{key}]]"] + [f"{k} = {toml_value(x)}" for k, x in item.items()]
            continue
        subs = {k: x for k, x in value.items() if isinstance(x, dict)}
        lines += ["", f"[{key}]"] + [f"{k} = {toml_value(x)}" for k, x in value.items() if k not in subs]
        for sub, table in subs.items():
            lines += ["", f"[{key}.{sub}]"] + [f"{k} = {toml_value(x)}" for k, x in table.items()]
    return "\n".join(lines).lstrip() + "\n"
