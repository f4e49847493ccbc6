// rce.js: the RCE client protocol (DESIGN section 3) from the browser. No build step, no
// dependencies: an ES module that any page imports with
//
//     import { Client } from "./rce.js";
//     const c = new Client({ master: "http://127.0.0.1:9000/", userID: "u", robotID: "r", password: "pw" });
//     await c.connect();                       // login over HTTP, then the robot endpoint's websocket
//     c.on("error", (reason) => ...);          // ER from the cloud (the session goes on)
//     c.on("status", (data) => ...);           // ST (interface and node statuses)
//     c.subscribe("resp", (msg, dm) => ...);   // DMs arriving on a robot-side interface
//     await c.request("CN", { addInterfaces: [...] });
//     await c.waitUp(["req", "resp"]);         // ST iu true for each, or the ER that came instead
//     c.publish("req", "std_msgs/String", { data: "hi" });
//     const resp = await c.call("srv", "Test/StringEcho", { data: "x" });
//
// Binary parts: an outgoing message value that is a Uint8Array/ArrayBuffer under key k is sent
// as `k*: id` plus a binary frame `id || bytes`; incoming `k*` keys (an id or a list of ids) are
// resolved from the binary frames, in either order, and handed over as `k: Uint8Array` (or a
// list). Parts that stay incomplete expire after `expiry` seconds (60, like the engine).
//
// The protocol acknowledges nothing on success: CC/CN/CX requests are answered only by an ER when
// they fail, and interfaces report ST {topic: "iu", status: true} once connected. `request()`
// follows each request with a probe the cloud must refuse (see barrier()), so it resolves when the
// request was handled and rejects with the ERs it caused; `waitUp()` waits for the interfaces.

export const CLIENT_VERSION = "20130902";
const enc = new TextEncoder();
const dec = new TextDecoder();

/** Errors from this library: `kind` is "login", "connect", "cloud" (an ER), "timeout" or "closed". */
export class RCEError extends Error {
  constructor(kind, message) {
    super(message);
    this.name = "RCEError";
    this.kind = kind;
  }
}

// ---------------------------------------------------------------------------------------------
// SHA-256 (hex) of the password. crypto.subtle exists only in secure contexts (https, localhost,
// 127.0.0.1); a page opened as http://LAN-IP/ falls back to the small implementation below
// (FIPS 180-4, checked against crypto.subtle by tests/web/test_web_client.py).
// ---------------------------------------------------------------------------------------------
export async function sha256Hex(text) {
  const bytes = enc.encode(text);
  if (globalThis.crypto && crypto.subtle) {
    const d = await crypto.subtle.digest("SHA-256", bytes);
    return hex(new Uint8Array(d));
  }
  return hex(sha256Fallback(bytes));
}

const K = new Uint32Array([
  0x428a2f98, 0x71374491, 0xb5c0fbcf, 0xe9b5dba5, 0x3956c25b, 0x59f111f1, 0x923f82a4, 0xab1c5ed5,
  0xd807aa98, 0x12835b01, 0x243185be, 0x550c7dc3, 0x72be5d74, 0x80deb1fe, 0x9bdc06a7, 0xc19bf174,
  0xe49b69c1, 0xefbe4786, 0x0fc19dc6, 0x240ca1cc, 0x2de92c6f, 0x4a7484aa, 0x5cb0a9dc, 0x76f988da,
  0x983e5152, 0xa831c66d, 0xb00327c8, 0xbf597fc7, 0xc6e00bf3, 0xd5a79147, 0x06ca6351, 0x14292967,
  0x27b70a85, 0x2e1b2138, 0x4d2c6dfc, 0x53380d13, 0x650a7354, 0x766a0abb, 0x81c2c92e, 0x92722c85,
  0xa2bfe8a1, 0xa81a664b, 0xc24b8b70, 0xc76c51a3, 0xd192e819, 0xd6990624, 0xf40e3585, 0x106aa070,
  0x19a4c116, 0x1e376c08, 0x2748774c, 0x34b0bcb5, 0x391c0cb3, 0x4ed8aa4a, 0x5b9cca4f, 0x682e6ff3,
  0x748f82ee, 0x78a5636f, 0x84c87814, 0x8cc70208, 0x90befffa, 0xa4506ceb, 0xbef9a3f7, 0xc67178f2]);

