// rce.js: the RCE client protocol (docs/design.md, section 3) from the browser. No build step, no
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
// Two layers, as rce.protocol.session and rce_client in Python:
// - `ClientSession` holds the rules of the robot side of a session, sans I/O: frames in, frames to
//   send and events out, time passed in as an argument. Its rules and its event names are those
//   of tests/vectors/README.md; tests/vectors/session.json checks them, here (in Chromium, by
//   tests/web/test_web_vectors.py) and in Python, so that the two cannot drift.
// - `Client` is the shell: the login, the websocket, the timers, promises and callbacks.
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
//
// Session resume (docs/INTERNALS.md "Session resume"), opt-in: `new Client({..., reconnect: true})`
// asks for it; when the link drops, the client dials the robot endpoint again with backoff and the
// session token the cloud gave (never the password, which is not kept), and resumes: what the page
// sent meanwhile goes out then, calls wait, and what the cloud sent meanwhile arrives. Events
// "disconnected" (reason), "reconnected" (url) and "resumed" (the cloud's ST data, with `dropped`).

export const CLIENT_VERSION = "20130902";
/** s an incomplete message or an orphan binary part waits (rce.protocol.DEFAULT_EXPIRY). */
export const DEFAULT_EXPIRY = 60;
/** bytes of binary parts held while they wait for their message (rce.protocol.Assembler). */
export const MAX_PENDING_BYTES = 256 * 1024 * 1024;
/** messages kept until the cloud acks them, to resend after a resume (rce.protocol.resume). */
export const DEFAULT_RESUME_BUFFER = 1000;
/** bytes of frames kept until the cloud acks them (rce.protocol.resume). */
export const DEFAULT_RESUME_BYTES = 64 * 1024 * 1024;
/** messages taken from the cloud before an AK goes out at once (rce.protocol.resume.ACK_EVERY). */
export const ACK_EVERY = 16;
/** s after the first message not yet acked before an AK goes out (rce.protocol.resume.ACK_DELAY). */
export const ACK_DELAY = 0.2;
const ID_LEN = 32;                       // chars of a binary part id (32 hex)
const HEX_ID = /^[0-9a-fA-F]{32}$/;
const enc = new TextEncoder();
const dec = new TextDecoder();

/**
 * Errors from this library: `kind` is "login", "connect", "cloud" (an ER), "timeout", "closed",
 * "protocol" (a frame the session cannot take) or "usage" (a bad argument).
 */
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
// Login (docs/design.md, section 3.1): GET MASTER/?userID=U&version=V -> {"url": ws_url, "current"?}
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


// ---------------------------------------------------------------------------------------------
// JSON values and binary parts (docs/design.md, section 3.4)
// ---------------------------------------------------------------------------------------------
const isBytes = (v) => v instanceof Uint8Array || v instanceof ArrayBuffer;
const isObject = (v) => v !== null && typeof v === "object" && !Array.isArray(v);
const nonEmpty = (what, v) => {
  if (typeof v !== "string" || !v) throw new RCEError("usage", `${what} must be a non-empty string: ${JSON.stringify(v)}`);
};
const kindOf = (v) => (v === null ? "null" : Array.isArray(v) ? "array" : typeof v);

/** Python's bool() of a JSON value: empty arrays and objects are false too. */
function truthy(v) {
  if (Array.isArray(v)) return v.length > 0;
  if (isObject(v)) return Object.keys(v).length > 0;
  return !!v;
}

/**
 * Outgoing: each bytes value under key k becomes `k*: id` (a list of bytes `k*: [ids]`), ids from
 * `nextId()`. Returns [jsonText, [binary frames `id || bytes`]], parts depth first in key order.
 */
function encodeMessage(obj, nextId) {
  const frames = [];
  const part = (v) => {
    const id = nextId();
    if (typeof id !== "string" || !HEX_ID.test(id)) {
      throw new RCEError("usage", `binary part id ${JSON.stringify(id)} is not 32 hex chars`);
    }
    const data = v instanceof ArrayBuffer ? new Uint8Array(v) : v;
    const f = new Uint8Array(ID_LEN + data.length);
    f.set(enc.encode(id));
    f.set(data, ID_LEN);
    frames.push(f);
    return id;
  };
  const walk = (o) => {
    if (Array.isArray(o)) return o.map(walk);
    if (!isObject(o) || isBytes(o)) return o;
    const out = {};
    for (const [k, v] of Object.entries(o)) {
      if (isBytes(v)) out[k + "*"] = part(v);
      else if (Array.isArray(v) && v.length && v.every(isBytes)) out[k + "*"] = v.map(part);
      else out[k] = walk(v);
    }
    return out;
  };
  return [JSON.stringify(walk(obj)), frames];
}

