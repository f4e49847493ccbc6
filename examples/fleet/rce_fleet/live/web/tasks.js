// tasks.js: the operators' tasks on the fleet page. fleet.js owns the login and the interfaces;
// this module owns the task panel:
//   sends    /fleet/task        (fleet/Task: errands as cells or place names, a priority)
//   sends    /fleet/task_cancel (fleet/TaskCancel)
//   receives /fleet/tasks       (fleet/TaskList: tasks with state, robot and times; answers to
//                                requests; each robot's activity, task and battery)
// and shows the queue (state, robot, age in sim s, a cancel button), each robot's battery and task, its
// stall alert (a robot holding work that makes no progress: in its row and in the log), and three
// small live plots: tasks done per minute, queue length, utilisation.
//
// Its model is window.fleetView.tasks (see `model` below).

const HISTORY_MAX = 360;          // plot samples kept
const SAMPLE_EVERY_S = 2;         // fleet s between plot samples
const ANSWER_TIMEOUT = 10000;     // ms a request waits for the fleet's answer
const PLOT_EVERY = 1000;          // ms between plot redraws
const ACTIVE = new Set(["queued", "assigned", "active"]);

export class TaskPanel {
  /** view: fleetView; $: id -> element; send(kind, msg): publish on "task" | "cancel";
   * log(kind, text) -> entry; settle(entry, kind, text); places: [{name, kind, cell}]. */
  constructor({ view, $, send, log, settle, places }) {
    Object.assign(this, { view, $, send, log, settle });
    this.places = places || [];
    this.picking = false;
    this.seq = 0;
    this.waiting = new Map();      // request -> {entry, text, deadline}
    this.rows = new Map();
    this.alerts = new Map();       // robot -> the stall alert the log has shown
    this.model = view.tasks = { list: [], robots: {}, stats: {}, answers: [], history: [], stamp: 0, lists: 0 };
    this.lastPlot = 0;
    const sel = $("task-place");
    for (const p of this.places) {
      const o = document.createElement("option");
      o.value = p.name;
      o.textContent = `${p.name} (${p.kind}, cell ${p.cell})`;
      sel.append(o);
    }
    sel.onchange = () => { if (sel.value) this.appendErrand(sel.value); sel.value = ""; };
    $("task-pick").onclick = () => this.setPicking(!this.picking);
    $("task-form").onsubmit = (ev) => { ev.preventDefault(); this.submit(); };
    $("task-queue").addEventListener("click", (ev) => {
      const b = ev.target.closest("button[data-cancel]");
      if (b) { this.cancel(b.dataset.cancel); return; }
      const tr = ev.target.closest("tr[data-task]");     // a click on a task shows its history (again: hides it)
      if (tr) { this.shown = this.shown === tr.dataset.task ? null : tr.dataset.task; this.renderHistory(); }
    });
    this.shown = null;             // the task whose history is shown
  }

  setPicking(on) {
    this.picking = on;
    this.$("task-pick").classList.toggle("on", on);
    this.$("task-pick").textContent = on ? "picking: click cells" : "pick cells";
  }

  appendErrand(e) {
    const inp = this.$("task-errands");
    const cur = inp.value.split(",").map((s) => s.trim()).filter(Boolean);
    cur.push(String(e));
    inp.value = cur.join(", ");
  }

  /** A click on the map while picking: the cell becomes the next errand (returns true). */
  pick(cell) {
    if (!this.picking || cell < 0) return false;
    const place = this.places.find((p) => p.cell === cell);
    this.appendErrand(place ? place.name : cell);
    return true;
  }

  submit() {
    const errands = this.$("task-errands").value.split(",").map((s) => s.trim()).filter(Boolean);
    const priority = Number(this.$("task-priority").value || 0);
    const text = `task ${errands.join(" -> ") || "(no errand)"}`;
    const request = this.request("task", { id: "", errands, priority, earliest_start_s: 0, deadline_s: 0,
                                           source: `operator:${this.view.robotID}` }, text);
    if (request) {
      this.$("task-errands").value = "";
      this.setPicking(false);
    }
  }

  cancel(id) {
    this.request("cancel", { id, source: `operator:${this.view.robotID}` }, `cancel task ${id}`);
  }

  request(kind, msg, text) {
    const request = `${this.view.robotID}-${++this.seq}`;
    const entry = this.log("pending", `${text}: sent`);
    try {
      this.send(kind, { request, ...msg });
    } catch (e) {
      this.settle(entry, "error", `${text}: ${e.message}`);
      return null;
    }
    this.waiting.set(request, { entry, text, deadline: Date.now() + ANSWER_TIMEOUT });
    return request;
  }

