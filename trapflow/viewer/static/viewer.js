// trapflow viewer: polls /api/state, draws the shown pair with its detections and tags,
// small live charts per pool, the VO top view, nodes, ledger, events and the modem.
// Plain JS, no build step, nothing fetched from outside the trap.
"use strict";

const POLL_MS = 500;
const view = { seq: null, boxes: 0, tags: 0, motion: 0, tracks: [], frames: 0, polls: 0, loading: false, busy: false };
window.trapflow = view; // read by the browser tests

const $ = (id) => document.getElementById(id);
const esc = (s) => String(s).replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" })[c]);

function drawPair(frame) {
  if (view.loading || frame.seq === view.seq) return;
  view.loading = true;
  const imgs = ["left", "right"].map((side) => {
    const img = new Image();
    img.src = `/frame/${frame.seq}/${side}.jpg`;
    return img.decode().then(() => img);
  });
  Promise.all(imgs).then(([l, r]) => {
    const scale = Math.min(1, 640 / frame.width);
    for (const [id, img] of [["left", l], ["right", r]]) {
      const c = $(id);
      c.width = Math.round(frame.width * scale);
      c.height = Math.round(frame.height * scale);
      c.getContext("2d").drawImage(img, 0, 0, c.width, c.height);
    }
    const ctx = $("left").getContext("2d");
    ctx.font = "13px sans-serif";
    ctx.lineWidth = 2;
    ctx.setLineDash([6, 4]);
    ctx.strokeStyle = "#ff66cc"; // what the motion gate saw moving
    for (const [x1, y1, x2, y2] of frame.motion) ctx.strokeRect(x1 * scale, y1 * scale, (x2 - x1) * scale, (y2 - y1) * scale);
    ctx.setLineDash([]);
    ctx.lineWidth = 2;
    for (const d of frame.detections) {
      const [x1, y1, x2, y2] = d.box.map((v) => v * scale);
      ctx.strokeStyle = "#ffdd33";
      ctx.strokeRect(x1, y1, x2 - x1, y2 - y1);
      ctx.fillStyle = "#ffdd33";
      ctx.fillText(`${trackText(d)}${d.label} ${(d.confidence * 100).toFixed(0)}%`, x1 + 2, Math.max(12, y1 - 3));
      ctx.fillText(measureText(d, true), x1 + 2, y2 + 13);
    }
    for (const t of frame.tags) {
      ctx.strokeStyle = "#33e0ff";
      ctx.beginPath();
      t.corners.forEach(([x, y], i) => (i ? ctx.lineTo(x * scale, y * scale) : ctx.moveTo(x * scale, y * scale)));
      ctx.closePath();
      ctx.stroke();
      ctx.fillStyle = "#33e0ff";
      ctx.fillText(`id ${t.id}`, t.corners[0][0] * scale, t.corners[0][1] * scale - 3);
    }
    view.seq = frame.seq;
    view.frames += 1;
    view.boxes = frame.detections.length;
    view.tags = frame.tags.length;
    view.motion = frame.motion.length;
    view.tracks = frame.detections.filter((d) => d.track !== undefined && d.track !== null).map((d) => d.track);
    $("boxes").innerHTML = frame.detections.map((d) =>
      `<li class="det" data-track="${d.track ?? ""}">${esc(trackText(d))}${esc(d.label)} ${(d.confidence * 100).toFixed(0)}%: <span class="measure">${esc(measureText(d, false))}</span></li>`).join("");
    $("left").dataset.motion = frame.motion.length;
    $("left").dataset.seq = frame.seq;
    $("left").dataset.boxes = frame.detections.length;
    $("seq").textContent = `seq ${frame.seq}, ${frame.detections.length} detections, ${frame.tags.length} tags`;
  }).catch(() => {}).finally(() => { view.loading = false; });
}

// A detection's track id as drawn on its box ("#12 "), empty while the track is unconfirmed.
function trackText(d) {
  return d.track !== undefined && d.track !== null ? `#${d.track} ` : "";
}