/** Ids referenced by `*` keys anywhere in `obj`, in order; RCEError "protocol" for a bad id. */
function refsOf(obj, acc = []) {
  if (Array.isArray(obj)) obj.forEach((v) => refsOf(v, acc));
  else if (isObject(obj)) {
    for (const [k, v] of Object.entries(obj)) {
      if (!k.endsWith("*")) { refsOf(v, acc); continue; }
      for (const id of Array.isArray(v) ? v : [v]) {
        if (typeof id !== "string" || !HEX_ID.test(id)) {
          throw new RCEError("protocol", `binary reference under key ${JSON.stringify(k)} must be a 32-hex-char id, ` +
                                         `got ${JSON.stringify(id)}`);
        }
        acc.push(id);
      }
    }
  }
  return acc;
}

/** `k*: id` -> `k: bytes` (`k*: [ids]` -> a list of bytes). */
function resolveRefs(obj, parts) {
  if (Array.isArray(obj)) return obj.map((v) => resolveRefs(v, parts));
  if (!isObject(obj)) return obj;
  const out = {};
  for (const [k, v] of Object.entries(obj)) {
    if (k.endsWith("*")) out[k.slice(0, -1)] = Array.isArray(v) ? v.map((id) => parts.get(id)) : parts.get(v);
    else out[k] = resolveRefs(v, parts);
  }
  return out;
}

/**
 * Joins JSON messages and their binary parts, in either order (as rce.protocol.Assembler): the
 * first message waiting for an id takes the part; parts wait at most `maxPendingBytes` in all.
 * Times are s; what waited more than `expiry` s goes in expire().
 */
class Assembler {
  constructor(expiry, maxPendingBytes) {
    this.expiry = expiry;
    this.maxPendingBytes = maxPendingBytes;
    this.waiting = [];           // {msg, refs, missing: Set, since}, oldest first
    this.parts = new Map();      // id -> {data, since}
    this.bytes = 0;              // payload bytes in this.parts
  }

  /** A JSON message (an object); returns the messages it completed (0 or 1). */
  text(msg, now) {
    const refs = refsOf(msg);
    if (!refs.length) return [msg];
    const missing = new Set(refs.filter((id) => !this.parts.has(id)));
    if (!missing.size) return [this._complete(msg, refs)];
    this.waiting.push({ msg, refs, missing, since: now });
    return [];
  }

  /** A binary frame `id || bytes`; returns the messages it completed (0 or 1). */
  binary(bytes, now) {
    if (bytes.length < ID_LEN) {
      throw new RCEError("protocol", `binary frame of ${bytes.length} bytes is shorter than its ${ID_LEN}-char id`);
    }
    const id = String.fromCharCode(...bytes.subarray(0, ID_LEN));
    if (!HEX_ID.test(id)) throw new RCEError("protocol", "binary frame does not start with a 32-hex-char id");
    const data = bytes.subarray(ID_LEN);
    const held = this.bytes - (this.parts.get(id)?.data.length ?? 0);   // a part sent again replaces the first
    if (held + data.length > this.maxPendingBytes) {
      throw new RCEError("protocol", `binary parts waiting for their message exceed ${this.maxPendingBytes} bytes`);
    }
    this.parts.set(id, { data, since: now });
    this.bytes = held + data.length;
    const w = this.waiting.find((x) => x.missing.has(id));
    if (!w) return [];
    w.missing.delete(id);
    if (w.missing.size) return [];
    this.waiting.splice(this.waiting.indexOf(w), 1);
    return [this._complete(w.msg, w.refs)];
  }

  _complete(msg, refs) {
    const taken = new Map(refs.map((id) => [id, this.parts.get(id).data]));
    for (const [id, data] of taken) { this.parts.delete(id); this.bytes -= data.length; }
    for (const w of this.waiting) w.refs.forEach((id) => taken.has(id) && w.missing.add(id));  // reused ids wait again
    return resolveRefs(msg, taken);
  }

  /** Drop messages and orphan parts that waited more than `expiry` s; one reason per drop. */
  expire(now) {
    const reasons = [];
    this.waiting = this.waiting.filter((w) => {
      if (now - w.since <= this.expiry) return true;
      const iTag = isObject(w.msg.data) ? w.msg.data.iTag : undefined;
      reasons.push(`message ${w.msg.type} for interface ${JSON.stringify(iTag ?? null)} expired after ` +
                   `${this.expiry} s waiting for ${w.missing.size} binary part(s)`);
      return false;
    });
    const wanted = new Set(this.waiting.flatMap((w) => w.refs));
    for (const [id, p] of this.parts) {
      if (now - p.since <= this.expiry || wanted.has(id)) continue;
      this.parts.delete(id);
      this.bytes -= p.data.length;
      reasons.push(`binary part ${id} expired after ${this.expiry} s with no message referring to it`);
    }
    return reasons;
  }
}

// ---------------------------------------------------------------------------------------------
// Session resume, sans I/O (as rce.protocol.resume): numbers, acks, the bounded buffer
// ---------------------------------------------------------------------------------------------
const isSessionStatus = (m) => m.type === "ST" && isObject(m.data) && m.data.topic === "session";
const frameSize = (f) => (typeof f === "string" ? f.length : f.byteLength);
const toOutput = (f) => ({ frame: typeof f === "string" ? { text: f } : { binary: f } });

