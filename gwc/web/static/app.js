// The GWC web HMI: plain JavaScript, no build step. It reads the HTTP API (GET), acts with POSTs that
// carry the session's CSRF token, and keeps every table live from the server's events (/api/events).
"use strict";

const state = { csrf: null, may: [], data: {}, tab: "machines", window: "" };
const LIVE = ["machines", "alarms", "lots", "orders", "requests", "modules", "record", "spc"];
const RECORD_TABS = ["oee", "timeline", "downtime"];
const E10 = { productive: "#2e9d4a", standby: "#f2c94c", engineering: "#9b59b6", scheduled_downtime: "#2f80ed",
              unscheduled_downtime: "#d64545", non_scheduled: "#9aa3ad" };
const SVG = "http://www.w3.org/2000/svg";
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

function svg(tag, attrs, text) {
  const el = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs || {})) el.setAttribute(k, String(v));
  if (text !== undefined) { const t = document.createElementNS(SVG, "title"); t.textContent = text; el.appendChild(t); }
  return el;
}

const pct = (x) => (x === null || x === undefined ? "-" : (100 * x).toFixed(1) + "%");
const num = (x, d) => (x === null || x === undefined ? "-" : Number(x).toFixed(d === undefined ? 3 : d));

// Horizontal bars, one row per item: [label, [[value 0..1 or seconds, colour, tip], ...]]; scale = the 100% value.
function bars(el, rows, scale, fmt) {
  el.replaceChildren();
  const rowH = 22, label = 120, width = Number(el.getAttribute("width")) - label - 60;
  el.setAttribute("height", Math.max(1, rows.length) * rowH + 4);
  rows.forEach(([name, items], i) => {
    const y = 2 + i * rowH;
    el.appendChild(svg("text", { x: 0, y: y + 14, class: "label" })).textContent = name;
    const h = (rowH - 4) / items.length;
    items.forEach(([v, colour, tip], j) => {
      const w = Math.max(0.5, (Number(v) || 0) / (scale || 1) * width);
      el.appendChild(svg("rect", { x: label, y: y + j * h, width: w, height: h - 1, fill: colour }, tip));
    });
    el.appendChild(svg("text", { x: label + width + 4, y: y + 14, class: "label" })).textContent = fmt(items[items.length - 1][0]);
  });
}

function drawTimelines(data) {
  const out = $("timelines");
  out.replaceChildren();
  // The axis starts at the window's start, or at the first thing known in it (a young cell's few
  // minutes drawn across the width, not as a sliver at the end of 8 hours).
  const firsts = Object.values(data.timelines).filter((s) => s.length).map((s) => Date.parse(s[0].start));
  const since = Math.max(Date.parse(data.since), Math.min(...firsts, Infinity) === Infinity ? 0 : Math.min(...firsts));
  const span = (Date.parse(data.until) - since) || 1, width = 900;
  $("timeline-axis").textContent = `${new Date(since).toISOString().slice(0, 19)} to ${data.until.slice(0, 19)} UTC`;
  for (const [machine, segs] of Object.entries(data.timelines)) {
    const row = document.createElement("div");
    row.className = "machine-line";
    const name = document.createElement("span"); name.className = "name"; name.textContent = machine; row.appendChild(name);
    const s = svg("svg", { id: "timeline-" + machine, class: "timeline", width, height: 22, "data-machine": machine });
    for (const g of segs) {
      const x = (Date.parse(g.start) - since) / span * width, w = Math.max(0.5, g.seconds * 1000 / span * width);
      s.appendChild(svg("rect", { x: x.toFixed(2), y: 0, width: w.toFixed(2), height: 22, fill: E10[g.e10] || "#666",
                                   "data-e10": g.e10, "data-status": g.status },
                        `${g.status} (${g.e10}, ${g.cause}) ${g.start.slice(11, 19)}-${g.end.slice(11, 19)} ${Math.round(g.seconds)} s`));
    }
    row.appendChild(s);
    out.appendChild(row);
  }
  const legend = $("timeline-legend");
  legend.replaceChildren(...Object.entries(E10).map(([k, c]) => {
    const sp = document.createElement("span");
    const box = svg("svg", { width: 12, height: 12 }); box.appendChild(svg("rect", { width: 12, height: 12, fill: c }));
    sp.appendChild(box); sp.append(" " + k.replace("_", " "));
    return sp;
  }));
}