// What the stereo pair measured of a detection: range and length with their sd, or why not.
function measureText(d, short) {
  const m = (v) => `${v.toFixed(2)} m`;
  const sd = (v) => (v !== undefined && v !== null ? ` ± ${v.toFixed(2)}` : "");
  if (d.range_m !== undefined && d.range_m !== null) {
    const range = `range ${m(d.range_m)}${sd(d.range_sd_m)}`;
    const length = d.length_m !== undefined && d.length_m !== null
      ? `, length ${m(d.length_m)}${sd(d.length_sd_m)}${!short && d.length_method ? ` (${d.length_method})` : ""}` : "";
    return range + length;
  }
  return d.unmeasured ? `unmeasured: ${d.unmeasured}` : (short ? "" : "not measured");
}

// Live counts of the current interval per label: visits and MaxN (counts.jsonl has the record).
function drawCounts(c) {
  const start = c.start_s === null ? "" : new Date(c.start_s * 1000).toISOString().slice(11, 16);
  $("counts-when").textContent = c.start_s === null ? "(no tracked detection yet)"
    : `(interval from ${start} UTC, ${c.interval_s / 60} min)`;
  $("counts").tBodies[0].innerHTML = c.labels.map((l) =>
    `<tr data-label="${esc(l.label)}"><td>${esc(l.label)}</td><td class="visits">${l.visits}</td><td class="maxn">${l.max_n}</td></tr>`).join("");
}

function sparkline(canvas, values, color, label, unit) {
  const ctx = canvas.getContext("2d");
  const w = canvas.width, h = canvas.height;
  ctx.clearRect(0, 0, w, h);
  const max = Math.max(1e-9, ...values);
  ctx.strokeStyle = color;
  ctx.beginPath();
  values.forEach((v, i) => {
    const x = values.length > 1 ? (i / (values.length - 1)) * (w - 2) + 1 : w / 2;
    const y = h - 2 - (v / max) * (h - 14);
    i ? ctx.lineTo(x, y) : ctx.moveTo(x, y);
  });
  ctx.stroke();
  ctx.fillStyle = "#cde";
  ctx.font = "10px sans-serif";
  const last = values.length ? values[values.length - 1] : 0;
  ctx.fillText(`${label} ${last}${unit}`, 2, 10);
  canvas.dataset.points = values.length;
}

function drawPools(pools, control) {
  const box = $("pools");
  for (const [name, p] of Object.entries(pools)) {
    let el = $(`pool-${name}`);
    if (!el) {
      el = document.createElement("div");
      el.className = "pool";
      el.id = `pool-${name}`;
      el.innerHTML = `<b>${esc(name)}</b> <span class="txt"></span>` +
        ["rate", "drops", "latency", "workers"].map((k) => `<canvas class="chart ${k}" width="180" height="40"></canvas>`).join("");
      box.appendChild(el);
    }
    const l = p.last || {};
    el.querySelector(".txt").textContent =
      `processed ${l.processed || 0}, dropped ${l.dropped || 0}, failed ${l.errors || 0}, lost ${l.lost || 0}`;
    // A pool behind the motion gate (it withheld or keeps pairs): is it withholding now?
    const gate = el.querySelector(".gate") || el.insertBefore(Object.assign(document.createElement("div"), { className: "gate" }), el.querySelector("canvas"));
    gate.hidden = !(l.gated || l.kept);
    gate.dataset.gated = p.gated_now ? "now" : "open";
    gate.textContent = p.gated_now ? `gated now: nothing moves (${l.gated} withheld)` : `gate open (${l.gated || 0} withheld)`;
    gate.className = `gate ${p.gated_now ? "shut" : "open"}`;
    drawControl(el, name, (control || {})[name]);
    sparkline(el.querySelector(".rate"), p.rate, "#7fdc8a", "rate", "/s");
    sparkline(el.querySelector(".drops"), p.drops, "#ff7b6b", "drops", "/s");
    sparkline(el.querySelector(".latency"), p.latency_ms, "#e8c35a", "latency", " ms");
    sparkline(el.querySelector(".workers"), p.workers, "#8fc3d8", "workers", "");
  }
}

