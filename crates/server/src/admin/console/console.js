// The Myriad web console: polls the admin API once a second and draws what it says.
// Plain JavaScript shipped inside the server binary (no build step, nothing from
// elsewhere). Every value from the server reaches the page through textContent or the
// canvas, never as HTML, so an account name cannot inject markup.
"use strict";

const TOKEN_KEY = "myriad-admin-token";
const PERIOD_MS = 1000;
const HISTORY = 60; // one-second samples in the stage chart
const MAP_CELLS = 64;
const COLORS = {
  background: "#10151d",
  world: "#1a2230",
  npc: [64, 150, 255], // shaded by density
  player: "#ffd23f",
  playerEdge: "#1a1200",
  cut: "#ff4d4d",
  grid: "#2c3646",
  text: "#9aa7b8",
  budget: "#ff9f43",
};
const STAGE_COLORS = ["#4e9af1", "#f1a34e", "#5cc97b", "#d96ad9", "#e8d44d", "#4fd1c5",
  "#f16e6e", "#9b8cf2", "#b0b8c4", "#8bc34a", "#ff8a65", "#90a4ae"];

const $ = (id) => document.getElementById(id);
const state = {
  token: null,
  timer: null,
  stageNames: [], // in order of first appearance, so a stage keeps its colour
  history: [], // [{stages: {name: ms}, budget: ms}]
  rows: new Map(), // account -> <tr>
  map: null,
};

class AuthError extends Error {}

// Takes the token from the fragment (`#token=…`, never sent to the server) into this
// tab's sessionStorage and drops the fragment from the address bar and history.
function readToken() {
  const fragment = new URLSearchParams(location.hash.slice(1));
  const given = fragment.get("token");
  if (given) {
    sessionStorage.setItem(TOKEN_KEY, given.trim());
    history.replaceState(null, "", location.pathname + location.search);
  }
  return sessionStorage.getItem(TOKEN_KEY);
}

// One API call; the token travels only in the Authorization header.
async function api(method, path, body) {
  // The audit names the console as the actor ("token:console").
  const headers = { Authorization: "Bearer " + state.token, "X-Myriad-Actor": "console" };
  const init = { method, cache: "no-store", headers };
  if (body !== undefined) {
    headers["Content-Type"] = "application/json";
    init.body = JSON.stringify(body);
  }
  let response;
  try {
    response = await fetch(path, init);
  } catch (e) {
    throw new Error("the server does not answer (" + e.message + ")");
  }
  if (response.status === 401) throw new AuthError("the server refused the token");
  const text = await response.text();
  let json = null;
  try {
    json = text ? JSON.parse(text) : null;
  } catch (_) {
    // Not JSON (a proxy's error page): reported below with the status.
  }
  if (!response.ok) {
    const why = json && json.error ? json.error : text.slice(0, 200);
    throw new Error(method + " " + path + ": " + response.status + " " + why);
  }
  return json;
}

function showError(message) {
  $("error").textContent = message;
  $("error").hidden = !message;
}

let noticeTimer = null;
function showNotice(message) {
  $("notice").textContent = message;
  $("notice").hidden = false;
  clearTimeout(noticeTimer);
  noticeTimer = setTimeout(() => { $("notice").hidden = true; }, 8000);
}

function askForToken(message) {
  stopPolling();
  showError(message);
  $("token-form").hidden = false;
  $("token-input").focus();
}

function stopPolling() {
  clearTimeout(state.timer);
  state.timer = null;
}

// One refresh; the next is scheduled when this one ends, so slow answers never pile up.
async function poll() {
  state.timer = null;
  try {
    const [st, map, players] = await Promise.all([
      api("GET", "/api/state"),
      api("GET", "/api/map?cells=" + MAP_CELLS),
      api("GET", "/api/players"),
    ]);
    showError("");
    renderState(st);
    state.map = map;
    drawMap($("map"), map);
    pushStages(st);
    drawStages($("stages"));
    renderPlayers(players);
  } catch (e) {
    if (e instanceof AuthError) {
      askForToken("The server refused the token (401): enter the admin token.");
      return;
    }
    showError(e.message);
  }
  state.timer = setTimeout(poll, PERIOD_MS);
}