  /** A fleet/TaskList from /fleet/tasks. */
  onList(msg) {
    const m = this.model;
    m.lists++;
    m.list = msg.tasks || [];
    m.answers = msg.answers || [];
    m.stamp = (msg.header?.stamp?.secs || 0) + (msg.header?.stamp?.nsecs || 0) / 1e9;
    m.stats = { queued: msg.queued, done: msg.done, failed: msg.failed, cancelled: msg.cancelled,
                deadlineMissed: msg.deadline_missed, meanS: msg.mean_s, p95S: msg.p95_s };
    m.robots = Object.fromEntries((msg.robots || []).map((r) => [r.robot, r]));
    for (const r of msg.robots || []) {
      const before = this.alerts.get(r.robot) || "";
      if ((r.alert || "") === before) continue;
      this.alerts.set(r.robot, r.alert || "");
      if (r.alert) this.log("error", `ALERT ${r.alert}`);
      else this.log("ok", `${r.robot} makes progress again`);
    }
    for (const a of m.answers) {
      const w = this.waiting.get(a.request);
      if (!w) continue;
      this.waiting.delete(a.request);
      if (a.ok) {
        const t = m.list.find((x) => x.id === a.id);
        this.settle(w.entry, "ok", `${w.text}: task ${a.id} ${t ? t.state : "ok"}`);
      } else {
        this.settle(w.entry, "error", `${w.text}: refused (${a.code}): ${a.error}`);
      }
    }
    const now = Date.now();
    for (const [k, w] of this.waiting) {
      if (now > w.deadline) {
        this.settle(w.entry, "error", `${w.text}: no answer from the fleet within ${ANSWER_TIMEOUT / 1000} s`);
        this.waiting.delete(k);
      }
    }
    this.sample();
    this.render();
  }

  sample() {
    const m = this.model, h = m.history;
    if (h.length && m.stamp - h[h.length - 1].t < SAMPLE_EVERY_S) return;
    const rs = Object.values(m.robots);
    const util = rs.length ? rs.reduce((s, r) => s + (r.since_s > 0 ? r.busy_s / r.since_s : 0), 0) / rs.length : 0;
    // tasks done per minute over the last minute of fleet time (or what there is of it)
    let old = h.length ? h[0] : null;
    for (let i = h.length - 1; i >= 0; i--) if (m.stamp - h[i].t >= 60) { old = h[i]; break; }
    const span = old ? Math.max(m.stamp - old.t, 1) : 0;
    const perMin = old && span > 0 ? (m.stats.done - old.done) * 60 / span : 0;
    h.push({ t: m.stamp, done: m.stats.done || 0, queue: m.stats.queued || 0, util, perMin });
    if (h.length > HISTORY_MAX) h.shift();
  }

  render() {
    const m = this.model;
    const tbody = this.$("task-queue").tBodies[0];
    const seen = new Set();
    let next = tbody.firstElementChild;   // where the list's next row belongs
    for (const t of m.list) {
      seen.add(t.id);
      let tr = this.rows.get(t.id);
      if (!tr) {
        tr = document.createElement("tr");
        tr.dataset.task = t.id;
        tr.innerHTML = `<td class="id"></td><td class="state"></td><td class="robot"></td><td class="errands"></td>` +
                       `<td class="age"></td><td class="act"></td>`;
        this.rows.set(t.id, tr);
      }
      // the list's order (open tasks, then the newest closed ones), moving only rows out of place: a row
      // moved between a press and its release under the pointer loses the operator's click
      if (tr === next) next = next.nextElementSibling;
      else tbody.insertBefore(tr, next);
      const set = (cls, text, title) => {
        const td = tr.querySelector(`.${cls}`);
        if (td.textContent !== text) td.textContent = text;
        if (title !== undefined && td.title !== title) td.title = title;
      };
      set("id", t.id);
      set("state", t.state, t.reason || "");
      set("robot", t.robot || "-");
      set("errands", t.errands.join(" → "), `cells ${t.cells.join(", ")}; next errand ${t.next_errand + 1}`);
      const end = ACTIVE.has(t.state) ? m.stamp : t.finished;
      set("age", `${Math.max(0, end - t.created).toFixed(0)} s`);
      const act = tr.querySelector(".act");
      const want = ACTIVE.has(t.state);
      if (want !== !!act.firstChild) {
        act.innerHTML = want ? `<button data-cancel="${t.id}" title="cancel this task">cancel</button>` : "";
      }
      tr.className = t.state + (t.id === this.shown ? " shown" : "");
    }
    this.renderHistory();
    for (const [id, tr] of this.rows) if (!seen.has(id)) { tr.remove(); this.rows.delete(id); }
    const s = m.stats;
    const summary = `queued ${s.queued} · done ${s.done} · failed ${s.failed} · cancelled ${s.cancelled}` +
                    ` · mean ${(+s.meanS || 0).toFixed(0)} s · p95 ${(+s.p95S || 0).toFixed(0)} s`;
    if (this.$("task-stats").textContent !== summary) this.$("task-stats").textContent = summary;
    this.renderWork();
    if (Date.now() - this.lastPlot > PLOT_EVERY) { this.lastPlot = Date.now(); this.plots(); }
  }

