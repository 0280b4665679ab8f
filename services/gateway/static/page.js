// The session page: lists, starts and stops sessions through the gateway's HTTP API, and draws each trajectory.
"use strict";

const $ = (id) => document.getElementById(id);
const rows = new Map();       // session id -> its table row
const trajectories = new Map(); // session id -> {frames, points}

function headers(json) {
  const h = json ? { "content-type": "application/json" } : {};
  const token = $("token").value.trim();
  if (token) h.authorization = "Bearer " + token;
  return h;
}

function say(text, isError) {
  $("message").textContent = text;
  $("message").className = isError ? "error" : "";
}

async function api(method, path, body) {
  const response = await fetch(path, { method, headers: headers(body !== undefined),
                                       body: body === undefined ? undefined : JSON.stringify(body) });
  if (!response.ok) {
    let detail = response.statusText;
    try { detail = (await response.json()).detail || detail; } catch (e) { /* not JSON */ }
    throw new Error(`${response.status}: ${detail}`);
  }
  return response;
}

async function startSession(event) {
  event.preventDefault();
  const body = { sequence: $("sequence").value.trim(), robot_id: $("robot").value.trim() || "robot1",
                 rate: Number($("rate").value || 0), record: $("record").checked };
  if ($("max-frames").value) body.max_frames = Number($("max-frames").value);
  if ($("start-frame").value) body.start = Number($("start-frame").value);
  const map = $("map-name").value === "__new__" ? $("new-map").value.trim() : $("map-name").value;
  const newMode = $("map-mode").value === "share" ? "share" : "build";  // a new map is built, alone or shared
  if (map) body.map = { name: map, mode: $("map-name").value === "__new__" ? newMode : $("map-mode").value };
  try {
    const info = await (await api("POST", "/sessions", body)).json();
    say(`started session ${info.id}`);
    await refresh();
  } catch (e) { say(`could not start: ${e.message}`, true); }
}

async function stopSession(id) {
  try { await api("DELETE", `/sessions/${id}`); say(`stopped session ${id}`); await refresh(); }
  catch (e) { say(`could not stop: ${e.message}`, true); }
}

// fetch + blob, so that downloads carry the token too
async function download(path, filename) {
  try {
    const blob = await (await api("GET", path)).blob();
    const link = document.createElement("a");
    link.href = URL.createObjectURL(blob);
    link.download = filename;
    document.body.appendChild(link);
    link.click();
    link.remove();
    setTimeout(() => URL.revokeObjectURL(link.href), 10000);
  } catch (e) { say(`download failed: ${e.message}`, true); }
}

function parseTum(text) {
  return text.split("\n").filter((l) => l && !l.startsWith("#"))
    .map((l) => l.trim().split(/\s+/).map(Number)).filter((v) => v.length >= 4);
}

// top view: camera x to the right, camera z (forward) up
function drawTrajectory(svg, points) {
  const w = 160, h = 100, pad = 6;
  svg.innerHTML = "";
  if (points.length < 2) return;
  const xs = points.map((p) => p[1]), zs = points.map((p) => p[3]);
  const minX = Math.min(...xs), maxX = Math.max(...xs), minZ = Math.min(...zs), maxZ = Math.max(...zs);
  const scale = Math.min((w - 2 * pad) / Math.max(maxX - minX, 1e-3), (h - 2 * pad) / Math.max(maxZ - minZ, 1e-3));
  const px = (p) => [pad + (p[1] - minX) * scale, h - pad - (p[3] - minZ) * scale];
  const ns = "http://www.w3.org/2000/svg";
  const line = document.createElementNS(ns, "polyline");
  line.setAttribute("points", points.map((p) => px(p).map((v) => v.toFixed(1)).join(",")).join(" "));
  line.setAttribute("fill", "none");
  line.setAttribute("stroke", "#2f6fde");
  line.setAttribute("stroke-width", "1.5");
  svg.appendChild(line);
  for (const [p, colour] of [[points[0], "#1e8449"], [points[points.length - 1], "#c0392b"]]) {
    const dot = document.createElementNS(ns, "circle");
    const [cx, cy] = px(p);
    dot.setAttribute("cx", cx); dot.setAttribute("cy", cy); dot.setAttribute("r", 3); dot.setAttribute("fill", colour);
    svg.appendChild(dot);
  }
}

function cell(row, name, numeric) {
  const td = document.createElement("td");
  td.className = name + (numeric ? " num" : "");
  row.appendChild(td);
  return td;
}