/** The `seq` of a message's envelope, or null; RCEError "protocol" for one that is not a positive integer. */
function readSeq(m) {
  if (!("seq" in m)) return null;
  if (!Number.isInteger(m.seq) || m.seq < 1) {
    throw new RCEError("protocol", `message.seq must be a positive integer, got ${JSON.stringify(m.seq)}`);
  }
  return m.seq;
}

/** The n of an AK's data {seq: n}; RCEError "protocol" otherwise. */
function readAck(data) {
  const seq = isObject(data) ? data.seq : undefined;
  if (!Number.isInteger(seq) || seq < 0) {
    throw new RCEError("protocol", `AK.data.seq must be a non-negative integer, got ${JSON.stringify(data ?? null)}`);
  }
  return seq;
}

/** The numbered messages the page sent, kept until the cloud acks them (at most maxMessages, maxBytes). */
class Outgoing {
  constructor(maxMessages, maxBytes) {
    Object.assign(this, { maxMessages, maxBytes, last: 0, acked: 0, forgotten: 0, bytes: 0 });
    this.kept = [];                  // {seq, frames, size}, oldest first
  }

  keep(seq, frames) {
    const size = frames.reduce((n, f) => n + frameSize(f), 0);
    this.kept.push({ seq, frames, size });
    this.bytes += size;
    while (this.kept.length > this.maxMessages || (this.bytes > this.maxBytes && this.kept.length > 1)) {
      this.bytes -= this.kept.shift().size;
      this.forgotten++;
    }
  }

  ack(n) {
    if (n > this.last) {
      throw new RCEError("protocol", `AK: seq ${n} was never sent (the last message sent is ${this.last})`);
    }
    while (this.kept.length && this.kept[0].seq <= n) this.bytes -= this.kept.shift().size;
    this.acked = Math.max(this.acked, n);
  }

  /** A resume: the cloud took every message up to n. {messages: [frames, ...] after n, lost}. */
  resendAfter(n) {
    this.ack(n);
    const first = this.kept.length ? this.kept[0].seq : this.last + 1;
    return { messages: this.kept.map((k) => k.frames), lost: Math.max(0, first - 1 - this.acked) };
  }

  clear() { this.kept = []; this.bytes = 0; }
}

/** Numbered messages taken from the cloud: each once; an AK after ackEvery of them or ackDelay s. */
class Incoming {
  constructor(ackEvery, ackDelay) {
    Object.assign(this, { ackEvery, ackDelay, last: 0, acked: 0, duplicates: 0, gaps: 0, unacked: 0, since: null });
  }

  take(seq, now) {
    if (seq === null) seq = this.last + 1;
    if (seq <= this.last) { this.duplicates++; return false; }
    this.gaps += seq - this.last - 1;
    this.last = seq;
    this.unacked++;
    if (this.since === null) this.since = now;
    return true;
  }

  ackDue(now) {
    if (!this.unacked || (this.unacked < this.ackEvery && now - this.since < this.ackDelay)) return null;
    this.reported();
    return this.last;
  }

  reported() { this.acked = this.last; this.unacked = 0; this.since = null; }
}

// ---------------------------------------------------------------------------------------------
// The session, sans I/O (tests/vectors/README.md)
// ---------------------------------------------------------------------------------------------
/**
 * The robot side of an RCE session without a socket, a timer or a clock: the same rules as
 * rce.protocol.session.ClientSession, checked by the shared vectors (tests/vectors/session.json).
 *
 * Every method returns the outputs, in order: `{frame: {text: string}}` and `{frame: {binary:
 * Uint8Array}}` to send, and events `{event: NAME, ...fields}` for the application:
 * status {data}, interface {iTag, up}, error {reason}, message {iTag, type, msgID, msg},
 * response {msgID, msg}, call_failed {msgID, reason}, barrier {token}, barrier_failed {token,
 * reason}, dropped {reason}. Times (`now`) are s on any monotonic clock; a frame without one is
 * taken at the last time seen.
 *
 * options: expiry (s an incomplete message waits for its binary parts), maxPendingBytes (bytes
 * of binary parts held while waiting), newId (the source of binary part ids; a test fixes them);
 * resume (ask for session resume: messages are numbered from the first and kept until acked, at most
 * resumeBuffer messages and resumeBytes bytes; the cloud's first message decides: ST session started
 * turns it on, anything else off; numbered messages from the cloud are taken once and acked every
 * ackEvery messages or ackDelay s). With resume the outputs also hold events session {data} and
 * detached {session, ack}; see detach(), attach(), resumeQuery().
 * Misuse (a msgID or token already pending, sending after close) throws RCEError "usage"/"closed".
 */
