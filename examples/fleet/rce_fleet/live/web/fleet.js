// fleet.js: the operator's page for the rce warehouse fleet. An RCE client (rce.js) in its own
// robot namespace (robotID operator-XXXXXX): it adds container-side interfaces to the fleet's
// container and its own robot-side converters, connects them, and then
//   receives /fleet/state   (fleet/FleetState, container SubscriberInterface -> our PublisherConverter)
//   sends    /fleet/goal    (fleet/RobotGoal,  our SubscriberConverter -> container PublisherInterface)
//   sends    /fleet/block   (fleet/CellBlock)
//   sends    /fleet/mission (std_msgs/String "start" | "stop"), when the fleet has that topic;
//   sends    /fleet/task, /fleet/task_cancel and receives /fleet/tasks: the task panel (tasks.js).
// Drawing is one canvas redrawn by requestAnimationFrame (the map, grid and cell numbers are
// pre-rendered into an offscreen layer); fleet states only update the model. The robot status
// table is refreshed at most 4 times a second and only where a value changed.
//
// Robots out of coverage: given config.json's `relays`, the page asks relays.json (follower -> relay,
// as the master knows it) every RELAYS_EVERY ms and draws a line from each follower to its relay.
//
// Everything a test needs is in window.fleetView (see `view` below).

import { Client, RCEError, newId } from "./rce.js";
import { TaskPanel } from "./tasks.js";

const $ = (id) => document.getElementById(id);
const PALETTE = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#17becf",
                 "#bcbd22", "#7f7f7f", "#393b79", "#ad494a"];
const TRAIL_MAX = 1500;          // points kept per robot trail
const ACTION_TIMEOUT = 6000;     // ms to wait for the planner to confirm an action
const TABLE_EVERY = 250;         // ms between status table refreshes
const RELAYS_EVERY = 1000;       // ms between asks for the followers' relays (relays.json)

// ---------------------------------------------------------------------------------------------
// configuration: URL query (master, user, container, map, mission) > config.json next to the page >
// defaults (the master that serves the page, the fleet container cTag_01, map.png next to the page).
// Served by rce-fleet, config.json, map.png and relays.json need a credential (401 without): the login
// then first asks the fleet's server for a token (POST api/login, the same user and password) and
// sends it with those calls (apiLogin); the master field is filled from config.json after it. With
// config.door (rce-fleet serve) the RCE session goes through the fleet's server too (rce/ws on this
// page's origin, the token as its password): the server carries it as the fleet's own user and checks
// each frame for the person's role, so a viewer's page adds no interface that publishes.
// ---------------------------------------------------------------------------------------------
let apiToken = null;             // bearer token from the fleet's server (POST api/login), while logged in
let apiRole = null;              // the role that came with it (viewer, operator, admin)

function authed(path, init = {}) {
  const headers = { ...(init.headers || {}), ...(apiToken ? { Authorization: `Bearer ${apiToken}` } : {}) };
  return fetch(path, { cache: "no-store", ...init, headers });
}

async function loadConfig() {
  const cfg = { master: location.origin + "/", user: "", container: "cTag_01", map: "map.png",
                robotPrefix: "operator", missionTopic: null, title: "", apiLogin: false };
  try {
    const r = await authed("config.json");
    if (r.ok) Object.assign(cfg, await r.json());
    else if (r.status === 401) cfg.apiLogin = true;
  } catch (e) { /* no config.json: served by rce-master --static, defaults are right */ }
  const q = new URLSearchParams(location.search);
  for (const k of ["master", "user", "container", "map"]) if (q.get(k)) cfg[k] = q.get(k);
  if (q.get("mission")) cfg.missionTopic = q.get("mission");
  if (q.has("password")) {
    // never take a password from the URL (it ends up in history and logs)
    history.replaceState(null, "", location.pathname + location.search.replace(/([?&])password=[^&]*&?/, "$1"));
  }
  return cfg;
}

// ---------------------------------------------------------------------------------------------
// model
// ---------------------------------------------------------------------------------------------
const view = window.fleetView = {
  connected: false, robotID: null, container: null, phase: "login",
  updates: 0, seq: 0, lastUpdate: 0, rate: 0,
  numbersDrawn: null,    // whether every cell carries its number (only where cells are large enough)
  grid: null,            // {rows, cols, cell_w, cell_h, grid_x, grid_y, res, origin, free: [bool]}
  robots: {},            // name -> {x, y, yaw, cell, goal, path, state, replans, cancels, error, ...}
  order: [],             // robot names, sorted (colour index)
  blocked: [], blockedBy: {},
  errors: [],            // the fleet's recent errors (FleetState.errors)
  replans: 0, lastPlanMs: 0, maxPlanMs: 0,
  visits: {},            // name -> [[t, cell]] every cell change seen (for tests and the report)
  trails: {},            // name -> [[x, y]]
  selected: null,        // robot whose goal the next click sets
  log: [],               // [{id, t, kind: "info"|"ok"|"error"|"pending", text}]
  cloudErrors: [],       // ER texts
  mission: null,         // {available: bool, running: bool}
  map: { loaded: false, error: null, width: 0, height: 0 },
  listeners: [],         // fn(fleetState) called for every /fleet/state (tests record with it)
  fps: 0, drawMs: 0,     // frames per second, mean drawing time per frame (ms)
  relays: {},            // follower -> relay robot (relays.json), while its link goes through the relay
  placement: null,       // --edge-hosts: {containers, moves} (placement.json), where compute runs
  relayLines: [],        // the follower -> relay lines the last frame drew: {follower, relay, from, to} (canvas px)
  // helpers for tests (client coordinates, CSS px); applyState draws a fleet state as if it came
  // from the cloud (replays, rendering tests)
  applyState: (st) => onFleetState(st),
  cellCenterClient: (cell) => cellCenterClient(cell),
  robotClient: (name) => robotClient(name),
  cellAtClient: (x, y) => cellAtClient(x, y),
};

let client = null;
let cfg = null;
let tags = null;                 // our interface tags
let pending = [];                // actions waiting for confirmation
let lastErrors = [];
let staticLayer = null, staticKey = "";
let drawn = {};                  // name -> {x, y, yaw} smoothed for drawing
let hoverCell = -1;
const NUMBERS_MIN_PX = 30;      // CSS px of a cell's shorter side from which every cell carries its number
let taskPanel = null;            // the task form, queue, robots' work and plots (tasks.js)
let needTable = true, lastTable = 0;
let rateWindow = [];

function colour(name) {
  const i = view.order.indexOf(name);
  return PALETTE[(i < 0 ? 0 : i) % PALETTE.length];
}