export function sha256Fallback(msg) {
  const bitLen = msg.length * 8;
  const padded = new Uint8Array(((msg.length + 9 + 63) >> 6) << 6);
  padded.set(msg);
  padded[msg.length] = 0x80;
  const dv = new DataView(padded.buffer);
  dv.setUint32(padded.length - 8, Math.floor(bitLen / 2 ** 32));
  dv.setUint32(padded.length - 4, bitLen >>> 0);
  const H = new Uint32Array([0x6a09e667, 0xbb67ae85, 0x3c6ef372, 0xa54ff53a,
                             0x510e527f, 0x9b05688c, 0x1f83d9ab, 0x5be0cd19]);
  const W = new Uint32Array(64);
  const rotr = (x, n) => (x >>> n) | (x << (32 - n));
  for (let off = 0; off < padded.length; off += 64) {
    for (let i = 0; i < 16; i++) W[i] = dv.getUint32(off + 4 * i);
    for (let i = 16; i < 64; i++) {
      const a = W[i - 15], b = W[i - 2];
      const s0 = rotr(a, 7) ^ rotr(a, 18) ^ (a >>> 3);
      const s1 = rotr(b, 17) ^ rotr(b, 19) ^ (b >>> 10);
      W[i] = (W[i - 16] + s0 + W[i - 7] + s1) >>> 0;
    }
    let [a, b, c, d, e, f, g, h] = H;
    for (let i = 0; i < 64; i++) {
      const S1 = rotr(e, 6) ^ rotr(e, 11) ^ rotr(e, 25);
      const t1 = (h + S1 + ((e & f) ^ (~e & g)) + K[i] + W[i]) >>> 0;
      const S0 = rotr(a, 2) ^ rotr(a, 13) ^ rotr(a, 22);
      const t2 = (S0 + ((a & b) ^ (a & c) ^ (b & c))) >>> 0;
      h = g; g = f; f = e; e = (d + t1) >>> 0; d = c; c = b; b = a; a = (t1 + t2) >>> 0;
    }
    H[0] += a; H[1] += b; H[2] += c; H[3] += d; H[4] += e; H[5] += f; H[6] += g; H[7] += h;
  }
  const out = new Uint8Array(32);
  const odv = new DataView(out.buffer);
  H.forEach((v, i) => odv.setUint32(4 * i, v));
  return out;
}

function hex(bytes) {
  return Array.from(bytes, (b) => b.toString(16).padStart(2, "0")).join("");
}

/** A fresh 32-hex-char id (binary part ids, msgIDs). */
export function newId() {
  const b = new Uint8Array(16);
  crypto.getRandomValues(b);
  return hex(b);
}

// ---------------------------------------------------------------------------------------------
// Login (DESIGN 3.1): GET MASTER/?userID=U&version=V -> {"url": ws_url, "current"?}
// ---------------------------------------------------------------------------------------------
export async function login(master, userID, version = CLIENT_VERSION) {
  const base = master.endsWith("/") ? master : master + "/";
  const url = `${base}?userID=${encodeURIComponent(userID)}&version=${encodeURIComponent(version)}`;
  let resp;
  try {
    resp = await fetch(url, { cache: "no-store" });
  } catch (e) {
    throw new RCEError("login", `cannot reach the master at ${base} (${e.message}); is rce-master running, ` +
                                `and does it allow this page's origin?`);
  }
  const body = await resp.text();
  if (!resp.ok) {
    throw new RCEError("login", `login refused by the master (HTTP ${resp.status}): ${body.trim()}`);
  }
  let data;
  try {
    data = JSON.parse(body);
  } catch (e) {
    throw new RCEError("login", `the master's login answer is not JSON: ${body.slice(0, 200)}`);
  }
  if (typeof data.url !== "string") throw new RCEError("login", `the master's login answer has no url: ${body}`);
  return data;
}

