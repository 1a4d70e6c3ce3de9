// ajtwin dashboard: draws the plots (plotly.js, served by this server) and applies the
// events pushed over the websocket. No framework; each page has one entry function.
"use strict";

// latencies: publish → drawn (ms); arrivals: publish → message received (ms)
const A = (window.__ajtwin = { latencies: [], arrivals: [], alarmsShown: [], events: 0 });
const COLORS = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b"];
const PLOT_CONFIG = { displaylogo: false, responsive: true };
const LIVE_MAX_POINTS = 7200;

function el(tag, attrs, text) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
  if (text !== undefined) e.textContent = text;
  return e;
}
// a number as a person reads it: significant digits, no e-notation (a value below 1e-6 of
// its unit is nothing a page needs: 0)
function fmt(v, digits) {
  if (v === null || v === undefined || !isFinite(v)) return "—";
  const a = Math.abs(v);
  if (a >= 1e5) return Math.round(v).toString();
  if (a < 1e-6) return "0";
  return Number(v.toPrecision(digits || 4)).toFixed(Math.max(0, (digits || 4) - 1 - Math.floor(Math.log10(a)))).replace(/(\.\d*?)0+$/, "$1").replace(/\.$/, "");
}
function minutes(t) { return t === null ? null : t / 60; }
// "2026-11-23T06:52:46+00:00" → "2026-11-23 06:52 UTC" (the registry's times are UTC)
function when(iso) {
  const d = new Date(iso);
  if (!iso || isNaN(d)) return iso ? String(iso) : "—";
  return d.toISOString().slice(0, 16).replace("T", " ") + " UTC";
}