export class ClientSession {
  constructor({ expiry = DEFAULT_EXPIRY, maxPendingBytes = MAX_PENDING_BYTES, newId: ids = newId, resume = false,
                resumeBuffer = DEFAULT_RESUME_BUFFER, resumeBytes = DEFAULT_RESUME_BYTES, ackEvery = ACK_EVERY,
                ackDelay = ACK_DELAY, ...rest } = {}) {
    const unknown = Object.keys(rest);
    if (unknown.length) throw new RCEError("usage", `ClientSession: unknown option(s) ${unknown.join(", ")}`);
    this.assembler = new Assembler(expiry, maxPendingBytes);
    this.state = resume ? "asked" : "off";          // off | asked -> live <-> detached -> resuming -> live
    this.token = null;                              // the session token the cloud gave
    this.grace = null;                              // s the cloud keeps the session detached
    this.outgoing = resume ? new Outgoing(resumeBuffer, resumeBytes) : null;
    this.incoming = resume ? new Incoming(ackEvery, ackDelay) : null;
    this.newId = ids;
    this.interfaces = new Map();      // iTag -> bool: its last ST iu
    this.calls = new Map();           // msgID -> {iTag, seq}: calls waiting for their response
    this.barriers = new Map();        // token -> seq: probes waiting for their ER
    this.seq = 0;                     // start order of calls and barriers
    this.now = 0;                     // s, the last time given
    this.dropped = 0;                 // frames and parts dropped (each also a `dropped` event)
    this.closed = false;
  }

  /** A text frame from the cloud. */
  receiveText(text, now = this.now) {
    this.now = now;
    let msg;
    try {
      msg = JSON.parse(text);
    } catch (e) {
      return this._drop(`malformed JSON: ${e.message}`);
    }
    if (!isObject(msg)) return this._drop(`message must be a JSON object, got ${kindOf(msg)}`);
    return this._take(() => this.assembler.text(msg, now));
  }

  /** A binary frame `id || bytes` from the cloud (Uint8Array or ArrayBuffer). */
  receiveBinary(data, now = this.now) {
    this.now = now;
    return this._take(() => this.assembler.binary(data instanceof Uint8Array ? data : new Uint8Array(data), now));
  }

  /** Send `{type, data}`; bytes values become binary parts. With resume: numbered and kept; nothing goes
   * out while detached or resuming (it goes after the resume). */
  send(type, data) {
    if (this.closed) throw new RCEError("closed", "the session is closed");
    let frames;
    if (this.outgoing) {
      const seq = this.outgoing.last + 1;
      const [text, parts] = encodeMessage({ type, seq, data }, this.newId);
      this.outgoing.last = seq;
      frames = [text, ...parts];
      this.outgoing.keep(seq, frames);
    } else {
      const [text, parts] = encodeMessage({ type, data }, this.newId);
      frames = [text, ...parts];
    }
    if (this.state === "detached" || this.state === "resuming") return [];
    return frames.map(toOutput);
  }

  /** Start a service call: DM {iTag, type, msgID, msg}; settled by `response` or `call_failed`. */
  call(iTag, type, msg, msgID) {
    nonEmpty("iTag", iTag);
    nonEmpty("msgID", msgID);
    if (this.calls.has(msgID)) throw new RCEError("usage", `a call with msgID ${msgID} is already pending`);
    const out = this.send("DM", { iTag, type, msgID, msg });
    this.calls.set(msgID, { iTag, seq: this.seq++ });
    return out;
  }

  /**
   * Start a barrier: a CX between two interfaces that cannot exist, which the cloud refuses with
   * an ER naming them after every request sent before it (`barrier {token}`).
   */
  barrier(token) {
    nonEmpty("token", token);
    if (this.barriers.has(token)) throw new RCEError("usage", `a barrier with token ${token} is already pending`);
    const out = this.send("CX", { connect: [{ tagA: `${token}/a`, tagB: `${token}/b` }] });
    this.barriers.set(token, this.seq++);
    return out;
  }

  /** Forget a call or a barrier the application gave up on (its timeout); no outputs. */
  forget(msgIDOrToken) {
    this.calls.delete(msgIDOrToken);
    this.barriers.delete(msgIDOrToken);
  }

  /** Time passes: drop incomplete messages and orphan parts older than `expiry`; an AK that is due goes out. */
  tick(now) {
    this.now = now;
    const out = this.assembler.expire(now).flatMap((reason) => this._drop(reason));
    return this.state === "live" ? [...out, ...this._ackIfDue()] : out;
  }

  /**
   * The link is lost. A live resumable session is kept: calls and barriers wait, sends are kept;
   * outputs [detached {session, ack}] (the resume query). Otherwise it is close(reason).
   */
  detach(reason) {
    if (this.state !== "live" && this.state !== "resuming") return this.close(reason);
    this.state = "detached";
    this.assembler = new Assembler(this.assembler.expiry, this.assembler.maxPendingBytes);  // resent whole
    return [{ event: "detached", session: this.token, ack: this.incoming.last }];
  }

  /** A new link is open with resumeQuery(); nothing new goes out until the cloud's ST session resumed. */
  attach() {
    if (this.state !== "detached") throw new RCEError("usage", `attach: the session is ${this.state}, not detached`);
    this.state = "resuming";
    this.incoming.reported();
    return [];
  }

  /** The query values of a resume: {session: token, ack: the last cloud message taken}. */
  resumeQuery() {
    return { session: this.token || "", ack: String(this.incoming ? this.incoming.last : 0) };
  }