// Runtime control of one pool (as `trapflow pool` does it): its lifecycle, worker count,
// policy and last change, with buttons that send one change each.
function drawControl(el, name, c) {
  let box = el.querySelector(".ctl");
  if (!c) { if (box) box.hidden = true; return; }
  if (!box) {
    box = document.createElement("div");
    box.className = "ctl";
    box.innerHTML = `<span class="ctl-state"></span> <span class="ctl-text"></span><br>` +
      `<button type="button" class="toggle"></button> ` +
      `<button type="button" class="less" title="One worker less">&minus;</button> ` +
      `<button type="button" class="more" title="One worker more">+</button> ` +
      `<span class="ctl-reply"></span>`;
    el.insertBefore(box, el.querySelector("canvas"));
    box.querySelector(".toggle").addEventListener("click", () =>
      changePool(box, { pool: name, active: box.dataset.state !== "active" }));
    box.querySelector(".less").addEventListener("click", () =>
      changePool(box, { pool: name, count: Number(box.dataset.count) - 1 }));
    box.querySelector(".more").addEventListener("click", () =>
      changePool(box, { pool: name, count: Number(box.dataset.count) + 1 }));
  }
  box.hidden = false;
  box.dataset.state = c.state;
  box.dataset.count = c.count;
  const st = box.querySelector(".ctl-state");
  st.textContent = c.state;
  st.className = `ctl-state ${c.state}`;
  const last = c.last_change ? `; last change at ${c.last_change.t_s} s: ${c.last_change.change}` : "";
  const off = c.off_by ? ` (off by ${c.off_by})` : "";
  const slow = c.min_interval_s ? `, at most one pair every ${c.min_interval_s} s` : "";
  box.querySelector(".ctl-text").textContent = `${c.count} workers, policy ${c.policy}${off}${slow}${last}`;
  box.querySelector(".toggle").textContent = c.state === "active" ? "Deactivate" : "Activate";
  box.querySelector(".less").disabled = c.count <= 1;
}

async function changePool(box, change) {
  const reply = box.querySelector(".ctl-reply");
  reply.textContent = "asking…";
  try {
    const r = await fetch("/api/pool", {
      method: "POST", body: JSON.stringify(change),
      headers: { "X-Trapflow-Control": "pool", "Content-Type": "application/json" },
    });
    const body = await r.text();
    let msg = body;
    try { const j = JSON.parse(body); msg = j.error || j.change || body; } catch (e) { /* plain text */ }
    reply.textContent = msg;
    reply.className = `ctl-reply ${r.ok ? "good" : "bad"}`;
  } catch (e) {
    reply.textContent = "viewer not answering";
    reply.className = "ctl-reply bad";
  }
}

// The degradation ladder's level, shown only where the status model has one.
function drawLevel(level, reason, forced) {
  const el = $("level");
  if (level === undefined || level === null) { el.hidden = true; return; }
  el.hidden = false;
  const why = [forced ? "forced" : "", reason || ""].filter((x) => x).join(": ");
  el.textContent = `level ${level}${why ? ` (${why})` : ""}`;
  el.dataset.level = level;
}

function drawVO(vo) {
  const c = $("vo"), ctx = c.getContext("2d");
  ctx.clearRect(0, 0, c.width, c.height);
  $("vo-ok").textContent = vo.ok_rate === null ? "no VO results" : `ok ${(vo.ok_rate * 100).toFixed(1)}% of ${vo.total}`;
  if (!vo.path.length) return;
  const xs = vo.path.map((p) => p[0]), zs = vo.path.map((p) => p[1]);
  const span = Math.max(0.1, Math.max(...xs) - Math.min(...xs), Math.max(...zs) - Math.min(...zs));
  const s = (c.width - 20) / span, cx = (Math.max(...xs) + Math.min(...xs)) / 2, cz = (Math.max(...zs) + Math.min(...zs)) / 2;
  ctx.strokeStyle = "#8fc3d8";
  ctx.beginPath();
  vo.path.forEach(([x, z], i) => {
    const px = c.width / 2 + (x - cx) * s, py = c.height / 2 - (z - cz) * s;
    i ? ctx.lineTo(px, py) : ctx.moveTo(px, py);
  });
  ctx.stroke();
  const [lx, lz] = vo.path[vo.path.length - 1];
  ctx.fillStyle = "#ffdd33";
  ctx.beginPath();
  ctx.arc(c.width / 2 + (lx - cx) * s, c.height / 2 - (lz - cz) * s, 4, 0, 2 * Math.PI);
  ctx.fill(); // where the rig is now
  c.dataset.points = vo.path.length;
}

