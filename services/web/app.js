// mtcw live view: one EventSource on /v1/points/stream (points, diagnostics, status), drawn with
// uPlot (vendored, MIT) at most once per animation frame: at the frame rate or the browser's pace,
// whichever is slower. The browser resumes a broken stream itself with Last-Event-ID (the cursor).
"use strict";

const KEEP = 600;                 // points per source on the time plots
const TEXT_EVERY_MS = 250;        // the text panels (numbers, bars, tables) at most 4 times a second
const COLOURS = ["#4c78a8", "#f58518", "#54a24b", "#b279a2", "#e45756", "#72b7b2"];
const MARKS = {                   // line kinds of the explained spectrum
  tone: ["#4c78a8", "static line f_i (S)"],
  doppler_upper: ["#54a24b", "Doppler line f_i + f_d (U)"],
  doppler_lower: ["#9c9c24", "Doppler line |f_i - f_d| (L)"],
  doppler: ["#e45756", "baseband Doppler |f_d|"],
  product: ["#999999", "tone product (left out)"],
  ghost: ["#b279a2", "ghost: product shifted by f_d (left out)"],
};

// what the test reads: window.mtcwView
const view = window.mtcwView = {
  points: 0, events: 0, diagnostics: 0, drawn: 0, latencies: [], latest: {}, errors: [],
  lastDiagnostics: null, status: null,
};

const sources = new Map();        // source -> {t, r, rlo, rhi, rflag, v, vlo, vhi, colour}
let dirty = { series: false, diag: false, status: false, latest: false };
let pendingLatency = [];          // trigger times (ms) of the points drawn in this animation frame
let stageHist = [];
let lastText = 0, lastLatText = 0;

function el(id) { return document.getElementById(id); }
function fmt(x, d = 4) { return x === null || x === undefined || !isFinite(x) ? "–" : Number(x).toPrecision(d); }
function fmtSigma(x) {
  if (x === null || x === undefined || !isFinite(x)) return "–";
  const a = Math.abs(x);
  if (a >= 1) return x.toPrecision(3) + " m";
  if (a >= 1e-3) return (x * 1e3).toPrecision(3) + " mm";
  return (x * 1e6).toPrecision(3) + " µm";
}

function source(name) {
  let s = sources.get(name);
  if (!s) {
    s = { t: [], r: [], rlo: [], rhi: [], rflag: [], v: [], vlo: [], vhi: [], colour: COLOURS[sources.size % COLOURS.length] };
    sources.set(name, s);
    rebuildTimePlots();
  }
  return s;
}

let catchingUp = true;

function addPoint(p, live) {
  const s = source(p.source);
  const t = p.t_ns / 1e9;
  const tg = p.status === "ok" && p.targets && p.targets.length ? p.targets[0] : null;
  s.t.push(t);
  if (tg) {
    const flagged = tg.blended || tg.cycle_ambiguous;
    s.r.push(tg.range_m); s.rlo.push(tg.range_m - tg.range_sigma_m); s.rhi.push(tg.range_m + tg.range_sigma_m);
    s.rflag.push(flagged ? tg.range_m : null);
    s.v.push(tg.velocity_mps); s.vlo.push(tg.velocity_mps - tg.velocity_sigma_mps); s.vhi.push(tg.velocity_mps + tg.velocity_sigma_mps);
  } else {                        // no_target or rejected: a gap
    for (const k of ["r", "rlo", "rhi", "rflag", "v", "vlo", "vhi"]) s[k].push(null);
  }
  if (s.t.length > KEEP) for (const k of ["t", "r", "rlo", "rhi", "rflag", "v", "vlo", "vhi"]) s[k].splice(0, s.t.length - KEEP);
  view.latest[p.source] = p;
  view.points += 1;
  if (p.stage_seconds) { stageHist.push(p.stage_seconds); if (stageHist.length > 50) stageHist.shift(); }
  if (live) pendingLatency.push(p.t_ns / 1e6);
  dirty.series = dirty.latest = true;
}

// ---- time plots -------------------------------------------------------------------------------
let rangePlot = null, speedPlot = null;

function plotWidth(id) { return Math.max(300, el(id).clientWidth); }