function newRow(info) {
  const row = document.createElement("tr");
  row.dataset.session = info.id;
  for (const [name, numeric] of [["id"], ["robot"], ["sequence"], ["state"], ["frames", 1], ["fps", 1],
                                 ["tracking"], ["ate", 1]]) cell(row, name, numeric);
  const svg = document.createElementNS("http://www.w3.org/2000/svg", "svg");
  svg.setAttribute("class", "traj");
  svg.setAttribute("width", "160");
  svg.setAttribute("height", "100");
  cell(row, "trajectory").appendChild(svg);
  const actions = cell(row, "actions");
  const stop = document.createElement("button");
  stop.textContent = "Stop";
  stop.className = "stop";
  stop.addEventListener("click", () => stopSession(info.id));
  const traj = document.createElement("button");
  traj.textContent = "Trajectory";
  traj.className = "download-trajectory";
  traj.addEventListener("click", () => download(`/sessions/${info.id}/trajectory`, `${info.id}_trajectory.txt`));
  const rec = document.createElement("button");
  rec.textContent = "Recording";
  rec.className = "download-recording";
  rec.addEventListener("click", () => download(`/sessions/${info.id}/recording`, `${info.id}.mcap`));
  actions.append(stop, traj, rec);
  $("sessions").tBodies[0].prepend(row);
  return row;
}

async function updateTrajectory(info, row) {
  const known = trajectories.get(info.id);
  // fetched again when it grew, was refined, or moved into a shared map's frame
  const version = `${info.frames} ${info.trajectory} ${info.merge ? info.merge.kind + info.merge.refinements : ""}`;
  if (known && known.version === version) return;
  const text = await (await api("GET", `/sessions/${info.id}/trajectory`)).text();
  const points = parseTum(text);
  trajectories.set(info.id, { version, points });
  drawTrajectory(row.querySelector("svg"), points);
}

function render(info) {
  const row = rows.get(info.id) || newRow(info);
  rows.set(info.id, row);
  const q = (name) => row.querySelector("td." + name);
  q("id").textContent = info.id;
  q("robot").textContent = info.robot_id;
  q("sequence").textContent = info.sequence;
  q("state").textContent = info.state;
  q("state").className = "state state-" + info.state;
  // poses received; once the source is done, out of the frames it sent
  q("frames").textContent = info.frames_sent === null ? String(info.frames) : `${info.frames} / ${info.frames_sent}`;
  q("fps").textContent = info.fps.toFixed(1);
  // the tracker's health: "degraded" (frames dropped, keyframe jobs late) with its figures on hover
  const degraded = info.health === "degraded";
  q("tracking").textContent = (info.latest_pose ? info.latest_pose.status : "–") + (degraded ? " · degraded" : "");
  q("tracking").title = info.health_detail || "";
  q("tracking").classList.toggle("degraded", degraded);
  q("ate").textContent = info.ate_rmse === null ? "–" : `${info.ate_rmse.toFixed(3)} m`;
  const active = info.state === "starting" || info.state === "running";
  row.querySelector("button.stop").classList.toggle("hidden", !active);
  row.querySelector("button.download-recording").classList.toggle("hidden", !info.recording || active);
  return updateTrajectory(info, row);
}

const ROBOT_COLOURS = ["#2f6fde", "#e67e22", "#8e44ad", "#16a085", "#c0392b", "#7f8c8d"];

// every robot of a shared map in the map's frame, one polyline each, on one top view
function drawSharedMap(figure, name, members) {
  const w = 320, h = 200, pad = 8, ns = "http://www.w3.org/2000/svg";
  const svg = figure.querySelector("svg");
  svg.innerHTML = "";
  const drawn = members.filter((m) => m.merge && (trajectories.get(m.id) || { points: [] }).points.length > 1);
  const all = drawn.flatMap((m) => trajectories.get(m.id).points);
  const caption = figure.querySelector("figcaption");
  caption.innerHTML = "";
  const title = document.createElement("strong");
  title.textContent = `map ${name}`;
  caption.append(title);
  members.forEach((m, i) => {
    const line = document.createElement("div");
    line.className = "member";
    line.dataset.robot = m.robot_id;
    line.style.color = ROBOT_COLOURS[i % ROBOT_COLOURS.length];
    const merge = m.merge;
    const when = merge ? new Date(merge.at * 1000).toLocaleTimeString() : "";
    line.textContent = `${m.robot_id}: ` + (merge === null ? `own frame ${name}/${m.robot_id}, not merged yet`
      : merge.kind === "defines" ? `defines frame ${name}`
      : merge.kind === "joined" ? `tracks in the stored map since ${when}`
      : `merged at ${when} into ${merge.into.join(", ")} (keyframe ${merge.keyframes}, inliers `
        + `${merge.inliers.join(", ")}${merge.refinements ? `, refined ${merge.refinements}×` : ""})`);
    caption.append(line);
  });
  if (all.length < 2) return;
  const xs = all.map((p) => p[1]), zs = all.map((p) => p[3]);
  const minX = Math.min(...xs), maxX = Math.max(...xs), minZ = Math.min(...zs), maxZ = Math.max(...zs);
  const scale = Math.min((w - 2 * pad) / Math.max(maxX - minX, 1e-3), (h - 2 * pad) / Math.max(maxZ - minZ, 1e-3));
  const px = (p) => [pad + (p[1] - minX) * scale, h - pad - (p[3] - minZ) * scale];
  for (const m of drawn) {
    const line = document.createElementNS(ns, "polyline");
    line.setAttribute("class", "robot-path");
    line.dataset.robot = m.robot_id;
    line.setAttribute("points", trajectories.get(m.id).points.map((p) => px(p).map((v) => v.toFixed(1)).join(","))
      .join(" "));
    line.setAttribute("fill", "none");
    line.setAttribute("stroke", ROBOT_COLOURS[members.indexOf(m) % ROBOT_COLOURS.length]);
    line.setAttribute("stroke-width", "1.5");
    svg.appendChild(line);
  }
}

