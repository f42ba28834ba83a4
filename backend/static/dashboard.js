// extrcal dashboard: plain JavaScript, no libraries, no network beyond this service.
// Reads the REST API and the event stream (GET /events, read with fetch so that a token
// can be sent); draws the room with a small perspective projection on a 2D canvas.
"use strict";

const $ = (id) => document.getElementById(id);
const COLORS = { current: "#1f6fd1", initial: "#9aa3ad", reference: "#2c9f45", person: "#e0742b" };
// COCO-17 skeleton
const BONES = [[5, 7], [7, 9], [6, 8], [8, 10], [5, 6], [5, 11], [6, 12], [11, 12], [11, 13], [13, 15],
  [12, 14], [14, 16], [0, 1], [0, 2], [1, 3], [2, 4], [0, 5], [0, 6]];

const S = {
  token: localStorage.getItem("extrcal.token") || "",
  sid: null,            // session shown
  follow: true,         // follow the service's current session
  brief: null,          // status_brief (events)
  status: null,         // GET /status
  session: null,        // GET /sessions/{id}
  history: [],          // GET /sessions/{id}/history + cycle events
  files: null,          // initial/reference/intrinsics of the session
  persons: [],          // latest hypotheses, if the service sends them
  view: { yaw: -0.9, pitch: 0.75, zoom: 1.3, panned: null },
  frame: null,          // world basis of the 3D view, fixed per session
};

class ApiError extends Error {
  constructor(status, detail) { super(detail); this.status = status; }
}

function headers(extra) {
  const h = Object.assign({}, extra || {});
  if (S.token) h["Authorization"] = "Bearer " + S.token;
  return h;
}

async function api(path, opts) {
  opts = opts || {};
  const r = await fetch(path, Object.assign({}, opts, { headers: headers(opts.headers) }));
  if (!r.ok) {
    let detail = r.statusText;
    try { detail = (await r.json()).detail || detail; } catch (e) { /* not JSON */ }
    throw new ApiError(r.status, detail);
  }
  return r.json();
}

function message(text, kind) {
  const m = $("message");
  m.textContent = text || "";
  m.className = "message" + (kind ? " " + kind : "");
}

const fmt = (v, d) => (v === null || v === undefined || !isFinite(v)) ? "–" : Number(v).toFixed(d);

// ------------------------------------------------------------------ math

const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const mul = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => Math.hypot(a[0], a[1], a[2]);
const unit = (a) => { const n = norm(a) || 1; return [a[0] / n, a[1] / n, a[2] / n]; };