/**
 * JSON.parse that also takes the NaN, Infinity and -Infinity tokens Python's json module writes
 * for non-finite floats (a pose not known yet is NaN); they become null.
 */
export function parseJSON(text) {
  try {
    return JSON.parse(text);
  } catch (e) {
    if (!/NaN|Infinity/.test(text)) throw e;
  }
  let out = "", i = 0, inStr = false;
  while (i < text.length) {
    const ch = text[i];
    if (inStr) {
      out += ch;
      if (ch === "\\") { out += text[i + 1] ?? ""; i += 2; continue; }
      if (ch === '"') inStr = false;
      i++;
    } else if (ch === '"') { inStr = true; out += ch; i++; }
    else if (text.startsWith("NaN", i)) { out += "null"; i += 3; }
    else if (text.startsWith("-Infinity", i)) { out += "null"; i += 9; }
    else if (text.startsWith("Infinity", i)) { out += "null"; i += 8; }
    else { out += ch; i++; }
  }
  return JSON.parse(out);
}

// ---------------------------------------------------------------------------------------------
// Binary parts
// ---------------------------------------------------------------------------------------------
function isBytes(v) {
  return v instanceof Uint8Array || v instanceof ArrayBuffer;
}

/** Outgoing: bytes values become `k*` ids; returns [jsonText, [binary frames]]. */
export function encodeMessage(obj) {
  const frames = [];
  const part = (v) => {
    const id = newId();
    const data = v instanceof ArrayBuffer ? new Uint8Array(v) : v;
    const f = new Uint8Array(32 + data.length);
    f.set(enc.encode(id));
    f.set(data, 32);
    frames.push(f);
    return id;
  };
  const walk = (o) => {
    if (Array.isArray(o)) return o.map(walk);
    if (o && typeof o === "object" && !isBytes(o)) {
      const out = {};
      for (const [k, v] of Object.entries(o)) {
        if (isBytes(v)) out[k + "*"] = part(v);
        else if (Array.isArray(v) && v.length && v.every(isBytes)) out[k + "*"] = v.map(part);
        else out[k] = walk(v);
      }
      return out;
    }
    return o;
  };
  return [JSON.stringify(walk(obj)), frames];
}

/** Ids referenced by `*` keys anywhere in `obj`. */
function refsOf(obj, acc = []) {
  if (Array.isArray(obj)) obj.forEach((v) => refsOf(v, acc));
  else if (obj && typeof obj === "object") {
    for (const [k, v] of Object.entries(obj)) {
      if (k.endsWith("*")) {
        for (const id of Array.isArray(v) ? v : [v]) {
          if (typeof id !== "string" || !/^[0-9a-fA-F]{32}$/.test(id)) {
            throw new RCEError("cloud", `binary part key ${JSON.stringify(k)} holds ${JSON.stringify(id)}, not a 32-hex-char id`);
          }
          acc.push(id.toLowerCase());
        }
      } else refsOf(v, acc);
    }
  }
  return acc;
}

function resolveRefs(obj, parts) {
  if (Array.isArray(obj)) return obj.map((v) => resolveRefs(v, parts));
  if (obj && typeof obj === "object") {
    const out = {};
    for (const [k, v] of Object.entries(obj)) {
      if (k.endsWith("*")) {
        const key = k.slice(0, -1);
        out[key] = Array.isArray(v) ? v.map((id) => parts.get(id.toLowerCase())) : parts.get(v.toLowerCase());
      } else out[k] = resolveRefs(v, parts);
    }
    return out;
  }
  return obj;
}

/** Collects JSON messages and binary parts in either order (DESIGN 3.4). */
export class Assembler {
  constructor(expiry = 60) {
    this.expiry = expiry * 1000;
    this.parts = new Map();      // id -> {data, t}
    this.waiting = [];           // {msg, refs:Set, t}
    this.expired = 0;
  }

