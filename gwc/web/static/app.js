// The GWC web HMI: plain JavaScript, no build step. It reads the HTTP API (GET), acts with POSTs that
// carry the session's CSRF token, and keeps every table live from the server's events (/api/events).
"use strict";

const state = { csrf: null, may: [], data: {}, tab: "machines" };
const $ = (id) => document.getElementById(id);

function say(text, ok) {
  const m = $("message");
  m.textContent = text;
  m.className = ok ? "ok" : "error";
}

async function api(method, path, body) {
  const headers = { "Accept": "application/json" };
  if (method !== "GET") headers["X-CSRF-Token"] = state.csrf || "";
  if (body !== undefined) headers["Content-Type"] = "application/json";
  const r = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body),
                                credentials: "same-origin" });
  let data = null;
  try { data = await r.json(); } catch (e) { data = null; }
  if (r.status === 401 && path !== "/api/login") showLogin();
  if (!r.ok) throw new Error((data && data.error) || r.statusText);
  return data;
}

async function act(path, body, done) {
  try {
    const out = await api("POST", path, body);
    say(done ? done(out) : (out.note || "done"), true);
  } catch (e) {
    say(e.message, false);
  }
}

function cell(text) {
  const td = document.createElement("td");
  td.textContent = text === null || text === undefined ? "" : String(text);
  return td;
}

function button(label, onclick, needs) {
  const b = document.createElement("button");
  b.textContent = label;
  b.onclick = onclick;
  if (needs && !state.may.includes(needs)) b.hidden = true;
  return b;
}

function table(id, rows, columns, extra) {
  const t = $(id);
  t.replaceChildren();
  const head = document.createElement("tr");
  for (const c of columns) { const th = document.createElement("th"); th.textContent = c; head.appendChild(th); }
  if (extra) head.appendChild(document.createElement("th"));
  t.appendChild(head);
  for (const r of rows) {
    const tr = document.createElement("tr");
    for (const c of columns) tr.appendChild(cell(r[c]));
    if (extra) { const td = document.createElement("td"); for (const b of extra(r)) td.appendChild(b); tr.appendChild(td); }
    t.appendChild(tr);
  }
}

const render = {
  machines(rows) {
    const tiles = $("machine-tiles");
    tiles.replaceChildren();
    for (const m of rows) {
      const d = document.createElement("div");
      d.className = "tile " + m.status;
      d.id = "machine-" + m.machine_id;
      d.dataset.status = m.status;
      const h = document.createElement("h3"); h.textContent = m.machine_id; d.appendChild(h);
      const s = document.createElement("div"); s.className = "status"; s.textContent = m.status; d.appendChild(s);
      const run = document.createElement("div");
      run.textContent = m.machine_run_id ? `run ${m.machine_run_id} ${m.recipe_id || ""}` : (m.wc === "on bus" ? "WC on bus" : "WC off the bus");
      d.appendChild(run);
      d.appendChild(button("Start", () => act(`/api/machines/${m.machine_id}/start`), "machine.start"));
      d.appendChild(button("Stop", () => act(`/api/machines/${m.machine_id}/stop`), "machine.stop"));
      tiles.appendChild(d);
    }
    table("machine-table", rows, ["machine_id", "kind", "status", "recipe_id", "machine_run_id", "start_time", "end_time", "accepts", "wc", "runs", "scrap"]);
  },
  alarms(rows) {
    $("alarm-count").textContent = rows.length ? `(${rows.length})` : "";
    table("alarm-table", rows, ["alarm_no", "alarm_id", "machine_id", "alarm_text", "raised_by", "raised_at"],
          (a) => [button("Clear", () => act(`/api/alarms/${a.alarm_no}/clear`), "alarm.clear")]);
  },
  lots(rows) {
    table("lot-table", rows, ["entity", "lot", "work_order", "product", "owner", "state", "result", "script", "since"], (e) => {
      const out = [];
      if (e.state === "waiting_import") out.push(button("Import", () => act(`/api/lots/${e.entity}/import`), "lot.import"));
      if (e.state === "waiting_export") out.push(button("Export", () => act(`/api/lots/${e.entity}/export`), "lot.export"));
      if (e.state === "held") for (const d of ["retry", "reroute", "fail"])
        out.push(button(d, () => act(`/api/lots/${e.entity}/release`, { decision: d }), "lot.release"));
      return out;
    });
  },
  orders(rows) {
    table("order-table", rows, ["work_order", "customer", "items", "status", "lots", "created", "due"]);
  },
  requests(data) {
    table("request-table", data.waiting || [], Object.keys((data.waiting || [])[0] || { request_key: 0 }));
    table("reserved-table", data.reserved || [], Object.keys((data.reserved || [])[0] || { machine_id: 0 }));
  },
  modules(rows) {
    table("module-table", rows, ["module", "started"]);
  },
};