// ---------------------------------------------------------------------------------------------
// log of actions and their results
// ---------------------------------------------------------------------------------------------
let logSeq = 0;
function log(kind, text) {
  const e = { id: ++logSeq, t: Date.now(), kind, text };
  view.log.push(e);
  if (view.log.length > 300) view.log.shift();
  const li = document.createElement("li");
  li.className = kind;
  li.dataset.id = e.id;
  li.innerHTML = `<time>${new Date(e.t).toLocaleTimeString()}</time> `;
  li.append(document.createTextNode(text));
  const ol = $("log");
  ol.prepend(li);
  while (ol.children.length > 120) ol.lastChild.remove();
  return e;
}

function settle(e, kind, text) {
  e.kind = kind;
  e.text = text;
  const li = document.querySelector(`#log li[data-id="${e.id}"]`);
  if (li) {
    li.className = kind;
    li.lastChild.textContent = text;
  }
}

/** Track an action: `check(fleetState)` returns null (not yet), or [ok, text]. `match(errText)`
 * tells whether a new fleet error is about this action. An ER within the first second fails it. */
function track(text, check, match) {
  const e = log("pending", `${text}: sent`);
  pending.push({ e, text, check, match, t: Date.now(), deadline: Date.now() + ACTION_TIMEOUT });
  return e;
}

function resolvePending(st, newErrors) {
  const now = Date.now();
  pending = pending.filter((p) => {
    const err = newErrors.find((x) => p.match && p.match(x));
    if (err) { settle(p.e, "error", `${p.text}: refused by the planner: ${err}`); return false; }
    const r = st ? p.check(st) : null;
    if (r) { settle(p.e, r[0] ? "ok" : "error", `${p.text}: ${r[1]}`); return false; }
    if (now > p.deadline) {
      settle(p.e, "error", `${p.text}: no confirmation from the fleet within ${ACTION_TIMEOUT / 1000} s`);
      return false;
    }
    return true;
  });
}

// errors the fleet reports are a bounded list, newest last: what is new since last time?
function newSince(prev, cur) {
  if (!prev.length) return cur.slice();
  for (let k = 0; k <= prev.length; k++) {
    const tail = prev.slice(k);
    if (tail.length <= cur.length && tail.every((v, i) => cur[i] === v)) return cur.slice(tail.length);
  }
  return cur.slice();
}

// ---------------------------------------------------------------------------------------------
// login and interface setup
// ---------------------------------------------------------------------------------------------
async function apiLogin(user, password) {
  // the fleet's server: a token for config.json, map.png and relays.json, then the configuration
  const r = await fetch("api/login", { method: "POST", cache: "no-store", headers: { "Content-Type": "application/json" },
                                       body: JSON.stringify({ user, password }) });
  const a = await r.json().catch(() => ({}));
  if (!r.ok) throw new Error(`the fleet's server refused the login: ${a.error || `HTTP ${r.status}`}`);
  apiToken = a.token;
  apiRole = a.role;
  cfg = { ...(await loadConfig()), apiLogin: true };
  view.config = { ...cfg };
  $("master").value = cfg.master;
  if (!$("container").value.trim()) $("container").value = cfg.container;
  if (cfg.title) $("title").textContent = cfg.title;
  await loadMap();
  startRelays();
  startPlacement();
}

async function apiLogout() {
  if (!apiToken) return;
  const r = authed("api/logout", { method: "POST" });
  apiToken = null;
  await r.catch(() => { /* the server is gone: the token dies with it */ });
}

async function onLogin(ev) {
  ev.preventDefault();
  const btn = $("login-btn");
  btn.disabled = true;
  $("login-error").textContent = "";
  const password = $("password").value;
  $("password").value = "";
  const robotID = `${cfg.robotPrefix}-${newId().slice(0, 6)}`;
  let c = null;
  view.phase = "connecting";
  setConn("connecting", "wait");
  try {
    if (cfg.apiLogin || apiToken) await apiLogin($("user").value.trim(), password);
    const container = $("container").value.trim() || cfg.container;
    // reconnect: a lost link is resumed with the session token the client keeps (the password is gone);
    // maxLag 0: an operator's commands (tasks, cancels, goals, blocks) are never shed by a loaded endpoint
    const door = apiToken && cfg.door ? new URL(cfg.door, location.href) : null;
    if (door) door.protocol = location.protocol === "https:" ? "wss:" : "ws:";
    c = new Client({ master: $("master").value.trim(), userID: $("user").value.trim(), robotID,
                     password: door ? apiToken : password, endpoint: door ? door.href : null,
                     reconnect: true, maxLag: 0 });
    await c.connect();
    client = c;
    view.updates = 0;                 // a new session: its first state is announced again
    lastErrors = [];
    pending = [];
    view.robotID = robotID;
    view.container = container;
    c.on("close", onClosed);
    c.on("notice", (t) => log("info", t));
    c.on("disconnected", (why) => {
      setConn("link lost; resuming", "wait");
      log("error", `link to the cloud lost (${why}); resuming`);
    });
    c.on("resumed", (st) => {
      setConn(`${c.userID} / ${c.robotID}`, "on");
      log("info", `session resumed${st.dropped ? ` (${st.dropped} message(s) from the cloud lost)` : ""}`);
    });
    c.on("status", onStatus);
    setConn(`connected as ${$("user").value.trim()} / ${robotID}`, "wait");
    log("info", `logged in at ${$("master").value.trim()}; robot endpoint ${c.wsUrl}`);
    await setupInterfaces(c, container, robotID);   // its requests report their own ERs
    c.on("error", onCloudError);
    view.connected = true;
    view.phase = "running";
    setConn(`${$("user").value.trim()} / ${robotID}`, "on");
    $("login").hidden = true;
    $("controls").hidden = false;
    $("logout").hidden = false;
  } catch (e) {
    view.phase = "login";
    view.loginError = e.message;
    $("login-error").textContent = e.message;
    setConn("offline", "off");
    log("error", e.message);
    if (c && !c.closed) {
      await cleanup(c);
      await new Promise((r) => setTimeout(r, 300));   // let the removal go out before we leave
      c.close();
    }
    client = null;
    await apiLogout();
  } finally {
    btn.disabled = false;
  }
}