function timeOpts(id, unit, keys) {
  const series = [{}];
  const bands = [];
  for (const [name, s] of sources) {
    const i = series.length;
    series.push({ label: `${name} ${unit}`, stroke: s.colour, width: 1.5, spanGaps: false, points: { show: false } });
    series.push({ label: "+σ", stroke: "transparent", points: { show: false } });
    series.push({ label: "−σ", stroke: "transparent", points: { show: false } });
    bands.push({ series: [i + 1, i + 2], fill: s.colour + "40" });
    if (keys.flag) series.push({ label: "flagged", stroke: "#d9480f", width: 0, paths: () => null,
                                 points: { show: true, size: 8, fill: "#d9480f", stroke: "#d9480f" } });
  }
  return {
    width: plotWidth(id), height: 190, bands, series, legend: { show: false },
    scales: { x: { time: true } }, cursor: { drag: { x: false, y: false } },
    axes: [{}, { label: unit, size: 70, values: (u, v) => v.map(x => fmt(x, 6)) }],
  };
}

function timeData(keys) {
  // one x axis for all sources (uPlot's aligned data): undefined where a source has no point
  const xs = [...new Set([].concat(...[...sources.values()].map(s => s.t)))].sort((a, b) => a - b);
  const data = [xs];
  for (const s of sources.values()) {
    const at = new Map(s.t.map((t, i) => [t, i]));
    const col = k => xs.map(x => (at.has(x) ? s[k][at.get(x)] : undefined));
    data.push(col(keys.v), col(keys.hi), col(keys.lo));
    if (keys.flag) data.push(col(keys.flag));
  }
  return data;
}

const RANGE_KEYS = { v: "r", hi: "rhi", lo: "rlo", flag: "rflag" };
const SPEED_KEYS = { v: "v", hi: "vhi", lo: "vlo" };

function rebuildTimePlots() {
  if (rangePlot) rangePlot.destroy();
  if (speedPlot) speedPlot.destroy();
  rangePlot = new uPlot(timeOpts("range", "m", RANGE_KEYS), timeData(RANGE_KEYS), el("range"));
  speedPlot = new uPlot(timeOpts("speed", "m/s", SPEED_KEYS), timeData(SPEED_KEYS), el("speed"));
}

// ---- spectrum and cost ------------------------------------------------------------------------
let specPlot = null, costPlot = null, diag = null;

function vline(u, x, colour, dashed, width) {
  const cx = u.valToPos(x, "x", true);
  if (!isFinite(cx) || cx < u.bbox.left || cx > u.bbox.left + u.bbox.width) return;
  const ctx = u.ctx;
  ctx.save();
  ctx.strokeStyle = colour; ctx.lineWidth = width; ctx.setLineDash(dashed ? [3, 3] : []);
  ctx.beginPath(); ctx.moveTo(cx, u.bbox.top); ctx.lineTo(cx, u.bbox.top + u.bbox.height); ctx.stroke();
  ctx.restore();
}

function marker(u, x, y, colour, square) {
  const cx = u.valToPos(x, "x", true), cy = u.valToPos(y, "y", true);
  const ctx = u.ctx, r = 5 * devicePixelRatio;
  ctx.save(); ctx.fillStyle = colour;
  if (square) ctx.fillRect(cx - r, cy - r, 2 * r, 2 * r);
  else { ctx.beginPath(); ctx.arc(cx, cy, r, 0, 2 * Math.PI); ctx.fill(); }
  ctx.restore();
}

function drawSpectrum() {
  const sp = diag.spectrum;
  if (!sp) return;
  const data = [sp.f_hz.map(f => f / 1e6), sp.power_db];
  if (!specPlot) {
    specPlot = new uPlot({
      width: plotWidth("spectrum"), height: 230, legend: { show: false }, cursor: { drag: { x: true, y: false } },
      series: [{}, { stroke: "#555", width: 1, points: { show: false } }],
      scales: { x: { time: false } },
      axes: [{ label: "frequency (MHz)" }, { label: "dB over noise floor", size: 55 }],
      hooks: { draw: [u => { if (diag) for (const ln of diag.lines) {
        const [c] = MARKS[ln.kind] || ["#000"];
        vline(u, ln.f_hz / 1e6, c, !ln.used, ln.used ? 1.2 : 1);
      } }] },
    }, data, el("spectrum"));
    el("spec-legend").innerHTML = Object.values(MARKS).map(([c, l]) =>
      `<span><i style="border-color:${c}"></i>${l}</span>`).join("") + `<span><i class="dash" style="border-color:#666"></i>dotted: not used</span>`;
  } else specPlot.setData(data);
  el("spec-info").textContent = `(${diag.source} seq ${diag.seq}, ${diag.profile}, ${sp.bins} bins of ${(sp.df_hz / 1e3).toFixed(1)} kHz; ` +
    `${diag.lines.filter(l => l.used).length} lines used, ${diag.lines.filter(l => !l.used).length} left out)`;
}