function show(topic, data) {
  state.data[topic] = data;
  if (render[topic]) render[topic](data);
}

async function loadAudit() {
  try {
    const rows = await api("GET", "/api/audit?limit=200");
    table("audit-table", rows.reverse(), ["audit_no", "at", "user_name", "role", "door", "address", "action", "target", "outcome", "note"]);
  } catch (e) { say(e.message, false); }
}

function switchTab(tab) {
  state.tab = tab;
  for (const s of document.querySelectorAll("section.tab")) s.hidden = s.id !== tab;
  for (const b of document.querySelectorAll("#tabs button")) b.classList.toggle("on", b.dataset.tab === tab);
  if (tab === "audit") loadAudit();
}

let events = null;
function listen() {
  if (events) events.close();
  events = new EventSource("/api/events");
  events.onopen = () => { $("live").textContent = "live"; };
  events.onerror = () => { $("live").textContent = "reconnecting..."; };
  for (const topic of ["machines", "alarms", "lots", "orders", "requests", "modules"])
    events.addEventListener(topic, (ev) => show(topic, JSON.parse(ev.data)));
  events.addEventListener("logout", () => { events.close(); showLogin(); });
}

function showLogin() {
  if (events) { events.close(); events = null; }
  state.csrf = null;
  $("login").hidden = false;
  $("tabs").hidden = true;
  $("who").hidden = true;
  for (const s of document.querySelectorAll("section.tab")) s.hidden = true;
  $("live").textContent = "not connected";
}

async function start() {
  let s;
  try { s = await api("GET", "/api/session"); } catch (e) { showLogin(); return; }
  state.csrf = s.csrf;
  state.may = s.may;
  $("login").hidden = true;
  $("tabs").hidden = false;
  $("who").hidden = false;
  $("user").textContent = `${s.user} (${s.role})`;
  for (const el of document.querySelectorAll("[data-needs]")) el.hidden = !state.may.includes(el.dataset.needs);
  switchTab(state.tab);
  for (const topic of ["machines", "alarms", "lots", "orders", "requests", "modules"])
    api("GET", "/api/" + topic).then((d) => show(topic, d)).catch(() => {});
  api("GET", "/api/order_form").then((f) => {
    for (const [id, items] of [["order-customer", f.customers], ["order-product", f.products]]) {
      const sel = $(id);
      sel.replaceChildren(...items.map((v) => { const o = document.createElement("option"); o.value = o.textContent = v; return o; }));
    }
  }).catch(() => {});
  listen();
}

document.addEventListener("DOMContentLoaded", () => {
  $("login").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    try {
      await api("POST", "/api/login", { user: $("login-user").value, password: $("login-password").value });
      $("login-password").value = "";
      say("", true);
      await start();
    } catch (e) { say(e.message, false); }
  });
  $("logout").onclick = async () => { await act("/api/logout"); showLogin(); };
  for (const b of document.querySelectorAll("#tabs button")) b.onclick = () => switchTab(b.dataset.tab);
  $("audit-reload").onclick = loadAudit;
  $("order-form").addEventListener("submit", (ev) => {
    ev.preventDefault();
    const items = `${$("order-product").value}=${$("order-quantity").value}`;
    act("/api/orders", { customer: $("order-customer").value, items },
        (o) => `work order ${o.work_order_id}: ` + o.lots.map((l) => `lot ${l.lot_id} (${l.entities.length} x ${l.product_id})`).join(", "));
  });
  start();
});