async function setupInterfaces(c, ctag, rid) {
  const s = rid.replace(/[^A-Za-z0-9_-]/g, "_");
  tags = {
    state: "state", goal: "goal", block: "block", mission: "mission", task: "task", cancel: "taskCancel",
    tasks: "tasks",
    cstate: `${s}_state`, cgoal: `${s}_goal`, cblock: `${s}_block`, cmission: `${s}_mission`,
    ctask: `${s}_task`, ccancel: `${s}_taskCancel`, ctasks: `${s}_tasks`,
  };
  // lane (control, state, bulk; docs/lanes.md): omitted, it comes from the class
  const I = (e, t, type, cls, addr, lane) => ({ endpointTag: e, interfaceTag: t, interfaceType: type, className: cls,
                                                 ...(addr ? { addr } : {}), ...(lane ? { lane } : {}) });
  const ifaces = [
    I(ctag, tags.cstate, "SubscriberInterface", "fleet/FleetState", "/fleet/state"),
    I(ctag, tags.cgoal, "PublisherInterface", "fleet/RobotGoal", "/fleet/goal"),
    I(ctag, tags.cblock, "PublisherInterface", "fleet/CellBlock", "/fleet/block"),
    I(rid, tags.state, "PublisherConverter", "fleet/FleetState"),
    I(rid, tags.goal, "SubscriberConverter", "fleet/RobotGoal", null, "control"),
    I(rid, tags.block, "SubscriberConverter", "fleet/CellBlock", null, "control"),
    I(ctag, tags.ctask, "PublisherInterface", "fleet/Task", "/fleet/task"),
    I(ctag, tags.ccancel, "PublisherInterface", "fleet/TaskCancel", "/fleet/task_cancel"),
    I(ctag, tags.ctasks, "SubscriberInterface", "fleet/TaskList", "/fleet/tasks"),
    I(rid, tags.task, "SubscriberConverter", "fleet/Task", null, "control"),
    I(rid, tags.cancel, "SubscriberConverter", "fleet/TaskCancel", null, "control"),
    I(rid, tags.tasks, "PublisherConverter", "fleet/TaskList"),
  ];
  const pairs = [[`${ctag}/${tags.cstate}`, `${rid}/${tags.state}`], [`${ctag}/${tags.cgoal}`, `${rid}/${tags.goal}`],
                 [`${ctag}/${tags.cblock}`, `${rid}/${tags.block}`], [`${ctag}/${tags.ctask}`, `${rid}/${tags.task}`],
                 [`${ctag}/${tags.ccancel}`, `${rid}/${tags.cancel}`], [`${ctag}/${tags.ctasks}`, `${rid}/${tags.tasks}`]];
  let up = [tags.state, tags.goal, tags.block, tags.task, tags.cancel, tags.tasks];
  if (cfg.missionTopic) {
    ifaces.push(I(ctag, tags.cmission, "PublisherInterface", "std_msgs/String", cfg.missionTopic),
                I(rid, tags.mission, "SubscriberConverter", "std_msgs/String"));
    pairs.push([`${ctag}/${tags.cmission}`, `${rid}/${tags.mission}`]);
    up.push(tags.mission);
  }
  if (apiRole === "viewer") {            // watches only: the fleet's server refuses what would publish
    const reads = [tags.state, tags.tasks];
    up = reads;
    ifaces.splice(0, ifaces.length, ...ifaces.filter((i) => !["PublisherInterface", "SubscriberConverter"]
      .includes(i.interfaceType)));
    pairs.splice(0, pairs.length, ...pairs.filter(([, b]) => reads.includes(b.split("/")[1])));
  }
  c.subscribe(tags.state, onFleetState);
  taskPanel = taskPanel || new TaskPanel({
    view, $, log, settle, places: cfg.places || [],
    send: (kind, msg) => publish(kind === "task" ? tags.task : tags.cancel,
                                 kind === "task" ? "fleet/Task" : "fleet/TaskCancel", msg),
  });
  c.subscribe(tags.tasks, (msg) => taskPanel.onList(msg));
  const step = (t) => { $("login-error").textContent = ""; log("info", t); };
  step(`adding interfaces to container ${ctag}`);
  try {
    await c.configure({ addInterfaces: ifaces });
  } catch (e) {
    const why = [...new Set(e.message.replace(/^CN: /, "").split("; "))].join("; ");
    throw new RCEError(e.kind, `cannot attach to the fleet container ${JSON.stringify(ctag)}: ${why}` +
                               (/does not exist/.test(why) ? " (is rce-fleet serve running for this user?)" : ""));
  }
  await c.connectInterfaces(pairs);
  await c.waitUp(up, 20000);
  view.mission = { available: !!cfg.missionTopic, running: false };
  $("mission").hidden = !cfg.missionTopic;
  step("interfaces up; waiting for the fleet state");
}

async function cleanup(c) {
  // container-side interfaces outlive our session (the master removes only robot-side ones): remove them
  if (!tags || !view.container) return;
  const rm = ["cstate", "cgoal", "cblock", "cmission", "ctask", "ccancel", "ctasks"].filter((k) => k !== "cmission" || cfg.missionTopic)
    .map((k) => ({ endpointTag: view.container, interfaceTag: tags[k] }));
  try { c.send("CN", { removeInterfaces: rm }); } catch (e) { /* closing anyway */ }
}

function onCloudError(reason) {
  view.cloudErrors.push(reason);
  // an ER right after an action is the cloud's answer to it (a message that does not fit its type,
  // an interface that went away); the robot endpoint answers DMs at once
  const p = pending.find((x) => Date.now() - x.t < 1500);
  if (p) {
    settle(p.e, "error", `${p.text}: the cloud refused it: ${reason}`);
    pending = pending.filter((x) => x !== p);
  } else if (/removeInterfaces|does not exist/.test(reason) && view.phase === "closing") {
    // cleanup of an interface that was never made
  } else {
    log("error", `cloud: ${reason}`);
  }
}

function onStatus(d) {
  if (d.topic === "iu" && d.status === false && view.connected) log("error", `interface ${d.iTag} lost its connection`);
  else if (d.topic === "container" && d.status === "lost") log("error", `container ${d.cTag} was lost`);
}

function onClosed() {
  const was = view.connected;
  view.connected = false;
  view.phase = "login";
  client = null;
  setConn("offline", "off");
  $("login").hidden = false;
  $("controls").hidden = true;
  $("logout").hidden = true;
  if (was) log("error", "connection to the cloud closed; log in again");
}