// the latest sessions of each shared map: those of its robots in the map's frame are drawn together
function renderSharedMaps(sessions) {
  const groups = new Map();
  for (const info of sessions) {
    if (!info.map || info.map.mode !== "share") continue;
    const byRobot = groups.get(info.map.name) || new Map();
    const seen = byRobot.get(info.robot_id);
    if (!seen || seen.created < info.created) byRobot.set(info.robot_id, info);
    groups.set(info.map.name, byRobot);
  }
  const box = $("shared-maps");
  for (const [name, byRobot] of groups) {
    let figure = box.querySelector(`figure[data-map="${CSS.escape(name)}"]`);
    if (!figure) {
      figure = document.createElement("figure");
      figure.dataset.map = name;
      const svg = document.createElementNS("http://www.w3.org/2000/svg", "svg");
      svg.setAttribute("class", "shared-map");
      svg.setAttribute("width", "320");
      svg.setAttribute("height", "200");
      figure.append(svg, document.createElement("figcaption"));
      box.append(figure);
    }
    const members = [...byRobot.values()].sort((a, b) => a.created - b.created);
    drawSharedMap(figure, name, members.filter((m) => m.merge !== null).concat(members.filter((m) => !m.merge)));
  }
  $("no-shared").classList.toggle("hidden", groups.size > 0);
}

async function refresh() {
  try {
    const sessions = await (await api("GET", "/sessions")).json();
    $("empty").classList.toggle("hidden", sessions.length > 0);
    await Promise.all(sessions.map(render));
    renderSharedMaps(sessions);
  } catch (e) { say(`cannot list sessions: ${e.message}`, true); }
}

// the map store's maps: listed, and offered to new sessions
async function refreshMaps() {
  let maps = [];
  try { maps = await (await api("GET", "/maps")).json(); } catch (e) { /* no map store */ }
  const body = $("maps").tBodies[0];
  body.innerHTML = "";
  for (const m of maps) {
    const row = body.insertRow();
    row.dataset.map = m.name;
    for (const value of [m.name, m.version, m.keyframes, m.landmarks, `${(m.size_bytes / 1e6).toFixed(2)} MB`,
                         m.built_by]) row.insertCell().textContent = value;
  }
  $("no-maps").classList.toggle("hidden", maps.length > 0);
  const select = $("map-name");
  const chosen = select.value;
  for (const option of [...select.options]) if (option.value && option.value !== "__new__") option.remove();
  for (const m of maps) select.add(new Option(`${m.name} (v${m.version})`, m.name));
  select.value = [...select.options].some((o) => o.value === chosen) ? chosen : "";
}

function showMapName() {
  $("new-map-label").classList.toggle("hidden", $("map-name").value !== "__new__");
}

async function showLiveLink() {
  try {
    const live = await (await fetch("/live")).json();
    if (live.foxglove_port) {
      const link = $("foxglove-link");
      const address = `${live.tls ? "wss" : "ws"}://${location.hostname}:${live.foxglove_port}`;
      link.title = address;
      const point = (ws) => {
        link.href = "https://app.foxglove.dev/?ds=foxglove-websocket&ds.url=" + (live.tls ? encodeURIComponent(ws) : ws);
      };
      if (!live.tls) {
        point(address);
      } else {
        // on TLS the live view needs a token in its URL: the view token the gateway gives for the token entered,
        // never the API token itself (the link goes to app.foxglove.dev)
        let asked = 0;
        const update = async () => {
          const mine = ++asked;
          let view = "";
          if ($("token").value.trim()) {
            try { view = (await (await api("GET", "/live")).json()).view_token || ""; } catch (e) { view = ""; }
          }
          if (mine !== asked) return; // a later keystroke asked again
          point(view ? `${address}/?token=${encodeURIComponent(view)}` : `${address}/?token=TOKEN`);
          link.title = view ? address : "enter your API token above: the link then carries its view token";
        };
        await update();
        $("token").addEventListener("change", update);
        $("token").addEventListener("input", update);
      }
      link.classList.remove("hidden");
    }
  } catch (e) { /* no live view */ }
}

$("start-form").addEventListener("submit", startSession);
$("map-name").addEventListener("change", showMapName);
showLiveLink();
refresh();
refreshMaps();
setInterval(refresh, 1000);
setInterval(refreshMaps, 5000);
