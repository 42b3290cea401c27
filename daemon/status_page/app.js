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

function zone(d) {
  // the browser's UTC offset at that moment: a time is never shown without its zone
  const off = -d.getTimezoneOffset(), a = Math.abs(off);
  return `UTC${off < 0 ? "-" : "+"}${String(Math.floor(a / 60)).padStart(2, "0")}:${String(a % 60).padStart(2, "0")}`;
}

function when(t) {
  if (t === null || t === undefined) return "-";
  const d = new Date(t * 1000);
  const pad = (n) => String(n).padStart(2, "0");
  return `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())} ${pad(d.getHours())}:` +
         `${pad(d.getMinutes())}:${pad(d.getSeconds())} ${zone(d)}`;
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
  const health = s.health || {level: s.state === "idle" ? "ok" : "fault", says: s.state || "unknown"};
  box.dataset.state = s.state || "";
  box.dataset.level = health.level;
  box.classList.toggle("running", running(s));
  let text = health.says;
  if (running(s) && !s.waiting) {
    text = `running ${s.routine || ""}${s.run_id ? ` (run ${s.run_id})` : ""}: ${s.state}` +
      health.says.slice(health.says.indexOf(";") < 0 ? health.says.length : health.says.indexOf(";"));
  } else if (s.waiting) {
    const left = Math.round(s.waiting.time_left_s);
    text = `${health.says} (${Math.floor(left / 60)} min ${String(left % 60).padStart(2, "0")} s left to confirm)`;
  }
  box.textContent = text;
  $("progress").textContent = running(s) && s.progress && !s.waiting ? `progress: ${s.progress}` : "";
  const last = s.last_run;
  $("reason").textContent = last ?
    `${running(s) ? "previous" : "last"} run ${last.id} (${last.routine}, ${when(last.at)}) ended ${last.state}` +
    `: code ${last.result_code} ${last.result}${last.verdict ? `, verdict ${last.verdict}` : ""}` +
    (last.reason ? `: ${last.reason}` : "") : "no run recorded yet";
  $("updated").textContent = `as of ${when(s.time)}` + (s.since ? `; in this state since ${when(s.since)}` : "");
  $("cell-name").textContent = s.cell && s.cell.name ? `: ${s.cell.name}` : "";
  const body = $("devices").tBodies[0];
  body.replaceChildren();
  for (const [name, how] of Object.entries(s.devices || {})) {
    const tr = el("tr");
    tr.dataset.device = name;
    const good = ["ready", "ok", "open", "none"].includes(how);
    tr.append(el("th", name), el("td", typeof how === "string" ? how.replace(/_/g, " ") : JSON.stringify(how),
                                 good ? "device-ok" : "device-bad"));
    body.append(tr);
  }
  const t = s.mounted_tool;
  $("mounted-tool").textContent = !t ? "none" : `tool ${t.id}${t.name ? ` (${t.name})` : ""}, ` +
    (t.read_at_run === undefined ? "" : t.read_at_run === null && t.source === "the cell file's `mounted`" ?
      "as the cell file says" : t.read_at_run === null ? `not read since the service started (${t.source})` :
      `as of run ${t.read_at_run} (read from ${t.source} at its start)`);
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

function plot(points, base, key, unit, label, cls, lines) {
  // one quantity against time, its band lines dashed: drawn to the largest of the points and the lines
  const W = 640, H = 200, L = 60, R = 120, T = 22, B = 34;
  const svg = document.createElementNS(SVG, "svg");
  svg.setAttribute("class", `drift-plot drift-${cls}`);
  svg.setAttribute("width", W);
  svg.setAttribute("height", H);
  svg.setAttribute("viewBox", `0 0 ${W} ${H}`);
  svg.setAttribute("role", "img");
  svg.setAttribute("aria-label", label);
  const used = points.filter((p) => p[base][key] !== null);
  const ts = points.map((p) => p.at);
  const shown = lines.filter((b) => b.value !== null && b.value !== undefined);
  const t0 = ts.length ? Math.min(...ts) : 0, t1 = ts.length ? Math.max(...ts) : 1;
  const vmax = Math.max(1e-3, ...used.map((p) => Math.abs(p[base][key])), ...shown.map((b) => b.value)) * 1.05;
  const x = (t) => L + (t1 > t0 ? (t - t0) / (t1 - t0) : 0.5) * (W - L - R);
  const y = (v) => H - B - (v / vmax) * (H - T - B);
  const line = (c, x1, y1, x2, y2) => {
    const e = document.createElementNS(SVG, "line");
    for (const [k, v] of Object.entries({x1, y1, x2, y2})) e.setAttribute(k, v);
    e.setAttribute("class", c);
    svg.append(e);
    return e;
  };
  const text = (str, tx, ty, c) => {
    const e = document.createElementNS(SVG, "text");
    e.setAttribute("x", tx); e.setAttribute("y", ty);
    if (c) e.setAttribute("class", c);
    e.textContent = str;
    svg.append(e);
  };
  line("axis", L, H - B, W - R, H - B);
  line("axis", L, T, L, H - B);
  text(`${num(vmax, 3)} ${unit}`, 4, T + 4);
  text(`0 ${unit}`, 4, H - B + 4);
  text(label, L + 6, T - 8, `label-${cls}`);
  text(when(t0), L, H - 8);
  if (t1 > t0) text(when(t1), W - R - 170, H - 8);
  for (const b of shown) {
    const e = line(`band band-${b.cls}`, L, y(b.value), W - R, y(b.value));
    e.dataset.band = b.cls;
    e.dataset.value = String(b.value);
    text(`${b.name} ${num(b.value, 3)} ${unit}`, W - R + 4, y(b.value) + 4, `band-label band-${b.cls}`);
  }
  const pts = used.map((p) => [x(p.at), y(p[base][key])]);
  const path = document.createElementNS(SVG, "path");
  path.setAttribute("class", `series series-${cls}`);
  path.dataset.series = key;
  path.dataset.points = String(pts.length);
  path.setAttribute("d", pts.map(([px, py], i) => `${i ? "L" : "M"}${px.toFixed(1)} ${py.toFixed(1)}`).join(" "));
  svg.append(path);
  for (const [px, py] of pts) {
    const c = document.createElementNS(SVG, "circle");
    c.setAttribute("cx", px.toFixed(1)); c.setAttribute("cy", py.toFixed(1)); c.setAttribute("r", 3);
    c.setAttribute("class", `point-${cls}`);
    svg.append(c);
  }
  return svg;
}

function drawDrift(history) {
  const box = $("drift-plot-box");
  const trend = history.trend;
  const points = trend ? trend.points : [];
  const base = trend && !trend.never_calibrated ? "since_first_calibration" : "since_last_calibration";
  const b = history.bands || {};
  const bands = (u) => [{name: "inner band", cls: "inner", value: b[`inner_${u}`]},
                        {name: "outer band", cls: "outer", value: b[`outer_${u}`]},
                        {name: "drift alarm", cls: "drift", value: b[`drift_${u}`]}];
  box.replaceChildren(plot(points, base, "tip_mm", "mm", "tip change (mm)", "tip", bands("mm")),
                      plot(points, base, "axis_deg", "deg", "axis change (deg)", "axis", bands("deg")));
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