function renderState(st) {
  $("version").textContent = st.version;
  $("role").textContent = st.role;
  $("backend").textContent = st.backend;
  $("tick").textContent = String(st.tick);
  $("tick-hz").textContent = st.tick_hz.toFixed(0) + " Hz";
  $("tick-ms").textContent = st.tick_ms.toFixed(2) + " ms";
  $("player-count").textContent = String(st.players);
  $("dilation").textContent = st.dilation.toFixed(2) + "×";
  $("dilation").classList.toggle("slow", st.dilation < 0.999);
  $("uptime").textContent = formatDuration(st.uptime_s);
}

function formatDuration(s) {
  const h = Math.floor(s / 3600), m = Math.floor((s % 3600) / 60), sec = Math.floor(s % 60);
  return (h ? h + "h " : "") + (h || m ? m + "m " : "") + sec + "s";
}

// The world seen from above, north (+z) up: NPC density as shaded cells, zone cuts as
// lines, players as dots.
function drawMap(canvas, map) {
  const ctx = canvas.getContext("2d");
  const W = canvas.width, H = canvas.height;
  ctx.fillStyle = COLORS.background;
  ctx.fillRect(0, 0, W, H);
  const b = map.bounds;
  const w = b.max_x - b.min_x, h = b.max_z - b.min_z;
  if (!(w > 0 && h > 0)) return;
  const scale = Math.min((W - 2) / w, (H - 2) / h);
  const ox = (W - w * scale) / 2, oy = (H - h * scale) / 2;
  const px = (x) => ox + (x - b.min_x) * scale;
  const pz = (z) => oy + (b.max_z - z) * scale;
  ctx.fillStyle = COLORS.world;
  ctx.fillRect(ox, oy, w * scale, h * scale);

  const n = map.cells, density = map.npc_density;
  let max = 0;
  for (const d of density) max = Math.max(max, d);
  const cw = (w * scale) / n, ch = (h * scale) / n;
  const [r, g, bl] = COLORS.npc;
  for (let row = 0; row < n; row++) {
    for (let col = 0; col < n; col++) {
      const d = density[row * n + col];
      if (!d) continue;
      // Square root: a few NPCs stay visible beside a crowd.
      const a = 0.15 + 0.85 * Math.sqrt(d / max);
      ctx.fillStyle = `rgba(${r},${g},${bl},${a.toFixed(3)})`;
      // Row 0 is the lowest z, drawn at the bottom.
      ctx.fillRect(ox + col * cw, oy + (n - 1 - row) * ch, Math.ceil(cw), Math.ceil(ch));
    }
  }

  if (map.cuts) {
    ctx.strokeStyle = COLORS.cut;
    ctx.lineWidth = 2;
    ctx.setLineDash([6, 4]);
    ctx.beginPath();
    // The inner cuts: the first and last of each list are the world's edges.
    for (const x of map.cuts.xs.slice(1, -1)) { ctx.moveTo(px(x), oy); ctx.lineTo(px(x), oy + h * scale); }
    for (const z of map.cuts.zs.slice(1, -1)) { ctx.moveTo(ox, pz(z)); ctx.lineTo(ox + w * scale, pz(z)); }
    ctx.stroke();
    ctx.setLineDash([]);
  }

  ctx.fillStyle = COLORS.player;
  ctx.strokeStyle = COLORS.playerEdge;
  ctx.lineWidth = 1;
  for (const p of map.players) {
    if (p.x == null || p.z == null) continue; // a player whose object is missing
    ctx.beginPath();
    ctx.arc(px(p.x), pz(p.z), 4, 0, 2 * Math.PI);
    ctx.fill();
    ctx.stroke();
  }
  $("map-caption").textContent =
    `x ${b.min_x.toFixed(0)}…${b.max_x.toFixed(0)}, z ${b.min_z.toFixed(0)}…${b.max_z.toFixed(0)}` +
    ` · ${map.players.length} players` +
    (map.cuts ? ` · zone cuts since the zones' tick ${map.cuts.since_tick}` : "");
}

// The player under the pointer, as the canvas's tooltip.
function mapTooltip(event) {
  const canvas = $("map"), map = state.map;
  if (!map) return;
  const rect = canvas.getBoundingClientRect();
  const mx = (event.clientX - rect.left) * (canvas.width / rect.width);
  const my = (event.clientY - rect.top) * (canvas.height / rect.height);
  const b = map.bounds, w = b.max_x - b.min_x, h = b.max_z - b.min_z;
  const scale = Math.min((canvas.width - 2) / w, (canvas.height - 2) / h);
  const ox = (canvas.width - w * scale) / 2, oy = (canvas.height - h * scale) / 2;
  let best = null, bestD = 64; // squared pixels
  for (const p of map.players) {
    if (p.x == null || p.z == null) continue;
    const dx = ox + (p.x - b.min_x) * scale - mx, dz = oy + (b.max_z - p.z) * scale - my;
    const d = dx * dx + dz * dz;
    if (d < bestD) { best = p; bestD = d; }
  }
  canvas.title = best ? `${best.account} (${best.x.toFixed(1)}, ${best.z.toFixed(1)})` : "";
}