async function onLogout() {
  if (!client) return;
  const c = client;
  view.phase = "closing";
  $("logout").disabled = true;
  if (tags && view.container) {
    // remove our container interfaces and wait until the cloud has (bounded), then leave
    const rm = ["cstate", "cgoal", "cblock", "cmission", "ctask", "ccancel", "ctasks"].filter((k) => k !== "cmission" || cfg.missionTopic)
      .map((k) => ({ endpointTag: view.container, interfaceTag: tags[k] }));
    try {
      await Promise.race([c.request("CN", { removeInterfaces: rm }), new Promise((r) => setTimeout(r, 3000))]);
    } catch (e) {
      log("error", `logout: ${e.message}`);
    }
  }
  view.connected = false;
  $("logout").disabled = false;
  c.close();
  await apiLogout();
  log("info", "logged out");
}

function setConn(text, cls) {
  $("conn").textContent = text;
  $("conn").className = `pill ${cls}`;
}

// ---------------------------------------------------------------------------------------------
// fleet state
// ---------------------------------------------------------------------------------------------
function num(v) { return typeof v === "number" && Number.isFinite(v) ? v : null; }

function onFleetState(st) {
  const now = performance.now();
  view.updates++;
  view.seq = st.seq;
  rateWindow.push(now);
  while (rateWindow.length && now - rateWindow[0] > 2000) rateWindow.shift();
  view.rate = rateWindow.length > 1 ? (rateWindow.length - 1) / ((now - rateWindow[0]) / 1000) : 0;
  view.lastUpdate = Date.now();

  const free = Array.from(st.free || "", (ch) => ch === "1");
  const g = { rows: st.rows, cols: st.cols, cell_w: st.cell_w, cell_h: st.cell_h, grid_x: st.grid_x,
              grid_y: st.grid_y, res: st.map_resolution,
              origin: [st.map_origin?.x || 0, st.map_origin?.y || 0, st.map_origin?.theta || 0], free };
  if (!view.grid || JSON.stringify(view.grid) !== JSON.stringify(g)) {
    view.grid = g;
    staticKey = "";
  }
  view.blocked = (st.blocked || []).slice();
  view.blockedBy = {};
  view.blocked.forEach((c, i) => { view.blockedBy[c] = (st.blocked_by || [])[i] || ""; });
  view.replans = st.replans;
  view.lastPlanMs = st.last_plan_ms;
  view.maxPlanMs = st.max_plan_ms;

  const names = (st.robots || []).map((r) => r.robot).sort((a, b) => a.localeCompare(b, "en", { numeric: true }));
  if (names.join() !== view.order.join()) { view.order = names; needTable = true; }
  const seen = new Set();
  for (const r of st.robots || []) {
    seen.add(r.robot);
    const prev = view.robots[r.robot];
    const rec = { x: num(r.x), y: num(r.y), yaw: num(r.yaw), cell: r.cell, goal: r.goal, path: r.path || [],
                  cleared: r.cleared, plan: r.plan, replans: r.replans, cancels: r.cancels, state: r.state,
                  error: r.error, errorPermanent: r.error_permanent, clientState: r.client_state,
                  distanceLeft: r.distance_left };
    view.robots[r.robot] = rec;
    if (rec.x !== null && rec.y !== null) {
      const tr = view.trails[r.robot] || (view.trails[r.robot] = []);
      const last = tr[tr.length - 1];
      if (!last || Math.hypot(last[0] - rec.x, last[1] - rec.y) > 0.01) tr.push([rec.x, rec.y]);
      if (tr.length > TRAIL_MAX) tr.splice(0, tr.length - TRAIL_MAX);
    }
    const v = view.visits[r.robot] || (view.visits[r.robot] = []);
    if (!v.length || v[v.length - 1][1] !== rec.cell) v.push([Date.now(), rec.cell]);
    if (prev && prev.state !== rec.state) {
      const key = `${rec.state}:${rec.goal}:${rec.plan}`;
      if (rec.state === "arrived" && prev.announced !== key) log("ok", `${r.robot} arrived at cell ${rec.goal}`);
      else if (rec.state === "unreachable" && prev.announced !== key &&
               !view.log.slice(-6).some((l) => rec.error && l.text.includes(rec.error))) {
        log("error", `${r.robot}: goal ${rec.goal} unreachable: ${rec.error}`);
      }
      rec.announced = key;
    } else if (prev) rec.announced = prev.announced;
    if (prev && prev.cancels !== rec.cancels) log("info", `${r.robot}: path cancelled and re-planned (cancelGoal)`);
  }
  for (const n of Object.keys(view.robots)) if (!seen.has(n)) delete view.robots[n];
  if (view.selected && !view.robots[view.selected]) select(null);

  const errs = st.errors || [];
  const fresh = newSince(lastErrors, errs);
  lastErrors = errs.slice();
  view.errors = errs.slice();
  const before = pending.length;
  resolvePending(st, fresh);
  // fleet errors that were no action's answer are shown as they come (not on the first state)
  if (view.updates > 1) {
    for (const e of fresh) if (!view.log.some((l) => l.text.includes(e))) log("error", `fleet: ${e}`);
  }
  if (before !== pending.length || view.updates === 1) needTable = true;
  if (view.updates === 1) log("ok", `fleet state received: ${st.rows}x${st.cols} grid, ${names.length} robot(s)`);
  needTable = true;
  for (const fn of view.listeners) {
    try { fn(st); } catch (e) { console.error("fleetView listener failed", e); }
  }
}

// ---------------------------------------------------------------------------------------------
// actions
// ---------------------------------------------------------------------------------------------
function publish(iTag, type, msg) {
  if (!client) throw new RCEError("closed", "not connected");
  client.publish(iTag, type, msg);
}

function toggleBlock(cell) {
  const g = view.grid;
  const block = !view.blocked.includes(cell);
  const what = `${block ? "block" : "unblock"} cell ${cell}`;
  try {
    publish(tags.block, "fleet/CellBlock", { cell, blocked: block, source: `operator:${view.robotID}` });
  } catch (e) { log("error", `${what}: ${e.message}`); return; }
  const r0 = view.replans;
  const cancels0 = Object.fromEntries(Object.entries(view.robots).map(([n, r]) => [n, r.cancels]));
  track(what, (st) => {
    const now = (st.blocked || []).includes(cell);
    if (now !== block) return null;
    if (!block) return [true, "done"];
    const hit = (st.robots || []).filter((r) => r.cancels !== (cancels0[r.robot] ?? r.cancels)).map((r) => r.robot);
    return [true, `blocked${g && !g.free[cell] ? " (an occupied cell anyway)" : ""}; re-plans ${r0} -> ${st.replans}` +
                  (hit.length ? `; ${hit.join(", ")} re-routed` : "")];
  }, (err) => new RegExp(`\\bcell ${cell}\\b`).test(err) && /block/.test(err));
}

