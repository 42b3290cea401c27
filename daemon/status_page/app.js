// The cellcal status page: polls the read-only JSON API (docs/api.md) and draws what it says.
// Every 1 s while a run is on, every 5 s otherwise; no reload, no library, no network beyond this server.
"use strict";

const FAST_MS = 1000, SLOW_MS = 5000;
const QUIET_STATES = new Set(["idle", "fault", "stopped", "unknown", "starting"]);
const SVG = "http://www.w3.org/2000/svg";
let lastRunsKey = null, selectedTool = null, historyKey = null, timer = null;

function $(id) { return document.getElementById(id); }

function el(tag, text, cls) {
  const e = document.createElement(tag);
  if (text !== undefined && text !== null) e.textContent = String(text);
  if (cls) e.className = cls;
  return e;
}

function when(t) {
  if (t === null || t === undefined) return "-";
  const d = new Date(t * 1000);
  const pad = (n) => String(n).padStart(2, "0");
  return `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())} ${pad(d.getHours())}:` +
         `${pad(d.getMinutes())}:${pad(d.getSeconds())}`;
}

function num(v, digits) { return (v === null || v === undefined) ? "-" : Number(v).toFixed(digits); }

async function getJSON(url) {
  const r = await fetch(url, {cache: "no-store", credentials: "omit"});
  if (!r.ok) {
    let msg = `${r.status}`;
    try { msg += ": " + (await r.json()).error.message; } catch (e) { /* not JSON */ }
    throw new Error(`${url}: ${msg}`);
  }
  return r.json();
}

function running(state) { return state && !QUIET_STATES.has(state.state); }

function showState(s) {
  const box = $("state");
  box.dataset.state = s.state || "";
  box.classList.toggle("running", running(s));
  let text = s.state || "unknown";
  if (running(s)) text = `running ${s.routine || ""}${s.run_id ? ` (run ${s.run_id})` : ""}: ${s.state}`;
  box.textContent = text;
  $("progress").textContent = running(s) && s.progress ? `progress: ${s.progress}` : "";
  $("reason").textContent = (s.state === "fault" || !running(s)) && s.reason ?
    `last run ended: ${s.reason}${s.result_code === null || s.result_code === undefined ? "" : ` (code ${s.result_code})`}` : "";
  $("updated").textContent = `as of ${when(s.time)}` + (s.since ? `; in this state since ${when(s.since)}` : "");
  $("cell-name").textContent = s.cell && s.cell.name ? `: ${s.cell.name}` : "";
  const body = $("devices").tBodies[0];
  body.replaceChildren();
  for (const [name, how] of Object.entries(s.devices || {})) {
    const tr = el("tr");
    tr.dataset.device = name;
    tr.append(el("th", name), el("td", typeof how === "string" ? how : JSON.stringify(how)));
    body.append(tr);
  }
  const t = s.mounted_tool;
  $("mounted-tool").textContent = t ? `tool ${t.id}${t.name ? ` (${t.name})` : ""}` : "none";
}

function showRuns(runs) {
  const body = $("runs").tBodies[0];
  body.replaceChildren();
  $("no-runs").hidden = runs.length > 0;
  for (const r of runs) {
    const tr = el("tr");
    tr.dataset.runId = r.id;
    const code = r.result_code === null ? "-" : `${r.result_code} ${r.result_name || ""}`;
    const report = el("td");
    if (r.report_url) {
      const a = el("a", "report", "report");
      a.href = r.report_url;
      report.append(a);
    }
    tr.append(el("td", r.id), el("td", r.routine), el("td", r.tool_id === null ? "-" : r.tool_id),
              el("td", r.state),
              el("td", code, r.result_code === null ? "" : (r.result_code === 0 ? "code-ok result" : "code-bad result")),
              el("td", r.verdict || "-", "verdict"), el("td", when(r.finished_at || r.started_at)), report);
    tr.title = r.reason || "";
    body.append(tr);
  }
}

async function refreshTools(state) {
  const tools = (await getJSON("/api/v1/tools")).tools;
  const select = $("tool-select");
  const mounted = state && state.mounted_tool ? state.mounted_tool.id : null;
  if (selectedTool === null || !tools.some((t) => t.id === selectedTool)) {
    const pick = tools.find((t) => t.id === mounted) || tools.find((t) => t.last_frame) || tools[0];
    selectedTool = pick ? pick.id : null;
  }
  select.replaceChildren();
  for (const t of tools) {
    const o = el("option", `tool ${t.id}${t.name ? ` (${t.name})` : ""}${t.mounted ? ", mounted" : ""}`);
    o.value = String(t.id);
    o.selected = t.id === selectedTool;
    select.append(o);
  }
}