  /** The link closed: every pending call and barrier fails, in the order they were started. */
  close(reason) {
    if (this.closed) return [];
    this.closed = true;
    this.state = "off";
    if (this.outgoing) this.outgoing.clear();
    const why = `connection closed: ${reason}`;
    const pending = [...[...this.calls].map(([msgID, c]) => [c.seq, { event: "call_failed", msgID, reason: why }]),
                     ...[...this.barriers].map(([token, seq]) => [seq, { event: "barrier_failed", token,
                                                                         reason: why }])];
    this.calls.clear();
    this.barriers.clear();
    return pending.sort((a, b) => a[0] - b[0]).map(([, ev]) => ev);
  }

  _drop(reason) {
    this.dropped++;
    return [{ event: "dropped", reason }];
  }

  /** Run an assembler step; a protocol error becomes `dropped`, complete messages are dispatched. */
  _take(step) {
    let done;
    try {
      done = step();
    } catch (e) {
      if (e instanceof RCEError && e.kind === "protocol") return this._drop(e.message);
      throw e;
    }
    return done.flatMap((m) => this._dispatch(m));
  }

  _ackIfDue() {
    const n = this.incoming.ackDue(this.now);
    return n === null ? [] : [{ frame: { text: JSON.stringify({ type: "AK", data: { seq: n } }) } }];
  }

  /** The session's own messages (resume): outputs when it took `m`, null when `m` is the application's. */
  _resumeRules(m) {
    const data = m.data;
    if (this.state === "asked") {                    // the cloud's first message decides
      if (isSessionStatus(m) && data.status === "started" && typeof data.session === "string") {
        this.state = "live";
        this.token = data.session;
        this.grace = data.grace ?? null;
        return [{ event: "session", data }];
      }
      this.state = "off";                            // the cloud does not offer resume
      this.outgoing = this.incoming = null;
      return null;
    }
    if (isSessionStatus(m)) {
      const out = this.state === "resuming" && data.status === "resumed" ? this._resumed(data) : [];
      return [...out, { event: "session", data }];
    }
    if (m.type === "AK") {
      try {
        this.outgoing.ack(readAck(data));
      } catch (e) {
        if (e instanceof RCEError && e.kind === "protocol") return this._drop(e.message);
        throw e;
      }
      return [];
    }
    let seq;
    try {
      seq = readSeq(m);
    } catch (e) {
      if (e instanceof RCEError && e.kind === "protocol") return this._drop(e.message);
      throw e;
    }
    if (!this.incoming.take(seq, this.now)) return [];
    return null;
  }

  /** The cloud's ST session resumed: resend what it did not take, then the link is live. */
  _resumed(data) {
    const out = [];
    let r;
    try {
      r = this.outgoing.resendAfter(readAck({ seq: data.ack }));
    } catch (e) {
      if (!(e instanceof RCEError && e.kind === "protocol")) throw e;
      out.push(...this._drop(`ST session resumed: ${e.message}`));
      r = this.outgoing.resendAfter(this.outgoing.acked);
    }
    this.state = "live";
    for (const frames of r.messages) out.push(...frames.map(toOutput));
    if (r.lost) {
      out.push(...this._drop(`${r.lost} message(s) to the cloud were lost: the resume buffer ` +
                             `(${this.outgoing.maxMessages} messages) forgot them before the cloud acked them`));
    }
    return out;
  }

  _dispatch(m) {
    if (this.state !== "off") {
      const own = this._resumeRules(m);
      if (own !== null) return own;
      if (this.incoming) return [...this._dispatchApp(m), ...this._ackIfDue()];
    }
    return this._dispatchApp(m);
  }

  _dispatchApp({ type, data }) {
    if (type === "ST") return this._status(data);
    if (type === "ER") return this._error(typeof data === "string" ? data : JSON.stringify(data ?? null));
    if (type !== "DM") return this._drop(`unexpected message type ${JSON.stringify(type ?? null)}, not DM, ST or ER`);
    if (!isObject(data)) return this._drop(`DM data must be a JSON object, got ${kindOf(data)}`);
    const msgID = data.msgID ?? null;
    const call = msgID === null ? undefined : this.calls.get(String(msgID));
    if (call && call.iTag === data.iTag) {
      this.calls.delete(String(msgID));
      return [{ event: "response", msgID: String(msgID), msg: data.msg ?? null }];
    }
    return [{ event: "message", iTag: data.iTag ?? null, type: data.type ?? null, msgID, msg: data.msg ?? null }];
  }

  _status(data) {
    const out = [];
    if (isObject(data) && data.topic === "iu" && typeof data.iTag === "string") {
      const up = truthy(data.status);
      this.interfaces.set(data.iTag, up);
      out.push({ event: "interface", iTag: data.iTag, up });
    }
    out.push({ event: "status", data: data ?? null });
    return out;
  }