  /** A JSON message; returns it complete (parts resolved) or null while parts are missing. */
  addMessage(msg) {
    const refs = refsOf(msg);
    if (!refs.length) return msg;
    const missing = new Set(refs.filter((id) => !this.parts.has(id)));
    if (!missing.size) return this._complete(msg, refs);
    this.waiting.push({ msg, refs, missing, t: Date.now() });
    return null;
  }

  /** A binary frame `id || bytes`; returns the messages it completed. */
  addPart(buf) {
    const bytes = new Uint8Array(buf);
    if (bytes.length < 32) throw new RCEError("cloud", `binary frame of ${bytes.length} bytes has no 32-char id`);
    const id = dec.decode(bytes.subarray(0, 32)).toLowerCase();
    this.parts.set(id, { data: bytes.subarray(32), t: Date.now() });
    const done = [];
    this.waiting = this.waiting.filter((w) => {
      w.missing.delete(id);
      if (w.missing.size) return true;
      done.push(this._complete(w.msg, w.refs));
      return false;
    });
    return done;
  }

  _complete(msg, refs) {
    const out = resolveRefs(msg, new Map(refs.map((id) => [id, this.parts.get(id).data])));
    refs.forEach((id) => this.parts.delete(id));
    return out;
  }

  /** Drop what waited longer than `expiry`; returns how many messages/parts were dropped. */
  expire(now = Date.now()) {
    let n = 0;
    this.waiting = this.waiting.filter((w) => (now - w.t < this.expiry) || (n++, false));
    for (const [id, p] of this.parts) if (now - p.t >= this.expiry) { this.parts.delete(id); n++; }
    this.expired += n;
    return n;
  }
}

// ---------------------------------------------------------------------------------------------
// The client
// ---------------------------------------------------------------------------------------------
export class Client {
  /**
   * options: master (login URL, e.g. "http://127.0.0.1:9000/"), userID, robotID, password (clear
   * text, hashed here, never stored), version, expiry (s, binary parts).
   */
  constructor({ master, userID, robotID, password, version = CLIENT_VERSION, expiry = 60 }) {
    this.master = master;
    this.userID = userID;
    this.robotID = robotID;
    this._password = password;
    this.version = version;
    this.ws = null;
    this.wsUrl = null;
    this.assembler = new Assembler(expiry);
    this.handlers = new Map();            // event -> Set(fn)
    this.subscribers = new Map();         // iTag -> Set(fn)
    this.calls = new Map();               // msgID -> {resolve, reject, timer}
    this._barriers = new Map();           // probe token -> {resolve, reject}
    this.iu = new Map();                  // iTag -> bool (robot-side interface connected)
    this.errors = [];                     // last ERs, newest last
    this.stats = { in: 0, out: 0, dm: 0, er: 0, st: 0 };
    this.closed = false;
    this._expiryTimer = null;
  }

  on(event, fn) {
    if (!this.handlers.has(event)) this.handlers.set(event, new Set());
    this.handlers.get(event).add(fn);
    return () => this.handlers.get(event).delete(fn);
  }

  _emit(event, ...args) {
    for (const fn of this.handlers.get(event) || []) {
      try { fn(...args); } catch (e) { console.error(`rce.js: ${event} handler failed`, e); }
    }
  }

  /** Log in at the master and open the robot endpoint's websocket. Rejects with an RCEError. */
  async connect() {
    const info = await login(this.master, this.userID, this.version);
    if (info.current) this._emit("notice", `the master speaks version ${info.current}, this client ${this.version}`);
    const pw = await sha256Hex(this._password);
    this._password = null;
    const q = `userID=${encodeURIComponent(this.userID)}&robotID=${encodeURIComponent(this.robotID)}&password=${pw}`;
    this.wsUrl = info.url;
    const url = info.url + (info.url.includes("?") ? "&" : "?") + q;
    await new Promise((resolve, reject) => {
      let open = false;
      let ws;
      try {
        ws = new WebSocket(url);
      } catch (e) {
        reject(new RCEError("connect", `cannot open the robot endpoint ${info.url}: ${e.message}`));
        return;
      }
      ws.binaryType = "arraybuffer";
      this.ws = ws;
      ws.onopen = () => { open = true; resolve(); };
      ws.onmessage = (ev) => this._receive(ev.data);
      ws.onclose = (ev) => {
        if (!open) {
          // a browser does not show the refused handshake's status (401/403/409) to the page
          reject(new RCEError("connect", `login refused by the robot endpoint ${info.url}: wrong password? ` +
                                         `(or robot ID ${JSON.stringify(this.robotID)} already connected; ` +
                                         `a browser does not see the reason)`));
          return;
        }
        this._closed(ev.code, ev.reason);
      };
    });
    this._expiryTimer = setInterval(() => {
      const n = this.assembler.expire();
      if (n) this._emit("notice", `${n} incomplete message(s)/binary part(s) expired`);
    }, 5000);
  }

