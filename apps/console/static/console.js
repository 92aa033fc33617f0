// RayFronts console page: calls the console's own JSON API (docs/commands.md, rayfronts console).
// With a token the page was opened as /?token=TOKEN: the console set an HttpOnly cookie and
// redirected here, so every request below (assets, API calls, event streams) carries it.
"use strict";
const $ = (id) => document.getElementById(id);
let stream = null;

async function api(url, opts) {
  const r = await fetch(url, Object.assign({ credentials: "same-origin" }, opts || {}));
  const body = await r.json();
  if (!r.ok) throw new Error(body.error || ("HTTP " + r.status));
  return body;
}

function fmt(v) { return Array.isArray(v) ? v.map((x) => Number(x).toFixed(2)).join(", ") : String(v ?? ""); }
function cell(tr, text) { const td = document.createElement("td"); td.textContent = text; tr.appendChild(td); }
function rows(id, items, cols) {
  const tb = $(id);
  tb.replaceChildren();
  items.forEach((it, i) => { const tr = document.createElement("tr"); cols(it, i).forEach((c) => cell(tr, c)); tb.appendChild(tr); });
}
function status(text) { $("status").textContent = text || ""; }
// a reply's missing_shards as a warning after the status line (shards that did not answer)
function missing(r) { const m = r.missing_shards || []; return m.length ? ` — shards that did not answer: ${m.join(", ")}` : ""; }
function split(text) { return text.split(",").map((s) => s.trim()).filter((s) => s); }

function showSearch(r) {
  rows("instances", r.found || [], (f) => [f.id, f.target ?? "", Number(f.confidence ?? f.score ?? 0).toFixed(3), fmt(f.centroid)]);
  rows("goals", r.look_next || [], (g, i) => [i + 1, fmt(g.position), Number(g.score ?? 0).toFixed(3), Number(g.gain_m3 ?? 0).toFixed(1)]);
  status(`map v${r.map_version}, ${r.frames_mapped} frames mapped, ${(r.found || []).length} found` + missing(r));
}

// a fleet search's reply: the shared found list, the candidates, and each robot's goal (or its state)
function showFleet(r) {
  showSearch(Object.assign({}, r, { look_next: r.candidates }));
  rows("fleet_goals", Object.keys(r.goals || {}).sort(), (name) => {
    const g = r.goals[name];
    const st = (r.robots[name] || {}).state || "";
    return [name, st, g ? fmt(g.position) : "", g ? Number(g.distance_m).toFixed(1) : ""];
  });
  status(`map v${r.map_version}, ${r.frames_mapped} frames mapped, ${(r.found || []).length} found, ` +
         `${Object.values(r.goals || {}).filter((g) => g).length} robots assigned` + missing(r));
}

function showQuery(r) {
  const a = (r.cluster_xyz || []).map((p, i) => [i + 1, Number(r.cluster_score[i]).toFixed(3), "voxels " + fmt(p)]);
  const b = (r.ray_origin || []).map((p, i) => [a.length + i + 1, Number(r.ray_score[i]).toFixed(3), "ray " + fmt(p)]);
  rows("answers", a.concat(b), (x) => x);
  status(`query ${JSON.stringify(r.query)}: ${a.length} clusters, ${b.length} rays` + missing(r));
}

function searchParams() {
  const p = new URLSearchParams();
  split($("q").value || "vehicle").forEach((t) => p.append("q", t));
  split($("background").value).forEach((t) => p.append("background", t));
  p.set("threshold", $("threshold").value || "0.5");
  return p;
}

async function doSearch() {
  if (stream) { stream.close(); stream = null; }
  status("searching…");
  const fleet = $("fleet").value.trim();
  const params = searchParams();
  if (fleet) params.set("fleet", fleet);
  const [path, show] = fleet ? ["/api/fleet_search", showFleet] : ["/api/search", showSearch];
  if (!fleet) $("fleet_goals").replaceChildren();
  if ($("live").checked) {
    stream = new EventSource(path + "/stream?" + params);
    stream.addEventListener("update", (ev) => show(JSON.parse(ev.data)));
    stream.onerror = () => status("stream interrupted (retrying)");
    return;
  }
  try { show(await api(path + "?" + params)); } catch (e) { status(e.message); }
}

async function doQuery() {
  status("querying…");
  try { showQuery(await api("/api/query?q=" + encodeURIComponent($("q").value || "vehicle") + "&top_k=5")); }
  catch (e) { status(e.message); }
}

async function doImage() {
  const f = $("image").files[0];
  if (!f) return;
  const form = new FormData();
  form.append("image", f);
  form.append("top_k", "5");
  status("image query…");
  try { showQuery(await api("/api/query", { method: "POST", body: form })); } catch (e) { status(e.message); }
}

async function refreshRobots() {
  try {
    const st = await api("/api/stats");
    const items = [];
    for (const [shard, s] of Object.entries(st.shards)) {
      for (const [name, r] of Object.entries(s.robots || {})) {
        items.push([shard || "-", name, r.mapped, r.rate_hz == null ? "" : Number(r.rate_hz).toFixed(2), r.dropped,
                    r.edge_status || (r.present ? "present" : "gone"),
                    r.last_seen_s_ago == null ? "" : r.last_seen_s_ago + " s ago"]);
      }
    }
    rows("robots", items, (x) => x);
  } catch (e) { rows("robots", [["-", e.message, "", "", "", "", ""]], (x) => x); }
}

async function init() {
  $("search").addEventListener("click", doSearch);
  $("query").addEventListener("click", doQuery);
  $("image").addEventListener("change", doImage);
  $("q").addEventListener("keydown", (ev) => { if (ev.key === "Enter") doSearch(); });
  try {
    const cfg = await api("/api/config");
    if (cfg.viewer_url) {
      const fr = document.createElement("iframe");
      fr.src = cfg.viewer_url;
      fr.title = "rerun web viewer";
      $("viewer").replaceChildren(fr);
    }
  } catch (e) { status(e.message); }
  refreshRobots();
  setInterval(refreshRobots, 3000);
}
init();