function pushStages(st) {
  for (const name of Object.keys(st.stages_ms)) {
    if (!state.stageNames.includes(name)) state.stageNames.push(name);
  }
  const rate = st.tick_rate || st.tick_hz; // the configured rate when the server gives it
  state.history.push({ stages: st.stages_ms, budget: rate > 0 ? 1000 / rate : 0 });
  if (state.history.length > HISTORY) state.history.shift();
}

// A stacked area chart of the stage times, newest on the right, with the tick's budget
// (1 / tick rate) as a dashed line when it fits.
function drawStages(canvas) {
  const ctx = canvas.getContext("2d");
  const W = canvas.width, H = canvas.height, left = 44, bottom = 18, top = 6;
  const plotW = W - left - 4, plotH = H - top - bottom;
  ctx.fillStyle = COLORS.background;
  ctx.fillRect(0, 0, W, H);
  const names = state.stageNames, hist = state.history;
  const totals = hist.map((s) => names.reduce((sum, n) => sum + (s.stages[n] || 0), 0));
  const peak = Math.max(0.1, ...totals);
  const yMax = niceCeiling(peak * 1.1);
  const y = (v) => top + plotH - (v / yMax) * plotH;
  const x = (i) => left + (plotW * (HISTORY - hist.length + i)) / (HISTORY - 1);

  ctx.strokeStyle = COLORS.grid;
  ctx.fillStyle = COLORS.text;
  ctx.font = "11px sans-serif";
  ctx.lineWidth = 1;
  for (let k = 0; k <= 4; k++) {
    const v = (yMax * k) / 4;
    ctx.beginPath();
    ctx.moveTo(left, y(v));
    ctx.lineTo(W - 4, y(v));
    ctx.stroke();
    ctx.fillText(String(Number(v.toFixed(2))), 2, y(v) + 4);
  }
  ctx.fillText("−60 s", left, H - 4);
  ctx.fillText("now", W - 28, H - 4);

  // Stacked areas: each stage from the running sum of those below it.
  const base = hist.map(() => 0);
  names.forEach((name, k) => {
    const topLine = hist.map((s, i) => base[i] + (s.stages[name] || 0));
    ctx.fillStyle = STAGE_COLORS[k % STAGE_COLORS.length];
    ctx.beginPath();
    hist.forEach((_, i) => (i ? ctx.lineTo(x(i), y(topLine[i])) : ctx.moveTo(x(i), y(topLine[i]))));
    for (let i = hist.length - 1; i >= 0; i--) ctx.lineTo(x(i), y(base[i]));
    ctx.closePath();
    ctx.fill();
    topLine.forEach((v, i) => { base[i] = v; });
  });

  const budget = hist.length ? hist[hist.length - 1].budget : 0;
  if (budget > 0 && budget <= yMax) {
    ctx.strokeStyle = COLORS.budget;
    ctx.setLineDash([4, 3]);
    ctx.beginPath();
    ctx.moveTo(left, y(budget));
    ctx.lineTo(W - 4, y(budget));
    ctx.stroke();
    ctx.setLineDash([]);
  }
  renderStageLegend(names, hist.length ? hist[hist.length - 1].stages : {});
}

function niceCeiling(v) {
  const p = Math.pow(10, Math.floor(Math.log10(v)));
  for (const m of [1, 2, 2.5, 5, 10]) if (v <= m * p) return m * p;
  return 10 * p;
}

function renderStageLegend(names, last) {
  const list = $("stage-legend");
  list.replaceChildren(...names.map((name, k) => {
    const li = document.createElement("li");
    li.dataset.stage = name;
    const swatch = document.createElement("span");
    swatch.className = "swatch";
    swatch.style.background = STAGE_COLORS[k % STAGE_COLORS.length];
    li.append(swatch, `${name} ${(last[name] || 0).toFixed(2)}`);
    return li;
  }));
}