  _closed(code, reason) {
    if (this.closed) return;
    this.closed = true;
    clearInterval(this._expiryTimer);
    for (const [, c] of this.calls) { clearTimeout(c.timer); c.reject(new RCEError("closed", "connection closed")); }
    this.calls.clear();
    for (const [, b] of this._barriers) b.reject(new RCEError("closed", "connection closed"));
    this._barriers.clear();
    this._emit("close", { code, reason });
  }

  close() {
    if (this.ws && this.ws.readyState <= 1) this.ws.close(1000, "bye");
    this._closed(1000, "closed by the page");
  }

  // -- outgoing ----------------------------------------------------------------------------------
  /** Send one protocol message `{type, data}` (bytes values become binary parts). */
  send(type, data) {
    if (!this.ws || this.ws.readyState !== WebSocket.OPEN) throw new RCEError("closed", "not connected to the cloud");
    const [text, frames] = encodeMessage({ type, data });
    this.ws.send(text);
    for (const f of frames) this.ws.send(f);
    this.stats.out++;
  }

  /**
   * A CC/DC/CN/CX request: resolves once the cloud has handled it, rejects with the ER(s) it
   * caused. The protocol has no positive ack, but the master handles a robot's requests one at a
   * time and in order and refuses each bad one with an ER; so after the request we send a probe
   * (a CX between two interfaces that cannot exist, see barrier()) and the probe's ER marks the
   * end: ERs that came before it belong to the request. (rce_client.Connection.barrier does the same.)
   */
  async request(type, data, timeout = 60000) {
    const errs = [];
    const off = this.on("error", (reason) => errs.push(reason));
    try {
      this.send(type, data);
      await this.barrier(timeout);
    } finally {
      off();
    }
    if (errs.length) throw new RCEError("cloud", errs.join("; "));
  }

  /** Resolve when the cloud has handled every request sent before (see request()). */
  barrier(timeout = 60000) {
    const token = `rcesync${newId().slice(0, 12)}`;
    return new Promise((resolve, reject) => {
      const timer = setTimeout(() => { this._barriers.delete(token); reject(new RCEError("timeout",
        `the cloud did not answer within ${timeout / 1000} s`)); }, timeout);
      this._barriers.set(token, { resolve: () => { clearTimeout(timer); resolve(); },
                                  reject: (e) => { clearTimeout(timer); reject(e); } });
      try {
        this.send("CX", { connect: [{ tagA: `${token}/a`, tagB: `${token}/b` }] });
      } catch (e) {
        this._barriers.delete(token);
        clearTimeout(timer);
        reject(e);
      }
    });
  }

  createContainer(containerTag, containerData) {
    return this.request("CC", containerData ? { containerTag, containerData } : { containerTag });
  }

  destroyContainer(containerTag) { return this.request("DC", { containerTag }); }

  configure(cn) { return this.request("CN", cn); }

  /** pairs: [[tagA, tagB], ...] */
  connectInterfaces(pairs) { return this.request("CX", { connect: pairs.map(([tagA, tagB]) => ({ tagA, tagB })) }); }

  disconnectInterfaces(pairs) {
    return this.request("CX", { disconnect: pairs.map(([tagA, tagB]) => ({ tagA, tagB })) });
  }