  /** The shown task's history: created, assigned (to whom), opened, each errand reached, and how it
   * ended, with fleet times (simulated s: the robots' clock); from its fleet/TaskStatus. */
  renderHistory() {
    const box = this.$("task-history");
    const t = this.shown && this.model.list.find((x) => x.id === this.shown);
    if (!t) { box.hidden = true; return; }
    const at = (s) => `${(+s).toFixed(1)} s sim`;     // fleet time: the robots' (simulated) clock
    const lines = [[t.created, `created by ${t.source || "?"}`]];
    if (t.assigned > 0) lines.push([t.assigned, `assigned to ${t.robot || "a robot"}`]);
    if (t.active > 0) lines.push([t.active, "opened (first errand reached)"]);
    (t.reached || []).forEach((s, i) => {
      if (i > 0 || !(t.active > 0)) lines.push([s, `errand ${i + 1} (${t.errands[i]}) reached`]);
    });
    if (!ACTIVE.has(t.state)) lines.push([t.finished, t.state + (t.reason ? `: ${t.reason}` : "")]);
    const items = [["", `task ${t.id}: ${t.errands.join(" → ")}`], ...lines.map(([sec, what]) => [at(sec), what])];
    const key = JSON.stringify(items);
    box.hidden = false;
    if (box.dataset.key === key) return;
    box.dataset.key = key;
    box.replaceChildren(...items.map(([when, what]) => {   // text only: ids and reasons are operators' strings
      const li = document.createElement("li");
      if (when) { const sp = document.createElement("span"); sp.textContent = when; li.append(sp); }
      li.append(document.createTextNode(what));
      return li;
    }));
  }

  renderWork() {
    const tbody = this.$("work").tBodies[0];
    const names = Object.keys(this.model.robots).sort((a, b) => a.localeCompare(b, "en", { numeric: true }));
    while (tbody.children.length > names.length) tbody.lastChild.remove();
    names.forEach((n, i) => {
      const r = this.model.robots[n];
      let tr = tbody.children[i];
      if (!tr) {
        tr = document.createElement("tr");
        tr.innerHTML = `<td class="id"></td><td class="act"></td><td class="task"></td>` +
                       `<td class="bat"><span class="bar"><i></i></span><b></b></td>`;
        tbody.append(tr);
      }
      tr.dataset.robot = n;
      tr.querySelector(".id").textContent = n;
      const act = tr.querySelector(".act");
      act.textContent = r.alert ? `${r.activity}: stalled ${(+r.stalled_s || 0).toFixed(0)} s` : r.activity;
      act.className = r.alert ? "act alert" : "act";
      act.title = r.alert || "";
      tr.querySelector(".task").textContent = r.task || "-";
      const pct = r.battery_pct;
      tr.querySelector(".bat b").textContent = pct >= 0 ? `${pct.toFixed(0)} %` : "-";
      const bar = tr.querySelector(".bat i");
      bar.style.width = `${Math.max(0, pct)}%`;
      bar.className = pct < 0 ? "" : pct < 20 ? "low" : pct < 50 ? "mid" : "";
    });
  }

  plots() {
    const h = this.model.history;
    const draw = (id, key, fmt, max) => {
      const c = this.$(id);
      const w = c.width = c.clientWidth * devicePixelRatio, ht = c.height = c.clientHeight * devicePixelRatio;
      const g = c.getContext("2d");
      g.clearRect(0, 0, w, ht);
      const vals = h.map((s) => s[key]);
      const top = Math.max(max || 0, ...vals, 1e-9);
      g.strokeStyle = "#2f5fb3";
      g.lineWidth = 1.5 * devicePixelRatio;
      g.beginPath();
      vals.forEach((v, i) => {
        const x = vals.length > 1 ? (i / (vals.length - 1)) * w : w;
        const y = ht - (v / top) * (ht - 14 * devicePixelRatio) - 2;
        i ? g.lineTo(x, y) : g.moveTo(x, y);
      });
      g.stroke();
      g.fillStyle = "#1d2330";
      g.font = `${10 * devicePixelRatio}px system-ui, sans-serif`;
      g.textBaseline = "top";
      g.fillText(`${c.dataset.label}: ${vals.length ? fmt(vals[vals.length - 1]) : "-"}`, 3, 2);
    };
    draw("plot-done", "perMin", (v) => v.toFixed(1));
    draw("plot-queue", "queue", (v) => String(v));
    draw("plot-util", "util", (v) => `${(v * 100).toFixed(0)} %`, 1);
  }
}