function drawTables(s) {
  $("nodes").tBodies[0].innerHTML = s.nodes.map((n) =>
    `<tr><td>${esc(n.name)}</td><td class="${esc(n.state)}">${esc(n.state)}</td><td>${n.restarts}</td><td>${esc(n.reason || "")}</td></tr>`).join("");
  const rows = [];
  if (s.ledger) {
    rows.push(["captured", s.ledger.produced], ["reached broker", s.ledger.reached_broker],
      ["dropped at capture", s.ledger.dropped_at_capture], ["failed at capture", s.ledger.failed_at_capture]);
    for (const [name, p] of Object.entries(s.ledger.pools)) {
      // Every state of the server's list (wire/pool_counters.py) that holds pairs, in its
      // order; processed, lost and the pairs on their way whenever the ledger has them.
      const always = ["processed", "lost", "in_progress", "unfinished_at_stop"];
      const states = s.ledger_states.filter(({ key }) => p[key] !== undefined
        && (p[key] || always.includes(key)))
        .map(({ key, label }) => `${label} ${p[key]}`);
      rows.push([name, `${states.join(", ")} (policy ${p.policy})`]);
    }
    const e = s.ledger.energy; // the power model's estimate so far (ledger.json's energy)
    if (e) {
      const days = e.days_on_battery !== undefined ? `, ${e.days_on_battery} days on the battery` : "";
      const gate = e.active_s !== undefined ? `; motion gate active ${e.active_s} s, idle ${e.idle_s} s` : "";
      rows.push([`energy (${e.board} model)`, `${e.busy_cores} cores busy, ${e.watts} W, ${e.wh_per_day} Wh/day${days}${gate}`]);
    }
  }
  $("ledger").tBodies[0].innerHTML = rows.map(([k, v]) => `<tr><td>${esc(k)}</td><td>${esc(v)}</td></tr>`).join("");
  $("modem").textContent = s.modem
    ? `${s.modem.state}${s.modem.reason ? " (" + s.modem.reason + ")" : ""}: backlog ${s.modem.backlog} records, in flight ${s.modem.in_flight}, ${s.modem.bytes_last_hour} B last hour`
    : "no modem in this pipeline";
  $("events").innerHTML = s.events.length ? s.events.map((e) =>
    `<figure>${e.thumb ? `<img alt="" src="/events/${encodeURI(e.thumb)}">` : ""}<figcaption>${esc(e.name)}${e.open ? " (recording)" : `, ${e.pairs} pairs`}</figcaption></figure>`).join("") : "none yet";
}

async function poll() {
  if (view.busy) return; // a slow browser skips polls instead of queueing them
  view.busy = true;
  try {
    const r = await fetch("/api/state", { cache: "no-store" });
    const s = await r.json();
    view.polls += 1;
    $("conn").textContent = s.status_error || "live";
    $("conn").className = s.status_error ? "bad" : "good";
    $("summary").textContent = `up ${s.uptime_s.toFixed(0)} s, ${s.pairs_in} pairs in (${s.rate_in}/s), shown ${s.frames.shown} of ${s.frames.received} tapped`;
    $("stereo").textContent = s.stereo ? `stereo: ${s.stereo.label} ${(s.stereo.confidence * 100).toFixed(0)}%` : "";
    if (s.frame) drawPair(s.frame);
    drawPools(s.pools, s.control);
    drawCounts(s.counts);
    drawLevel(s.level, s.level_reason, s.level_forced);
    drawVO(s.vo);
    drawTables(s);
  } catch (e) {
    $("conn").textContent = "viewer not answering";
    $("conn").className = "bad";
  } finally {
    view.busy = false;
  }
}

$("stop").addEventListener("click", async () => {
  $("stop").disabled = true;
  const r = await fetch("/api/stop", { method: "POST", headers: { "X-Trapflow-Control": "stop" } });
  $("stop").textContent = r.ok ? "stopping…" : "stop refused";
});

setInterval(poll, POLL_MS);
poll();
