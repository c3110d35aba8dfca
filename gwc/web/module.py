"""The web HMI as a cell module (`gwc run web`, `[[module]] name = "web"`): an HTTPS server
(Starlette on uvicorn) in the module's own event loop, beside its bus attachment.

It owns no table. The live pages are fed from what it hears on the bus (UPD_ME_ST, RUN_COMPL,
ALARM_CLE, CELL_EVENT, LOT_MOVED: each wakes a re-read of what it touches) and from a re-read of
the tables every `refresh` seconds; a topic that changed goes to every open page as a server-sent
event. Actions are conversations on its bus attachment, in the name of the person who asked.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import time
from typing import Any

import uvicorn

from gwc.config import Config
from gwc.errors import ConfigError, GwcError
from gwc.ipc.bus import Conversation
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv
from gwc.module import Handler, Module
from gwc.web import tls
from gwc.web.actions import Actions
from gwc.web.app import Live, Web, build_app
from gwc.web.cellview import SLOW_TOPICS, TOPICS, Reader, read_view
from gwc.web.settings import load_settings

LISTENS: dict[str, tuple[str, ...]] = {
    Conv.UPD_ME_ST: ("machines", "record"),
    Conv.RUN_COMPL: ("machines", "record", "spc"),
    Conv.ALARM_CLE: ("alarms",),
    Conv.CELL_EVENT: ("alarms", "lots"),
    Conv.LOT_MOVED: ("lots", "orders", "requests"),
}
STOP_GRACE = 2  # s the HTTPS server has to close its connections at shutdown
# Broadcasts come in bursts (a lot's step is several): a read follows the first at once, the rest of a
# burst waits until this long after it, and is read together. Pages then change at most this often.
COALESCE_S = 0.5


class WebModule(Module):
    role = None  # it reads and writes through its own connection (gwc.web.cellview.Reader, as gwc_hi)

    def __init__(self, cfg: Config, name: str, log: logging.Logger) -> None:
        super().__init__(cfg, name, log)
        self.settings = load_settings(cfg)
        self.reader = Reader(cfg, log)
        self.live = Live()
        self.web = Web(
            self.settings,
            self.reader,
            Actions(cfg, self.bus, log),
            self.live,
            log,
            self.read_topic,
            self.modules,
            self.touched,
        )
        self.server: uvicorn.Server | None = None
        self._serving: asyncio.Task[None] | None = None
        self._refresher: asyncio.Task[None] | None = None
        self._dirty: set[str] = set()
        self._urgent: set[str] = set()  # slow topics an action of the web's changed: read at once
        self._slow_read: dict[str, float] = dict.fromkeys(SLOW_TOPICS, -1e9)
        self._pending_slow: set[str] = set()
        self._wake = asyncio.Event()

    def handlers(self) -> dict[str, Handler]:
        return dict.fromkeys(LISTENS, self.heard)

    async def heard(self, conv: Conversation) -> None:
        self._dirty.update(LISTENS.get(conv.cls, ()))
        self._wake.set()

    def touched(self, topic: str) -> None:
        """An action of the web's changed `topic`: the open pages see it at the next read."""
        self._dirty.add(topic)
        self._urgent.add(topic)
        self._wake.set()

    def modules(self) -> list[dict[str, Any]]:
        return [
            {"module": name, "started": Conv.SHUTDOWN in p.interest or Conv.ME_SHUT in p.interest}
            for name, p in sorted(self.bus.peers().items())
        ]

    async def read_topic(self, topic: str) -> Any:
        peers = set(self.bus.peers())
        return await self.reader.run(lambda conn: read_view(self.cfg, self.log, conn, topic, peers))

    async def on_startup(self) -> str:
        s = self.settings
        cert, key = await asyncio.to_thread(tls.certificate, s, self.cfg.cell_name)
        family = socket.AF_INET6 if ":" in s.host else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((s.host, s.port))
        except OSError as e:
            sock.close()
            raise ConfigError(f"[web] listen {s.listen}: cannot listen there: {e}") from None
        config = uvicorn.Config(
            build_app(self.web),
            ssl_certfile=str(cert),
            ssl_keyfile=str(key),
            log_config=None,
            access_log=False,
            lifespan="off",
            timeout_graceful_shutdown=STOP_GRACE,
            server_header=False,
        )
        config.load()
        self.server = uvicorn.Server(config)
        # uvicorn's serve() would take the process's signals: the module's own lifecycle keeps them.
        self.server.lifespan = config.lifespan_class(config)
        await self.server.startup(sockets=[sock])
        self._serving = asyncio.get_running_loop().create_task(self.server.main_loop())
        self._refresher = asyncio.get_running_loop().create_task(self._refresh_loop())
        self.log.info("web HMI listening at https://%s (certificate %s)", s.listen, cert)
        return AckCode.ACK_OK

    async def on_shutdown(self) -> str | None:
        if self._refresher is not None:
            self._refresher.cancel()
        self.live.close_all()
        if self.server is not None:
            began = time.monotonic()
            self.server.should_exit = True
            if self._serving is not None:
                await asyncio.wait({self._serving}, timeout=STOP_GRACE)
            await self.server.shutdown()
            self.server = None
            self.log.info("web HMI stopped in %.2f s", time.monotonic() - began)
        await asyncio.to_thread(self.reader.close)
        return None

    async def _refresh_loop(self) -> None:
        """Each topic re-read when a broadcast touches it, and all every `refresh` seconds, while a page
        is open; what changed goes to the pages."""
        last_full = last_read = 0.0
        while True:
            try:
                await asyncio.wait_for(self._wake.wait(), timeout=self.settings.refresh)
            except TimeoutError:
                pass
            since = time.monotonic() - last_read
            if since < COALESCE_S:
                await asyncio.sleep(COALESCE_S - since)
            self._wake.clear()
            if not self.live.streams:
                self._dirty.clear()
                self._pending_slow.clear()
                continue
            if time.monotonic() - last_full >= self.settings.refresh:
                self._dirty.update(TOPICS)
                last_full = time.monotonic()
            now = time.monotonic()
            for topic, (least, most) in SLOW_TOPICS.items():
                since_slow = now - self._slow_read[topic]
                wanted = topic in self._dirty or topic in self._pending_slow
                if topic in self._urgent or since_slow >= most or (wanted and since_slow >= least):
                    self._dirty.add(topic)
                    self._pending_slow.discard(topic)
                    self._slow_read[topic] = now
                elif wanted:  # read when `least` has passed (the loop wakes every `refresh` s)
                    self._dirty.discard(topic)
                    self._pending_slow.add(topic)
            what, self._dirty, self._urgent = self._dirty, set(), set()
            last_read = time.monotonic()
            self.live.publish("modules", self.modules())
            for topic in sorted(what):
                try:
                    self.live.publish(topic, await self.read_topic(topic))
                except GwcError as e:
                    self.log.warning("web: could not read %s: %s", topic, e)
                except Exception:
                    self.log.exception("web: reading %s failed", topic)