function drawRecord(data) {
  $("record-span").textContent = `${data.since.slice(0, 19)} to ${data.until.slice(0, 19)} UTC, cell OEE ${pct(data.oee.cell.oee)}`;
  const rows = [...data.oee.machines, { machine_id: "(cell)", ...data.oee.cell }];
  table("oee-table", rows.map((r) => ({ ...r, availability: pct(r.availability), performance: pct(r.performance),
                                           quality: pct(r.quality), oee: pct(r.oee) })),
        ["machine_id", "planned_s", "run_s", "down_s", "availability", "performance", "quality", "oee", "parts", "good_parts"]);
  bars($("oee-chart"), rows.map((r) => [r.machine_id, [[r.availability, "#9ec5e8", "availability " + pct(r.availability)],
                                                        [r.performance, "#b5dcb3", "performance " + pct(r.performance)],
                                                        [r.quality, "#f5d89a", "quality " + pct(r.quality)],
                                                        [r.oee, "#2e86de", "OEE " + pct(r.oee)]]]), 1, pct);
  drawTimelines(data);
  const pareto = data.oee.cell.downtime;
  const most = Math.max(1, ...pareto.map((d) => d.seconds));
  bars($("pareto-chart"), pareto.map((d) => [d.reason || "(none given)", [[d.seconds, "#d64545", `${d.events} event(s)`]]]),
       most, (v) => `${Math.round(v)} s`);
  const reasons = Object.values(data.reasons).flat();
  table("downtime-table", [...data.downtime].reverse(), ["event_id", "machine_id", "started_at", "ended_at", "cause", "reason", "e10_state"],
        (ev) => {
          if (!state.may.includes("downtime.reason")) return [];
          const sel = document.createElement("select");
          sel.id = "reason-" + ev.event_id;
          for (const [category, rs] of Object.entries(data.reasons)) {
            const g = document.createElement("optgroup"); g.label = category;
            for (const r of rs) { const o = document.createElement("option"); o.value = o.textContent = r; g.appendChild(o); }
            sel.appendChild(g);
          }
          if (ev.reason && reasons.includes(ev.reason)) sel.value = ev.reason;
          return [sel, button("Set reason", () => act(`/api/downtime/${ev.event_id}/reason`, { reason: sel.value }), "downtime.reason")];
        });
}

function drawSpc(charts) {
  const out = $("spc-charts");
  out.replaceChildren();
  if (!charts.length) { const p = document.createElement("p"); p.textContent = "No measured features yet."; out.appendChild(p); }
  for (const c of charts) {
    const box = document.createElement("div");
    box.className = "spc-chart";
    box.id = `spc-${c.machine_id}-${c.recipe_id}-${c.feature}`;
    const h = document.createElement("h3");
    h.textContent = `${c.machine_id} ${c.recipe_id} ${c.feature}: Cp ${num(c.cp, 2)}, Cpk ${num(c.cpk, 2)}, ` +
                    `${c.violations.length} rule(s) broken, ${c.out_of_tolerance} out of tolerance`;
    box.appendChild(h);
    const w = 640, ht = 170, pad = 10, v = c.values;
    const lsl = c.nominal - c.tol, usl = c.nominal + c.tol;
    const lines = [["USL", usl, "#999", "1 3"], ["LSL", lsl, "#999", "1 3"]];
    if (c.ucl !== null) lines.push(["UCL", c.ucl, "#c33", "4 3"], ["CL", c.center, "#393", ""], ["LCL", c.lcl, "#c33", "4 3"]);
    const lo = Math.min(...v, ...lines.map((l) => l[1])), hi = Math.max(...v, ...lines.map((l) => l[1])), span = (hi - lo) || 1;
    const y = (x) => pad + (hi - x) / span * (ht - 2 * pad), x = (i) => pad + i * (w - 2 * pad) / Math.max(1, v.length - 1);
    const s = svg("svg", { width: w, height: ht, class: "spc" });
    for (const [name, val, colour, dash] of lines)
      s.appendChild(svg("line", { x1: pad, x2: w - pad, y1: y(val).toFixed(1), y2: y(val).toFixed(1), stroke: colour,
                                  "stroke-dasharray": dash }, `${name} ${num(val, 4)}`));
    s.appendChild(svg("polyline", { points: v.map((p, i) => `${x(i).toFixed(1)},${y(p).toFixed(1)}`).join(" "),
                                    fill: "none", stroke: "#333", "stroke-width": 1 }));
    const bad = new Map(c.violations.map((b) => [b.part - 1, b.text]));
    v.forEach((p, i) => s.appendChild(svg("circle", { cx: x(i).toFixed(1), cy: y(p).toFixed(1), r: bad.has(i) ? 3.5 : 2,
                                                       fill: bad.has(i) ? "#d00" : "#333", "data-broken": bad.has(i) ? 1 : 0 },
                                          `part ${i + 1}: ${num(p, 4)}${bad.has(i) ? " - " + bad.get(i) : ""}`)));
    box.appendChild(s);
    out.appendChild(box);
  }
}