function quatToR(q) {  // [x, y, z, w] → rows of world_R_cam
  const n = Math.hypot(q[0], q[1], q[2], q[3]) || 1;
  const [x, y, z, w] = [q[0] / n, q[1] / n, q[2] / n, q[3] / n];
  return [
    [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
    [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
    [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
  ];
}
const col = (R, j) => [R[0][j], R[1][j], R[2][j]];
const Rv = (R, v) => [dot(R[0], v), dot(R[1], v), dot(R[2], v)];

// ------------------------------------------------------------------ data

async function refreshStatus() {
  try {
    S.status = await api("/status");
    if (!S.brief) S.brief = { session: S.status.session };
    renderHeader();
    renderTable();
  } catch (e) {
    if (e.status === 401) message("reading needs the token (protect_reads)", "error");
  }
}

async function refreshSessions() {
  let list = [];
  try { list = await api("/sessions"); } catch (e) { return; }
  const sel = $("sessions");
  const keep = S.sid;
  sel.innerHTML = "";
  for (const s of list) {
    const o = document.createElement("option");
    o.value = s.id;
    o.textContent = `${s.name ? s.name + " · " : ""}${s.id} · ${s.state}${s.cycles ? " · " + s.cycles + " cycles" : ""}`;
    sel.appendChild(o);
  }
  const current = S.brief && S.brief.session ? S.brief.session.id : null;
  const want = (S.follow && current) || keep || (list[0] && list[0].id) || null;
  if (want) sel.value = want;
  if (want !== S.sid) await showSession(want);
}

async function showSession(sid) {
  S.sid = sid;
  S.history = [];
  S.files = null;
  S.session = null;
  S.frame = null;
  S.persons = [];
  if (!sid) { render(); return; }
  try {
    const [session, history, files] = await Promise.all([
      api(`/sessions/${sid}`), api(`/sessions/${sid}/history`),
      api(`/dashboard/api/sessions/${sid}/cameras`).catch(() => null)]);
    if (S.sid !== sid) return;  // another session was chosen meanwhile
    S.session = session;
    S.history = history;
    S.files = files;
  } catch (e) {
    message(`session ${sid}: ${e.message}`, "error");
  }
  render();
}

let sessionTimer = null;
function refreshSessionSoon() {  // at most twice a second, however fast cycles come
  if (sessionTimer) return;
  sessionTimer = setTimeout(async () => {
    sessionTimer = null;
    if (!S.sid) return;
    try {
      const s = await api(`/sessions/${S.sid}`);
      if (s.id === S.sid) { S.session = s; render(); }
    } catch (e) { /* next event retries */ }
  }, 500);
}

function onEvent(kind, data) {
  if (kind === "hello" || kind === "status") {
    const before = S.brief && S.brief.session ? S.brief.session.id : null;
    S.brief = data;
    const now = data.session ? data.session.id : null;
    renderHeader();
    if (now !== before) refreshSessions();
  } else if (kind === "cycle") {
    if (data.session !== S.sid) return;
    const last = S.history.length ? S.history[S.history.length - 1].cycle : -1;
    if (data.cycle > last) S.history.push(data);
    else S.history = S.history.filter((h) => h.cycle < data.cycle).concat([data]);  // a resumed session
    renderCharts();
    refreshSessionSoon();
  } else if (kind === "session") {
    refreshSessions();
    if (data.id === S.sid) refreshSessionSoon();
  } else if (kind === "hypotheses") {
    // {session, persons: [[[x, y, z] | null × 17], ...]}: drawn when the service sends them
    if (!data.session || data.session === S.sid) { S.persons = data.persons || []; drawRoom(); }
  }
}

async function events() {
  // EventSource cannot send a token; fetch can, and reads the same text/event-stream.
  for (;;) {
    try {
      const r = await fetch("/events", { headers: headers({ Accept: "text/event-stream" }) });
      if (!r.ok || !r.body) throw new ApiError(r.status, r.statusText);
      setConn("live");
      const reader = r.body.getReader();
      const dec = new TextDecoder();
      let buf = "";
      for (;;) {
        const { value, done } = await reader.read();
        if (done) break;
        buf += dec.decode(value, { stream: true });
        let i;
        while ((i = buf.indexOf("\n\n")) >= 0) {
          const block = buf.slice(0, i);
          buf = buf.slice(i + 2);
          let kind = "message";
          const data = [];
          for (const line of block.split("\n")) {
            if (line.startsWith("event:")) kind = line.slice(6).trim();
            else if (line.startsWith("data:")) data.push(line.slice(5).replace(/^ /, ""));
          }
          if (data.length) {
            try { onEvent(kind, JSON.parse(data.join("\n"))); } catch (e) { console.error(e); }
          }
        }
      }
    } catch (e) { /* reconnect below */ }
    setConn("reconnecting");
    await new Promise((res) => setTimeout(res, 2000));
  }
}

function setConn(state) {
  const c = $("conn");
  c.dataset.state = state;
  c.textContent = state === "live" ? "live" : state;
}

// ------------------------------------------------------------------ header and table

function renderHeader() {
  const st = S.status;
  if (st) $("site").textContent = `site ${st.site}`;
  const b = S.brief || {};
  const s = S.session;
  const live = b.session && s && b.session.id === s.id ? b.session : null;
  $("session-name").textContent = s ? (s.name || s.id) : "none";
  $("session-state").textContent = live ? live.state : s ? s.state : "–";
  $("cycle").textContent = live ? live.cycle : s ? (s.cycles || (s.last_cycle ? s.last_cycle.cycle : 0)) : "–";
  const cams = s ? s.cameras : [];
  const nconv = live ? live.cameras_converged : cams.filter((c) => c.converged).length;
  const ncams = live ? live.cameras : cams.length;
  $("converged").textContent = ncams ? `${nconv}/${ncams}` : "–";
  const acc = (live && live.accuracy) || (s && s.accuracy);
  $("accuracy").textContent = acc ? `${fmt(acc.position_mean * 100, 1)} cm · ${fmt(acc.orientation_mean, 2)}°` : "–";
  $("sensors").textContent = b.sensors_active !== undefined ? b.sensors_active : "–";
  $("reason").textContent = live ? live.reason : s ? s.reason : "No session yet: start one on the right.";
  const running = !!(b.session && ["waiting_for_data", "calibrating", "converged"].includes(b.session.state));
  $("stop").disabled = !running;
  $("start").disabled = running;
}

function esc(text) {
  return String(text).replace(/[&<>"']/g, (ch) => ({"&": "&amp;", "<": "&lt;", ">": "&gt;", "\"": "&quot;", "'": "&#39;"})[ch]);
}

function renderTable() {
  const tb = $("cameras").tBodies[0];
  const s = S.session;
  const sensors = (S.status && S.status.sensors) || {};
  const rows = [];
  for (const c of (s ? s.cameras : [])) {
    const sen = sensors[c.name] || {};
    const ago = sen.last_seen_ago;
    rows.push(`<tr data-camera="${c.name}"><td>${c.name}</td><td>${c.observations}</td><td>${c.cycles}</td>` +
      `<td>${fmt(c.std_translation * 100, 2)}</td><td>${fmt(c.std_rotation, 3)}</td>` +
      `<td>${fmt(c.change_translation === null ? null : c.change_translation * 100, 3)}</td>` +
      `<td class="${c.converged ? "yes" : "no"}">${c.converged ? "yes" : "no"}</td>` +
      `<td class="${ago !== undefined && ago !== null && ago > 5 ? "stale" : ""}">${ago === undefined || ago === null ? "never" : fmt(ago, 1) + " s ago"}</td>` +
      `<td>${fmt(sen.rate, 1)}</td>` +
      // the sensor's warnings (clock, latency, keypoint confidences): a mark here, the words on hover
      `<td class="${(sen.warnings || []).length ? "warn" : ""}" title="${esc((sen.warnings || []).join("\n"))}">` +
      `${(sen.warnings || []).length ? "\u26a0 " + sen.warnings.length : ""}</td></tr>`);
  }
  tb.innerHTML = rows.join("");
}

// ------------------------------------------------------------------ charts

function drawChart(canvas, title, series, opts) {
  const ctx = canvas.getContext("2d");
  const W = canvas.width, H = canvas.height;
  const ml = 52, mr = 16, mt = 34, mb = 22;
  ctx.clearRect(0, 0, W, H);
  ctx.font = "600 12px system-ui, sans-serif";
  ctx.fillStyle = "#1d2430";
  ctx.fillText(title, ml, 14);
  const log = !!opts.log;
  const pts = [];
  for (const s of series) for (const [x, y] of s.points) if (y !== null && isFinite(y) && (!log || y > 0)) pts.push([x, y]);
  let lx = ml;
  ctx.font = "11px system-ui, sans-serif";
  for (const s of series) {
    ctx.fillStyle = s.color; ctx.fillRect(lx, 22, 14, 3);
    ctx.fillStyle = "#333"; ctx.fillText(s.name, lx + 18, 27);
    lx += 26 + ctx.measureText(s.name).width;
  }
  canvas.dataset.points = String(pts.length);
  if (!pts.length) {
    ctx.fillStyle = "#8a94a3"; ctx.fillText("no data yet", W / 2 - 30, H / 2);
    return;
  }
  let x0 = Math.min(...pts.map((p) => p[0])), x1 = Math.max(...pts.map((p) => p[0]));
  if (x1 === x0) { x0 -= 1; x1 += 1; }
  let ys = pts.map((p) => p[1]);
  if (opts.hline) ys = ys.concat([opts.hline[0]]);
  let y0, y1, ticks;
  const f = log ? Math.log10 : (v) => v;
  if (log) {
    y0 = Math.floor(Math.log10(Math.min(...ys))); y1 = Math.ceil(Math.log10(Math.max(...ys)));
    if (y1 === y0) y1 += 1;
    ticks = []; for (let k = y0; k <= y1; k++) ticks.push(Math.pow(10, k));
  } else {
    y0 = Math.min(0, Math.min(...ys)); y1 = Math.max(...ys) * 1.08 || 1;
    const step = niceStep((y1 - y0) / 4);
    ticks = []; for (let v = Math.ceil(y0 / step) * step; v <= y1 + 1e-12; v += step) ticks.push(v);
  }
  const pw = W - ml - mr, ph = H - mt - mb;
  const X = (v) => ml + (v - x0) / (x1 - x0) * pw;
  const Y = (v) => mt + ph - (f(v) - y0) / (y1 - y0) * ph;
  ctx.strokeStyle = "#eceff3"; ctx.fillStyle = "#66707d"; ctx.lineWidth = 1;
  for (const v of ticks) {
    const y = Y(v);
    ctx.beginPath(); ctx.moveTo(ml, y); ctx.lineTo(ml + pw, y); ctx.stroke();
    const label = log ? (Math.abs(Math.log10(v)) >= 3 ? "1e" + Math.round(Math.log10(v)) : String(v)) : String(+v.toPrecision(3));
    ctx.fillText(label, ml - 6 - ctx.measureText(label).width, y + 4);
  }
  const xs = niceStep((x1 - x0) / 5);
  for (let v = Math.ceil(x0 / xs) * xs; v <= x1; v += xs) {
    const x = X(v);
    ctx.beginPath(); ctx.moveTo(x, mt); ctx.lineTo(x, mt + ph); ctx.stroke();
    ctx.fillText(String(+v.toPrecision(4)), x - 8, H - 8);
  }
  if (opts.hline && (!log || opts.hline[0] > 0)) {
    ctx.setLineDash([5, 4]); ctx.strokeStyle = "#555";
    const y = Y(opts.hline[0]);
    ctx.beginPath(); ctx.moveTo(ml, y); ctx.lineTo(ml + pw, y); ctx.stroke(); ctx.setLineDash([]);
    ctx.fillText(opts.hline[1], ml + pw - ctx.measureText(opts.hline[1]).width - 4, y - 4);
  }
  for (const s of series) {
    ctx.strokeStyle = s.color; ctx.lineWidth = s.width || 1.6;
    ctx.beginPath();
    let pen = false;
    for (const [x, y] of s.points) {
      if (y === null || !isFinite(y) || (log && y <= 0)) { pen = false; continue; }
      if (pen) ctx.lineTo(X(x), Y(y)); else ctx.moveTo(X(x), Y(y));
      pen = true;
    }
    ctx.stroke();
  }
}

function niceStep(raw) {
  if (!(raw > 0)) return 1;
  const mag = Math.pow(10, Math.floor(Math.log10(raw)));
  for (const m of [1, 2, 2.5, 5, 10]) if (m * mag >= raw) return m * mag;
  return 10 * mag;
}

function meanStd(h, k) {
  const pc = h.per_camera;
  if (!pc) return null;
  const v = Object.values(pc).map((x) => x[k]).filter((x) => x !== null && isFinite(x));
  return v.length ? v.reduce((a, b) => a + b, 0) / v.length : null;
}

function renderCharts() {
  const H = S.history;
  const P = (key, scale) => H.map((h) => [h.cycle, h[key] === null || h[key] === undefined ? null : h[key] * (scale || 1)]);
  drawChart($("chart-change"), "Pose change per cycle (max over cameras) vs cycle", [
    { name: "translation cm", color: COLORS.current, points: P("max_change_translation", 100) },
    { name: "rotation °", color: "#c5392f", points: P("max_change_rotation") },
  ], { log: true });
  drawChart($("chart-std"), "Std of the estimate vs cycle", [
    { name: "max translation cm", color: COLORS.current, points: P("max_std_translation", 100) },
    { name: "mean translation cm", color: "#7fa9e0", points: H.map((h) => [h.cycle, meanStd(h, 0) === null ? null : meanStd(h, 0) * 100]) },
    { name: "max rotation °", color: "#c5392f", points: P("max_std_rotation") },
  ], { log: true });
  const acc = (k, s) => H.map((h) => [h.cycle, h.accuracy && h.accuracy[k] !== null && h.accuracy[k] !== undefined ? h.accuracy[k] * s : null]);
  drawChart($("chart-error"), "Error vs reference (mean over cameras) vs cycle", [
    { name: "position cm", color: COLORS.current, points: acc("position_mean", 100) },
    { name: "shape cm", color: COLORS.reference, points: acc("shape_position_mean", 100) },
    { name: "orientation °", color: "#c5392f", points: acc("orientation_mean", 1) },
  ], { log: true, hline: [5.3, "paper 5.3 cm"] });
  drawChart($("chart-reproj"), "Reprojection error (median of the cycle) vs cycle", [
    { name: "px", color: COLORS.person, points: P("reprojection_px") },
  ], {});
}

// ------------------------------------------------------------------ the room

function cameraSets() {
  const sets = {};
  const pose = (t, q) => ({ t, R: quatToR(q) });
  if (S.files && S.files.initial) {
    sets.initial = {};
    for (const [n, c] of Object.entries(S.files.initial)) sets.initial[n] = pose(c.translation, c.rotation);
  }
  if (S.files && S.files.reference) {
    sets.reference = {};
    for (const [n, c] of Object.entries(S.files.reference)) sets.reference[n] = pose(c.translation, c.rotation);
  }
  if (S.session && S.session.cameras.length) {
    sets.current = {};
    for (const c of S.session.cameras) sets.current[c.name] = pose(c.translation, c.rotation);
  }
  return sets;
}

function worldFrame(sets) {
  // "up" = mean of the cameras' up directions (-y of OpenCV's camera axes): cameras hang
  // roughly upright. Fixed per session so that the view does not jump while poses move.
  const base = sets.initial || sets.current || sets.reference;
  if (!base) return null;
  const cams = Object.values(base);
  let up = [0, 0, 0];
  let c = [0, 0, 0];
  for (const p of cams) { up = sub(up, col(p.R, 1)); c = add(c, p.t); }
  c = mul(c, 1 / cams.length);
  up = norm(up) / cams.length > 0.5 ? unit(up) : [0, 0, 1];
  let e1 = Math.abs(up[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0];
  e1 = unit(sub(e1, mul(up, dot(e1, up))));
  const e2 = cross(up, e1);
  let spread = 0, lowest = Infinity;
  for (const p of cams) {
    const d = sub(p.t, c);
    spread = Math.max(spread, Math.hypot(dot(d, e1), dot(d, e2)));
    lowest = Math.min(lowest, dot(d, up));
  }
  spread = Math.max(spread, 1);
  // the floor: about 2.5 m below the lowest camera (ceiling-mounted cameras), a guess
  // only used for the grid
  const floor = add(c, mul(up, lowest - 2.5));
  return { up, e1, e2, centre: c, spread, floor };
}

function projector(canvas, fr) {
  const v = S.view;
  const dist = fr.spread * 2.6 / v.zoom;
  const target = v.panned || add(fr.centre, mul(fr.up, -1.2));
  const dir = add(add(mul(fr.e1, Math.cos(v.pitch) * Math.cos(v.yaw)), mul(fr.e2, Math.cos(v.pitch) * Math.sin(v.yaw))),
    mul(fr.up, Math.sin(v.pitch)));
  const eye = add(target, mul(dir, dist));
  const fwd = unit(sub(target, eye));
  const right = unit(cross(fwd, fr.up));
  const upv = cross(right, fwd);
  const F = canvas.width * 0.9;
  return (p) => {
    const d = sub(p, eye);
    const z = dot(d, fwd);
    if (z < 0.05) return null;
    return [canvas.width / 2 + F * dot(d, right) / z, canvas.height / 2 - F * dot(d, upv) / z];
  };
}

function frustum(p, intr, depth) {
  let xs = [-1, 1], ys = [-0.6, 0.6];
  if (intr) {
    xs = [-intr.cx / intr.fx, (intr.width - intr.cx) / intr.fx];
    ys = [-intr.cy / intr.fy, (intr.height - intr.cy) / intr.fy];
  }
  const corners = [[xs[0], ys[0]], [xs[1], ys[0]], [xs[1], ys[1]], [xs[0], ys[1]]]
    .map(([x, y]) => add(p.t, Rv(p.R, [x * depth, y * depth, depth])));
  return corners;
}

function drawRoom() {
  const canvas = $("room");
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const sets = cameraSets();
  if (!S.frame) S.frame = worldFrame(sets);
  const fr = S.frame;
  const drawn = {};
  if (!fr) {
    ctx.fillStyle = "#8a94a3"; ctx.font = "14px system-ui, sans-serif";
    ctx.fillText("no cameras yet", canvas.width / 2 - 45, canvas.height / 2);
    canvas.dataset.drawn = JSON.stringify(drawn);
    return;
  }
  const P = projector(canvas, fr);
  const line = (a, b) => { const A = P(a), B = P(b); if (A && B) { ctx.moveTo(A[0], A[1]); ctx.lineTo(B[0], B[1]); } };
  // floor grid, 1 m (or coarser for large rooms)
  const step = Math.pow(10, Math.floor(Math.log10(fr.spread))) / (fr.spread < 20 ? 1 : 2);
  const ext = Math.ceil(fr.spread * 1.2 / step) * step;
  ctx.strokeStyle = "#e3e7ed"; ctx.lineWidth = 1; ctx.beginPath();
  for (let s = -ext; s <= ext + 1e-9; s += step) {
    line(add(fr.floor, add(mul(fr.e1, s), mul(fr.e2, -ext))), add(fr.floor, add(mul(fr.e1, s), mul(fr.e2, ext))));
    line(add(fr.floor, add(mul(fr.e2, s), mul(fr.e1, -ext))), add(fr.floor, add(mul(fr.e2, s), mul(fr.e1, ext))));
  }
  ctx.stroke();
  const depth = Math.min(Math.max(fr.spread * 0.05, 0.2), 1.5);
  const intr = (S.files && S.files.intrinsics) || {};
  for (const kind of ["reference", "initial", "current"]) {
    const set = sets[kind];
    if (!set) continue;
    drawn[kind] = 0;
    ctx.strokeStyle = COLORS[kind];
    ctx.lineWidth = kind === "current" ? 1.6 : 1.1;
    ctx.setLineDash(kind === "initial" ? [3, 3] : kind === "reference" ? [6, 3] : []);
    for (const [n, p] of Object.entries(set)) {
      const c = frustum(p, intr[n], depth);
      ctx.beginPath();
      for (let i = 0; i < 4; i++) { line(p.t, c[i]); line(c[i], c[(i + 1) % 4]); }
      ctx.stroke();
      const A = P(p.t);
      if (A) drawn[kind] += 1;
      if (A && kind === "current") {
        ctx.setLineDash([]);
        // the top edge (image row 0) thicker: which way is up in the image
        ctx.lineWidth = 3; ctx.beginPath(); line(c[0], c[1]); ctx.stroke(); ctx.lineWidth = 1.6;
        ctx.fillStyle = "#23354d"; ctx.font = "11px system-ui, sans-serif";
        ctx.fillText(n, A[0] + 4, A[1] - 4);
      }
    }
  }
  ctx.setLineDash([]);
  // person hypotheses as skeletons
  drawn.persons = 0;
  ctx.strokeStyle = COLORS.person; ctx.lineWidth = 2;
  for (const person of S.persons) {
    ctx.beginPath();
    for (const [a, b] of BONES) if (person[a] && person[b]) line(person[a], person[b]);
    ctx.stroke();
    drawn.persons += 1;
  }
  canvas.dataset.drawn = JSON.stringify(drawn);
}

function bindOrbit() {
  const canvas = $("room");
  let drag = null;
  canvas.addEventListener("pointerdown", (e) => { drag = [e.clientX, e.clientY]; canvas.setPointerCapture(e.pointerId); });
  canvas.addEventListener("pointerup", () => { drag = null; });
  canvas.addEventListener("pointermove", (e) => {
    if (!drag) return;
    S.view.yaw -= (e.clientX - drag[0]) * 0.008;
    S.view.pitch = Math.min(1.55, Math.max(0.05, S.view.pitch + (e.clientY - drag[1]) * 0.008));
    drag = [e.clientX, e.clientY];
    drawRoom();
  });
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    S.view.zoom = Math.min(8, Math.max(0.3, S.view.zoom * Math.exp(-e.deltaY * 0.001)));
    drawRoom();
  }, { passive: false });
  canvas.addEventListener("dblclick", () => { S.view = { yaw: -0.9, pitch: 0.75, zoom: 1.3, panned: null }; drawRoom(); });
}

// ------------------------------------------------------------------ controls

async function readFile(id) {
  const f = $(id).files[0];
  return f ? await f.text() : null;
}

async function start() {
  const body = { name: $("name").value || null, stop: { converged: $("stop-converged").checked } };
  for (const [key, id] of [["intrinsics_yaml", "f-intrinsics"], ["initial_yaml", "f-initial"], ["reference_yaml", "f-reference"]]) {
    const text = await readFile(id);
    if (text) body[key] = text;
  }
  try {
    const s = await api("/sessions", { method: "POST", body: JSON.stringify(body), headers: { "Content-Type": "application/json" } });
    message(`session ${s.id} started`, "ok");
    S.follow = true;
    await refreshSessions();
  } catch (e) {
    message(e.status === 401 ? "start needs the token" : e.message, "error");
  }
}

async function stop() {
  const sid = S.brief && S.brief.session ? S.brief.session.id : S.sid;
  if (!sid) return;
  try {
    await api(`/sessions/${sid}/stop?wait=false`, { method: "POST" });
    message(`stopping ${sid}: final adjustment, then the result is written`, "ok");
  } catch (e) {
    message(e.status === 401 ? "stop needs the token" : e.message, "error");
  }
}

async function download() {
  if (!S.sid) return;
  const f = $("fmt").value;
  try {
    const r = await fetch(`/sessions/${S.sid}/result?format=${encodeURIComponent(f)}`, { headers: headers() });
    if (!r.ok) throw new ApiError(r.status, (await r.json().catch(() => ({}))).detail || r.statusText);
    const blob = await r.blob();
    const cd = r.headers.get("Content-Disposition") || "";
    const m = /filename="([^"]+)"/.exec(cd);
    const a = document.createElement("a");
    a.href = URL.createObjectURL(blob);
    a.download = m ? m[1] : `extrcal-${S.sid}.${f === "json" ? "json" : "txt"}`;
    a.click();
    setTimeout(() => URL.revokeObjectURL(a.href), 5000);
  } catch (e) {
    message(e.message, "error");
  }
}

function render() {
  renderHeader();
  renderTable();
  renderCharts();
  drawRoom();
}

function boot() {
  $("token").value = S.token;
  $("token").addEventListener("change", () => {
    S.token = $("token").value.trim();
    localStorage.setItem("extrcal.token", S.token);
  });
  $("start").addEventListener("click", start);
  $("stop").addEventListener("click", stop);
  $("download").addEventListener("click", download);
  $("sessions").addEventListener("change", (e) => {
    const current = S.brief && S.brief.session ? S.brief.session.id : null;
    S.follow = e.target.value === current;
    showSession(e.target.value);
  });
  bindOrbit();
  render();
  refreshStatus().then(refreshSessions);
  setInterval(refreshStatus, 2000);  // per-sensor "last seen" and rates (not in the events)
  setInterval(refreshSessions, 10000);  // states and cycle counts in the session list
  events();
}

boot();