function sendGoal(robot, cell) {
  const what = `${robot} -> cell ${cell}`;
  try {
    publish(tags.goal, "fleet/RobotGoal", { robot, cell });
  } catch (e) { log("error", `${what}: ${e.message}`); return; }
  track(what, (st) => {
    const r = (st.robots || []).find((x) => x.robot === robot);
    if (!r || r.goal !== cell) return null;
    if (r.state === "unreachable") return [false, `unreachable: ${r.error}`];
    if (r.state === "arrived") return [true, "already there"];
    return [true, `on its way (${Math.max(r.path.length - 1, 0)} cells, ${r.state})`];
  }, (err) => err.startsWith(`${robot}:`) || err.includes(`'${robot}'`));
}

function mission(cmd) {
  const what = `mission ${cmd}`;
  try {
    publish(tags.mission, "std_msgs/String", { data: cmd });
  } catch (e) { log("error", `${what}: ${e.message}`); return; }
  view.mission.running = cmd === "start";
  // a random mission gives every robot a new goal; stop drops them
  const goals0 = Object.fromEntries(Object.entries(view.robots).map(([n, r]) => [n, r.goal]));
  track(what, (st) => {
    const goals = (st.robots || []).filter((r) => r.goal >= 0).length;
    const fresh = (st.robots || []).filter((r) => r.goal >= 0 && r.goal !== goals0[r.robot]).length;
    if (cmd === "start" && fresh > 0) return [true, `${goals} robot(s) have goals`];
    if (cmd === "stop" && goals === 0) return [true, "every robot stopped"];
    return null;
  }, (err) => /mission/i.test(err));
}

function select(name) {
  view.selected = name;
  needTable = true;
  const hint = $("hint");
  if (name) {
    hint.innerHTML = "";
    hint.append(`Click a cell to send `, Object.assign(document.createElement("b"), { textContent: name }),
                ` there. `, Object.assign(document.createElement("button"), {
                  id: "deselect", textContent: "done (Esc)", onclick: () => select(null) }));
    hint.style.borderColor = colour(name);
  } else {
    hint.textContent = "Click a cell to block or unblock it. Pick a robot (here or in the list) to give it a goal.";
    hint.style.borderColor = "";
  }
}

// ---------------------------------------------------------------------------------------------
// geometry: world (m) <-> grid units (col_f, row_f; cell (r, c) covers [c, c+1) x [r, r+1)) <-> canvas
// ---------------------------------------------------------------------------------------------
function worldToGrid(x, y) {
  const g = view.grid;
  const [ox, oy, yaw] = g.origin;
  const rot = (px, py) => {
    let dx = px - ox, dy = py - oy;
    if (yaw) { const c = Math.cos(yaw), s = Math.sin(yaw); [dx, dy] = [c * dx + s * dy, -s * dx + c * dy]; }
    return [dx, dy];
  };
  const [gx, gy] = rot(g.grid_x, g.grid_y);
  const [dx, dy] = rot(x, y);
  return [(dx - gx) / g.cell_w, (gy - dy) / g.cell_h];
}

const canvas = $("map");
const ctx = canvas.getContext("2d");
let T = { s: 1, sx: 1, sy: 1, ox: 0, oy: 0, dpr: 1 };   // grid units -> canvas device px

function layout() {
  const dpr = window.devicePixelRatio || 1;
  const rect = canvas.getBoundingClientRect();
  const w = Math.max(1, Math.round(rect.width * dpr)), h = Math.max(1, Math.round(rect.height * dpr));
  if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; staticKey = ""; }
  const g = view.grid;
  if (!g) return;
  const pad = 0.015;
  const wm = g.cols * g.cell_w, hm = g.rows * g.cell_h;
  const s = Math.min(w * (1 - 2 * pad) / wm, h * (1 - 2 * pad) / hm);   // device px per metre
  T = { s, sx: s * g.cell_w, sy: s * g.cell_h, ox: (w - wm * s) / 2, oy: (h - hm * s) / 2, dpr };
}

const G2C = (c, r) => [T.ox + c * T.sx, T.oy + r * T.sy];
const W2C = (x, y) => { const [c, r] = worldToGrid(x, y); return G2C(c, r); };

function cellCenterClient(cell) {
  if (!view.grid) return null;
  const rect = canvas.getBoundingClientRect();
  const r = Math.floor(cell / view.grid.cols), c = cell % view.grid.cols;
  const [px, py] = G2C(c + 0.5, r + 0.5);
  return { x: rect.left + px / T.dpr, y: rect.top + py / T.dpr };
}

function robotClient(name) {
  const d = drawn[name];
  if (!d || !view.grid) return null;
  const rect = canvas.getBoundingClientRect();
  const [px, py] = W2C(d.x, d.y);
  return { x: rect.left + px / T.dpr, y: rect.top + py / T.dpr };
}

function cellAtClient(x, y) {
  const g = view.grid;
  if (!g) return -1;
  const rect = canvas.getBoundingClientRect();
  const px = (x - rect.left) * T.dpr, py = (y - rect.top) * T.dpr;
  const c = Math.floor((px - T.ox) / T.sx), r = Math.floor((py - T.oy) / T.sy);
  return r >= 0 && r < g.rows && c >= 0 && c < g.cols ? r * g.cols + c : -1;
}

function robotAtClient(x, y) {
  let best = null, bd = Infinity;
  for (const n of view.order) {
    const p = robotClient(n);
    if (!p) continue;
    const d = Math.hypot(p.x - x, p.y - y);
    if (d < bd) { bd = d; best = n; }
  }
  const radius = Math.max(12, robotRadiusPx() / T.dpr + 6);
  return bd <= radius ? best : null;
}

function robotRadiusPx() {
  return Math.max(5 * T.dpr, 0.16 * T.s);   // TurtleBot3 burger ~0.105 m radius, drawn a bit larger
}

// ---------------------------------------------------------------------------------------------
// map image
// ---------------------------------------------------------------------------------------------
const mapImg = new Image();
mapImg.onload = () => {
  view.map = { loaded: true, error: null, width: mapImg.naturalWidth, height: mapImg.naturalHeight };
  staticKey = "";
};
mapImg.onerror = () => { view.map = { loaded: false, error: `cannot load ${mapImg.src}`, width: 0, height: 0 }; };

async function loadMap() {
  // with a token the image comes through fetch (an <img> cannot send the Authorization header)
  const url = new URL(cfg.map, location.href);
  if (!apiToken || url.origin !== location.origin) { mapImg.src = url.href; return; }
  try {
    const r = await authed(url.href);
    if (!r.ok) throw new Error(`HTTP ${r.status}`);
    if (mapImg.src.startsWith("blob:")) URL.revokeObjectURL(mapImg.src);
    mapImg.src = URL.createObjectURL(await r.blob());
  } catch (e) {
    view.map = { loaded: false, error: `cannot load ${url.href}: ${e.message}`, width: 0, height: 0 };
  }
}