async function loadRecord() {
  try {
    const data = await api("GET", "/api/record" + (state.window ? `?since=${encodeURIComponent(state.window)}` : ""));
    if (state.window) drawRecord(data); else show("record", data);
  } catch (e) { say(e.message, false); }
}

async function loadRecipes() {
  try {
    const rows = await api("GET", "/api/recipes");
    table("recipe-table", rows, ["recipe_id", "versions", "approved", "checksum", "file", "machines", "description"], (r) =>
      (r.approved !== r.versions || r.file !== "ok")
        ? [button(`Approve v${r.versions}`, () => act(`/api/recipes/${encodeURIComponent(r.recipe_id)}/approve`, { version: r.versions }, (o) => { loadRecipes(); return o.note; }), "recipe.approve")]
        : []);
  } catch (e) { say(e.message, false); }
}

async function trace(entity) {
  const out = $("trace-result");
  out.replaceChildren();
  try {
    const t = await api("GET", `/api/trace/entity/${entity}`);
    const h = document.createElement("h3");
    h.id = "trace-head";
    h.textContent = `entity ${t.entity_id}, lot ${t.lot_id}, work order ${t.work_order_id}: ${t.state}`;
    out.appendChild(h);
    for (const [id, rows, cols] of [
      ["trace-steps", t.steps.map((s) => ({ ...s, recipe: `${s.recipe_id}@${s.recipe_version}`,
                                            results: Object.entries(s.results || {}).map(([k, v]) => `${k}=${v}`).join(" ") })),
       ["machine_id", "recipe", "machine_run_id", "started_at", "ended_at", "verdict", "results"]],
      ["trace-actions", t.actions, ["at", "action", "by"]],
      ["trace-states", t.states, ["at", "state", "lot_id", "reason"]],
    ]) { const tb = document.createElement("table"); tb.id = id; out.appendChild(tb); table(id, rows, cols); }
  } catch (e) { say(e.message, false); }
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
    $("machine-names").replaceChildren(...rows.map((m) => { const o = document.createElement("option"); o.value = m.machine_id; return o; }));
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
  // The record and the charts are big: drawn only while their tab is shown (and when it is chosen).
  record(data) {
    if (!state.window && RECORD_TABS.includes(state.tab)) drawRecord(data);  // a chosen window is not live
  },
  spc(charts) {
    if (state.tab === "spc") drawSpc(charts);
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
  $("record-bar").hidden = !RECORD_TABS.includes(tab);
  if (tab === "audit") loadAudit();
  if (tab === "recipes") loadRecipes();
  if (RECORD_TABS.includes(tab) && !state.window && state.data.record) drawRecord(state.data.record);
  if (tab === "spc" && state.data.spc) drawSpc(state.data.spc);
}

let events = null;
function listen() {
  if (events) events.close();
  events = new EventSource("/api/events");
  events.onopen = () => { $("live").textContent = "live"; };
  events.onerror = () => { $("live").textContent = "reconnecting..."; };
  for (const topic of LIVE)
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
  for (const topic of LIVE.filter((t) => t !== "record"))
    api("GET", "/api/" + topic).then((d) => show(topic, d)).catch(() => {});
  api("GET", "/api/order_form").then((f) => {
    for (const [id, items] of [["order-customer", f.customers], ["order-product", f.products]]) {
      const sel = $(id);
      sel.replaceChildren(...items.map((v) => { const o = document.createElement("option"); o.value = o.textContent = v; return o; }));
    }
  }).catch(() => {});
  loadRecord();
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
  $("recipes-reload").onclick = loadRecipes;
  $("record-window").onchange = () => { state.window = $("record-window").value; loadRecord(); };
  $("trace-form").addEventListener("submit", (ev) => { ev.preventDefault(); trace($("trace-entity").value); });
  $("where-form").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const q = new URLSearchParams();
    for (const k of ["machine", "recipe", "since", "until"]) if ($("where-" + k).value) q.set(k, $("where-" + k).value);
    try {
      const rows = await api("GET", "/api/trace/where?" + q);
      table("where-table", rows, ["entity_id", "machine_id", "machine_run_id", "recipe_id", "recipe_version", "started_at", "ended_at"],
            (r) => [button("Trace", () => { $("trace-entity").value = r.entity_id; trace(r.entity_id); })]);
    } catch (e) { say(e.message, false); }
  });
  $("order-form").addEventListener("submit", (ev) => {
    ev.preventDefault();
    const items = `${$("order-product").value}=${$("order-quantity").value}`;
    act("/api/orders", { customer: $("order-customer").value, items },
        (o) => `work order ${o.work_order_id}: ` + o.lots.map((l) => `lot ${l.lot_id} (${l.entities.length} x ${l.product_id})`).join(", "));
  });
  start();
});
