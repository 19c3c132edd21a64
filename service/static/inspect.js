// hmpf inspection page: every data call sends the key the user typed (header X-API-Key,
// kept in sessionStorage). No framework, no build step.
"use strict";
const $ = (id) => document.getElementById(id);
const state = { refs: null, thumbs: new Map(), tracks: new Map(), history: [], file: null };
const HISTORY = 50;

function key() { return sessionStorage.getItem("hmpf-key") || ""; }

function showError(msg) { const e = $("error"); e.textContent = msg; e.hidden = !msg; }

async function api(path, init = {}) {
  const headers = Object.assign({ "X-API-Key": key() }, init.headers || {});
  const r = await fetch(path, Object.assign({}, init, { headers }));
  if (!r.ok) {
    let msg = `${r.status} ${r.statusText}`;
    try { const b = await r.json(); if (b.error) msg = `${r.status} ${b.error.code}: ${b.error.message}`; } catch (_) { /* not JSON */ }
    const err = new Error(msg); err.status = r.status; throw err;
  }
  return r;
}

async function useKey(k) {
  sessionStorage.setItem("hmpf-key", k);
  state.thumbs.clear();
  try {
    const info = await (await api("/v1/index")).json();
    state.refs = await (await api("/v1/references")).json();
    $("index-info").textContent = `index ${info.version}: ${info.references} references` +
      (state.refs.thumbnails ? "" : " (no thumbnails)") + (info.has_positions ? ", positions" : "");
    $("go").disabled = false;
    showError("");
  } catch (e) {
    $("go").disabled = true;
    $("index-info").textContent = "";
    showError(`Key refused or service unavailable: ${e.message}`);
  }
}

// A reference thumbnail as an <img> (or a placeholder when the index has none).
async function thumb(ref) {
  if (!state.thumbs.has(ref)) {
    state.thumbs.set(ref, api(`/v1/references/${encodeURIComponent(ref)}/thumbnail`)
      .then(async (r) => URL.createObjectURL(await r.blob())).catch(() => null));
  }
  return state.thumbs.get(ref);
}

async function setThumb(img, ref) {
  const url = await thumb(ref);
  if (url) { img.src = url; img.classList.remove("placeholder"); }
  else { img.removeAttribute("src"); img.alt = "no thumbnail"; img.classList.add("placeholder"); }
}

function field(dl, name, value, cls) {
  const dt = document.createElement("dt"); dt.textContent = name;
  const dd = document.createElement("dd"); dd.textContent = value; if (cls) dd.className = cls;
  dl.append(dt, dd);
}

const fmt = (x, d = 3) => (x === null || x === undefined ? "—" : Number(x).toFixed(d));

function showAnswer(a) {
  const dl = $("answer-fields"); dl.replaceChildren();
  const m = a.match;
  if (!m) { field(dl, "match", "none (the GPS prior left no reference)", "no"); }
  else {
    field(dl, "match", `${m.name} (#${m.reference_id})`);
    field(dl, "accepted", m.accepted ? "yes" : "no", m.accepted ? "yes" : "no");
    field(dl, "decided by", m.accepted_by);
    field(dl, "p_correct", fmt(m.p_correct));
    field(dl, "score (z)", fmt(m.score, 2));
    field(dl, "confidence", fmt(m.confidence));
    field(dl, "from", a.match_source);
    if (m.lat !== null && m.lon !== null) field(dl, "position", `${fmt(m.lat, 6)}, ${fmt(m.lon, 6)}`);
  }
  if (a.sequence) {
    const s = a.sequence;
    field(dl, "sequence", `${s.status}, ${s.frames} frames, mass ${fmt(s.mass, 2)}, ${s.off_map ? "off the map" : s.locked ? "accepted" : "not accepted"}`);
  }
  if (a.prior) field(dl, "prior", a.prior.applied ? `${a.prior.references} references within ${a.prior.radius_m} m` : a.prior.reason);
  field(dl, "index", a.index_version);
  field(dl, "time", `${fmt(a.timing_ms.total, 0)} ms`);
  $("match-caption").textContent = m ? `reference ${m.name}` : "no match";
  if (m) setThumb($("match-thumb"), m.name); else $("match-thumb").removeAttribute("src");
}

function bar(label, v) {
  const row = document.createElement("div"); row.className = "bar";
  const name = document.createElement("span"); name.textContent = label;
  const track = document.createElement("span"); const fill = document.createElement("i");
  fill.style.width = `${Math.max(0, Math.min(1, v || 0)) * 100}%`; track.append(fill);
  const num = document.createElement("span"); num.textContent = fmt(v, 2);
  row.append(name, track, num); return row;
}