// --edge-hosts: where each move_client runs and the placer's word on it (placement.json, every 1 s)
let placementTimer = null;
function startPlacement() {
  if (!cfg.placement || placementTimer) return;
  const table = document.getElementById("placement");
  table.hidden = false;
  const ask = async () => {
    try {
      const r = await authed("placement.json");
      if (!r.ok) return;
      view.placement = await r.json();
      const body = table.querySelector("tbody");
      body.replaceChildren(...(view.placement.containers || []).map((c) => {
        const tr = document.createElement("tr");
        const cells = [c.ctag, c.runs, c.best, c.misses, c.node_ms == null ? "-" : c.node_ms.toFixed(1), c.why];
        for (const v of cells) {
          const td = document.createElement("td");
          td.textContent = String(v ?? "-");
          tr.append(td);
        }
        tr.lastChild.className = "why";
        tr.lastChild.title = c.why || "";
        if (c.move) tr.className = "moving";
        return tr;
      }));
    } catch (e) { /* the demo is stopping: keep the last */ }
  };
  ask();
  placementTimer = setInterval(ask, RELAYS_EVERY);
}

let relaysTimer = null;
function startRelays() {
  if (!cfg.relays || relaysTimer) return;
  const askRelays = async () => {
    try {
      const r = await authed("relays.json");
      if (r.ok) view.relays = (await r.json()).relays || {};
    } catch (e) { /* the demo is stopping: keep the last */ }
  };
  askRelays();
  relaysTimer = setInterval(askRelays, RELAYS_EVERY);
}

// ---------------------------------------------------------------------------------------------
// drawing
// ---------------------------------------------------------------------------------------------
function buildStatic() {
  const g = view.grid;
  const key = `${canvas.width}x${canvas.height}:${view.map.loaded}:${g.rows}x${g.cols}:${g.free.join("")}`;
  if (key === staticKey) return;
  staticKey = key;
  if (!staticLayer) staticLayer = document.createElement("canvas");
  staticLayer.width = canvas.width;
  staticLayer.height = canvas.height;
  const c = staticLayer.getContext("2d");
  c.fillStyle = "#d9dde3";
  c.fillRect(0, 0, staticLayer.width, staticLayer.height);
  if (view.map.loaded) {
    // the image's lower-left corner is the map origin; in the image frame (yaw applied) it spans
    // width*res x height*res metres
    const res = g.res, [ox, oy, yaw] = g.origin;
    const W = mapImg.naturalWidth * res, H = mapImg.naturalHeight * res;
    const [c0, r0] = worldToGrid(ox, oy);       // lower-left corner, grid units
    c.save();
    const [px, py] = G2C(c0, r0);
    c.translate(px, py);
    c.rotate(-yaw);
    c.imageSmoothingEnabled = false;
    c.drawImage(mapImg, 0, -H * T.s, W * T.s, H * T.s);
    c.restore();
  } else {
    c.fillStyle = "#fff";
    const [x0, y0] = G2C(0, 0), [x1, y1] = G2C(g.cols, g.rows);
    c.fillRect(x0, y0, x1 - x0, y1 - y0);
  }
  // cells robots cannot use
  c.fillStyle = "rgba(60, 60, 70, 0.28)";
  for (let i = 0; i < g.rows * g.cols; i++) {
    if (g.free[i]) continue;
    const [x, y] = G2C(i % g.cols, Math.floor(i / g.cols));
    c.fillRect(x, y, T.sx, T.sy);
  }
  // grid lines
  c.strokeStyle = "rgba(40, 70, 120, 0.55)";
  c.lineWidth = Math.max(1, T.dpr);
  c.beginPath();
  for (let i = 0; i <= g.cols; i++) { const [x, y0] = G2C(i, 0), [, y1] = G2C(i, g.rows); c.moveTo(x, y0); c.lineTo(x, y1); }
  for (let j = 0; j <= g.rows; j++) { const [x0, y] = G2C(0, j), [x1] = G2C(g.cols, j); c.moveTo(x0, y); c.lineTo(x1, y); }
  c.stroke();
  // cell numbers (top-left of each cell), only where cells are large enough to carry them legibly;
  // on a warehouse the numbers would bury the map: a cell's number shows on hover (#cell-info)
  view.numbersDrawn = Math.min(T.sx, T.sy) >= NUMBERS_MIN_PX * T.dpr;
  if (!view.numbersDrawn) return;
  const fs = Math.max(9 * T.dpr, Math.min(T.sx, T.sy) * 0.16);
  c.font = `${fs}px ui-monospace, monospace`;
  c.textBaseline = "top";
  for (let i = 0; i < g.rows * g.cols; i++) {
    const [x, y] = G2C(i % g.cols, Math.floor(i / g.cols));
    c.fillStyle = g.free[i] ? "rgba(30, 50, 90, 0.75)" : "rgba(30, 30, 30, 0.45)";
    c.fillText(String(i), x + 3 * T.dpr, y + 2 * T.dpr);
  }
}

function cellRect(cell, inset = 0) {
  const g = view.grid;
  const [x, y] = G2C(cell % g.cols, Math.floor(cell / g.cols));
  return [x + inset, y + inset, T.sx - 2 * inset, T.sy - 2 * inset];
}

function cellCentre(cell) {
  const g = view.grid;
  return G2C(cell % g.cols + 0.5, Math.floor(cell / g.cols) + 0.5);
}

let lastFrame = performance.now();
let frames = 0, fpsT = performance.now(), drawSum = 0;
function frame(now) {
  requestAnimationFrame(frame);
  const t0 = performance.now();
  draw(now);
  drawSum += performance.now() - t0;
  frames++;
  if (now - fpsT > 1000) {
    view.fps = frames * 1000 / (now - fpsT);
    view.drawMs = drawSum / frames;
    frames = 0; drawSum = 0; fpsT = now;
  }
}