function drawCost() {
  const cand = diag.candidates.find(c => c.reported) || diag.candidates[0];
  if (!cand) { el("cost-info").textContent = `(${diag.status}: ${diag.reason || ""})`; return; }
  const c = cand.cost;
  const data = [c.range_m, c.j];
  if (!costPlot) {
    costPlot = new uPlot({
      width: plotWidth("cost"), height: 210, legend: { show: false }, cursor: { drag: { x: true, y: false } },
      series: [{}, { stroke: "#333", width: 1.2, points: { show: false } }],
      scales: { x: { time: false }, y: { range: [-1.05, 1.1] } },
      axes: [{ label: "range L (m)" }, { label: "J(L)", size: 45 }],
      hooks: { draw: [u => {
        const cc = u._cand; if (!cc) return;
        marker(u, cc.chosen_m, cc.j_chosen, "#e45756", false);
        if (cc.runner_up_m !== null) marker(u, cc.runner_up_m, cc.j_runner_up, "#f58518", true);
      }] },
    }, data, el("cost"));
  }
  costPlot._cand = c;
  costPlot.setData(data);
  el("cost-info").textContent = `(candidate ${cand.candidate}: ● chosen ${fmt(c.chosen_m, 7)} m, J ${fmt(c.j_chosen, 3)}; ` +
    (c.runner_up_m === null ? "no runner-up)" : `■ runner-up ${fmt(c.runner_up_m, 6)} m, J ${fmt(c.j_runner_up, 3)}; margin ${fmt(c.margin, 3)})`);
}

// ---- bars and tables --------------------------------------------------------------------------
function bars(id, rows, max, unit, lowBelow) {
  el(id).innerHTML = rows.map(([label, v, text]) =>
    `<div class="row"><span>${label}</span><div class="bar${lowBelow !== undefined && v < lowBelow ? " low" : ""}" ` +
    `style="width:${Math.max(0, Math.min(100, 100 * v / max)).toFixed(1)}%"></div><span class="val">${text}</span></div>`).join("");
}

function drawLatest() {
  const parts = [];
  let newest = null;
  for (const [name, p] of Object.entries(view.latest)) {
    if (!newest || p.t_ns > newest.t_ns) newest = p;
    const tg = p.status === "ok" && p.targets.length ? p.targets[0] : null;
    const flags = tg ? ["blended", "cycle_ambiguous", "near_edge"].filter(f => tg[f]) : [];
    parts.push(`<span class="src" data-source="${name}" ${tg ? `data-range-m="${tg.range_m}"` : ""} data-seq="${p.seq}">` +
      `${name}: ` + (tg ? `<b>${fmt(tg.range_m, 8)} m</b> ± ${fmtSigma(tg.range_sigma_m)}, ` +
      `<b>${fmt(tg.velocity_mps, 4)} m/s</b> ± ${fmt(tg.velocity_sigma_mps, 2)} (${tg.direction})` +
      (tg.range_rate_mps !== undefined && tg.range_rate_mps !== null ?
        `, range rate <b>${fmt(tg.range_rate_mps, 4)} m/s</b> ± ${fmt(tg.range_rate_sigma_mps, 2)} over ${tg.track_frames} frames` : "")
      : `<b>${p.status}</b> ${p.reason || ""}`) +
      ` <span class="dim">seq ${p.seq}${p.latency_s !== undefined && p.latency_s !== null ? `, point ${(p.latency_s * 1e3).toFixed(0)} ms after trigger` : ""}</span>` +
      flags.map(f => `<span class="flag">${f}</span>`).join("") + `</span>`);
  }
  el("latest").innerHTML = parts.join("");
  if (newest) {
    const snr = Object.entries(newest.tone_snr_db || {}).sort((a, b) => a[0] - b[0]);
    bars("snr", snr.map(([tone, db]) => [`${(tone / 1e6).toFixed(1)} MHz`, db, db.toFixed(1)]), 80, "dB", 10);
    const mean = {};
    for (const h of stageHist) for (const [k, v] of Object.entries(h)) mean[k] = (mean[k] || 0) + v / stageHist.length;
    const st = Object.entries(newest.stage_seconds || {});
    const top = Math.max(1e-6, ...st.map(([, v]) => v), ...Object.values(mean));
    bars("stages", st.map(([k, v]) => [k, v, `${(v * 1e3).toFixed(1)} / ${((mean[k] || 0) * 1e3).toFixed(1)}`]), top, "ms");
  }
}

function row(k, v, cls) { return `<tr><td>${k}</td><td class="${cls || "num"}">${v}</td></tr>`; }