function showTiers(a) {
  const root = $("tiers"); root.replaceChildren();
  const best = a.match ? a.match.reference_id : -1;
  const lists = a.tiers.map((t) => ({ title: `Tier ${t.tier}: ${t.methods.join(" + ")} (k ${t.k}, over ${t.inputs} references, ${fmt(t.time_ms, 0)} ms)`, cands: t.candidates }));
  lists.push({ title: "Final ranking (Combined score)", cands: a.candidates.map((c) => Object.assign({}, c, { scores: { combined: null } })), combined: true });
  for (const list of lists) {
    const div = document.createElement("div"); div.className = "tier";
    const h = document.createElement("h3"); h.textContent = list.title; div.append(h);
    const row = document.createElement("div"); row.className = "cands";
    for (const c of list.cands) {
      const card = document.createElement("div"); card.className = "cand" + (c.reference_id === best ? " match" : "");
      const img = document.createElement("img"); img.alt = c.name; setThumb(img, c.name);
      const cap = document.createElement("div"); cap.textContent = `${c.name} (#${c.reference_id})`;
      card.append(img, cap);
      if (list.combined) { const z = document.createElement("div"); z.textContent = `z ${fmt(c.score, 2)}`; card.append(z); }
      else for (const [mid, v] of Object.entries(c.scores || {})) card.append(bar(mid, v));
      row.append(card);
    }
    div.append(row); root.append(div);
  }
}

const SVG = "http://www.w3.org/2000/svg";
function svg(w, h) { const s = document.createElementNS(SVG, "svg"); s.setAttribute("width", w); s.setAttribute("height", h); s.setAttribute("viewBox", `0 0 ${w} ${h}`); return s; }
function dot(s, x, y, r, fill, extra = {}) {
  const c = document.createElementNS(SVG, "circle");
  Object.entries(Object.assign({ cx: x, cy: y, r, fill }, extra)).forEach(([k, v]) => c.setAttribute(k, v));
  s.append(c); return c;
}

// The references as points (equirectangular, no map tiles), candidates and answer marked.
function plotPositions(a) {
  const refs = state.refs; const fig = $("positions-fig");
  if (!refs || !refs.lat) { fig.hidden = true; return; }
  const pts = refs.lat.map((la, i) => [la, refs.lon[i]]).filter(([la, lo]) => la !== null && lo !== null);
  if (!pts.length) { fig.hidden = true; return; }
  const W = 360, H = 300, P = 12;
  const lats = pts.map((p) => p[0]), lons = pts.map((p) => p[1]);
  const k = Math.cos((Math.min(...lats) + Math.max(...lats)) / 2 * Math.PI / 180);
  const x0 = Math.min(...lons) * k, y0 = Math.max(...lats);
  const span = Math.max((Math.max(...lons) - Math.min(...lons)) * k, Math.max(...lats) - Math.min(...lats), 1e-9);
  const sc = Math.min(W, H) - 2 * P;
  const xy = (la, lo) => [P + (lo * k - x0) / span * sc, P + (y0 - la) / span * sc];
  const s = svg(W, H);
  refs.lat.forEach((la, i) => { if (la !== null && refs.lon[i] !== null) dot(s, ...xy(la, refs.lon[i]), 1.6, "#aaa"); });
  const mark = (id, r, fill) => { const la = refs.lat[id], lo = refs.lon[id]; if (la !== null && lo !== null) dot(s, ...xy(la, lo), r, fill, { "data-ref": id }); };
  for (const t of a.tiers) for (const c of t.candidates) mark(c.reference_id, 3.5, "#f39c12");
  if (a.match) mark(a.match.reference_id, 6, "#d33");
  if (a.prior) {
    const [cx, cy] = xy(a.prior.lat, a.prior.lon);
    dot(s, cx, cy, a.prior.radius_m / 111320 / span * sc, "none", { stroke: "#333", "stroke-dasharray": "4 3" });
  }
  $("plot-positions").replaceChildren(s); fig.hidden = false;
}