// ---------------------------------------------------------------- websocket
function connect(machine, onEvent) {
  const conn = document.getElementById("conn");
  let delay = 1000;
  function open() {
    const url = (location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws" +
      (machine ? "?machine=" + encodeURIComponent(machine) : "");
    const ws = new WebSocket(url);
    ws.onopen = () => { delay = 1000; conn.textContent = "● live"; conn.classList.add("up"); };
    ws.onmessage = (msg) => {
      const ev = JSON.parse(msg.data);
      A.events += 1;
      if (ev.type === "sample" && A.arrivals.length < 10000) A.arrivals.push(Date.now() - ev.published_at * 1000);
      onEvent(ev);
    };
    ws.onclose = () => {
      conn.textContent = "○ reconnecting"; conn.classList.remove("up");
      setTimeout(open, delay); delay = Math.min(delay * 2, 10000);  // bounded back-off
    };
  }
  open();
}

async function getJSON(url) {
  const r = await fetch(url, { credentials: "same-origin" });
  const body = await r.json().catch(() => ({}));
  if (!r.ok) throw new Error(body.error || r.status + " " + r.statusText);
  return body;
}
async function postJSON(url, data) {
  const r = await fetch(url, {
    method: "POST", credentials: "same-origin",
    headers: { "Content-Type": "application/json" }, body: JSON.stringify(data),
  });
  const body = await r.json().catch(() => ({ error: r.status + " " + r.statusText }));
  if (!r.ok) throw new Error(body.error || r.status + " " + r.statusText);
  return body;
}

// ---------------------------------------------------------------- fleet page
function fleetPage() {
  const tbody = document.getElementById("fleet-rows");
  let timer = null, last = 0;
  async function refresh() {
    timer = null; last = Date.now();
    const r = await fetch("/fragment/fleet-rows", { credentials: "same-origin" });
    if (r.ok) { tbody.innerHTML = await r.text(); A.fleetRefreshed = Date.now(); }
  }
  function schedule(now) {
    if (now) { if (timer) clearTimeout(timer); refresh(); return; }
    if (!timer) timer = setTimeout(refresh, Math.max(0, 2000 - (Date.now() - last)));
  }
  connect(null, (ev) => {
    if (ev.type === "sample") schedule(ev.alarms && ev.alarms.length > 0);
    // hello: the socket (re)opened — what was pushed between the page's rows and now
    // (a print that ended meanwhile) never reaches it, so the rows are read again
    else schedule(true);
  });
}

// ---------------------------------------------------------------- figures
// Each figure is a list of rows (subplots sharing x); a trace map keeps, per kind of
// series, the trace indices so live samples can be appended with extendTraces.
function rowsLayout(nrows, titles, extra) {
  const layout = Object.assign({
    margin: { l: 70, r: 12, t: 30, b: 40 }, showlegend: true,
    legend: { orientation: "h", x: 0, y: 1.0, yanchor: "bottom", font: { size: 11 } },
    grid: { rows: nrows, columns: 1, pattern: "coupled", ygap: 0.12 },
    xaxis: { title: { text: "time [min]" } }, hovermode: "x",
    font: { size: 11 }, paper_bgcolor: "#fff", plot_bgcolor: "#fff",
  }, extra || {});
  titles.forEach((t, r) => {
    layout["yaxis" + (r ? r + 1 : "")] = { title: { text: t, font: { size: 11 } }, gridcolor: "#eee",
      exponentformat: "e", zeroline: false };
  });
  return layout;
}
function ax(r) { return r ? "y" + (r + 1) : "y"; }

function buildOutputs(s) {
  const n = s.names, t = s.time_s.map(minutes), traces = [], map = { meas: [], pred: [] };
  for (let i = 0; i < 5; i++) {
    // the prediction first, the measurements drawn over it (else a close fit hides them)
    map.pred.push(traces.length);
    traces.push({ x: t, y: s.predicted ? s.predicted.map((r) => outScaled(n, i, r[i])) : [], mode: "lines",
      line: { width: 1.4, color: COLORS[0] }, name: "one-step prediction", legendgroup: "p",
      showlegend: i === 0, yaxis: ax(i) });
    map.meas.push(traces.length);
    traces.push({ x: t, y: s.measured ? s.measured.map((r) => outScaled(n, i, r[i])) : [], mode: "markers",
      marker: { size: 2.5, color: "#555" }, name: "measured", legendgroup: "m",
      showlegend: i === 0, yaxis: ax(i) });
  }
  const titles = n.outputs.map((o, i) => o + " [" + n.output_units[i] + "]");
  return { traces, layout: rowsLayout(5, titles), map };
}

// a state in the unit a page shows it in (φ_A: a volume fraction, shown in ppm)
function scaled(n, i, v) { return v === null || v === undefined ? v : v * ((n.state_scale || [])[i] || 1); }
// an output in the unit a page shows it in (Q_m in nL/s)
function outScaled(n, i, v) { return v === null || v === undefined ? v : v * ((n.output_scale || [])[i] || 1); }

function buildStates(s) {
  const n = s.names, t = s.time_s.map(minutes), traces = [], map = { lo: [], hi: [], mean: [], truth: [] };
  for (let i = 0; i < 5; i++) {
    const m = s.means.map((r) => scaled(n, i, r[i])), sd = s.stds.map((r) => scaled(n, i, r[i]));
    map.lo.push(traces.length);
    traces.push({ x: t, y: m.map((v, k) => v === null ? null : v - 2 * sd[k]), mode: "lines",
      line: { width: 0 }, hoverinfo: "skip", showlegend: false, yaxis: ax(i) });
    map.hi.push(traces.length);
    traces.push({ x: t, y: m.map((v, k) => v === null ? null : v + 2 * sd[k]), mode: "lines",
      line: { width: 0 }, fill: "tonexty", fillcolor: "rgba(31,119,180,0.22)", name: "±2σ",
      legendgroup: "b", showlegend: i === 0, yaxis: ax(i) });
    map.mean.push(traces.length);
    traces.push({ x: t, y: m, mode: "lines", line: { width: 1.5, color: COLORS[0] },
      name: "estimate x̂", legendgroup: "e", showlegend: i === 0, yaxis: ax(i) });
    if (s.truth) {
      map.truth.push(traces.length);
      traces.push({ x: t, y: s.truth.map((r) => scaled(n, i, r[i])), mode: "lines",
        line: { width: 1.2, color: "#222", dash: "dot" }, name: "truth (virtual printer)",
        legendgroup: "t", showlegend: i === 0, yaxis: ax(i) });
    }
  }
  const titles = n.states.map((o, i) => o + (n.state_units[i] !== "–" ? " [" + n.state_units[i] + "]" : ""));
  return { traces, layout: rowsLayout(5, titles), map };
}

function buildDetectors(s) {
  const d = s.detectors, traces = [], map = { cusum: [], nis: [] };
  if (!d) return null;
  const t = s.time_s.map(minutes);
  d.channels.forEach((c, j) => {
    map.cusum.push(traces.length);
    traces.push({ x: t, y: d.cusum.map((r) => r[j] === null ? null : r[j] / d.cusum_thresholds[j]),
      mode: "lines", line: { width: 1.2, color: COLORS[j % COLORS.length] },
      name: "CUSUM " + c + " (h=" + d.cusum_thresholds[j] + ")", yaxis: "y" });
  });
  map.nis.push(traces.length);
  traces.push({ x: t, y: d.window_nis_log10p, mode: "lines", line: { width: 1.3, color: "#444" },
    name: "windowed NIS (" + d.window_s + " s)", yaxis: "y2" });
  // seven detectors: a legend of three rows, kept below the chart's toolbar by the top margin
  const layout = rowsLayout(2, ["CUSUM g / h", "NIS −log₁₀ p"], { margin: { l: 70, r: 12, t: 96, b: 40 } });
  layout.shapes = [
    { type: "line", xref: "paper", x0: 0, x1: 1, yref: "y", y0: 1, y1: 1, line: { color: "#c62828", dash: "dash", width: 1.2 } },
    { type: "line", xref: "paper", x0: 0, x1: 1, yref: "y2", y0: d.window_nis_threshold, y1: d.window_nis_threshold, line: { color: "#c62828", dash: "dash", width: 1.2 } },
  ];
  layout.annotations = [
    { xref: "paper", x: 1, xanchor: "right", yref: "y", y: 1, text: "alarm threshold", showarrow: false, yanchor: "bottom", font: { color: "#c62828", size: 10 } },
    { xref: "paper", x: 1, xanchor: "right", yref: "y2", y: d.window_nis_threshold, text: "p = 1e-9", showarrow: false, yanchor: "bottom", font: { color: "#c62828", size: 10 } },
  ];
  return { traces, layout, map };
}

// θ [1/s] as the drift rate a page shows (per cent of the state per hour)
function thetaShown(n, v) { return v === null || v === undefined ? v : v * (n.theta_scale || 1); }

function buildTheta(s) {
  if (!s.theta) return null;
  const n = s.names, t = s.time_s.map(minutes), traces = [], map = { theta: [] };
  for (let i = 0; i < 5; i++) {
    map.theta.push(traces.length);
    traces.push({ x: t, y: s.theta.map((r) => thetaShown(n, r[i])), mode: "lines", line: { width: 1.4, color: COLORS[i] },
      name: "drift rate of " + n.states[i], showlegend: false, yaxis: ax(i) });
  }
  const layout = rowsLayout(5, n.states.map((x) => x + " [" + (n.theta_unit || "1/s") + "]"));
  // a print shorter than EM's first window keeps θ as it started: say so, not five flat lines
  const first = s.theta.find((r) => r && r.every((v) => v !== null));
  const unchanged = first && s.theta.every((r) => !r || r.every((v, i) => v === null || v === first[i]));
  if (unchanged) {
    layout.annotations = [{ xref: "paper", yref: "paper", x: 0.5, y: 1.0, yanchor: "bottom",
      showarrow: false, font: { size: 11, color: "#6b7585" },
      text: "θ unchanged in this print: EM had no full window of data to re-estimate it yet" }];
  }
  return { traces, layout, map, unchangedFrom: unchanged ? first : null };
}

function alarmShapes(alarms, existing) {
  const shapes = (existing || []).slice();
  for (const a of alarms) {
    shapes.push({ type: "line", xref: "x", yref: "paper", x0: a.detected_s / 60, x1: a.detected_s / 60,
      y0: 0, y1: 1, line: { color: "#c62828", width: 1.2, dash: "dot" } });
  }
  return shapes;
}


// ---------------------------------------------------------------- part map (machine page)
// The part drawn from the machine's program: printed portions coloured by L_w − target
// (diverging scale, µm; without a tolerance, by L_w itself), flagged portions ringed (their
// colour stays visible), alarms marked where the nozzle was. A live print's map fills in
// from "part" events; a stored print's is asked for once (the server re-runs the twin).
function partMap(name) {
  const div = document.getElementById("plot-part");
  const table = document.getElementById("part-flagged");
  const box = document.getElementById("part-tolerance");
  const status = document.getElementById("part-status");
  let data = null, current = null, timer = null, typed = false;
  A.part = { portions: 0, flagged: 0, draws: 0, kind: null };
  box.addEventListener("input", () => { typed = true; });

  function say(text) { status.textContent = text || ""; }
  // no map to draw (a print stored without its program): no empty box, one line says why
  function shown(yes) { div.hidden = !yes; table.hidden = !yes; }
  function tolText(tol) {
    return fmt((tol[0] + tol[1]) / 2, 4) + "±" + fmt((tol[1] - tol[0]) / 2, 3);
  }
  function traces() {
    const out = [{
      type: "scattergl", mode: "lines", x: data.outline.x, y: data.outline.y, name: "part (program)",
      line: { color: "#c8c8c8", width: 1 }, hoverinfo: "skip",
    }];
    const P = data.portions, Q = data.points;
    if (P && Q && Q.portion.length) {
      const first = P.index[0];
      const at = (i) => i - first;  // portions are numbered on from the first one held
      const lw = Q.portion.map((i) => P.lw_mean_um[at(i)]);
      // with a tolerance: L_w − target on a diverging scale centred on 0, the tolerance
      // within it; without one there is no target: L_w itself on a sequential scale
      const tol = data.tolerance_um;
      let marker;
      if (tol) {
        const t = data.target_um != null ? data.target_um : (tol[0] + tol[1]) / 2;
        const dev = lw.map((v) => (v === null ? null : v - t));
        const half = (tol[1] - tol[0]) / 2;
        const big = dev.filter((v) => v !== null).map(Math.abs).sort((a, b) => a - b);
        const lim = Math.max(1.5 * half, big.length ? big[Math.floor(0.99 * (big.length - 1))] : 1);
        marker = { color: dev, colorscale: "RdBu", cmin: -lim, cmax: lim,
                   colorbar: { title: { text: "L_w − target [µm]", side: "right" }, thickness: 14 } };
      } else {
        marker = { color: lw, colorscale: "Viridis",
                   colorbar: { title: { text: "L_w [µm]", side: "right" }, thickness: 14 } };
      }
      out.push({
        type: "scattergl", mode: "markers", x: Q.x, y: Q.y,
        name: tol ? "printed: L_w − target" : "printed: L_w (no tolerance set)",
        marker: Object.assign({ size: 5 }, marker),
        text: Q.portion.map((i) => "stroke " + P.stroke[at(i)] + " portion " + P.portion[at(i)] +
          "<br>printed " + fmt(P.printed_from_s[at(i)] / 60, 4) + " min<br>L_w " + fmt(P.lw_mean_um[at(i)], 4) +
          " µm [" + fmt(P.lw_lo_um[at(i)], 4) + ", " + fmt(P.lw_hi_um[at(i)], 4) + "]<br>P(out) " + fmt(P.p_out[at(i)], 3)),
        hoverinfo: "text",
      });
      // flagged portions: one thin open ring at the middle of each (rings on every point
      // would merge into a black mass), so the points' own colour (how far out) stays visible
      const fx = [], fy = [];
      let start = 0;
      Q.portion.forEach((i, k) => {
        if (k + 1 < Q.portion.length && Q.portion[k + 1] === i) return;  // portion goes on
        const mid = Math.floor((start + k) / 2);
        if (P.flagged[at(i)]) { fx.push(Q.x[mid]); fy.push(Q.y[mid]); }
        start = k + 1;
      });
      if (fx.length) {
        out.push({
          type: "scattergl", mode: "markers", x: fx, y: fy, hoverinfo: "skip",
          name: "flagged (P(out) ≥ " + fmt(data.flag_probability, 2) + ")",
          marker: { symbol: "circle-open", size: 10, color: "#222", line: { width: 1 } },
        });
      }
    }
    const al = data.alarms || [];
    if (al.length) {
      out.push({
        type: "scatter", mode: "markers+text", x: al.map((a) => a.x), y: al.map((a) => a.y),
        text: al.map((a) => "A" + a.alarm + " " + a.cause.replace(/_/g, " ")), textposition: "top right",
        name: "alarm raised (nozzle there)", marker: { symbol: "x", size: 13, color: "#d00000" },
        textfont: { color: "#900000" },
      });
      out.push({
        type: "scatter", mode: "markers", x: al.map((a) => a.onset_x), y: al.map((a) => a.onset_y),
        name: "alarm onset", marker: { symbol: "circle-open", size: 12, color: "#d00000", line: { width: 2 } },
      });
    }
    return out;
  }
  function renderFlagged() {
    const tb = document.querySelector("#part-flagged tbody");
    tb.innerHTML = "";
    const P = data.portions;
    if (!P) return;
    const rows = P.index.map((_, j) => j).filter((j) => P.flagged[j])
      .sort((a, b) => P.p_out[b] - P.p_out[a]).slice(0, 20);
    for (const j of rows) {
      const tr = el("tr");
      tr.append(el("td", {}, String(P.stroke[j]))); tr.append(el("td", {}, String(P.portion[j])));
      tr.append(el("td", {}, "run " + (P.repetition[j] + 1)));
      tr.append(el("td", {}, fmt(P.printed_from_s[j] / 60, 4) + " min"));
      tr.append(el("td", {}, fmt(P.lw_mean_um[j], 4) + " [" + fmt(P.lw_lo_um[j], 4) + ", " + fmt(P.lw_hi_um[j], 4) + "]"));
      tr.append(el("td", { class: "cause" }, fmt(P.p_out[j], 3)));
      tb.append(tr);
    }
  }
  function draw() {
    timer = null;
    if (!data) return;
    const P = data.portions;
    const n = P ? P.index.length : 0, m = P ? P.flagged.filter(Boolean).length : 0;
    const tol = data.tolerance_um ? tolText(data.tolerance_um) + " µm" : "none set";
    // the box shows the tolerance the map uses (the stored or live print's), unless typed in
    if (!typed) box.value = data.tolerance_um ? tolText(data.tolerance_um) : "";
    document.getElementById("part-title").textContent = "(" + data.program + (current && current.kind === "live" ?
      ", live" : ", print #" + (current ? current.seq : "")) + "; tolerance " + tol + ")";
    shown(true);
    say(n + " portions printed, " + (data.tolerance_um ? m + " flagged" :
      "no tolerance set: coloured by L_w; give one to flag the portions out of it") +
      (data.repetitions > 1 ? " · runs of the looped job side by side" : ""));
    const layout = {
      // the top margin keeps the colour bar clear of the chart's toolbar
      margin: { t: 36, r: 10, b: 40, l: 50 }, showlegend: true,
      legend: { orientation: "h", y: -0.12 }, xaxis: { title: { text: "x [mm]" }, zeroline: false },
      yaxis: { title: { text: "y [mm]" }, scaleanchor: "x", scaleratio: 1, zeroline: false },
      uirevision: current ? current.kind + (current.seq || "") : "part",
    };
    Plotly.react(div, traces(), layout, PLOT_CONFIG);
    renderFlagged();
    A.part = { portions: n, flagged: m, draws: A.part.draws + 1, kind: current && current.kind };
  }
  function later() { if (!timer) timer = setTimeout(draw, 400); }
  function merge(chunk) {
    if (!data) return;
    if (chunk.outline) Object.assign(data, chunk.outline);
    for (const key of ["portions", "points"]) {
      if (!chunk[key]) continue;
      if (!data[key]) { data[key] = {}; for (const k of Object.keys(chunk[key])) data[key][k] = []; }
      for (const [k, v] of Object.entries(chunk[key])) (data[key][k] = data[key][k] || []).push(...v);
    }
    if (chunk.alarms) data.alarms = (data.alarms || []).concat(chunk.alarms);
  }
  async function showLive() {
    current = { kind: "live" };
    try {
      data = await getJSON("/api/machine/" + encodeURIComponent(name) + "/part/live");
      draw();
    } catch (e) { say("no live part map: " + e.message); }
  }
  async function showPrint(p) {
    if (!p.program) {
      if (!current || current.kind !== "live") {
        data = null; Plotly.purge(div); shown(false);
        document.getElementById("part-title").textContent = "";
        say("print #" + p.seq + " was stored without its program (ajtwin ingest --job PROGRAM.prg keeps it)");
      }
      return;
    }
    current = { kind: "print", seq: p.seq };
    // a tolerance typed in overrides the stored one; the box's own filling does not
    const tol = typed ? box.value.trim() : "";
    say("mapping print #" + p.seq + " (the twin runs over it once; up to a minute for a long print)…");
    try {
      const url = "/api/machine/" + encodeURIComponent(name) + "/print/" + p.seq + "/part" +
        (tol ? "?tolerance=" + encodeURIComponent(tol) : "");
      const got = await getJSON(url);
      if (current.kind === "print" && current.seq === p.seq) { data = got; draw(); }
    } catch (e) { say("part map of print #" + p.seq + ": " + e.message); }
  }
  document.getElementById("part-apply").onclick = () => {
    if (current && current.kind === "print") showPrint({ seq: current.seq, program: true });
    typed = false;
  };
  return {
    showLive, showPrint,
    onOutline(ev) { current = { kind: "live" }; data = ev.part; draw(); },
    onChunk(ev) { if (current && current.kind === "live") { merge(ev.chunk); later(); } },
  };
}

// ---------------------------------------------------------------- machine page
function machinePage() {
  const name = document.body.dataset.machine;
  const figs = {};
  const part = partMap(name);
  let view = null, info = null, queue = [], frame = null;

  function showError(msg) {
    const e = document.getElementById("error");
    e.textContent = msg; e.hidden = !msg;
  }
  function setStatus(status) {
    const s = document.getElementById("status");
    s.className = "status " + status;
    s.textContent = { mismatch: "model–machine mismatch" }[status] || status;
  }

  function renderLink(link) {
    // the live twin's machine link (text from the server: one wording for both pages)
    const b = document.getElementById("link");
    if (!b) return;
    b.hidden = !(link && link.text);
    if (b.hidden) return;
    b.className = "link " + link.state;
    b.textContent = link.text;
    b.title = link.reason || link.url || "";
    A.link = link;
  }

  function renderSummary(m, latest) {
    const box = document.getElementById("summary");
    box.innerHTML = "";
    const n = m.names;
    const mean = latest ? latest.states : (m.last && m.last.mean);
    const std = latest ? latest.state_stds : (m.last && m.last.std);
    const where = latest ? "live, " + fmt(latest.time_s / 60, 3) + " min" :
      (m.last ? "end of print #" + m.last.seq : "no prints yet");
    if (mean) n.states.forEach((s, i) => {
      const c = el("div", { class: "card" });
      c.append(el("div", { class: "dim" }, s + (n.state_units[i] !== "–" ? " [" + n.state_units[i] + "]" : "")));
      c.append(el("div", { class: "big" }, fmt(scaled(n, i, mean[i]))));
      c.append(el("div", { class: "dim" }, "± " + fmt(scaled(n, i, 2 * std[i]), 2) + " (2σ) · " + where));
      box.append(c);
    });
    if (latest && latest.settling) {
      // ready to print: the start-up has settled (a new verdict after an atomizer restart)
      const r = latest.settling;
      const c = el("div", { class: "card ready " + (r.ready ? "yes" : "no"), id: "ready" });
      c.append(el("div", { class: "dim" }, "ready to print"));
      c.append(el("div", { class: "big" }, r.ready ? "ready" : "not yet"));
      const off = !r.ready && (r.text || "").startsWith("the atomizer is off");
      c.append(el("div", { class: "dim" }, r.ready ? "settled at " + fmt(r.ready_at_s / 60, 3) + " min"
        : off ? "the atomizer is off" : "the start-up is still settling"));
      c.title = r.text || "";
      box.append(c);
    }
    if (m.aerosol_level) {
      const c = el("div", { class: "card aerosol-level", id: "aerosol-level" });
      c.append(el("div", { class: "dim" }, "φ_A's level"));
      c.append(el("div", {}, m.aerosol_level.note));
      box.append(c);
    }
    const extra = [["commissioned_at", "last commissioned"], ["last_maintenance_at", "last maintained"]];
    for (const [k, label] of extra) if (m[k]) {
      const c = el("div", { class: "card" });
      c.append(el("div", { class: "dim" }, label)); c.append(el("div", {}, when(m[k])));
      if (k === "last_maintenance_at" && m.last_maintenance) c.append(el("div", { class: "dim" }, m.last_maintenance));
      box.append(c);
    }
    if (m.mismatch) {
      const c = el("div", { class: "card mismatch", id: "mismatch" });
      c.append(el("div", { class: "dim" }, "model–machine mismatch, print #" + m.mismatch.seq));
      // one line in words (a notice, not a fault); the guard's reasons on demand
      c.append(el("div", { class: "notice" }, m.mismatch.line));
      const more = el("details", { class: "more" });
      more.append(el("summary", {}, "details"));
      more.append(el("p", {}, m.mismatch.message));
      c.append(more);
      box.append(c);
    }
    if (m.calibration) {
      const cal = m.calibration;
      const c = el("div", { class: "card calibration", id: "calibration" });
      c.append(el("div", { class: "dim" }, "active calibration " + cal.id + " · " + cal.source + " · " + when(cal.created_at)));
      const t = el("table", { class: "grid small" });
      for (const p of cal.parameters) {
        const tr = el("tr", p.determined ? {} : { class: "dim", title: "not determined by the print (prior)" });
        tr.append(el("td", {}, p.name));
        tr.append(el("td", { class: "num" }, fmt(p.value, 4)));
        tr.append(el("td", { class: "num" }, p.std_error == null ? "" : "± " + fmt(p.std_error, 2)));
        t.append(tr);
      }
      c.append(t);
      box.append(c);
    }
  }

  // an alarm's cause in words and what to do (data/causes.toml through the page's names)
  function causeText(a) {
    const c = ((info && info.names && info.names.causes) || {})[a.cause];
    if (!c) return a.description;
    return c.words + (c.action ? ": " + c.action.split("{machine}").join(name) : "");
  }

  function alarmRow(a, live) {
    const tr = el("tr", live ? { class: "live" } : {});
    tr.append(el("td", {}, live ? "live" : "#" + a.seq));
    tr.append(el("td", {}, fmt(a.detected_s / 60, 3) + " min"));
    tr.append(el("td", {}, fmt(a.onset_s / 60, 3) + " min"));
    // the guard's events are the mismatch the card above names: not a fault, said once
    const mismatch = a.cause === "model_machine_mismatch";
    tr.append(mismatch ? el("td", { class: "notice" }, "model–machine mismatch (not a fault; see above)")
      : el("td", { class: "cause" }, causeText(a)));
    tr.append(el("td", { class: "dim" }, a.detectors));
    return tr;
  }
  function renderAlarms(m) {
    const tb = document.querySelector("#alarms tbody");
    tb.innerHTML = "";
    for (const a of m.live.alarms) tb.append(alarmRow(a, true));
    for (const a of m.alarms.slice().reverse()) tb.append(alarmRow(a, false));
    if (!tb.children.length) {
      const tr = el("tr"); tr.append(el("td", { colspan: 5, class: "empty" }, "no alarms")); tb.append(tr);
    }
  }
  function renderHistory(m) {
    const tb = document.querySelector("#history tbody");
    tb.innerHTML = "";
    if (m.live.samples.length) {
      const tr = el("tr", { class: view && view.kind === "live" ? "selected" : "" });
      tr.append(el("td", {}, "live"));
      tr.append(el("td", {}, m.live.printing ? "printing now" : "ended"));
      tr.append(el("td", {}, fmt(m.live.samples[m.live.samples.length - 1].time_s / 60, 3) + " min"));
      tr.append(el("td", {}, m.live.samples[0].source || "live twin"));
      tr.append(el("td")); tr.append(el("td", {}, String(m.live.alarms.length)));
      const b = el("button", {}, "show"); b.onclick = () => { showLive(); if (info.live_part) part.showLive(); };
      const td = el("td"); td.append(b); tr.append(td); tb.append(tr);
    }
    for (const p of m.prints.slice().reverse()) {
      const tr = el("tr", { "data-seq": p.seq, class: view && view.kind === "print" && view.seq === p.seq ? "selected" : "" });
      tr.append(el("td", {}, "#" + p.seq));
      tr.append(el("td", {}, p.ingested_at.replace("T", " ").replace("+00:00", " UTC")));
      tr.append(el("td", {}, fmt(p.duration_min, 3) + " min"));
      const kept = p.status && p.status !== "ok" ? " · " + p.status + (p.status_reason ? ": " + p.status_reason : "") + " (not the twin's start)" : "";
      tr.append(el("td", { class: "dim" }, (p.scenario ? p.scenario + " · " : "") + p.source + kept));
      tr.append(el("td", {}, fmt(p.mean_nis, 3)));
      tr.append(el("td", p.anomalies ? { class: "cause" } : {}, String(p.anomalies)));
      const b = el("button", {}, "show"); b.onclick = () => { loadPrint(p.seq); part.showPrint(p); };
      const td = el("td"); td.append(b); tr.append(td); tb.append(tr);
    }
  }

  function draw(series, alarms) {
    const build = { outputs: buildOutputs, states: buildStates, detectors: buildDetectors, theta: buildTheta };
    for (const [key, fn] of Object.entries(build)) {
      const div = document.getElementById("plot-" + key);
      const fig = fn(series);
      if (!fig) { Plotly.purge(div); div.textContent = "not recorded for this print"; continue; }
      fig.layout.shapes = alarmShapes(alarms, fig.layout.shapes);
      Plotly.react(div, fig.traces, fig.layout, PLOT_CONFIG);
      figs[key] = fig;
    }
  }

  async function loadPrint(seq) {
    try {
      const s = await getJSON("/api/machine/" + encodeURIComponent(name) + "/print/" + seq);
      view = { kind: "print", seq };
      document.getElementById("view-title").textContent = "Print #" + seq + " (" + fmt(s.n_samples / 60, 3) + " min from the registry)";
      draw(s, s.alarms);
      A.drawnPrint = seq;
      if (info) renderHistory(info);
    } catch (e) { showError(e.message); }
  }

  function liveSeries(samples) {
    const pick = (k) => samples.map((s) => s[k] || [null, null, null, null, null]);
    const d0 = samples.find((s) => s.detectors);
    return {
      names: info.names, time_s: samples.map((s) => s.time_s), means: pick("states"),
      stds: pick("state_stds"), measured: pick("measured"), predicted: pick("predicted"),
      theta: samples.some((s) => s.theta) ? pick("theta") : null,
      truth: samples.some((s) => s.truth) ? pick("truth") : null,
      detectors: d0 ? {
        channels: ["L_w", "L_o", "P_c", "P_s", "Q_m", "P_c+P_s"],
        cusum: samples.map((s) => s.detectors ? s.detectors.cusum : [null, null, null, null, null, null]),
        cusum_thresholds: d0.detectors.cusum_thresholds,
        window_nis_log10p: samples.map((s) => s.detectors ? s.detectors.window_nis_log10p : null),
        window_nis_threshold: d0.detectors.window_nis_threshold, window_s: 120,
      } : null,
    };
  }

  function showLive() {
    view = { kind: "live" };
    document.getElementById("view-title").textContent = "Live print";
    if (info.live.samples.length) draw(liveSeries(info.live.samples), info.live.alarms);
    renderHistory(info);
  }

  function appendLive(batch) {
    // one extendTraces per figure for everything that arrived since the last frame
    const t = batch.map((s) => s.time_s / 60);
    const col = (k, i) => batch.map((s) => (s[k] ? s[k][i] : null));
    const ext = (key, pairs) => {
      const div = document.getElementById("plot-" + key);
      if (!figs[key] || !pairs.length) return;
      Plotly.extendTraces(div, { x: pairs.map(() => t), y: pairs.map((p) => p[1]) },
        pairs.map((p) => p[0]), LIVE_MAX_POINTS);
    };
    const o = figs.outputs.map, st = figs.states.map;
    const op = [];
    const on = info.names;
    const ocol = (k, i) => col(k, i).map((v) => outScaled(on, i, v));
    for (let i = 0; i < 5; i++) { op.push([o.meas[i], ocol("measured", i)]); op.push([o.pred[i], ocol("predicted", i)]); }
    ext("outputs", op);
    const sp = [];
    const n = info.names;
    for (let i = 0; i < 5; i++) {
      const m = col("states", i).map((v) => scaled(n, i, v));
      const sd = col("state_stds", i).map((v) => scaled(n, i, v));
      sp.push([st.lo[i], m.map((v, k) => v === null ? null : v - 2 * sd[k])]);
      sp.push([st.hi[i], m.map((v, k) => v === null ? null : v + 2 * sd[k])]);
      sp.push([st.mean[i], m]);
      if (st.truth.length) sp.push([st.truth[i], col("truth", i).map((v) => scaled(n, i, v))]);
    }
    ext("states", sp);
    if (figs.detectors) {
      const d = figs.detectors.map, th = batch.find((s) => s.detectors);
      if (th) {
        const h = th.detectors.cusum_thresholds;
        const dp = d.cusum.map((idx, j) => [idx, batch.map((s) => s.detectors && s.detectors.cusum[j] !== null ? s.detectors.cusum[j] / h[j] : null)]);
        dp.push([d.nis[0], batch.map((s) => s.detectors ? s.detectors.window_nis_log10p : null)]);
        ext("detectors", dp);
      }
    }
    if (figs.theta) {
      ext("theta", figs.theta.map.theta.map((idx, i) => [idx, col("theta", i).map((v) => thetaShown(info.names, v))]));
      const first = figs.theta.unchangedFrom;  // EM landed: the "θ unchanged" note goes
      if (first && batch.some((b) => b.theta && b.theta.some((v, i) => v !== null && v !== first[i]))) {
        figs.theta.unchangedFrom = null;
        Plotly.relayout(document.getElementById("plot-theta"), { annotations: [] });
      }
    }
    const now = Date.now();
    if (now - (A.historyDrawn || 0) > 2000) { renderHistory(info); A.historyDrawn = now; }
    for (const s of batch) A.latencies.push(now - s.published_at * 1000);
    if (A.latencies.length > 10000) A.latencies.splice(0, A.latencies.length - 10000);
    renderSummary(info, batch[batch.length - 1]);
  }

  function onAlarm(s) {
    const tb = document.querySelector("#alarms tbody");
    const empty = tb.querySelector("td.empty");
    if (empty) empty.parentElement.remove();
    const now = Date.now();
    for (const a of s.alarms) {
      const tr = alarmRow(a, true);
      tr.dataset.publishedAt = s.published_at; tr.dataset.shownAt = now / 1000;
      tb.prepend(tr);
      let banner = document.getElementById("alarm-banner");
      if (!banner) {
        banner = el("div", { id: "alarm-banner", class: "banner" });
        document.getElementById("summary").before(banner);
      }
      banner.textContent = "ALARM at " + fmt(a.detected_s / 60, 3) + " min of the live print — likely cause: " + causeText(a);
      A.alarmsShown.push({ cause: a.cause, detected_s: a.detected_s, published_at: s.published_at, shown_at: now / 1000 });
      info.live.alarms.push(a);
      renderHistory(info);
      for (const key of ["outputs", "states", "detectors", "theta"]) {
        const div = document.getElementById("plot-" + key);
        if (figs[key]) Plotly.relayout(div, { shapes: alarmShapes([a], div.layout.shapes) });
      }
    }
    setStatus("alarm");
  }

  function flush() {
    frame = null;
    const batch = queue; queue = [];
    info.live.samples.push(...batch);
    if (!view || view.kind !== "live") return;
    if (!figs.outputs) showLive();  // the first samples of a live print: draw them whole
    else appendLive(batch);
  }

  async function load() {
    try {
      info = await getJSON("/api/machine/" + encodeURIComponent(name));
    } catch (e) { showError(e.message); return; }
    setStatus(info.status);
    renderLink(info.link);
    const live = info.live.samples;
    renderSummary(info, live.length && info.live.printing ? live[live.length - 1] : null);
    renderAlarms(info);
    if (live.length && (info.live.printing || !info.prints.length)) showLive();
    else if (info.prints.length) await loadPrint(info.prints[info.prints.length - 1].seq);
    renderHistory(info);
    if (info.live_part) part.showLive();
    else if (info.prints.length) part.showPrint(info.prints[info.prints.length - 1]);
  }

  connect(name, async (ev) => {
    if (!info) return;
    if (ev.type === "sample") {
      if (!view || view.kind !== "live") {
        if (!info.live.printing) {  // a live print started: follow it
          info.live.printing = true; info.live.samples = []; info.live.alarms = [];
          view = { kind: "live" }; figs.outputs = null; setStatus("printing");
        }
      }
      if (ev.alarms && ev.alarms.length) onAlarm(ev);
      queue.push(ev);
      if (!frame) frame = requestAnimationFrame(flush);
    } else if (ev.type === "link") {
      if (ev.machine === name) { info.link = ev.link; renderLink(ev.link); }
    } else if (ev.type === "print_end") {
      info.live.printing = false; renderHistory(info);
    } else if (ev.type === "print" && ev.machine === name) {
      const keep = view;
      const fresh = await getJSON("/api/machine/" + encodeURIComponent(name));
      info = fresh; setStatus(info.status); renderAlarms(info); renderHistory(info);
      A.lastPrintEvent = ev.seq;
      if (!keep || keep.kind !== "live" || !info.live.printing) await loadPrint(ev.seq);
    } else if (ev.type === "part_outline" && ev.machine === name) {
      part.onOutline(ev);
    } else if (ev.type === "part" && ev.machine === name) {
      part.onChunk(ev);
    } else if (ev.type === "feed_error") {
      showError("live feed stopped: " + ev.message);
    }
  });
  load();
}

// ---------------------------------------------------------------- what-if page
function whatifPage() {
  const name = document.body.dataset.machine;
  document.getElementById("conn").textContent = "";  // nothing is pushed to this page
  const tbody = document.querySelector("#changes tbody");
  const template = tbody.querySelector("tr.change").cloneNode(true);
  function wireRemove(tr) { tr.querySelector(".remove").onclick = () => tr.remove(); }
  tbody.querySelectorAll("tr.change").forEach(wireRemove);
  document.getElementById("add-change").onclick = () => {
    const tr = template.cloneNode(true); wireRemove(tr); tbody.append(tr);
  };

  function showErr(id, msg) { const e = document.getElementById(id); e.textContent = msg || ""; e.hidden = !msg; }

  document.getElementById("forecast-form").onsubmit = async (evt) => {
    evt.preventDefault();
    showErr("forecast-error", "");
    const busy = document.getElementById("forecast-busy");
    busy.textContent = "computing… (the first run in a server compiles the model: ~10–30 s)";
    const changes = [...tbody.querySelectorAll("tr.change")].map((tr) => ({
      input: tr.querySelector("[name=input]").value, value: tr.querySelector("[name=value]").value,
      at: tr.querySelector("[name=at]").value,
    }));
    try {
      const fc = await postJSON("/api/machine/" + encodeURIComponent(name) + "/forecast", {
        changes, horizon: document.getElementById("horizon").value,
        nominal_theta: document.getElementById("nominal-theta").checked,
        with_sensor_noise: document.getElementById("sensor-noise").checked,
      });
      drawForecast(fc);
      const ul = document.getElementById("forecast-warnings"); ul.innerHTML = "";
      for (const w of fc.warnings) ul.append(el("li", {}, w));
      busy.textContent = "forecast from the end of print #" + fc.from_print;
    } catch (e) { busy.textContent = ""; showErr("forecast-error", e.message); }
  };

  function drawForecast(fc) {
    const t = fc.time_min, traces = [];
    for (let i = 0; i < 4; i++) {
      const m = fc.outputs.map((r) => r[i]), sd = fc.output_stds.map((r) => r[i]);
      traces.push({ x: t, y: m.map((v, k) => v - 2 * sd[k]), mode: "lines", line: { width: 0 }, showlegend: false, hoverinfo: "skip", yaxis: ax(i) });
      traces.push({ x: t, y: m.map((v, k) => v + 2 * sd[k]), mode: "lines", line: { width: 0 }, fill: "tonexty",
        fillcolor: "rgba(31,119,180,0.25)", name: "±2σ", legendgroup: "b", showlegend: i === 0, yaxis: ax(i) });
      traces.push({ x: t, y: m, mode: "lines", line: { width: 1.6, color: COLORS[0] }, name: "forecast",
        legendgroup: "f", showlegend: i === 0, yaxis: ax(i) });
    }
    const names = ["Q_c [sccm]", "Q_s [sccm]", "I_A / 10 [mA]"], cols = [1, 2, 0];
    cols.forEach((c, j) => traces.push({ x: t, y: fc.inputs.map((r) => (c === 0 ? r[c] / 10 : r[c])),
      mode: "lines", line: { width: 1.4, color: COLORS[j + 1] }, name: names[j], yaxis: "y5" }));
    const titles = fc.output_names.map((o, i) => o + " [" + fc.output_units[i] + "]").concat(["inputs"]);
    const layout = rowsLayout(5, titles);
    layout.xaxis.title.text = "minutes from now";
    const div = document.getElementById("plot-forecast");
    if (div.classList.contains("placeholder")) { div.classList.remove("placeholder"); div.textContent = ""; }
    Plotly.react(div, traces, layout, PLOT_CONFIG);
    A.forecastDrawn = (A.forecastDrawn || 0) + 1;
  }

  document.getElementById("advise-form").onsubmit = async (evt) => {
    evt.preventDefault();
    showErr("advise-error", "");
    const busy = document.getElementById("advise-busy");
    busy.textContent = "searching inputs… (several forecasts; ~5–30 s)";
    const box = document.getElementById("advice"); box.innerHTML = "";
    try {
      const a = await postJSON("/api/machine/" + encodeURIComponent(name) + "/advise", {
        target: document.getElementById("target").value,
        max_overspray: document.getElementById("max-overspray").value,
        settle: document.getElementById("settle").value,
        nominal_theta: document.getElementById("nominal-theta").checked,
        anyway: document.getElementById("advise-anyway").checked,
      });
      busy.textContent = "";
      if (a.open_fault) box.append(el("p", { class: "cause" }, "advised with an open fault: " + a.open_fault));
      if (a.limit_note) box.append(el("p", { class: "notice", id: "advice-limits" }, a.limit_note));
      box.append(el("p", { class: a.reachable && a.overspray_ok ? "" : "cause" }, a.message + " (judged " + a.settle_s + " s after the change)"));
      const table = el("table", { class: "advice", id: "advice-table" });
      const head = el("tr"); for (const h of ["", "now", "advised", "± 2σ"]) head.append(el("th", {}, h));
      table.append(head);
      const label = { atomizer_current_mA: "I_A [mA]", carrier_flow_sccm: "Q_c [sccm]", sheath_flow_sccm: "Q_s [sccm]",
        linewidth_um: "L_w [µm]", overspray_um: "L_o [µm]", carrier_pressure_Pa: "P_c [Pa]", sheath_pressure_Pa: "P_s [Pa]" };
      for (const r of a.rows) {
        const tr = el("tr");
        tr.append(el("td", {}, label[r.name] || r.name)); tr.append(el("td", {}, fmt(r.now)));
        tr.append(el("td", {}, fmt(r.advised))); tr.append(el("td", {}, r.std === null ? "" : fmt(2 * r.std, 2)));
        table.append(tr);
      }
      box.append(table);
    } catch (e) { busy.textContent = ""; showErr("advise-error", e.message); }
  };
}

window.addEventListener("DOMContentLoaded", () => {
  const page = document.body.dataset.page;
  if (page === "fleet") fleetPage();
  else if (page === "machine") machinePage();
  else if (page === "whatif") whatifPage();
});