  /** An ER: the barrier whose token it holds passes, or the call it names fails, or it is the application's. */
  _error(reason) {
    for (const token of this.barriers.keys()) {
      if (reason.includes(token)) { this.barriers.delete(token); return [{ event: "barrier", token }]; }
    }
    const calls = [...this.calls];                          // in the order they were started
    const alone = (iTag) => calls.filter(([, c]) => c.iTag === iTag).length === 1;
    const names = (iTag) => [`'${iTag}'`, `"${iTag}"`, `/${iTag}`].some((s) => reason.includes(s));
    const call = calls.find(([id]) => reason.includes(id)) || calls.find(([, c]) => alone(c.iTag) && names(c.iTag));
    const msgID = call?.[0];
    if (msgID === undefined) return [{ event: "error", reason }];
    this.calls.delete(msgID);
    return [{ event: "call_failed", msgID, reason }];
  }
}

// ---------------------------------------------------------------------------------------------
// The client: a websocket shell around ClientSession
// ---------------------------------------------------------------------------------------------
/** ms the cloud may take to handle a request and its barrier (request(), barrier()). */
export const REQUEST_TIMEOUT_MS = 60000;
/** ms a service call waits for its response (call()). */
export const CALL_TIMEOUT_MS = 30000;
/** ms waitUp() waits for the interfaces' ST iu. */
export const WAIT_UP_TIMEOUT_MS = 30000;
/** ms between two passes that expire incomplete messages (a period, not a deadline). */
const EXPIRE_PERIOD_MS = 5000;
/** ms before the second attempt to reconnect; it doubles after each failure ... */
export const RECONNECT_WAIT_MS = 50;
/** ms ... up to this (each wait shortened by up to half at random, so that pages spread out). */
export const RECONNECT_WAIT_MAX_MS = 1000;
/** s a page keeps trying to resume when the cloud did not say its grace (rce.protocol.resume.DEFAULT_GRACE). */
const DEFAULT_GRACE = 30;
const FINAL_CLOSE = [1000, 1008];                   // close codes by which the cloud ends a session
const clock = () => performance.now() / 1000;      // s, monotonic

export class Client {
  /**
   * options: master (login URL, e.g. "http://127.0.0.1:9000/"), userID, robotID, password (clear
   * text, hashed here, never stored), version, expiry (s, binary parts), endpoint (the websocket URL
   * of a known robot endpoint: no login at the master); reconnect (ask for session
   * resume and ride out lost links), maxReconnectAttempts (dials per gap; null: until the session's
   * grace has passed), reconnectWaitMs, maxReconnectWaitMs (the backoff), resumeBuffer (messages kept
   * until the cloud acks them); maxLag (s the robot endpoint may stay behind this connection's frames
   * before it sheds its topic messages, counted; 0: never, for an operator's commands; null: the
   * endpoint's default, 1 s; docs/INTERNALS.md "A peer that does not keep up"), kept across resumes.
   *
   * Events (on()): "status" (data of every ST), "interface" (iTag, up), "error" (the text of an
   * ER that no call or barrier took), "message" (dm: {iTag, type, msgID, msg}), "notice" (text:
   * what the session dropped, a version note), "close" ({code, reason}); with reconnect:
   * "disconnected" (reason), "reconnected" (url), "resumed" (the cloud's ST session data: dropped, ...).
   * A browser does not see why a handshake was refused: a resume the cloud refuses (the grace has
   * passed) looks like an unreachable endpoint, and the page tries until the grace has passed.
   */
  constructor({ master, userID, robotID, password, version = CLIENT_VERSION, expiry = DEFAULT_EXPIRY, endpoint = null,
                reconnect = false, maxReconnectAttempts = null, reconnectWaitMs = RECONNECT_WAIT_MS,
                maxReconnectWaitMs = RECONNECT_WAIT_MAX_MS, resumeBuffer = DEFAULT_RESUME_BUFFER, maxLag = null }) {
    if (maxLag !== null && !(typeof maxLag === "number" && maxLag >= 0 && Number.isFinite(maxLag))) {
      throw new RCEError("usage", `maxLag must be null or a number of seconds >= 0, got ${JSON.stringify(maxLag)}`);
    }
    this.maxLag = maxLag;
    this.master = master;
    this.endpoint = endpoint;
    this.userID = userID;
    this.robotID = robotID;
    this._password = password;
    this.version = version;
    this.ws = null;
    this.wsUrl = null;
    this.reconnect = reconnect ? { maxAttempts: maxReconnectAttempts, waitMs: reconnectWaitMs,
                                   maxWaitMs: Math.max(reconnectWaitMs, maxReconnectWaitMs) } : null;
    this.resumes = 0;
    this._gap = null;                     // while resuming: {attempts, failures, deadline, timer}
    this.session = new ClientSession({ expiry, resume: reconnect, resumeBuffer });
    this.handlers = new Map();            // event -> Set(fn)
    this.subscribers = new Map();         // iTag -> Set(fn)
    this._waiting = new Map();            // msgID or barrier token -> {resolve, reject}
    this.closed = false;
    this._closing = false;                // close() was called: the link's end is not a loss
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
    const info = this.endpoint ? { url: this.endpoint } : await login(this.master, this.userID, this.version);
    if (info.current) this._emit("notice", `the master speaks version ${info.current}, this client ${this.version}`);
    const pw = await sha256Hex(this._password);
    this._password = null;
    this.wsUrl = info.url;
    // refusal=http: a refused login closes the handshake (the 2013 form, an ER on an open socket, is for clients
    // that send nothing but userID, robotID and password)
    const url = this._url({ password: pw, refusal: "http", ...(this.reconnect ? { resume: "1" } : {}) });
    const opened = await this._open(url);
    if (!opened) {
      // a browser does not show the refused handshake's status (401/403/409) to the page
      throw new RCEError("connect", `login refused by the robot endpoint ${info.url}: wrong password? ` +
                                    `(or robot ID ${JSON.stringify(this.robotID)} already connected; ` +
                                    `a browser does not see the reason)`);
    }
    const period = this.reconnect ? Math.min(EXPIRE_PERIOD_MS, ACK_DELAY * 500) : EXPIRE_PERIOD_MS;   // AKs on time
    this._expiryTimer = setInterval(() => this._apply(this.session.tick(clock())), period);
  }