// Sequence mode: the estimate (reference id, mass) and the single-frame match per frame.
function plotBelief() {
  const h = state.history; const fig = $("belief-fig");
  if (!h.length) { fig.hidden = true; return; }
  const W = 360, H = 300, P = 24;
  const ids = h.flatMap((f) => [f.estimate, f.single]).filter((v) => v !== null);
  const lo = Math.min(...ids), hi = Math.max(...ids, lo + 1);
  const x = (i) => P + (h.length === 1 ? 0.5 : i / (h.length - 1)) * (W - 2 * P);
  const y = (v) => H - P - (v - lo) / (hi - lo) * (H - 2 * P);
  const s = svg(W, H);
  const path = h.map((f, i) => (f.estimate === null ? null : `${x(i)},${y(f.estimate)}`)).filter(Boolean);
  if (path.length > 1) { const l = document.createElementNS(SVG, "polyline"); l.setAttribute("points", path.join(" ")); l.setAttribute("fill", "none"); l.setAttribute("stroke", "#4a7bd0"); s.append(l); }
  h.forEach((f, i) => {
    if (f.single !== null) dot(s, x(i), y(f.single), 2.5, "#999");
    if (f.estimate !== null) dot(s, x(i), y(f.estimate), 4, "#4a7bd0", { "fill-opacity": 0.2 + 0.8 * f.mass });
  });
  const t = document.createElementNS(SVG, "text"); t.setAttribute("x", 4); t.setAttribute("y", 14); t.setAttribute("font-size", 11);
  t.textContent = `reference id ${lo}..${hi}, last ${h.length} frames`; s.append(t);
  $("plot-belief").replaceChildren(s); fig.hidden = false;
}

async function showEvidence(a) {
  const img = $("evidence"), cap = $("evidence-caption");
  img.removeAttribute("src"); cap.textContent = "";
  if (!a.match) return;
  const form = new FormData(); form.append("image", state.file);
  try {
    const r = await api(`/v1/evidence?reference=${encodeURIComponent(a.match.name)}`, { method: "POST", body: form });
    img.src = URL.createObjectURL(await r.blob());
    cap.textContent = `${r.headers.get("X-Hmpf-Evidence-Method")}: ${r.headers.get("X-Hmpf-Evidence-Pairs")} matched pairs, query left, ${a.match.name} right`;
  } catch (e) { cap.textContent = `no evidence image: ${e.message}`; }
}

async function localise() {
  if (!state.file) { showError("Pick or drop an image first."); return; }
  const form = new FormData(); form.append("image", state.file);
  const lat = $("lat").value, lon = $("lon").value, radius = $("radius").value;
  if (lat || lon || radius) { form.append("lat", lat); form.append("lon", lon); form.append("radius_m", radius); }
  form.append("top_k", $("topk").value || "5");
  const vehicle = $("vehicle").value.trim();
  if (vehicle) { form.append("vehicle_id", vehicle); if (state.tracks.has(vehicle)) form.append("track", state.tracks.get(vehicle)); }
  $("go").disabled = true;
  try {
    const a = await (await api("/v1/localize", { method: "POST", body: form })).json();
    showError("");
    if (state.refs && a.index_version !== state.refs.index_version) {  // reloaded: new data
      state.thumbs.clear();
      state.refs = await (await api("/v1/references")).json();
    }
    $("query-img").src = URL.createObjectURL(state.file);
    if (a.sequence) {
      state.tracks.set(vehicle, a.sequence.track);
      const est = a.sequence.match;
      state.history.push({ estimate: est ? est.reference_id : null, mass: a.sequence.mass, single: a.single ? a.single.reference_id : null });
      state.history = state.history.slice(-HISTORY);
    }
    showAnswer(a); showTiers(a); plotPositions(a); plotBelief();
    $("answer").hidden = false;
    await showEvidence(a);
    document.body.dataset.answered = String(Number(document.body.dataset.answered || 0) + 1);
  } catch (e) { showError(`Localisation failed: ${e.message}`); }
  finally { $("go").disabled = false; }
}

function pick(file) { if (file) { state.file = file; $("drop").firstChild.textContent = `${file.name} `; } }

$("key-form").addEventListener("submit", (ev) => { ev.preventDefault(); useKey($("key").value.trim()); });
$("query-form").addEventListener("submit", (ev) => { ev.preventDefault(); localise(); });
$("image").addEventListener("change", (ev) => pick(ev.target.files[0]));
const drop = $("drop");
drop.addEventListener("dragover", (ev) => { ev.preventDefault(); drop.classList.add("over"); });
drop.addEventListener("dragleave", () => drop.classList.remove("over"));
drop.addEventListener("drop", (ev) => { ev.preventDefault(); drop.classList.remove("over"); pick(ev.dataTransfer.files[0]); });
if (key()) { $("key").value = key(); useKey(key()); }