// Updates the players table in place, keyed by account, so a button under the pointer
// survives the refresh.
function renderPlayers(players) {
  const tbody = $("players").tBodies[0];
  const seen = new Set();
  players.sort((a, b) => a.account.localeCompare(b.account, undefined, { numeric: true }));
  for (const p of players) {
    seen.add(p.account);
    let tr = state.rows.get(p.account);
    if (!tr) {
      tr = newRow(p.account);
      state.rows.set(p.account, tr);
    }
    const cells = tr.cells; // 0: account, 1: the buttons
    cells[2].textContent = String(p.user_id);
    cells[3].textContent = String(p.entity);
    cells[4].textContent = p.addr || "–"; // null until the player's first datagram
    cells[5].textContent = new Date(p.connected_since).toLocaleTimeString([], { hour12: false });
    cells[5].title = p.connected_since;
    cells[6].textContent = p.position.map((v) => (v == null ? "–" : v.toFixed(1))).join(", ");
    cells[7].textContent = (p.bytes_per_s / 1000).toFixed(1);
    tbody.append(tr); // moves it into sorted order
  }
  for (const [account, tr] of state.rows) {
    if (!seen.has(account)) {
      tr.remove();
      state.rows.delete(account);
    }
  }
  $("players-caption").textContent = `(${players.length})`;
}

function newRow(account) {
  const tr = document.createElement("tr");
  tr.dataset.account = account;
  for (let i = 0; i < 8; i++) tr.append(document.createElement("td"));
  tr.cells[0].textContent = account;
  const kick = button("Kick", "kick", account, () => kickPlayer(account, kick));
  const ban = button("Ban…", "ban", account, () => openBan(account));
  tr.cells[1].append(kick, ban);
  return tr;
}

function button(label, cls, account, onClick) {
  const b = document.createElement("button");
  b.type = "button";
  b.className = cls;
  b.dataset.account = account;
  b.textContent = label;
  b.addEventListener("click", onClick);
  return b;
}

async function kickPlayer(account, btn) {
  btn.disabled = true;
  try {
    await api("POST", `/api/players/${encodeURIComponent(account)}/kick`, { reason: "kicked from the web console" });
    showNotice(`Kicked ${account}.`);
  } catch (e) {
    if (e instanceof AuthError) askForToken("The server refused the token (401): enter the admin token.");
    else showError(`Kick ${account}: ${e.message}`);
  } finally {
    btn.disabled = false;
  }
}

function openBan(account) {
  $("ban-account").textContent = account;
  $("ban-dialog").dataset.account = account;
  $("ban-reason").value = "";
  $("ban-until").value = "";
  $("ban-dialog").showModal();
  $("ban-reason").focus();
}

async function submitBan(event) {
  event.preventDefault();
  const dialog = $("ban-dialog"), account = dialog.dataset.account;
  const reason = $("ban-reason").value.trim();
  if (!reason) { $("ban-reason").reportValidity(); return; }
  let until = null;
  if ($("ban-until").value) {
    const at = new Date($("ban-until").value); // local time, as the picker shows it
    if (Number.isNaN(at.getTime()) || at <= new Date()) {
      showError("The ban's end must be a time in the future.");
      return;
    }
    until = at.toISOString().replace(/\.\d{3}Z$/, "Z");
  }
  dialog.close();
  try {
    const reply = await api("POST", `/api/accounts/${encodeURIComponent(account)}/ban`, { reason, until });
    showNotice(`Banned ${account}` + (until ? ` until ${until}` : "") + (reply && reply.kicked ? " and kicked it." : "."));
  } catch (e) {
    if (e instanceof AuthError) askForToken("The server refused the token (401): enter the admin token.");
    else showError(`Ban ${account}: ${e.message}`);
  }
}

function start() {
  state.token = readToken();
  $("map").addEventListener("mousemove", mapTooltip);
  $("ban-form").addEventListener("submit", submitBan);
  $("ban-cancel").addEventListener("click", () => $("ban-dialog").close());
  $("token-form").addEventListener("submit", (event) => {
    event.preventDefault();
    const token = $("token-input").value.trim();
    if (!token) return;
    sessionStorage.setItem(TOKEN_KEY, token);
    state.token = token;
    $("token-input").value = "";
    $("token-form").hidden = true;
    showError("");
    stopPolling();
    poll();
  });
  $("forget-token").addEventListener("click", () => {
    sessionStorage.removeItem(TOKEN_KEY);
    state.token = null;
    askForToken("Token forgotten: enter the admin token to go on.");
  });
  if (state.token) poll();
  else askForToken("Enter the admin token (data/admin.token), or open the address `myriad admin console-url` prints.");
}

document.addEventListener("DOMContentLoaded", start);