function drawDrift(history) {
  const box = $("drift-plot-box");
  const trend = history.trend;
  const points = trend ? trend.points : [];
  const series = [
    {key: "tip_mm", label: "tip change (mm)", cls: "tip"},
    {key: "axis_deg", label: "axis change (deg)", cls: "axis"},
  ];
  const base = trend && !trend.never_calibrated ? "since_first_calibration" : "since_last_calibration";
  const W = 640, H = 240, L = 50, R = 20, T = 20, B = 34;
  const svg = document.createElementNS(SVG, "svg");
  svg.setAttribute("class", "drift-plot");
  svg.setAttribute("width", W);
  svg.setAttribute("height", H);
  svg.setAttribute("viewBox", `0 0 ${W} ${H}`);
  svg.setAttribute("role", "img");
  const ts = points.map((p) => p.at);
  const values = [];
  for (const s of series) for (const p of points) { const v = p[base][s.key]; if (v !== null) values.push(v); }
  const t0 = ts.length ? Math.min(...ts) : 0, t1 = ts.length ? Math.max(...ts) : 1;
  const vmax = Math.max(1e-3, ...values.map(Math.abs));
  const x = (t) => L + (t1 > t0 ? (t - t0) / (t1 - t0) : 0.5) * (W - L - R);
  const y = (v) => H - B - (v / vmax) * (H - T - B);
  const line = (cls, x1, y1, x2, y2) => {
    const e = document.createElementNS(SVG, "line");
    for (const [k, v] of Object.entries({x1, y1, x2, y2})) e.setAttribute(k, v);
    e.setAttribute("class", cls);
    svg.append(e);
  };
  const text = (s, tx, ty, cls) => {
    const e = document.createElementNS(SVG, "text");
    e.setAttribute("x", tx); e.setAttribute("y", ty);
    if (cls) e.setAttribute("class", cls);
    e.textContent = s;
    svg.append(e);
  };
  line("grid", L, y(vmax), W - R, y(vmax));
  line("axis", L, H - B, W - R, H - B);
  line("axis", L, T, L, H - B);
  text(num(vmax, 3), 4, y(vmax) + 4);
  text("0", 4, H - B + 4);
  text(when(t0), L, H - 8);
  if (t1 > t0) text(when(t1), W - R - 130, H - 8);
  series.forEach((s, k) => {
    const pts = points.filter((p) => p[base][s.key] !== null).map((p) => [x(p.at), y(p[base][s.key])]);
    const path = document.createElementNS(SVG, "path");
    path.setAttribute("class", `series series-${s.cls}`);
    path.dataset.series = s.key;
    path.dataset.points = String(pts.length);
    path.setAttribute("d", pts.map(([px, py], i) => `${i ? "L" : "M"}${px.toFixed(1)} ${py.toFixed(1)}`).join(" "));
    svg.append(path);
    for (const [px, py] of pts) {
      const c = document.createElementNS(SVG, "circle");
      c.setAttribute("cx", px.toFixed(1)); c.setAttribute("cy", py.toFixed(1)); c.setAttribute("r", 3);
      c.setAttribute("class", `point-${s.cls}`);
      svg.append(c);
    }
    text(s.label, L + 10 + k * 170, T - 6, `label-${s.cls}`);
  });
  box.replaceChildren(svg);
  $("drift-note").textContent = !trend ? "No measured frame of this tool yet." :
    (trend.never_calibrated ? "Never calibrated here: changes against the controller's frame. " :
      `Against the first full calibration (run ${trend.first_calibration.run_id}). `) +
    (trend.rate && trend.rate.tip_mm_per_week !== null ?
      `Tip drifts ${num(trend.rate.tip_mm_per_week, 4)} mm per week since the last full calibration.` : "");
  const body = $("frames").tBodies[0];
  body.replaceChildren();
  for (const f of history.tool_frames.slice(-20).reverse()) {
    const tr = el("tr");
    tr.append(el("td", when(f.at)), el("td", f.action), el("td", f.run_id === null ? "-" : f.run_id));
    for (const k of ["x_mm", "y_mm", "z_mm", "rx_deg", "ry_deg", "rz_deg"]) tr.append(el("td", num(f.tool_frame[k], 4)));
    body.append(tr);
  }
}

async function refreshHistory(force) {
  if (selectedTool === null) {
    $("drift-note").textContent = "No tool known to the cell file or the store.";
    return;
  }
  const key = `${selectedTool}/${lastRunsKey}`;
  if (!force && key === historyKey) return;
  drawDrift(await getJSON(`/api/v1/tools/${selectedTool}/history`));
  historyKey = key;
}

async function tick() {
  let state = null;
  try {
    state = await getJSON("/api/v1/state");
    showState(state);
    const runs = (await getJSON("/api/v1/runs?limit=20")).runs;
    showRuns(runs);
    const key = runs.map((r) => `${r.id}:${r.state}`).join(",");
    if (key !== lastRunsKey || selectedTool === null) {
      lastRunsKey = key;
      await refreshTools(state);
    }
    await refreshHistory(false);
    $("error").hidden = true;
  } catch (e) {
    $("error").textContent = `cannot reach the service: ${e.message}`;
    $("error").hidden = false;
  }
  clearTimeout(timer);
  timer = setTimeout(tick, running(state) ? FAST_MS : SLOW_MS);
}

document.addEventListener("DOMContentLoaded", () => {
  $("tool-select").addEventListener("change", (ev) => {
    selectedTool = Number(ev.target.value);
    refreshHistory(true).catch((e) => { $("error").textContent = e.message; $("error").hidden = false; });
  });
  tick();
});