  /** The robot endpoint's URL with userID, robotID and `extra` query values. */
  _url(extra) {
    const q = new URLSearchParams({ userID: this.userID, robotID: this.robotID,
                                    ...(this.maxLag !== null ? { maxLag: String(this.maxLag) } : {}), ...extra });
    return this.wsUrl + (this.wsUrl.includes("?") ? "&" : "?") + q.toString();
  }

  /** Open a websocket to `url`; resolves true once open (it is then this.ws), false if it closed first. */
  _open(url) {
    return new Promise((resolve) => {
      let ws;
      try {
        ws = new WebSocket(url);
      } catch (e) {
        resolve(false);
        return;
      }
      let open = false;
      ws.binaryType = "arraybuffer";
      ws.onopen = () => { open = true; this.ws = ws; resolve(true); };
      ws.onmessage = (ev) => {
        if (ws !== this.ws) return;                     // an old link
        this._apply(typeof ev.data === "string" ? this.session.receiveText(ev.data, clock())
                                                : this.session.receiveBinary(ev.data, clock()));
      };
      ws.onclose = (ev) => { if (!open) resolve(false); else this._linkLost(ws, ev.code, ev.reason); };
    });
  }

  /** A link closed: with reconnect (and a session the cloud did not end) keep the session and resume. */
  _linkLost(ws, code, reason) {
    if (ws !== this.ws || this.closed) return;
    const why = reason || `code ${code}`;
    if (this.reconnect && !this._closing && !FINAL_CLOSE.includes(code)) {
      const out = this.session.detach(why);
      if (out.some((o) => o.event === "detached")) {
        const grace = this.session.grace ?? DEFAULT_GRACE;
        this._gap = { attempts: 0, failures: 0, deadline: clock() + grace, timer: null };
        this._emit("disconnected", why);
        this._redial();
        return;
      }
      this._apply(out);
    }
    this._closed(code, reason);
  }

  /** One resume attempt with the session token; on failure the next after a backoff, until the grace. */
  async _redial() {
    const gap = this._gap;
    if (!gap || this.closed) return;
    gap.attempts++;
    const opened = await this._open(this._url(this.session.resumeQuery()));
    if (this.closed) {                                 // closed by the page meanwhile
      if (opened) this.ws.close(1000, "bye");
      return;
    }
    if (opened) {
      this._gap = null;
      this._apply(this.session.attach());
      this._emit("reconnected", this.wsUrl);
      return;
    }
    const r = this.reconnect;
    const delay = Math.min(r.waitMs * 2 ** gap.failures++, r.maxWaitMs) * (1 - 0.5 * Math.random());
    if (this.closed || (r.maxAttempts !== null && gap.attempts >= r.maxAttempts) ||
        clock() + delay / 1000 > gap.deadline) {
      this._gap = null;
      this._closed(1006, `could not resume the session (${gap.attempts} attempt(s))`);
      return;
    }
    gap.timer = setTimeout(() => this._redial(), delay);
  }

  _closed(code, reason) {
    if (this.closed) return;
    this.closed = true;
    clearInterval(this._expiryTimer);
    if (this._gap) clearTimeout(this._gap.timer);
    this._gap = null;
    this._apply(this.session.close(reason || `code ${code}`));
    this._emit("close", { code, reason });
  }

  close() {
    this._closing = true;
    if (this.ws && this.ws.readyState <= 1) this.ws.close(1000, "bye");
    this._closed(1000, "closed by the page");
  }

  /** Carry out the session's outputs: frames go to the websocket, events to promises and callbacks. */
  _apply(outputs) {
    for (const o of outputs) {
      if (o.frame) { this.ws.send("text" in o.frame ? o.frame.text : o.frame.binary); continue; }
      switch (o.event) {
        case "status": this._emit("status", o.data); break;
        case "interface": this._emit("interface", o.iTag, o.up); break;
        case "error": this._emit("error", o.reason); break;
        case "message": this._message({ iTag: o.iTag, type: o.type, msgID: o.msgID, msg: o.msg }); break;
        case "response": this._settle(o.msgID, null, o.msg); break;
        case "call_failed": this._settle(o.msgID, new RCEError(this.closed ? "closed" : "cloud", o.reason)); break;
        case "barrier": this._settle(o.token, null); break;
        case "barrier_failed": this._settle(o.token, new RCEError("closed", o.reason)); break;
        case "dropped": this._emit("notice", `dropped from the cloud: ${o.reason}`); break;
        case "session":
          if (o.data.status === "resumed") { this.resumes++; this._emit("resumed", o.data); }
          break;
        case "detached": break;                       // _linkLost starts the resume
        default: console.error(`rce.js: unknown session output`, o);
      }
    }
  }