  /** Resolve when each robot-side interface in `iTags` reported ST iu true; reject on an ER or timeout. */
  waitUp(iTags, timeout = 30000) {
    const left = new Set(iTags.filter((t) => !this.iu.get(t)));
    if (!left.size) return Promise.resolve();
    return new Promise((resolve, reject) => {
      const offs = [];
      const done = (err) => { clearTimeout(timer); offs.forEach((f) => f()); err ? reject(err) : resolve(); };
      offs.push(this.on("status", (d) => {
        if (d.topic === "iu" && d.status === true) { left.delete(d.iTag); if (!left.size) done(); }
      }));
      offs.push(this.on("error", (reason) => done(new RCEError("cloud", reason))));
      offs.push(this.on("close", () => done(new RCEError("closed", "connection closed"))));
      const timer = setTimeout(() => done(new RCEError("timeout",
        `interfaces not connected within ${timeout / 1000} s: ${[...left].join(", ")}`)), timeout);
    });
  }

  /** Publish on a robot-side SubscriberConverter (msg: JSON) or SubscriberForwarder (msg: Uint8Array). */
  publish(iTag, type, msg, msgID = "") {
    this.send("DM", { iTag, type, msgID, msg });      // bytes become the binary part msg*
    this.stats.dm++;
  }

  /** Call a service through a robot-side ServiceProvider interface; resolves with the response msg. */
  call(iTag, type, msg, timeout = 30000) {
    const msgID = newId();
    return new Promise((resolve, reject) => {
      const timer = setTimeout(() => { this.calls.delete(msgID); reject(new RCEError("timeout",
        `no response from ${iTag} (${type}) within ${timeout / 1000} s`)); }, timeout);
      this.calls.set(msgID, { resolve, reject, timer });
      try { this.send("DM", { iTag, type, msgID, msg }); } catch (e) {
        clearTimeout(timer); this.calls.delete(msgID); reject(e);
      }
    });
  }

  /** fn(msg, dm) for each DM arriving on the robot-side interface `iTag`. Returns an unsubscribe function. */
  subscribe(iTag, fn) {
    if (!this.subscribers.has(iTag)) this.subscribers.set(iTag, new Set());
    this.subscribers.get(iTag).add(fn);
    return () => this.subscribers.get(iTag).delete(fn);
  }

  // -- incoming ----------------------------------------------------------------------------------
  _receive(data) {
    this.stats.in++;
    let complete = [];
    try {
      if (typeof data === "string") {
        const m = parseJSON(data);
        if (!m || typeof m !== "object" || typeof m.type !== "string") throw new Error("not {type, data}");
        const done = this.assembler.addMessage(m);
        if (done) complete = [done];
      } else {
        complete = this.assembler.addPart(data);
      }
    } catch (e) {
      this._emit("notice", `bad frame from the cloud ignored: ${e.message}`);
      return;
    }
    for (const m of complete) this._dispatch(m);
  }

  _dispatch(m) {
    const d = m.data;
    if (m.type === "DM") {
      const call = d.msgID && this.calls.get(d.msgID);
      if (call) {
        clearTimeout(call.timer);
        this.calls.delete(d.msgID);
        call.resolve(d.msg);
      }
      for (const fn of this.subscribers.get(d.iTag) || []) {
        try { fn(d.msg, d); } catch (e) { console.error(`rce.js: subscriber of ${d.iTag} failed`, e); }
      }
      this._emit("message", d);
    } else if (m.type === "ST") {
      this.stats.st++;
      if (d && d.topic === "iu") this.iu.set(d.iTag, !!d.status);
      this._emit("status", d);
    } else if (m.type === "ER") {
      this.stats.er++;
      const reason = typeof d === "string" ? d : JSON.stringify(d);
      for (const [token, b] of this._barriers) {
        if (reason.includes(token)) { this._barriers.delete(token); b.resolve(); return; }
      }
      this.errors.push({ t: Date.now(), reason });
      if (this.errors.length > 50) this.errors.shift();
      this._emit("error", reason);
    } else {
      this._emit("notice", `unknown message type ${m.type} from the cloud`);
    }
  }
}
