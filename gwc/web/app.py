"""The web HMI's HTTP side (docs/web.md): the pages, the HTTP API under them, and the live updates
(server-sent events). Every action is a POST with the session's CSRF token in X-CSRF-Token, checked
against the role table and appended to the audit trail (gwc.users); nothing acts on a GET.
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from starlette.applications import Starlette
from starlette.datastructures import MutableHeaders
from starlette.middleware import Middleware
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response, StreamingResponse
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from gwc.errors import (
    ConfigError,
    ConversationTimeout,
    DatabaseError,
    DatabaseUnavailable,
    Forbidden,
    GwcError,
    ModuleError,
    NotAuthenticated,
    Refused,
)
from gwc.users import Action, Person, refuse_unless, store
from gwc.users.doors import audit
from gwc.users.passwords import verify
from gwc.users.roles import LOWEST, allowed
from gwc.web import record as view
from gwc.web.actions import Actions
from gwc.web.cellview import Reader, plain
from gwc.web.sessions import Lockout, Session, Sessions
from gwc.web.settings import WebSettings

STATIC = Path(__file__).parent / "static"
COOKIE = "gwc_session"
KEEPALIVE = 15.0  # s between SSE comments on a quiet stream (proxies close silent connections)
HEADERS = {
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; frame-ancestors 'none'; base-uri 'none'",
    "X-Frame-Options": "DENY",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Strict-Transport-Security": "max-age=31536000",
}
# What a person may do through the web (docs/web.md): each POST route's action in the role table.
WEB_ACTIONS: dict[str, Action] = {
    "POST /api/machines/{id}/start": Action.MACHINE_START,
    "POST /api/machines/{id}/stop": Action.MACHINE_STOP,
    "POST /api/alarms/{alarm_no}/clear": Action.ALARM_CLEAR,
    "POST /api/orders": Action.ORDER_ENTER,
    "POST /api/lots/{entity_id}/import": Action.LOT_IMPORT,
    "POST /api/lots/{entity_id}/export": Action.LOT_EXPORT,
    "POST /api/lots/{entity_id}/release": Action.LOT_RELEASE,
    "POST /api/downtime/{event_id}/reason": Action.DOWNTIME_REASON,
    "POST /api/recipes/{recipe_id}/approve": Action.RECIPE_APPROVE,
    "GET /api/audit": Action.AUDIT_READ,
    "POST /api/logout": Action.VIEW,
}
# Topics a new event stream is not given the latest of: a page reads them (GET) as it opens, and the
# latest may be older than that read (they are re-read seldom: gwc.web.cellview.SLOW_TOPICS).
NO_REPLAY = frozenset({"record", "spc"})
# The live topics an action changes, read again at once after it (the others follow their broadcasts).
TOUCHES: dict[Action, tuple[str, ...]] = {Action.DOWNTIME_REASON: ("record",)}
NOBODY = Person("(none)", role=next(iter(LOWEST.values())), door="web")  # an act without a session, for the trail


class HttpError(GwcError):
    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


class Live:
    """The latest of each topic and the open event streams: a changed topic goes to every stream."""

    def __init__(self) -> None:
        self.latest: dict[str, str] = {}
        self.streams: set[asyncio.Queue[tuple[str, str] | None]] = set()

    def publish(self, topic: str, data: Any) -> None:
        text = json.dumps(data, default=str)
        if self.latest.get(topic) == text:
            return
        self.latest[topic] = text
        for q in self.streams:
            q.put_nowait((topic, text))

    def close_all(self) -> None:
        for q in self.streams:
            q.put_nowait(None)


@dataclass
class Web:
    """The parts the routes use (the web module holds them)."""

    settings: WebSettings
    reader: Reader
    actions: Actions
    live: Live
    log: logging.Logger
    read_topic: Callable[[str], Awaitable[Any]]  # a topic's rows now
    modules: Callable[[], list[dict[str, Any]]]  # who is on the bus
    touched: Callable[[str], None] = lambda topic: None  # an action changed a live topic: read it now

    def __post_init__(self) -> None:
        self.sessions = Sessions(self.settings.session_idle_s, self.settings.session_max_s)
        self.lockout = Lockout(self.settings.lockout_after, self.settings.lockout_s)


def _address(request: Request) -> str:
    return request.client.host if request.client else ""


def _error(status: int, message: str) -> JSONResponse:
    return JSONResponse({"error": message}, status_code=status, headers={"Cache-Control": "no-store"})


def build_app(web: Web) -> Starlette:
    """The Starlette application over `web`."""

    async def write_audit(who: Person, action: str, target: str, outcome: str, note: str) -> None:
        try:
            await web.reader.run(lambda c: audit(c, who, action, target, outcome, note))
        except GwcError as e:  # the act was refused or done: its row is lost, said in the log
            web.log.error("audit row not written (%s %s %s %s by %s): %s", action, target, outcome, note, who.name, e)

    def session_of(request: Request) -> Session:
        s = web.sessions.get(request.cookies.get(COOKIE))
        if s is None:
            raise HttpError(401, "not logged in, or the session has expired: log in (POST /api/login)")
        return s

    async def acting(request: Request, action: Action, target: str) -> Person:
        """The person behind a POST: a session, its CSRF token, an Origin of this site, a role that may."""
        s = web.sessions.get(request.cookies.get(COOKIE))
        who = NOBODY if s is None else s.person
        who = Person(who.name, who.role, "web", _address(request), who.managed)
        origin = request.headers.get("origin")
        why = ""
        if s is None:
            why = "not logged in, or the session has expired: log in first"
        elif origin is not None and origin != f"https://{request.headers.get('host', '')}":
            why = f"request from another site ({origin}) refused"
        elif not Sessions.csrf_ok(s, request.headers.get("x-csrf-token")):
            why = "missing or wrong CSRF token (X-CSRF-Token): reload the page"
        if why:
            await write_audit(who, action, target, "refused", why)
            web.log.warning("web: %s %s by %s from %s refused: %s", action, target, who.name, who.address, why)
            raise HttpError(401 if s is None else 403, why)
        try:
            await web.reader.run(lambda c: refuse_unless(c, who, action, target, web.log))
        except Forbidden as e:
            raise HttpError(403, str(e)) from None
        return who

    async def perform(
        request: Request, action: Action, target: str, do: Callable[[Person], Awaitable[Any]]
    ) -> Response:
        try:
            who = await acting(request, action, target)
        except HttpError as e:
            return _error(e.status, str(e))
        try:
            out = await do(who)
        except (Refused, ConfigError, ModuleError) as e:
            await write_audit(who, action, target, "failed", str(e))
            return _error(409, str(e))
        except ConversationTimeout as e:
            await write_audit(who, action, target, "failed", str(e))
            return _error(504, str(e))
        except (GwcError, ValueError) as e:
            await write_audit(who, action, target, "failed", str(e))
            return _error(400, str(e))
        note = out if isinstance(out, str) else json.dumps(out, default=str)[:500]
        await write_audit(who, action, target, "ok", note)
        for topic in TOUCHES.get(action, ()):
            web.touched(topic)
        web.log.info("web: %s %s by %s (%s): %s", action, target, who.name, who.role.name, note)
        return JSONResponse({"ok": True, "note": out} if isinstance(out, str) else {"ok": True, **out})

    async def body(request: Request) -> dict[str, Any]:
        try:
            data = await request.json()
        except ValueError:
            raise HttpError(400, "the body must be JSON") from None
        if not isinstance(data, dict):
            raise HttpError(400, "the body must be a JSON object")
        return data

    # ------------------------------------------------------------------ sessions

    async def api_login(request: Request) -> Response:
        address = _address(request)
        if request.headers.get("content-type", "").split(";")[0].strip() != "application/json":
            return _error(415, "send the login as application/json")
        try:
            data = await body(request)
        except HttpError as e:
            return _error(e.status, str(e))
        name, password = data.get("user"), data.get("password")
        if not isinstance(name, str) or not isinstance(password, str) or not name or len(name) > 64:
            return _error(400, 'give {"user": NAME, "password": PASSWORD}')
        tried = Person(name, NOBODY.role, "web", address)
        locked = web.lockout.locked_for(name, address)
        if locked > 0:
            await write_audit(tried, "login", name, "refused", f"locked for {locked:.0f} s more")
            return _error(429, f"login locked for {locked:.0f} s after too many wrong passwords")
        try:
            user = await web.reader.run(lambda c: store.get_user(c, name))
            # the hash is checked off the reader's lock: the pages' reads do not wait for it
            if not await asyncio.to_thread(verify, user.password_hash if user else None, password) or user is None:
                raise NotAuthenticated("wrong user name or password")
            who = Person(user.user_name, user.role, "web", address)
        except NotAuthenticated as e:
            web.lockout.failed(name, address)
            await write_audit(tried, "login", name, "refused", str(e))
            web.log.warning("web: login of %r from %s refused: %s", name, address, e)
            return _error(401, str(e))
        web.lockout.succeeded(name)
        s = web.sessions.open(who)
        await write_audit(who, "login", name, "ok", "")
        web.log.info("web: %s (%s) logged in from %s", who.name, who.role.name, address)
        resp = JSONResponse({"csrf": s.csrf, "user": who.name, "role": who.role.name})
        resp.set_cookie(
            COOKIE,
            s.token,
            max_age=int(web.settings.session_max_s),
            httponly=True,
            secure=True,
            samesite="strict",
            path="/",
        )
        return resp

    async def api_logout(request: Request) -> Response:
        try:
            who = await acting(request, Action.VIEW, "logout")
        except HttpError as e:
            return _error(e.status, str(e))
        web.sessions.close(request.cookies.get(COOKIE, ""))
        await write_audit(who, "logout", who.name, "ok", "")
        resp = JSONResponse({"ok": True})
        resp.delete_cookie(COOKIE, path="/", secure=True, httponly=True, samesite="strict")
        return resp

    async def api_session(request: Request) -> Response:
        try:
            s = session_of(request)
        except HttpError as e:
            return _error(e.status, str(e))
        may = [a.value for a in Action if allowed(s.person.role, a)]
        return JSONResponse(
            {"user": s.person.name, "role": s.person.role.name, "csrf": s.csrf, "may": may},
            headers={"Cache-Control": "no-store"},
        )

    # ------------------------------------------------------------------ reading

    def reading(topic: str) -> Callable[[Request], Awaitable[Response]]:
        async def read(request: Request) -> Response:
            try:
                session_of(request)
                data = web.modules() if topic == "modules" else await web.read_topic(topic)
            except HttpError as e:
                return _error(e.status, str(e))
            except GwcError as e:
                return _error(503, str(e))
            return JSONResponse(data, headers={"Cache-Control": "no-store"})

        return read

    async def api_audit(request: Request) -> Response:
        try:
            s = session_of(request)
        except HttpError as e:
            return _error(e.status, str(e))
        who = Person(s.person.name, s.person.role, "web", _address(request))
        q = request.query_params
        user = q.get("user") or None
        since = None
        if q.get("since"):
            from gwc.client.record import parse_when

            try:
                since = parse_when(q["since"])
            except GwcError as e:
                return _error(400, str(e))
        try:
            await web.reader.run(lambda c: refuse_unless(c, who, Action.AUDIT_READ, user or "", web.log))
            rows = await web.reader.run(lambda c: store.audit_rows(c, since, user, int(q.get("limit", 500))))
        except Forbidden as e:
            return _error(403, str(e))
        except (GwcError, ValueError) as e:
            return _error(400, str(e))
        await write_audit(who, Action.AUDIT_READ, user or "", "ok", f"{len(rows)} rows")
        out = [{**r.__dict__, "at": r.at.isoformat() if r.at else None} for r in rows]
        return JSONResponse(out, headers={"Cache-Control": "no-store"})

    async def api_events(request: Request) -> Response:
        try:
            s = session_of(request)
        except HttpError as e:
            return _error(e.status, str(e))
        q: asyncio.Queue[tuple[str, str] | None] = asyncio.Queue()
        for topic, text in web.live.latest.items():
            if topic not in NO_REPLAY:
                q.put_nowait((topic, text))
        web.live.streams.add(q)

        async def stream() -> AsyncIterator[str]:
            try:
                yield "retry: 1000\n\n"
                while True:
                    try:
                        item = await asyncio.wait_for(q.get(), KEEPALIVE)
                    except TimeoutError:
                        item = ("", "")
                    if item is None or not web.sessions.alive(s.token):
                        yield "event: logout\ndata: {}\n\n"
                        return
                    topic, text = item
                    yield f"event: {topic}\ndata: {text}\n\n" if topic else ": keepalive\n\n"
            finally:
                web.live.streams.discard(q)

        return StreamingResponse(
            stream(), media_type="text/event-stream", headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"}
        )

    # ------------------------------------------------------------------ acting

    async def api_machine(request: Request) -> Response:
        machine, verb = request.path_params["machine_id"], request.path_params["verb"]
        if verb not in ("start", "stop"):
            return _error(404, f"no action {verb!r} on a machine (start, stop)")
        action = Action.MACHINE_START if verb == "start" else Action.MACHINE_STOP
        return await perform(request, action, machine, lambda who: web.actions.machine(machine, verb == "start"))

    async def api_alarm_clear(request: Request) -> Response:
        no = int(request.path_params["alarm_no"])
        return await perform(request, Action.ALARM_CLEAR, str(no), lambda who: web.actions.clear_alarm(no, who.by))

    async def api_lot(request: Request) -> Response:
        entity, verb = int(request.path_params["entity_id"]), request.path_params["verb"]
        actions = {"import": Action.LOT_IMPORT, "export": Action.LOT_EXPORT, "release": Action.LOT_RELEASE}
        if verb not in actions:
            return _error(404, f"no action {verb!r} on a lot entity (import, export, release)")

        async def do(who: Person) -> str:
            decision = verb
            if verb == "release":
                decision = str((await body(request)).get("decision", ""))
                if decision not in ("retry", "reroute", "fail"):
                    raise GwcError('release needs {"decision": "retry" | "reroute" | "fail"}')
            return await web.actions.decide(entity, decision, who.by)

        return await perform(request, actions[verb], str(entity), do)

    async def api_order(request: Request) -> Response:
        from gwc.client.orders import parse_items

        async def do(who: Person) -> dict[str, Any]:
            data = await body(request)
            customer = str(data.get("customer") or "").strip()
            if not customer:
                raise GwcError("customer: a customer id is needed")
            raw = data.get("items") or ""
            words = raw if isinstance(raw, list) else [w for w in re.split(r"[\s,]+", str(raw).strip()) if w]
            items = parse_items(tuple(str(w) for w in words))
            priority = data.get("priority") or None
            made = await web.actions.enter_order(customer, items, int(priority) if priority else None)
            return {
                "work_order_id": made["work_order_id"],
                "lots": [
                    {"lot_id": lot["lot_id"], "product_id": lot["product_id"], "entities": lot["entities"]}
                    for lot in made["lots"]
                ],
            }

        return await perform(request, Action.ORDER_ENTER, "new order", do)

    async def api_downtime_reason(request: Request) -> Response:
        event = int(request.path_params["event_id"])

        async def do(who: Person) -> str:
            reason = str((await body(request)).get("reason") or "").strip()
            if not reason:
                raise GwcError('give {"reason": REASON}, one of the reason tree\'s (GET /api/record: reasons)')
            return await web.actions.downtime_reason(event, reason, who.by)

        return await perform(request, Action.DOWNTIME_REASON, str(event), do)

    async def api_recipe_approve(request: Request) -> Response:
        recipe = request.path_params["recipe_id"]

        async def do(who: Person) -> str:
            version = (await body(request)).get("version")
            if version is not None and (isinstance(version, bool) or not isinstance(version, int)):
                raise GwcError('version: a whole number, or none for the latest ({"version": 3})')
            return await web.actions.approve_recipe(recipe, version, who.by)

        return await perform(request, Action.RECIPE_APPROVE, recipe, do)

    # ------------------------------------------------------------------ the record and quality

    def looking(read: Callable[[Request], Awaitable[Any]]) -> Callable[[Request], Awaitable[Response]]:
        """A GET of the record's or quality's pages: a session, then `read`; bad input a 400."""

        async def get(request: Request) -> Response:
            try:
                session_of(request)
                data = await read(request)
            except HttpError as e:
                return _error(e.status, str(e))
            except (DatabaseError, DatabaseUnavailable) as e:
                return _error(503, str(e))
            except (GwcError, ValueError) as e:
                return _error(400, str(e))
            return JSONResponse(data, headers={"Cache-Control": "no-store"})

        return get

    async def read_record(request: Request) -> Any:
        q = request.query_params
        a, b = view.window(web.reader.cfg, q.get("since"), q.get("until"))
        return await web.reader.run(lambda c: view.record_view(web.reader.cfg, c, a, b))

    async def read_spc(request: Request) -> Any:
        machine = request.query_params.get("machine") or None
        return await web.reader.run(lambda c: view.spc_view(web.reader.cfg, c, machine))

    async def read_trace(request: Request) -> Any:
        entity = int(request.path_params["entity_id"])
        return await web.reader.run(lambda c: view.trace_view(c, entity))

    async def read_where(request: Request) -> Any:
        q = request.query_params
        if not any(q.get(k) for k in ("machine", "recipe", "since", "until")):
            raise GwcError("say where: machine, recipe (RECIPE or RECIPE@VERSION), since or until")
        cfg = web.reader.cfg
        return await web.reader.run(
            lambda c: view.where_view(cfg, c, q.get("machine"), q.get("recipe"), q.get("since"), q.get("until"))
        )

    async def read_recipes(request: Request) -> Any:
        from gwc.client.recipes import list_recipes

        return plain(await asyncio.to_thread(list_recipes, web.reader.cfg))

    async def page(request: Request) -> Response:
        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-store"})

    routes = [
        Route("/", page),
        Route("/api/login", api_login, methods=["POST"]),
        Route("/api/logout", api_logout, methods=["POST"]),
        Route("/api/session", api_session),
        Route("/api/events", api_events),
        Route("/api/audit", api_audit),
        *(
            Route(f"/api/{t}", reading(t))
            for t in ("machines", "alarms", "lots", "orders", "requests", "modules", "order_form")
        ),
        Route("/api/machines/{machine_id}/{verb}", api_machine, methods=["POST"]),
        Route("/api/alarms/{alarm_no:int}/clear", api_alarm_clear, methods=["POST"]),
        Route("/api/lots/{entity_id:int}/{verb}", api_lot, methods=["POST"]),
        Route("/api/orders", api_order, methods=["POST"]),
        Route("/api/downtime/{event_id:int}/reason", api_downtime_reason, methods=["POST"]),
        Route("/api/recipes/{recipe_id}/approve", api_recipe_approve, methods=["POST"]),
        Route("/api/record", looking(read_record)),
        Route("/api/spc", looking(read_spc)),
        Route("/api/trace/entity/{entity_id:int}", looking(read_trace)),
        Route("/api/trace/where", looking(read_where)),
        Route("/api/recipes", looking(read_recipes)),
        Mount("/static", StaticFiles(directory=STATIC), name="static"),
    ]
    return Starlette(routes=routes, middleware=[Middleware(SecurityHeaders)])


class SecurityHeaders:
    """Adds HEADERS to every response (pure ASGI: the event stream passes through unbuffered)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                MutableHeaders(scope=message).update(HEADERS)
            await send(message)

        await self.app(scope, receive, with_headers)