function drawStatus() {
  const s = view.status; if (!s) return;
  const b = s.books;
  const rej = Object.entries(s.reasons.rejected).map(([k, v]) => `${k} ${v}`).join(", ") || "none";
  const ref = Object.entries(s.reasons.refused).map(([k, v]) => `${k} ${v}`).join(", ") || "none";
  el("counts").innerHTML = row("received", b.received) + row("processed", b.processed) + row("rejected", b.rejected) +
    row("rejected by reason", rej, "") + row("dropped (never arrived)", b.dropped) + row("late", b.late) +
    row("held for reordering", b.held_for_reordering) + row("refused messages", ref, "") +
    row("last frame", b.last_frame_age_s === null ? "none yet" : `${b.last_frame_age_s.toFixed(1)} s ago`) +
    row("receiver", s.receiver, "") + row("store", s.store, "");
  const healthy = s.receiver === "alive" && b.last_frame_age_s !== null && b.last_frame_age_s < s.stale_after_s;
  const h = el("health");
  h.textContent = healthy ? "healthy" : (s.receiver !== "alive" ? `receiver ${s.receiver}` : "no recent frame");
  h.className = "pill " + (healthy ? "ok" : "warn");
  const f = s.view;
  el("feed").innerHTML = f ? row("explained", f.explained) + row("passed over (rate bound)", f.passed_over) +
    row("lost before the feed (ZeroMQ HWM)", f.lost) + row("explanations this page skipped", view.skippedDiag || 0) +
    row("connected to the monitor stream", f.connected ? "yes" : "no", "") + row("rate limit", `${f.rate_hz} /s (${f.profile})`, "") +
    row("errors", f.errors) : row("feed", "off (view_rate_hz = 0)", "");
}

// ---- the drawing loop -------------------------------------------------------------------------
function frame() {
  try {
    if (dirty.series) {
      rangePlot.setData(timeData(RANGE_KEYS));
      speedPlot.setData(timeData(SPEED_KEYS));
      view.drawn += 1;
      const drawnTriggers = pendingLatency; pendingLatency = [];
      // the next animation frame starts once this one is on screen: trigger-to-pixel then
      requestAnimationFrame(() => {
        const now = Date.now();
        for (const t of drawnTriggers) view.latencies.push(now - t);
        if (view.latencies.length > 1000) view.latencies.splice(0, view.latencies.length - 1000);
        if (now - lastLatText >= 1000 && view.latencies.length) {
          lastLatText = now;
          const l = [...view.latencies].sort((a, b) => a - b);
          el("lat").textContent = `trigger→pixel p50 ${l[Math.floor(l.length / 2)].toFixed(0)} ms`;
        }
      });
    }
    if (dirty.diag && diag) { drawSpectrum(); drawCost(); }
    dirty.series = dirty.diag = false;
    const now = performance.now();
    if (now - lastText >= TEXT_EVERY_MS && (dirty.latest || dirty.status)) {
      lastText = now;
      if (dirty.latest) drawLatest();
      if (dirty.status) drawStatus();
      dirty.latest = dirty.status = false;
    }
  } catch (e) {
    view.errors.push(String(e));
    throw e;
  } finally {
    requestAnimationFrame(frame);
  }
}

// ---- the stream -------------------------------------------------------------------------------
function connect() {
  const es = new EventSource("v1/points/stream?tail=300&diagnostics=1&status=1");
  const conn = el("conn");
  // the first points event after a (re)connection is history (tail or catch-up): not a latency
  es.onopen = () => { conn.textContent = "live"; conn.className = "pill ok"; catchingUp = true; };
  es.onerror = () => { conn.textContent = "reconnecting"; conn.className = "pill off"; };  // EventSource retries itself
  es.addEventListener("points", ev => {
    view.events += 1;
    view.lastEventId = ev.lastEventId;
    for (const p of JSON.parse(ev.data).points) addPoint(p, !catchingUp);
    catchingUp = false;
  });
  es.addEventListener("diagnostics", ev => {
    const msg = JSON.parse(ev.data);
    if (view.diagVersion) view.skippedDiag = (view.skippedDiag || 0) + Math.max(0, msg.version - view.diagVersion - 1);
    view.diagVersion = msg.version;
    diag = msg.explain;
    view.diagnostics += 1;
    view.lastDiagnostics = { seq: diag.seq, source: diag.source, status: diag.status };
    dirty.diag = true;
  });
  es.addEventListener("status", ev => { view.status = JSON.parse(ev.data); dirty.status = true; });
  view.eventSource = es;
}

window.addEventListener("resize", () => {
  for (const [p, id] of [[rangePlot, "range"], [speedPlot, "speed"], [specPlot, "spectrum"], [costPlot, "cost"]])
    if (p) p.setSize({ width: plotWidth(id), height: p.height });
});

rebuildTimePlots();
connect();
requestAnimationFrame(frame);