  _message(dm) {
    for (const fn of this.subscribers.get(dm.iTag) || []) {
      try { fn(dm.msg, dm); } catch (e) { console.error(`rce.js: subscriber of ${dm.iTag} failed`, e); }
    }
    this._emit("message", dm);
  }

  _settle(key, err, value) {
    const w = this._waiting.get(key);
    if (!w) return;
    this._waiting.delete(key);
    if (err) w.reject(err); else w.resolve(value);
  }

  /** A promise settled by the session's events for `key` (a msgID or a token), or by a timeout. */
  _await(key, timeout, timeoutText, start) {
    return new Promise((resolve, reject) => {
      const timer = setTimeout(() => {
        this._waiting.delete(key);
        this.session.forget(key);
        reject(new RCEError("timeout", timeoutText));
      }, timeout);
      this._waiting.set(key, { resolve: (v) => { clearTimeout(timer); resolve(v); },
                               reject: (e) => { clearTimeout(timer); reject(e); } });
      try {
        this._requireOpen();
        this._apply(start());
      } catch (e) {
        this._settle(key, e);
      }
    });
  }

  _requireOpen() {
    const kept = this.session.state === "detached" || this.session.state === "resuming";   // sent after the resume
    if (this.closed || !this.ws || (!kept && this.ws.readyState !== WebSocket.OPEN)) {
      throw new RCEError("closed", "not connected to the cloud");
    }
  }

  // -- outgoing ----------------------------------------------------------------------------------
  /** Send one protocol message `{type, data}` (bytes values become binary parts). */
  send(type, data) {
    this._requireOpen();
    this._apply(this.session.send(type, data));
  }

  /**
   * A CC/DC/CN/CX request: resolves once the cloud has handled it, rejects with the ER(s) it
   * caused. The protocol has no positive ack, but the master handles a robot's requests one at a
   * time and in order and refuses each bad one with an ER; so after the request we send a probe
   * (a CX between two interfaces that cannot exist, see barrier()) and the probe's ER marks the
   * end: ERs that came before it belong to the request. (rce_client.Connection.barrier does the same.)
   */
  async request(type, data, timeout = REQUEST_TIMEOUT_MS) {
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

  /** Resolve when the cloud has handled every request sent before (see request()); timeout in ms. */
  barrier(timeout = REQUEST_TIMEOUT_MS) {
    const token = `rcesync${newId().slice(0, 12)}`;
    return this._await(token, timeout, `the cloud did not answer within ${timeout / 1000} s`,
                       () => this.session.barrier(token));
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

  /** Resolve when each robot-side interface in `iTags` reported ST iu true; reject on an ER, close or timeout (ms). */
  waitUp(iTags, timeout = WAIT_UP_TIMEOUT_MS) {
    const left = new Set(iTags.filter((t) => !this.session.interfaces.get(t)));
    if (!left.size) return Promise.resolve();
    return new Promise((resolve, reject) => {
      const offs = [];
      const done = (err) => { clearTimeout(timer); offs.forEach((f) => f()); err ? reject(err) : resolve(); };
      offs.push(this.on("interface", (iTag, up) => { if (up) { left.delete(iTag); if (!left.size) done(); } }));
      offs.push(this.on("error", (reason) => done(new RCEError("cloud", reason))));
      offs.push(this.on("close", () => done(new RCEError("closed", "connection closed"))));
      const timer = setTimeout(() => done(new RCEError("timeout",
        `interfaces not connected within ${timeout / 1000} s: ${[...left].join(", ")}`)), timeout);
    });
  }

  /** Publish on a robot-side SubscriberConverter (msg: JSON) or SubscriberForwarder (msg: Uint8Array). */
  publish(iTag, type, msg, msgID = "") {
    this.send("DM", { iTag, type, msgID, msg });      // bytes become the binary part msg*
  }

  /** Call a service through a robot-side ServiceProvider interface; resolves with the response msg (timeout in ms). */
  call(iTag, type, msg, timeout = CALL_TIMEOUT_MS) {
    const msgID = newId();
    return this._await(msgID, timeout, `no response from ${iTag} (${type}) within ${timeout / 1000} s`,
                       () => this.session.call(iTag, type, msg, msgID));
  }

  /** fn(msg, dm) for each DM arriving on the robot-side interface `iTag`. Returns an unsubscribe function. */
  subscribe(iTag, fn) {
    if (!this.subscribers.has(iTag)) this.subscribers.set(iTag, new Set());
    this.subscribers.get(iTag).add(fn);
    return () => this.subscribers.get(iTag).delete(fn);
  }
}