function draw(now) {
  const dt = Math.min(0.25, (now - lastFrame) / 1000);
  lastFrame = now;
  layout();
  const g = view.grid;
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  if (!g) {
    ctx.fillStyle = "#d9dde3";
    ctx.fillRect(0, 0, canvas.width, canvas.height);
    ctx.fillStyle = "#445";
    ctx.font = `${14 * T.dpr}px system-ui, sans-serif`;
    ctx.fillText(view.connected ? "waiting for /fleet/state ..." : "log in to see the fleet", 20 * T.dpr, 30 * T.dpr);
    return;
  }
  buildStatic();
  ctx.drawImage(staticLayer, 0, 0);
  const lw = Math.max(1.5 * T.dpr, 0.03 * T.s);

  // hover
  if (hoverCell >= 0) {
    ctx.fillStyle = view.selected ? "rgba(255, 215, 0, 0.25)" : "rgba(255, 80, 80, 0.18)";
    ctx.fillRect(...cellRect(hoverCell));
  }
  // blocked cells: red, crossed
  for (const cell of view.blocked) {
    const [x, y, w, h] = cellRect(cell, 2 * T.dpr);
    ctx.fillStyle = "rgba(220, 40, 40, 0.35)";
    ctx.fillRect(x, y, w, h);
    ctx.strokeStyle = "rgba(180, 20, 20, 0.9)";
    ctx.lineWidth = lw;
    ctx.strokeRect(x, y, w, h);
    ctx.beginPath();
    ctx.moveTo(x, y); ctx.lineTo(x + w, y + h); ctx.moveTo(x + w, y); ctx.lineTo(x, y + h);
    ctx.stroke();
    const by = view.blockedBy[cell];
    if (by) {
      ctx.fillStyle = "rgba(120, 0, 0, 0.9)";
      ctx.font = `${Math.max(8 * T.dpr, T.sy * 0.12)}px system-ui, sans-serif`;
      ctx.textBaseline = "bottom";
      ctx.fillText(by.split(":")[0], x + 3 * T.dpr, y + h - 2 * T.dpr);
    }
  }
  // trails (thin), planned paths (cleared part solid, the rest dashed), goals
  for (const name of view.order) {
    const col = colour(name);
    const tr = view.trails[name];
    if (tr && tr.length > 1) {
      ctx.strokeStyle = col;
      ctx.globalAlpha = 0.45;
      ctx.lineWidth = Math.max(1, lw * 0.6);
      ctx.setLineDash([]);
      ctx.beginPath();
      tr.forEach(([x, y], i) => { const [px, py] = W2C(x, y); i ? ctx.lineTo(px, py) : ctx.moveTo(px, py); });
      ctx.stroke();
      ctx.globalAlpha = 1;
    }
    const r = view.robots[name];
    const d = drawn[name];
    if (r && r.path && r.path.length > 1) {
      const pts = r.path.map(cellCentre);
      if (d) pts[0] = W2C(d.x, d.y);
      const k = Math.max(0, Math.min(r.cleared, pts.length - 1));
      ctx.strokeStyle = col;
      ctx.lineWidth = lw * 1.6;
      ctx.lineJoin = "round";
      ctx.globalAlpha = 0.85;
      ctx.setLineDash([]);
      ctx.beginPath();
      pts.slice(0, k + 1).forEach(([x, y], i) => (i ? ctx.lineTo(x, y) : ctx.moveTo(x, y)));
      ctx.stroke();
      ctx.setLineDash([6 * T.dpr, 5 * T.dpr]);
      ctx.beginPath();
      pts.slice(k).forEach(([x, y], i) => (i ? ctx.lineTo(x, y) : ctx.moveTo(x, y)));
      ctx.stroke();
      ctx.setLineDash([]);
      ctx.globalAlpha = 1;
    }
    if (r && r.goal >= 0 && r.state !== "arrived") {
      const [cx, cy] = cellCentre(r.goal);
      const rr = Math.min(T.sx, T.sy) * 0.3;
      ctx.strokeStyle = col;
      ctx.lineWidth = lw * 1.4;
      ctx.beginPath();
      ctx.arc(cx, cy, rr, 0, 2 * Math.PI);
      ctx.moveTo(cx - rr * 0.5, cy); ctx.lineTo(cx + rr * 0.5, cy);
      ctx.moveTo(cx, cy - rr * 0.5); ctx.lineTo(cx, cy + rr * 0.5);
      ctx.stroke();
      if (r.state === "unreachable") {
        ctx.fillStyle = "rgba(200, 0, 0, 0.85)";
        ctx.font = `bold ${Math.max(10 * T.dpr, rr)}px system-ui, sans-serif`;
        ctx.textBaseline = "middle";
        ctx.fillText("!", cx + rr * 1.1, cy);
      }
    }
  }
  // follower -> relay: a dashed line in the relay's colour (drawn robots only)
  const lines = [];
  for (const [f, rl] of Object.entries(view.relays)) {
    const df = drawn[f], dr = drawn[rl];
    if (!df || !dr) continue;
    const from = W2C(df.x, df.y), to = W2C(dr.x, dr.y);
    ctx.strokeStyle = colour(rl);
    ctx.lineWidth = lw * 1.2;
    ctx.setLineDash([3 * T.dpr, 3 * T.dpr]);
    ctx.beginPath(); ctx.moveTo(...from); ctx.lineTo(...to); ctx.stroke();
    ctx.setLineDash([]);
    lines.push({ follower: f, relay: rl, from, to });
  }
  view.relayLines = lines;
  // robots: smoothed towards the latest pose (10 Hz states drawn at the display's rate)
  const a = 1 - Math.exp(-dt / 0.08);
  const R = robotRadiusPx();
  for (const name of view.order) {
    const r = view.robots[name];
    if (!r || r.x === null) continue;
    let d = drawn[name];
    if (!d || Math.hypot(d.x - r.x, d.y - r.y) > 2) d = drawn[name] = { x: r.x, y: r.y, yaw: r.yaw || 0 };
    d.x += (r.x - d.x) * a;
    d.y += (r.y - d.y) * a;
    let dy = (r.yaw || 0) - d.yaw;
    dy = Math.atan2(Math.sin(dy), Math.cos(dy));
    d.yaw += dy * a;
    const [px, py] = W2C(d.x, d.y);
    const col = colour(name);
    if (name === view.selected) {
      ctx.fillStyle = "rgba(255, 215, 0, 0.55)";
      ctx.beginPath(); ctx.arc(px, py, R * 1.7, 0, 2 * Math.PI); ctx.fill();
    }
    // heading: world yaw is counter-clockwise from +x; the canvas y axis points down
    const [hx0, hy0] = W2C(d.x + Math.cos(d.yaw) * 0.3, d.y + Math.sin(d.yaw) * 0.3);
    const hl = Math.hypot(hx0 - px, hy0 - py) || 1;
    const ux = (hx0 - px) / hl, uy = (hy0 - py) / hl;
    ctx.fillStyle = col;
    ctx.strokeStyle = "#fff";
    ctx.lineWidth = Math.max(1, T.dpr * 1.5);
    ctx.beginPath(); ctx.arc(px, py, R, 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
    ctx.fillStyle = "#fff";            // a white arrow head inside the disc, pointing where it heads
    ctx.beginPath();
    ctx.moveTo(px + ux * R * 0.85, py + uy * R * 0.85);
    ctx.lineTo(px - ux * R * 0.35 - uy * R * 0.5, py - uy * R * 0.35 + ux * R * 0.5);
    ctx.lineTo(px - ux * R * 0.1, py - uy * R * 0.1);
    ctx.lineTo(px - ux * R * 0.35 + uy * R * 0.5, py - uy * R * 0.35 - ux * R * 0.5);
    ctx.closePath();
    ctx.fill();
    ctx.font = `bold ${Math.max(10 * T.dpr, R * 0.9)}px system-ui, sans-serif`;
    ctx.textBaseline = "bottom";
    ctx.lineWidth = 3 * T.dpr;
    ctx.strokeStyle = "rgba(255,255,255,0.9)";
    const label = name.replace(/^Robot/, "R");
    ctx.strokeText(label, px + R * 0.9, py - R * 0.7);
    ctx.fillStyle = "#111";
    ctx.fillText(label, px + R * 0.9, py - R * 0.7);
  }
  for (const n of Object.keys(drawn)) if (!view.robots[n]) delete drawn[n];

  if (needTable && now - lastTable > TABLE_EVERY) { lastTable = now; needTable = false; renderTable(); }
  if (pending.length && now - (frame.lastPend || 0) > 500) { frame.lastPend = now; resolvePending(null, []); }
}

// ---------------------------------------------------------------------------------------------
// robot status table (rows made once per robot; only changed text is written)
// ---------------------------------------------------------------------------------------------
const rows = new Map();
function renderTable() {
  const tbody = $("robots").tBodies[0];
  for (const [n, tr] of rows) if (!view.robots[n]) { tr.remove(); rows.delete(n); }
  view.order.forEach((name) => {
    let tr = rows.get(name);
    if (!tr) {
      tr = document.createElement("tr");
      tr.dataset.robot = name;
      tr.innerHTML = `<td class="sw"><i></i></td><td class="id"></td><td class="state"></td><td class="cell"></td>` +
                     `<td class="goal"></td><td class="replans"></td><td class="left"></td>`;
      tr.onclick = () => select(view.selected === name ? null : name);
      rows.set(name, tr);
    }
    if (tr.parentNode !== tbody || tbody.children[view.order.indexOf(name)] !== tr) tbody.append(tr);
    const r = view.robots[name];
    const set = (cls, text, title) => {
      const td = tr.querySelector(`.${cls}`);
      if (td.textContent !== text) td.textContent = text;
      if (title !== undefined && td.title !== title) td.title = title;
    };
    tr.querySelector("i").style.background = colour(name);
    set("id", name);
    set("state", r.state + (r.clientState && r.clientState !== r.state ? ` / ${r.clientState}` : ""),
        r.error || "");
    set("cell", r.cell >= 0 ? String(r.cell) : "-");
    set("goal", r.goal >= 0 ? String(r.goal) : "-");
    set("replans", `${r.replans}${r.cancels ? ` (${r.cancels} cancel${r.cancels > 1 ? "s" : ""})` : ""}`);
    set("left", r.distanceLeft ? `${r.distanceLeft.toFixed(1)} m` : "");
    tr.className = `${name === view.selected ? "selected " : ""}${r.state}`;
  });
  const s = `${view.rate.toFixed(1)} states/s · re-plans ${view.replans} · last plan ${(+view.lastPlanMs).toFixed(1)} ms` +
            ` · max ${(+view.maxPlanMs).toFixed(1)} ms · blocked ${view.blocked.length ? view.blocked.join(", ") : "none"}`;
  if ($("stats").textContent !== s) $("stats").textContent = s;
}

// ---------------------------------------------------------------------------------------------
// input
// ---------------------------------------------------------------------------------------------
function cellInfo(cell, x, y) {
  // the hovered cell's number (and place, and whether robots can use it), next to the pointer
  const box = $("cell-info");
  if (cell < 0 || !view.grid) { box.hidden = true; return; }
  const place = ((taskPanel && taskPanel.places) || []).find((p) => p.cell === cell);
  box.textContent = `cell ${cell}` + (place ? ` · ${place.name} (${place.kind})` : "") +
                    (view.grid.free[cell] ? "" : " · not free");
  const rect = canvas.parentElement.getBoundingClientRect();
  box.style.left = `${x - rect.left + 14}px`;
  box.style.top = `${y - rect.top + 14}px`;
  box.hidden = false;
}
canvas.addEventListener("mousemove", (ev) => {
  hoverCell = cellAtClient(ev.clientX, ev.clientY);
  cellInfo(hoverCell, ev.clientX, ev.clientY);
});
canvas.addEventListener("mouseleave", () => { hoverCell = -1; cellInfo(-1); });
canvas.addEventListener("click", (ev) => {
  if (!view.connected || !view.grid) return;
  const robot = robotAtClient(ev.clientX, ev.clientY);
  const cell = cellAtClient(ev.clientX, ev.clientY);
  if (taskPanel && taskPanel.pick(cell)) return;     // picking a task's errands: the click is a cell
  if (robot && robot !== view.selected) { select(robot); return; }
  if (cell < 0) return;
  if (view.selected) sendGoal(view.selected, cell);
  else toggleBlock(cell);
});
document.addEventListener("keydown", (ev) => {
  if (ev.key === "Escape") select(null);
});
$("login").addEventListener("submit", onLogin);
$("logout").addEventListener("click", onLogout);
$("mission-start").addEventListener("click", () => mission("start"));
$("mission-stop").addEventListener("click", () => mission("stop"));
window.addEventListener("pagehide", () => { if (client) { cleanup(client); client.close(); } });

// ---------------------------------------------------------------------------------------------
// start
// ---------------------------------------------------------------------------------------------
cfg = await loadConfig();
view.config = { ...cfg };
$("master").value = cfg.master;
$("user").value = cfg.user || "";
$("container").value = cfg.container;
if (cfg.title) $("title").textContent = cfg.title;
if (cfg.user) $("password").focus(); else $("user").focus();
if (cfg.apiLogin) {
  // the fleet's server names the master after the login
  $("master").required = false;
  $("master").closest("label").hidden = true;
} else {
  loadMap();
  startRelays();
  startPlacement();
}
select(null);
requestAnimationFrame(frame);
