// TopoFusion operator picture: plain JavaScript, no library, nothing loaded from elsewhere.
//
// Data: server-sent events from picture/events (one JSON snapshot about every second; see
// service/api/picture.py for its fields: the cells of each row are named by its `columns`),
// the coastlines and borders from static/basemap.json (Natural Earth, made by
// lab/topofusion_lab/basemap.py), and each radar's performance from radars/{id}/performance
// (every 10 s at most; absent is shown as "-").
//
// Map: a local equirectangular projection around the mean of the radar sites (x east, y north,
// in km; distances are true near the centre, which is what a radar network's few hundred km
// need).  Three stacked layers: an SVG below (basemap, graticule, coverage), a canvas for
// everything there is one of per track (tracks, trails, links, system tracks, labels: a canvas
// stays fast with thousands, where a DOM node each would not), an SVG above (sites, bias
// arrows).  Wheel zooms about the pointer, drag pans, double-click fits the sites, a click
// selects the nearest track.
//
// The address reproduces the view (docs/picture.md lists the parameters): the filters (q,
// fl_min, fl_max, status, kind, radar), trail, hide (layers), sel (the selection), view
// (centre and scale); the page writes them back as they change.  Page options: range_km
// (coverage ring radius), leader_s (velocity leader, s), max_items (the feed's cap per kind).
"use strict";
(() => {
  const params = new URLSearchParams(window.location.search);
  const positive = (v, fallback) => {
    const x = Number(v);
    return v !== null && Number.isFinite(x) && x > 0 ? x : fallback;
  };
  const RANGE_KM = positive(params.get("range_km"), 250);
  const LEADER_S = positive(params.get("leader_s"), 60);
  // the feed's cap per kind: a whole number, at most the feed's largest (MAX_ITEMS_LIMIT of
  // service/api/picture.py); anything else is the feed's default (a value the feed refuses
  // would leave the page without a feed: a browser does not retry a refused one)
  const MAX_ITEMS_LIMIT = 20000;
  const MAX_ITEMS = (() => {
    const x = Number(params.get("max_items"));
    return params.has("max_items") && Number.isInteger(x) && x >= 1 ? Math.min(x, MAX_ITEMS_LIMIT) : null;
  })();
  const EARTH_KM = 6371.0088;
  const RAD = Math.PI / 180;
  const KNOT_MPS = 1852 / 3600;
  const PALETTE = ["#6ab0ff", "#7be0a8", "#ff9f6a", "#c79bff", "#5fd6e0", "#f2e06b", "#ff7aa8", "#a8c46a"];
  const SYSTEM_COLOUR = "#ffd54a";
  const LINK_COLOUR = "#9fb8c4";
  const TRAIL_COLOUR = "#e8dcb0"; // paler than the system tracks' yellow: where they were
  const SELECTED_COLOUR = "#ffffff";
  const LABEL_FONT = 'bold 11px system-ui, "DejaVu Sans", sans-serif';
  const LABEL_H = 12;
  const GRATICULE_STEPS = [0.05, 0.1, 0.25, 0.5, 1, 2, 5, 10, 20];
  const BIAS_SCALES = [1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000];
  const BIAS_MAX_PX = 90;
  const STALE_S = 5;
  const DEFAULT_TRAIL = 10;
  const MAX_TRAIL = 100;
  const PERF_EVERY_MS = 10000; // the performance route is asked at most this often per radar
  const LIST_MAX = 100; // rows of the system track list (the map shows them all)
  const HIT_PX = 9; // a click selects a track this close at most
  const CLICK_PX = 4; // a press that moves further is a drag, not a click
  const STATUSES = ["confirmed", "tentative", "all"];
  const KINDS = ["all", "paired", "unpaired"];
  const LAYERS = ["basemap", "coverage", "tracks", "trails", "links", "system", "labels", "biases"];

  const $ = (id) => document.getElementById(id);
  const wrap = $("map-wrap");
  const canvas = $("tracks-canvas");
  const ctx = canvas.getContext("2d");
  const layer = {
    graticule: $("layer-graticule"),
    coverage: $("layer-coverage"),
    sites: $("layer-sites"),
    biases: $("layer-biases"),
    land: $("basemap-land"),
    borders: $("basemap-borders"),
  };

  // -- the address: filters, layers, selection, view ----------------------------------------
  function number(v) {
    if (v === null || v === undefined || String(v).trim() === "") return null;
    const x = Number(v);
    return Number.isFinite(x) ? x : null;
  }

  function readFilters(p) {
    const radar = p.get("radar");
    return {
      q: (p.get("q") || "").trim(),
      fl_min: number(p.get("fl_min")),
      fl_max: number(p.get("fl_max")),
      status: STATUSES.includes(p.get("status")) ? p.get("status") : "confirmed",
      kind: KINDS.includes(p.get("kind")) ? p.get("kind") : "all",
      radars: radar ? new Set(radar.split(",").filter(Boolean)) : null,
      trail: Math.min(MAX_TRAIL, Math.max(0, Math.round(number(p.get("trail")) ?? DEFAULT_TRAIL))),
    };
  }

  /** `sel=T-17` (a system track) or `sel=A/A-9` (radar A's track A-9). */
  function readSelection(v) {
    if (!v) return null;
    const at = v.indexOf("/");
    return at < 0 ? { kind: "system", id: v } : { kind: "track", radar: v.slice(0, at), id: v.slice(at + 1) };
  }

  const selectionKey = (s) => (s.kind === "system" ? s.id : `${s.radar}/${s.id}`);

  const filters = readFilters(params);
  const hidden = new Set((params.get("hide") || "").split(","));
  const show = Object.fromEntries(LAYERS.map((k) => [k, !hidden.has(k)]));

  const state = {
    data: null,
    ix: null, // the latest snapshot's indexes (index())
    visible: null, // what passes the filters (applyFilters())
    centre: null, // [lat0, lon0] of the projection
    siteKey: "",
    radarKey: "",
    view: null, // {cx, cy} world km at the middle of the map, scale px/km
    viewParam: params.get("view"), // the address's view, taken once the projection is known
    userView: Boolean(params.get("view")), // written to the address once the user moved the map
    selection: readSelection(params.get("sel")),
    colours: {},
    updates: 0,
    lastEvent: 0,
    pending: false,
    drawn: { system: [], tracks: [], highlighted: [] },
    source: null,
    feedStatus: null,
  };
  // the last `trail` positions of each track in the latest snapshot, [lat, lon, lat, lon, ...]
  const trails = new Map();
  const perf = {}; // radar -> {at, busy, body}: the performance route's latest answer
  const basemap = { land: [], borders: [] };

  function writeAddress() {
    const p = new URLSearchParams(window.location.search);
    const put = (k, v, fallback) => (v === null || v === "" || v === fallback ? p.delete(k) : p.set(k, String(v)));
    put("q", filters.q, "");
    put("fl_min", filters.fl_min, null);
    put("fl_max", filters.fl_max, null);
    put("status", filters.status, "confirmed");
    put("kind", filters.kind, "all");
    put("radar", filters.radars ? [...filters.radars].sort().join(",") : null, null);
    put("trail", filters.trail, DEFAULT_TRAIL);
    put("hide", LAYERS.filter((k) => !show[k]).join(","), "");
    put("sel", state.selection ? selectionKey(state.selection) : null, null);
    // (the address's own view until the first snapshot has let the page take it)
    put("view", state.userView && state.view && state.centre ? viewText() : state.viewParam, null);
    // commas and slashes read better unescaped, and are valid in a query
    const q = p.toString().replace(/%2C/gi, ",").replace(/%2F/gi, "/");
    const url = window.location.pathname + (q ? "?" + q : "") + window.location.hash;
    if (url !== window.location.pathname + window.location.search + window.location.hash) {
      window.history.replaceState(null, "", url);
    }
  }

  function viewText() {
    const [lat, lon] = unproject(state.view.cx, state.view.cy);
    return `${lat.toFixed(4)},${lon.toFixed(4)},${Number(state.view.scale.toPrecision(4))}`;
  }

  function takeViewParam() {
    const v = (state.viewParam || "").split(",").map(Number);
    state.viewParam = null;
    if (v.length !== 3 || !v.every(Number.isFinite) || v[2] <= 0) return false;
    const [cx, cy] = project(v[0], v[1]);
    state.view = { cx, cy, scale: Math.min(2000, Math.max(0.01, v[2])) };
    schedule();
    return true;
  }

  // -- helpers -----------------------------------------------------------------------------
  const DASH = "\u2013";
  const esc = (s) =>
    String(s).replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[c]);
  const f = (x, digits = 0) => (Number.isFinite(x) ? x.toFixed(digits) : DASH);
  const signed = (x, digits) => (x >= 0 ? "+" : "\u2212") + Math.abs(x).toFixed(digits);
  const text = (v) => (v === null || v === undefined ? DASH : esc(v));
  const flText = (fl) => (Number.isFinite(fl) ? String(Math.round(fl)).padStart(3, "0") : DASH);
  const pct = (x, digits = 1) => (Number.isFinite(x) ? (100 * x).toFixed(digits) + " %" : DASH);

  function duration(s) {
    if (!Number.isFinite(s)) return DASH;
    const a = Math.abs(s);
    const sign = s < 0 ? "\u2212" : "";
    if (a < 100) return sign + a.toFixed(1) + " s";
    if (a < 2 * 3600) return sign + (a / 60).toFixed(1) + " min";
    if (a < 2 * 86400) return sign + (a / 3600).toFixed(1) + " h";
    return sign + (a / 86400).toFixed(1) + " d";
  }

  function utc(t) {
    if (!Number.isFinite(t)) return DASH;
    return new Date(t * 1000).toISOString().replace("T", " ").replace(/\.\d+Z$/, "Z");
  }

  function motion(ve, vn) {
    if (!Number.isFinite(ve) || !Number.isFinite(vn)) return DASH;
    const heading = (Math.atan2(ve, vn) / RAD + 360) % 360;
    return `${f(Math.hypot(ve, vn) / KNOT_MPS)} kt, ${f(heading).padStart(3, "0")}\u00b0`;
  }

  function colour(radar) {
    if (!(radar in state.colours)) {
      state.colours[radar] = PALETTE[Object.keys(state.colours).length % PALETTE.length];
    }
    return state.colours[radar];
  }

  // -- projection ----------------------------------------------------------------------------
  function wrapLon(dlon) {
    if (dlon > 180) return dlon - 360;
    if (dlon < -180) return dlon + 360;
    return dlon;
  }

  function project(lat, lon) {
    const [lat0, lon0] = state.centre;
    return [EARTH_KM * wrapLon(lon - lon0) * RAD * Math.cos(lat0 * RAD), EARTH_KM * (lat - lat0) * RAD];
  }

  function unproject(x, y) {
    const [lat0, lon0] = state.centre;
    return [lat0 + y / (EARTH_KM * RAD), lon0 + x / (EARTH_KM * RAD * Math.cos(lat0 * RAD))];
  }

  // The map's size, asked of the layout once per task (a redraw projects thousands of points,
  // and a layout query each would cost more than the drawing).
  let sized = null;
  function size() {
    if (!sized) {
      const r = wrap.getBoundingClientRect();
      sized = [Math.max(r.width, 1), Math.max(r.height, 1)];
      queueMicrotask(() => {
        sized = null;
      });
    }
    return sized;
  }

  function screen(x, y) {
    const [w, h] = size();
    const v = state.view;
    return [w / 2 + (x - v.cx) * v.scale, h / 2 - (y - v.cy) * v.scale];
  }

  function world(sx, sy) {
    const [w, h] = size();
    const v = state.view;
    return [v.cx + (sx - w / 2) / v.scale, v.cy - (sy - h / 2) / v.scale];
  }

  const at = (lat, lon) => screen(...project(lat, lon));

  /** The latitudes and (unwrapped) longitudes the map shows: the projection is a plate carrée,
   * so its corners bound it. */
  function viewBounds() {
    const [w, h] = size();
    const corners = [world(0, 0), world(w, 0), world(0, h), world(w, h)].map(([x, y]) => unproject(x, y));
    const lats = corners.map((c) => c[0]);
    const lons = corners.map((c) => c[1]);
    return [Math.min(...lats), Math.max(...lats), Math.min(...lons), Math.max(...lons)];
  }

  /** The point `km` away from (lat, lon) on the great circle of bearing `deg`. */
  function destination(lat, lon, deg, km) {
    const d = km / EARTH_KM;
    const p1 = lat * RAD;
    const b = deg * RAD;
    const p2 = Math.asin(Math.sin(p1) * Math.cos(d) + Math.cos(p1) * Math.sin(d) * Math.cos(b));
    const l2 = lon * RAD + Math.atan2(Math.sin(b) * Math.sin(d) * Math.cos(p1), Math.cos(d) - Math.sin(p1) * Math.sin(p2));
    return [p2 / RAD, ((l2 / RAD + 540) % 360) - 180];
  }

  function setCentre(data) {
    const sites = data.sites;
    const S = state.ix.S;
    let pts = sites.map((s) => [s.latitude_deg, s.longitude_deg]);
    if (!pts.length) pts = data.system_tracks.map((t) => [t[S.lat], t[S.lon]]);
    if (!pts.length) return false;
    const key = sites.map((s) => `${s.radar_id}@${s.latitude_deg},${s.longitude_deg}`).join(";");
    if (state.centre && key === state.siteKey) return false;
    state.siteKey = key;
    const lat0 = pts.reduce((a, p) => a + p[0], 0) / pts.length;
    // mean longitude through unit vectors (a network across the antimeridian)
    const sx = pts.reduce((a, p) => a + Math.cos(p[1] * RAD), 0);
    const sy = pts.reduce((a, p) => a + Math.sin(p[1] * RAD), 0);
    state.centre = [lat0, Math.atan2(sy, sx) / RAD];
    return true;
  }

  function fit() {
    if (!state.centre || !state.data) return;
    const S = state.ix.S;
    const pts = state.data.sites.map((s) => project(s.latitude_deg, s.longitude_deg));
    const pad = pts.length ? RANGE_KM * 1.05 : 50;
    if (!pts.length) state.data.system_tracks.forEach((t) => pts.push(project(t[S.lat], t[S.lon])));
    if (!pts.length) pts.push([0, 0]);
    const xs = pts.map((p) => p[0]);
    const ys = pts.map((p) => p[1]);
    const x0 = Math.min(...xs) - pad;
    const x1 = Math.max(...xs) + pad;
    const y0 = Math.min(...ys) - pad;
    const y1 = Math.max(...ys) + pad;
    const [w, h] = size();
    state.view = { cx: (x0 + x1) / 2, cy: (y0 + y1) / 2, scale: Math.min(w / (x1 - x0), h / (y1 - y0)) };
    schedule();
  }

  // -- the snapshot: indexes, filters, trails ------------------------------------------------
  function columns(d, kind) {
    return Object.fromEntries(d.columns[kind].map((name, i) => [name, i]));
  }

  function index(d) {
    const S = columns(d, "system_tracks");
    const T = columns(d, "tracks");
    const L = columns(d, "links");
    const systemOf = new Map(); // "radar/track" -> its system track's row
    for (const row of d.system_tracks) for (const [r, t] of row[S.members]) systemOf.set(`${r}/${t}`, row);
    const trackRow = new Map(); // "radar/track" -> its row
    for (const [radar, rows] of Object.entries(d.tracks)) for (const row of rows) trackRow.set(`${radar}/${row[T.id]}`, row);
    const systemRow = new Map(d.system_tracks.map((row) => [row[S.id], row]));
    return { S, T, L, systemOf, trackRow, systemRow };
  }

  function applyFilters() {
    const d = state.data;
    if (!d) return;
    const { S, T, L, systemOf } = state.ix;
    const q = filters.q.toLowerCase();
    const has = (v) => v !== null && v !== undefined && String(v).toLowerCase().includes(q);
    const banded = filters.fl_min !== null || filters.fl_max !== null;
    const flOk = (fl) =>
      !banded ||
      (Number.isFinite(fl) && (filters.fl_min === null || fl >= filters.fl_min) && (filters.fl_max === null || fl <= filters.fl_max));
    const statusOk = (confirmed) => filters.status === "all" || (filters.status === "confirmed") === Boolean(confirmed);
    const kindOk = (paired) => filters.kind === "all" || (filters.kind === "paired") === paired;
    const system = d.system_tracks.filter((row) => {
      const members = row[S.members];
      return (
        statusOk(row[S.confirmed]) &&
        flOk(row[S.fl]) &&
        kindOk(members.length >= 2) &&
        (!filters.radars || members.some((m) => filters.radars.has(m[0]))) &&
        (!q || has(row[S.id]) || has(row[S.mode_s]) || has(row[S.mode_3a]) || members.some((m) => has(m[1])))
      );
    });
    const tracks = [];
    const trackKeys = new Set();
    for (const [radar, rows] of Object.entries(d.tracks)) {
      if (filters.radars && !filters.radars.has(radar)) continue;
      for (const row of rows) {
        const key = `${radar}/${row[T.id]}`;
        const sys = systemOf.get(key);
        if (!statusOk(row[T.confirmed]) || !flOk(row[T.fl]) || !kindOk(sys !== undefined && sys[S.members].length >= 2)) continue;
        if (q && !(has(row[T.id]) || has(row[T.mode_s]) || has(row[T.mode_3a]) || (sys && has(sys[S.id])))) continue;
        tracks.push([radar, row]);
        trackKeys.add(key);
      }
    }
    const linkStatusOk = (s) => filters.status === "all" || (s === "c") === (filters.status === "confirmed");
    const links = d.links.filter(
      (l) =>
        linkStatusOk(l[L.status]) &&
        (trackKeys.has(`${l[L.radar_a]}/${l[L.track_a]}`) || trackKeys.has(`${l[L.radar_b]}/${l[L.track_b]}`)),
    );
    state.visible = { system, tracks, links };
  }

  /** Each track's last `trail` positions (the current one included); tracks gone are forgotten,
   * so memory stays within (tracks in the snapshot) x trail. */
  function updateTrails(d) {
    const { S, T } = state.ix;
    const keep = 2 * filters.trail;
    const seen = new Set();
    const add = (key, lat, lon) => {
      seen.add(key);
      let t = trails.get(key);
      if (!t) trails.set(key, (t = []));
      const n = t.length;
      if (n && t[n - 2] === lat && t[n - 1] === lon) return;
      t.push(lat, lon);
      if (t.length > keep) t.splice(0, t.length - keep);
    };
    if (keep > 0) {
      for (const row of d.system_tracks) add(`S:${row[S.id]}`, row[S.lat], row[S.lon]);
      for (const [radar, rows] of Object.entries(d.tracks)) for (const row of rows) add(`R:${radar}/${row[T.id]}`, row[T.lat], row[T.lon]);
    }
    for (const key of trails.keys()) if (!seen.has(key)) trails.delete(key);
  }

  // -- drawing -------------------------------------------------------------------------------
  function schedule() {
    if (state.pending) return;
    state.pending = true;
    window.requestAnimationFrame(() => {
      state.pending = false;
      draw();
    });
  }

  function onScreen(sx, sy, margin = 40) {
    const [w, h] = size();
    return sx > -margin && sy > -margin && sx < w + margin && sy < h + margin;
  }

  function drawGraticule([latLo, latHi, lonLo, lonHi]) {
    const [w, h] = size();
    const pxPerDegLat = EARTH_KM * RAD * state.view.scale;
    const step = GRATICULE_STEPS.find((s) => s * pxPerDegLat >= 70) || GRATICULE_STEPS[GRATICULE_STEPS.length - 1];
    const digits = step < 0.1 ? 2 : step < 1 ? (step === 0.5 ? 1 : 2) : 0;
    const out = [];
    for (let lat = Math.max(-89, Math.floor(latLo / step) * step); lat <= Math.min(89, latHi); lat += step) {
      const [, sy] = at(lat, state.centre[1]);
      if (sy < 16 || sy > h) continue;
      const label = Math.abs(lat).toFixed(digits) + "\u00b0" + (lat >= 0 ? "N" : "S");
      out.push(`<line x1="0" y1="${f(sy, 1)}" x2="${f(w, 1)}" y2="${f(sy, 1)}"></line>`);
      out.push(`<text x="4" y="${f(sy - 3, 1)}">${label}</text>`);
    }
    for (let lon = Math.floor(lonLo / step) * step; lon <= lonHi; lon += step) {
      const [sx] = at(state.centre[0], lon);
      if (sx < 40 || sx > w) continue;
      const l = ((lon + 540) % 360) - 180;
      const label = Math.abs(l).toFixed(digits) + "\u00b0" + (l >= 0 ? "E" : "W");
      out.push(`<line x1="${f(sx, 1)}" y1="0" x2="${f(sx, 1)}" y2="${f(h, 1)}"></line>`);
      out.push(`<text x="${f(sx + 3, 1)}" y="12">${label}</text>`);
    }
    layer.graticule.innerHTML = out.join("");
    const km = 100 / state.view.scale;
    $("scale").textContent = `100 px = ${km >= 10 ? f(km) : f(km, 2)} km \u00b7 grid ${step}\u00b0`;
  }

  // The basemap: flat [lon, lat, ...] arrays with their bounding boxes (decoded once).
  function decodeBasemap(lines, unit) {
    return lines.map((flat) => {
      const pts = new Float64Array(flat.length);
      const box = [Infinity, Infinity, -Infinity, -Infinity]; // lon min, lat min, lon max, lat max
      let x = 0;
      let y = 0;
      for (let i = 0; i < flat.length; i += 2) {
        x += flat[i];
        y += flat[i + 1];
        pts[i] = x * unit;
        pts[i + 1] = y * unit;
        box[0] = Math.min(box[0], pts[i]);
        box[1] = Math.min(box[1], pts[i + 1]);
        box[2] = Math.max(box[2], pts[i]);
        box[3] = Math.max(box[3], pts[i + 1]);
      }
      return { pts, box };
    });
  }

  function loadBasemap() {
    fetch("static/basemap.json")
      .then((r) => (r.ok ? r.json() : null))
      .then((b) => {
        if (!b) return;
        basemap.land = decodeBasemap(b.land, b.unit);
        basemap.borders = decodeBasemap(b.borders, b.unit);
        document.body.dataset.basemap = String(basemap.land.length + basemap.borders.length);
        schedule();
      })
      .catch(() => {}); // the picture works without it
  }

  /** An SVG path of the pieces that may be on the map: a piece whose box misses the view, or
   * is under two pixels on it, is skipped, and so is a point under a pixel from the last. */
  function basemapPath(pieces, closed, [latLo, latHi, lonLo, lonHi]) {
    const lon0 = state.centre[1];
    const pxPerDeg = EARTH_KM * RAD * state.view.scale;
    const lonOk = (a, b) => [-360, 0, 360].some((k) => a + k <= lonHi && b + k >= lonLo);
    const out = [];
    for (const { pts, box } of pieces) {
      if (box[3] < latLo || box[1] > latHi || !lonOk(box[0], box[2])) continue;
      if ((box[3] - box[1]) * pxPerDeg < 2 && (box[2] - box[0]) * pxPerDeg < 2) continue;
      let lx = NaN;
      let ly = NaN;
      let ldl = NaN;
      for (let i = 0; i < pts.length; i += 2) {
        const [sx, sy] = at(pts[i + 1], pts[i]);
        const dl = wrapLon(pts[i] - lon0);
        const jump = !(Math.abs(dl - ldl) < 180); // the first point, or across the far side
        if (!jump && Math.abs(sx - lx) < 1 && Math.abs(sy - ly) < 1 && i + 2 < pts.length) continue;
        out.push((jump ? "M" : "L") + sx.toFixed(1) + "," + sy.toFixed(1));
        lx = sx;
        ly = sy;
        ldl = dl;
      }
      if (closed) out.push("Z");
    }
    return out.join("");
  }

  function drawBasemap(bounds) {
    layer.land.setAttribute("d", show.basemap ? basemapPath(basemap.land, true, bounds) : "");
    layer.borders.setAttribute("d", show.basemap ? basemapPath(basemap.borders, false, bounds) : "");
  }

  function drawCoverage(sites) {
    if (!show.coverage) return "";
    return sites
      .map((s) => {
        const pts = [];
        for (let b = 0; b <= 360; b += 5) {
          const [sx, sy] = at(...destination(s.latitude_deg, s.longitude_deg, b, RANGE_KM));
          pts.push(`${f(sx, 1)},${f(sy, 1)}`);
        }
        return `<path d="M${pts.join("L")}Z" stroke="${colour(s.radar_id)}"></path>`;
      })
      .join("");
  }

  function drawSites(sites) {
    return sites
      .map((s) => {
        const [sx, sy] = at(s.latitude_deg, s.longitude_deg);
        const c = colour(s.radar_id);
        return (
          `<g class="site" data-radar-id="${esc(s.radar_id)}">` +
          `<path d="M${f(sx, 1)},${f(sy - 8, 1)}l7,12h-14z" fill="${c}"></path>` +
          `<text x="${f(sx + 9, 1)}" y="${f(sy + 4, 1)}">${esc(s.radar_id)}</text></g>`
        );
      })
      .join("");
  }

  function drawBiases(biases, sites) {
    const byId = Object.fromEntries(sites.map((s) => [s.radar_id, s]));
    const known = biases.filter((b) => b.radar_id in byId);
    // displacement (m) of a plot on the ring due north of the radar: east = azimuth, north = range
    const vec = (b) => [RANGE_KM * 1000 * b.azimuth_deg * RAD, b.range_m];
    const sig = (b) => [RANGE_KM * 1000 * b.azimuth_sigma_deg * RAD, b.range_sigma_m];
    const longest = Math.max(1, ...known.map((b) => Math.hypot(...vec(b)) + Math.max(...sig(b))));
    const mPerPx = BIAS_SCALES.find((s) => longest / s <= BIAS_MAX_PX) || BIAS_SCALES[BIAS_SCALES.length - 1];
    $("bias-scale").textContent = String(mPerPx);
    if (!show.biases) return "";
    return known
      .map((b) => {
        const s = byId[b.radar_id];
        const [sx, sy] = at(s.latitude_deg, s.longitude_deg);
        const [de, dn] = vec(b);
        const [se, sn] = sig(b);
        const tx = sx + de / mPerPx;
        const ty = sy - dn / mPerPx;
        const len = Math.hypot(tx - sx, ty - sy);
        let head = "";
        if (len >= 4) {
          const ux = (tx - sx) / len;
          const uy = (ty - sy) / len;
          const p = (a, b2) => `${f(tx - ux * a + uy * b2, 1)},${f(ty - uy * a - ux * b2, 1)}`;
          head = `<path class="head" d="M${f(tx, 1)},${f(ty, 1)}L${p(8, 4)}L${p(8, -4)}Z"></path>`;
        }
        return (
          `<g class="bias" data-radar-id="${esc(b.radar_id)}">` +
          `<ellipse cx="${f(tx, 1)}" cy="${f(ty, 1)}" rx="${f(Math.max(1, se / mPerPx), 1)}" ` +
          `ry="${f(Math.max(1, sn / mPerPx), 1)}"></ellipse>` +
          `<line x1="${f(sx, 1)}" y1="${f(sy, 1)}" x2="${f(tx, 1)}" y2="${f(ty, 1)}"></line>${head}</g>`
        );
      })
      .join("");
  }

  /** The selected tracks' keys ("radar/track"), the selected system track's id, the links to
   * highlight (a system track's: between two of its members; a radar track's: all of its). */
  function selected() {
    const sel = state.selection;
    const out = { system: null, tracks: new Set(), links: [] };
    if (!sel || !state.data) return out;
    const { S, L, systemRow } = state.ix;
    if (sel.kind === "system") {
      const row = systemRow.get(sel.id);
      if (!row) return out;
      out.system = sel.id;
      for (const [r, t] of row[S.members]) out.tracks.add(`${r}/${t}`);
    } else {
      out.tracks.add(`${sel.radar}/${sel.id}`);
    }
    const both = sel.kind === "system";
    out.links = state.data.links.filter((l) => {
      const a = out.tracks.has(`${l[L.radar_a]}/${l[L.track_a]}`);
      const b = out.tracks.has(`${l[L.radar_b]}/${l[L.track_b]}`);
      return both ? a && b : a || b;
    });
    return out;
  }

  /** A track's trail into the current path, through its past positions (into `dots` if
   * given, to be marked: a trail then reads as history, apart from the leader ahead). */
  function drawTrail(key, lat, lon, dots) {
    const t = trails.get(key);
    if (!t || t.length < 4) return false;
    let [px, py] = at(t[0], t[1]);
    ctx.moveTo(px, py);
    for (let i = 0; i < t.length; i += 2) {
      [px, py] = at(t[i], t[i + 1]);
      ctx.lineTo(px, py);
      if (dots) dots.push(px, py);
    }
    const [sx, sy] = at(lat, lon);
    ctx.lineTo(sx, sy);
    return true;
  }

  const labelWidths = new Map(); // label -> px (labels change little from frame to frame)

  /** Labels that do not overlap: each in the first free one of four places around its track
   * (after the track symbols, which they must not cover either), or not at all; the selected
   * track first, then confirmed ones with more members. */
  function drawLabels(items) {
    const CELL = 48;
    const grid = new Map();
    const cells = (x, y, w, h, fn) => {
      for (let i = Math.floor(x / CELL); i <= Math.floor((x + w) / CELL); i++) {
        for (let j = Math.floor(y / CELL); j <= Math.floor((y + h) / CELL); j++) if (fn(i * 100003 + j)) return true;
      }
      return false;
    };
    const free = (r) =>
      !cells(r[0], r[1], r[2], r[3], (k) =>
        (grid.get(k) || []).some((o) => r[0] < o[0] + o[2] && o[0] < r[0] + r[2] && r[1] < o[1] + o[3] && o[1] < r[1] + r[3]),
      );
    const take = (r) =>
      cells(r[0], r[1], r[2], r[3], (k) => {
        if (!grid.has(k)) grid.set(k, []);
        grid.get(k).push(r);
        return false;
      });
    for (const it of items) take([it.sx - 5, it.sy - 5, 10, 10]);
    ctx.font = LABEL_FONT;
    ctx.textBaseline = "top";
    let shown = 0;
    let hiddenCount = 0;
    for (const it of items.filter((i) => i.label).sort((a, b) => b.rank - a.rank)) {
      let w = labelWidths.get(it.label);
      if (w === undefined) {
        if (labelWidths.size > 20000) labelWidths.clear(); // ids come and go: bounded
        w = ctx.measureText(it.label).width + 2;
        labelWidths.set(it.label, w);
      }
      const places = [
        [it.sx + 7, it.sy - 6 - LABEL_H],
        [it.sx + 7, it.sy + 6],
        [it.sx - 7 - w, it.sy - 6 - LABEL_H],
        [it.sx - 7 - w, it.sy + 6],
      ];
      const place = places.map(([x, y]) => [x, y, w, LABEL_H]).find(free);
      if (!place) {
        hiddenCount += 1;
        continue;
      }
      take(place);
      ctx.fillStyle = it.colour;
      ctx.fillText(it.label, place[0] + 1, place[1]);
      shown += 1;
    }
    canvas.dataset.labels = String(shown);
    canvas.dataset.labelsHidden = String(hiddenCount);
  }

  function drawCanvas() {
    const [w, h] = size();
    const dpr = window.devicePixelRatio || 1;
    if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
      canvas.width = Math.round(w * dpr);
      canvas.height = Math.round(h * dpr);
    }
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, h);
    const v = state.visible;
    const { S, T, L } = state.ix;
    const sel = selected();
    const drawn = { system: [], tracks: [], highlighted: [] };
    let nTrails = 0;

    // trails, under everything else
    if (show.trails && filters.trail > 1) {
      ctx.lineWidth = 1.5;
      if (show.tracks) {
        ctx.globalAlpha = 0.35;
        for (const [radar, rows] of groupByRadar(v.tracks)) {
          ctx.strokeStyle = colour(radar);
          ctx.beginPath();
          for (const row of rows) if (drawTrail(`R:${radar}/${row[T.id]}`, row[T.lat], row[T.lon])) nTrails += 1;
          ctx.stroke();
        }
      }
      if (show.system) {
        const dots = [];
        ctx.globalAlpha = 0.4;
        ctx.lineWidth = 1;
        ctx.strokeStyle = TRAIL_COLOUR;
        ctx.beginPath();
        for (const row of v.system) if (drawTrail(`S:${row[S.id]}`, row[S.lat], row[S.lon], dots)) nTrails += 1;
        ctx.stroke();
        ctx.globalAlpha = 0.8;
        ctx.fillStyle = TRAIL_COLOUR;
        ctx.beginPath();
        for (let i = 0; i < dots.length; i += 2) ctx.rect(dots[i] - 1, dots[i + 1] - 1, 2, 2);
        ctx.fill();
      }
      ctx.globalAlpha = 1;
    }

    // correlation links
    let nLinks = 0;
    if (show.links) {
      ctx.setLineDash([3, 2]);
      ctx.lineWidth = 1;
      ctx.strokeStyle = LINK_COLOUR;
      for (const confirmed of [true, false]) {
        ctx.globalAlpha = confirmed ? 0.6 : 0.25;
        ctx.beginPath();
        for (const l of v.links) {
          if ((l[L.status] === "c") !== confirmed) continue;
          const [x1, y1] = at(l[L.lat_a], l[L.lon_a]);
          const [x2, y2] = at(l[L.lat_b], l[L.lon_b]);
          if (!onScreen(x1, y1) && !onScreen(x2, y2)) continue;
          ctx.moveTo(x1, y1);
          ctx.lineTo(x2, y2);
          nLinks += 1;
        }
        ctx.stroke();
      }
      ctx.setLineDash([]);
      ctx.globalAlpha = 1;
    }

    // radar tracks: one path per radar and status
    if (show.tracks) {
      for (const [radar, rows] of groupByRadar(v.tracks)) {
        ctx.fillStyle = colour(radar);
        for (const confirmed of [1, 0]) {
          ctx.globalAlpha = confirmed ? 0.6 : 0.25;
          ctx.beginPath();
          for (const row of rows) {
            if (Boolean(row[T.confirmed]) !== Boolean(confirmed)) continue;
            const [sx, sy] = at(row[T.lat], row[T.lon]);
            if (!onScreen(sx, sy)) continue;
            ctx.rect(sx - 2, sy - 2, 4, 4); // (thousands of arcs cost a software rasteriser dear)
            drawn.tracks.push([sx, sy, radar, row]);
          }
          ctx.fill();
        }
      }
      ctx.globalAlpha = 1;
    }

    // system tracks: a square and a velocity leader each
    const labels = [];
    if (show.system) {
      ctx.strokeStyle = SYSTEM_COLOUR;
      for (const confirmed of [1, 0]) {
        ctx.setLineDash(confirmed ? [] : [2, 2]);
        ctx.beginPath();
        for (const row of v.system) {
          if (Boolean(row[S.confirmed]) !== Boolean(confirmed)) continue;
          const [x, y] = project(row[S.lat], row[S.lon]);
          const [sx, sy] = screen(x, y);
          if (!onScreen(sx, sy)) continue;
          const [lx, ly] = screen(x + (row[S.ve] * LEADER_S) / 1000, y + (row[S.vn] * LEADER_S) / 1000);
          ctx.rect(sx - 4, sy - 4, 8, 8);
          ctx.moveTo(sx, sy);
          ctx.lineTo(lx, ly);
          drawn.system.push([sx, sy, row]);
          const id = row[S.id];
          labels.push({
            sx,
            sy,
            label: show.labels ? `${id} ${flText(row[S.fl])}` : "",
            colour: id === sel.system ? SELECTED_COLOUR : SYSTEM_COLOUR,
            rank: (id === sel.system ? 1e6 : 0) + (confirmed ? 1e3 : 0) + row[S.members].length,
          });
        }
        ctx.lineWidth = 2;
        ctx.stroke();
      }
      ctx.setLineDash([]);
    }

    // the selection: its links (whatever the filters), its members and itself, ringed
    if (sel.tracks.size) {
      ctx.strokeStyle = SELECTED_COLOUR;
      ctx.lineWidth = 3;
      ctx.lineCap = "round"; // a link shorter than a pixel still shows
      ctx.beginPath();
      for (const l of sel.links) {
        const [x1, y1] = at(l[L.lat_a], l[L.lon_a]);
        const [x2, y2] = at(l[L.lat_b], l[L.lon_b]);
        ctx.moveTo(x1, y1);
        ctx.lineTo(x2, y2);
        drawn.highlighted.push([x1, y1, x2, y2]);
      }
      ctx.stroke();
      ctx.lineCap = "butt";
      ctx.lineWidth = 2;
      ctx.beginPath();
      for (const key of sel.tracks) {
        const row = state.ix.trackRow.get(key);
        if (!row) continue;
        const [sx, sy] = at(row[T.lat], row[T.lon]);
        ctx.moveTo(sx + 6, sy);
        ctx.arc(sx, sy, 6, 0, 2 * Math.PI);
        if (state.selection.kind === "track") {
          labels.push({ sx, sy, label: show.labels ? key : "", colour: SELECTED_COLOUR, rank: 2e6 });
        }
      }
      const row = sel.system === null ? null : state.ix.systemRow.get(sel.system);
      if (row) {
        const [sx, sy] = at(row[S.lat], row[S.lon]);
        ctx.moveTo(sx + 10, sy);
        ctx.arc(sx, sy, 10, 0, 2 * Math.PI);
      }
      ctx.stroke();
    }

    drawLabels(labels);
    state.drawn = drawn;
    Object.assign(canvas.dataset, {
      system: String(drawn.system.length),
      tracks: String(drawn.tracks.length),
      links: String(nLinks),
      trails: String(nTrails),
      highlighted: String(drawn.highlighted.length),
    });
  }

  function groupByRadar(tracks) {
    const out = new Map();
    for (const [radar, row] of tracks) {
      if (!out.has(radar)) out.set(radar, []);
      out.get(radar).push(row);
    }
    return out;
  }

  function draw() {
    const d = state.data;
    if (!d || !state.centre || !state.view) return;
    const bounds = viewBounds();
    drawBasemap(bounds);
    drawGraticule(bounds);
    layer.coverage.innerHTML = drawCoverage(d.sites);
    drawCanvas();
    layer.sites.innerHTML = drawSites(d.sites);
    layer.biases.innerHTML = drawBiases(d.biases, d.sites);
  }

  // -- panels --------------------------------------------------------------------------------
  function panels(d) {
    const h = d.health;
    $("health").tBodies[0].innerHTML = h.radars
      .map((r) => {
        const lagClass = r.expired ? "bad" : r.lag_s > 10 ? "warn" : "";
        const rateText = Number.isFinite(r.plots_s) ? `${f(r.plots_s, 1)}/s (${f(r.batches_s, 1)} b/s)` : DASH;
        const rejClass = r.rejected + r.lost_batches > 0 ? "warn" : "";
        return (
          `<tr data-radar-id="${esc(r.radar_id)}"><td><span class="swatch" style="background:${colour(r.radar_id)}">` +
          `</span>${esc(r.radar_id)}${r.expired ? " (expired)" : ""}</td><td>${rateText}</td>` +
          `<td class="${lagClass}">${duration(r.lag_s)}</td>` +
          `<td class="${rejClass}">${r.rejected}${r.lost_batches ? ` (${r.lost_batches})` : ""}</td>` +
          `<td>${r.window_plots}</td><td>${r.tracks_confirmed} / ${r.tracks_tentative}</td></tr>`
        );
      })
      .join("");
    $("bias-table").tBodies[0].innerHTML = d.biases.length
      ? d.biases
          .map(
            (b) =>
              `<tr data-radar-id="${esc(b.radar_id)}"><td>${esc(b.radar_id)}</td>` +
              `<td>${signed(b.range_m, 0)} \u00b1${f(b.range_sigma_m)} m</td>` +
              `<td>${signed(b.azimuth_deg, 3)} \u00b1${f(b.azimuth_sigma_deg, 3)}\u00b0</td>` +
              `<td>${b.pairs_used}</td></tr>`,
          )
          .join("")
      : '<tr><td colspan="4">none yet</td></tr>';
    const c = h.correlation;
    const q = h.queue || {};
    const items = [
      ["method", esc(h.method)],
      ["latency p50 / p99", `${f(c.p50_ms, 1)} / ${f(c.p99_ms, 1)} ms`],
      ["last update", `${f(c.last_ms, 1)} ms`],
      ["updates", String(c.updates)],
      ["pairs", `${h.pairs_confirmed} confirmed, ${h.pairs_tentative} tentative (${h.pairs_held ?? 0} held)`],
      ["ingest queue", `${q.depth ?? DASH} / ${q.capacity ?? DASH} (dropped ${q.dropped ?? 0})`],
    ];
    if (h.missing_partitions.length) items.push(["missing workers", h.missing_partitions.join(", ")]);
    $("correlation").innerHTML = items.map(([k, v]) => `<dt>${k}</dt><dd>${v}</dd>`).join("");
    const rej = Object.entries(h.rejected);
    $("rejections").innerHTML = rej.length ? rej.map(([k, v]) => `<li>${esc(k)}: ${v}</li>`).join("") : "<li>none</li>";
    // a replay (or a run faster or slower than real time): its data clock, not the wall's
    const badge = $("replay");
    badge.hidden = !h.replay;
    const speed = Number.isFinite(h.data_speed) && Math.abs(h.data_speed - 1) > 0.05 ? ` \u00b7 \u00d7${f(h.data_speed, 1)}` : "";
    badge.textContent = h.replay ? `replay \u00b7 data clock ${utc(h.data_time_s)}${speed}` : "";
    const t = d.truncated;
    const cut = Object.entries(t).filter(([, n]) => n > 0);
    $("truncated").hidden = !cut.length;
    $("truncated").textContent = cut.length
      ? `Not drawn (over ${d.max_items} per kind): ` + cut.map(([k, n]) => `${n} ${k.replace("_", " ")}`).join(", ")
      : "";
  }

  function summary() {
    const d = state.data;
    const v = state.visible;
    const nTracks = Object.values(d.tracks).reduce((a, r) => a + r.length, 0);
    const of = (shown, all) => (shown === all ? String(all) : `${shown} of ${all}`);
    $("summary").textContent =
      `data time ${utc(d.time_s)} \u00b7 ${d.sites.length} radars \u00b7 ` +
      `${of(v.system.length, d.system_tracks.length)} system tracks \u00b7 ${of(v.tracks.length, nTracks)} radar tracks \u00b7 ` +
      `${of(v.links.length, d.links.length)} links`;
  }

  function renderList() {
    const { S } = state.ix;
    const rows = state.visible.system;
    const num = (id) => Number(String(id).replace(/^\D+/, "")) || 0;
    const sorted = [...rows].sort((a, b) => num(a[S.id]) - num(b[S.id]));
    const selectedId = state.selection && state.selection.kind === "system" ? state.selection.id : null;
    $("track-count").textContent = rows.length > LIST_MAX ? `(first ${LIST_MAX} of ${rows.length})` : `(${rows.length})`;
    $("track-list").tBodies[0].innerHTML = sorted
      .slice(0, LIST_MAX)
      .map((row) => {
        const id = row[S.id];
        const sources = row[S.members].map((m) => esc(m[0])).join(" ");
        return (
          `<tr data-select="${esc(id)}"${id === selectedId ? ' class="selected"' : ""}><td>${esc(id)}</td>` +
          `<td>${flText(row[S.fl])}</td><td>${text(row[S.mode_s])}</td><td>${text(row[S.mode_3a])}</td><td>${sources}</td></tr>`
        );
      })
      .join("");
  }

  function pairRows(links, mine) {
    const { L } = state.ix;
    if (!links.length) return "<p>no pairs</p>";
    const body = links
      .map((l) => {
        const a = `${l[L.radar_a]}/${l[L.track_a]}`;
        const b = `${l[L.radar_b]}/${l[L.track_b]}`;
        const other = mine.has(a) && !mine.has(b) ? b : a;
        return (
          `<tr data-select="${esc(other)}"><td>${esc(a)} \u2194 ${esc(b)}</td><td>${f(l[L.score], 3)}</td>` +
          `<td>${text(l[L.basis])}</td><td>${l[L.status] === "c" ? "confirmed" : "tentative"}</td></tr>`
        );
      })
      .join("");
    return `<table class="pairs"><thead><tr><th>pair</th><th>score</th><th>basis</th><th>status</th></tr></thead><tbody>${body}</tbody></table>`;
  }

  function facts(items) {
    return `<dl>${items.map(([k, v]) => `<dt>${k}</dt><dd>${v}</dd>`).join("")}</dl>`;
  }

  // What a system track's and a radar track's panels both show; C: the row's column indices.
  function trackFacts(row, C) {
    return [
      ["Mode S", text(row[C.mode_s])],
      ["Mode 3/A", text(row[C.mode_3a])],
      ["flight level", flText(row[C.fl])],
      ["speed, heading", motion(row[C.ve], row[C.vn])],
      ["age", duration(row[C.age_s])],
    ];
  }

  function renderSelection() {
    const box = $("selection");
    const sel = state.selection;
    if (!sel || !state.data) {
      box.hidden = true;
      return;
    }
    box.hidden = false;
    const { S, T, systemRow, trackRow, systemOf } = state.ix;
    const body = $("selection-body");
    const picked = selected();
    if (sel.kind === "system") {
      const row = systemRow.get(sel.id);
      if (!row) {
        body.innerHTML = `<h3>System track ${esc(sel.id)}</h3><p>not in the latest picture</p>`;
        return;
      }
      const members = row[S.members]
        .map(([r, t]) => {
          const m = trackRow.get(`${r}/${t}`);
          const cell = (k, fn) => (m ? fn(m[T[k]]) : DASH);
          return (
            `<tr data-select="${esc(`${r}/${t}`)}"><td><span class="swatch" style="background:${colour(r)}"></span>${esc(r)}</td>` +
            `<td>${esc(t)}</td><td>${cell("mode_s", text)}</td><td>${cell("mode_3a", text)}</td><td>${cell("fl", flText)}</td>` +
            `<td>${m ? motion(m[T.ve], m[T.vn]) : DASH}</td><td>${cell("age_s", duration)}</td></tr>`
          );
        })
        .join("");
      body.innerHTML =
        `<h3 id="selection-title">System track ${esc(row[S.id])} \u00b7 ${row[S.confirmed] ? "confirmed" : "tentative"}</h3>` +
        facts([
          ...trackFacts(row, S),
          ["position \u03c3", `${f(row[S.sigma_m])} m`],
          ["basis", `${row[S.members].length} member(s): ${row[S.members].map((m) => esc(m[0])).join(", ")}`],
        ]) +
        `<h3>Members</h3><table class="members"><thead><tr><th>source</th><th>track</th><th>Mode S</th><th>3/A</th>` +
        `<th>FL</th><th>speed, hdg</th><th>age</th></tr></thead><tbody>${members}</tbody></table>` +
        `<h3>Pairs</h3>${pairRows(picked.links, picked.tracks)}`;
    } else {
      const key = selectionKey(sel);
      const row = trackRow.get(key);
      if (!row) {
        body.innerHTML = `<h3>Radar track ${esc(key)}</h3><p>not in the latest picture</p>`;
        return;
      }
      const sys = systemOf.get(key);
      body.innerHTML =
        `<h3 id="selection-title">Radar track ${esc(key)} \u00b7 ${row[T.confirmed] ? "confirmed" : "tentative"}</h3>` +
        facts([
          ...trackFacts(row, T),
          [
            "system track",
            sys ? `<a href="#" data-select="${esc(sys[S.id])}">${esc(sys[S.id])}</a> (${sys[S.members].length} member(s))` : DASH,
          ],
          ["basis", picked.links.length ? `${picked.links.length} pair(s)` : "unpaired"],
        ]) +
        `<h3>Pairs</h3>${pairRows(picked.links, picked.tracks)}`;
    }
  }

  function renderPerformance() {
    const radars = state.data ? state.data.health.radars : [];
    const cell = (value, verdict, required) => {
      const cls = verdict === true ? "good" : verdict === false ? "bad" : "";
      const title = Number.isFinite(required) ? ` title="required: ${pct(required)}"` : "";
      return `<td class="${cls}"${title}>${value}</td>`;
    };
    $("performance").tBodies[0].innerHTML = radars
      .map(({ radar_id: id }) => {
        const p = (perf[id] && perf[id].body) || {};
        const det = p.detection || {};
        const req = p.requirements || {};
        const ok = p.verdict || {};
        const pd = Number.isFinite(det.pd) ? pct(det.pd) + (Number.isFinite(det.pd_sigma) ? ` \u00b1${f(100 * det.pd_sigma, 1)}` : "") : DASH;
        const rms = p.position && Number.isFinite(p.position.rms_m) ? `${f(p.position.rms_m)} m` : DASH;
        return (
          `<tr data-perf-radar="${esc(id)}"><td><span class="swatch" style="background:${colour(id)}"></span>${esc(id)}</td>` +
          cell(pd, ok.pd, req.pd_min) +
          `<td>${rms}</td>` +
          cell(pct(p.mode_3a && p.mode_3a.rate), ok.mode_3a, req.mode_3a_min) +
          cell(pct(p.mode_c && p.mode_c.rate), ok.mode_c, req.mode_c_min) +
          `<td>${Number.isFinite(p.aircraft) ? p.aircraft : DASH}</td></tr>`
        );
      })
      .join("");
  }

  /** Each radar's performance, asked at most every PERF_EVERY_MS; an error or a 404 (a
   * service without the route, or a radar without references) shows as "-". */
  function pollPerformance(radars) {
    const now = Date.now();
    for (const { radar_id: id } of radars) {
      const p = perf[id] || (perf[id] = { at: -Infinity, busy: false, body: null });
      if (p.busy || now - p.at < PERF_EVERY_MS) continue;
      p.busy = true;
      p.at = now;
      fetch(`radars/${encodeURIComponent(id)}/performance`, { cache: "no-store" })
        .then((r) => (r.ok ? r.json() : null))
        .catch(() => null)
        .then((body) => {
          p.body = body && typeof body === "object" ? body : null;
          p.busy = false;
          renderPerformance();
        });
    }
    renderPerformance();
  }

  // -- filters and selection in the page ------------------------------------------------------
  const form = $("filters");

  function fillForm() {
    form.q.value = filters.q;
    form.fl_min.value = filters.fl_min === null ? "" : String(filters.fl_min);
    form.fl_max.value = filters.fl_max === null ? "" : String(filters.fl_max);
    form.status.value = filters.status;
    form.kind.value = filters.kind;
    form.trail.value = String(filters.trail);
    for (const input of document.querySelectorAll("#layers input")) input.checked = show[input.name];
    $("trail-n").textContent = String(filters.trail);
  }

  function syncRadarFilter(sites) {
    const key = sites.map((s) => s.radar_id).join(",");
    if (key === state.radarKey) return;
    state.radarKey = key;
    $("radar-filter").innerHTML =
      "<legend>radars</legend>" +
      sites
        .map(
          (s) =>
            `<label><input type="checkbox" name="radar" value="${esc(s.radar_id)}"` +
            `${!filters.radars || filters.radars.has(s.radar_id) ? " checked" : ""}>` +
            `<span class="swatch" style="background:${colour(s.radar_id)}"></span>${esc(s.radar_id)}</label>`,
        )
        .join("");
  }

  function readForm() {
    filters.q = form.q.value.trim();
    filters.fl_min = number(form.fl_min.value);
    filters.fl_max = number(form.fl_max.value);
    filters.status = STATUSES.includes(form.status.value) ? form.status.value : "confirmed";
    filters.kind = KINDS.includes(form.kind.value) ? form.kind.value : "all";
    filters.trail = Math.min(MAX_TRAIL, Math.max(0, Math.round(number(form.trail.value) ?? DEFAULT_TRAIL)));
    const boxes = [...form.querySelectorAll('input[name="radar"]')];
    const checked = boxes.filter((b) => b.checked).map((b) => b.value);
    filters.radars = checked.length === boxes.length ? null : new Set(checked);
    $("trail-n").textContent = String(filters.trail);
  }

  function refilter() {
    writeAddress();
    if (feedStatus() !== state.feedStatus) connect();
    if (!state.data) return;
    applyFilters();
    summary();
    renderList();
    schedule();
  }

  function select(sel) {
    state.selection = sel;
    writeAddress();
    renderSelection();
    if (state.data) renderList();
    schedule();
  }

  function pick(sx, sy) {
    const near = (items) => {
      let best = null;
      let bestD = HIT_PX * HIT_PX;
      for (const item of items) {
        const d2 = (item[0] - sx) ** 2 + (item[1] - sy) ** 2;
        if (d2 <= bestD) {
          best = item;
          bestD = d2;
        }
      }
      return best;
    };
    const { S, T } = state.ix;
    const sys = near(state.drawn.system);
    if (sys) return { kind: "system", id: sys[2][S.id] };
    const trk = near(state.drawn.tracks);
    return trk ? { kind: "track", radar: trk[2], id: trk[3][T.id] } : null;
  }

  // -- live data -----------------------------------------------------------------------------
  function connection(cls, label) {
    const el = $("connection");
    el.className = cls;
    el.textContent = label;
  }

  function take(d) {
    state.data = d;
    state.ix = index(d);
    state.updates += 1;
    state.lastEvent = Date.now();
    document.body.dataset.updates = String(state.updates);
    document.body.dataset.timeS = d.time_s === null ? "" : String(d.time_s);
    connection("state-live", "live");
    updateTrails(d);
    if (setCentre(d) || !state.view) {
      if (!takeViewParam()) fit();
    }
    syncRadarFilter(d.sites);
    applyFilters();
    panels(d);
    summary();
    renderList();
    renderSelection();
    pollPerformance(d.health.radars);
    schedule();
  }

  // the feed carries tentative rows only when the filters may show them
  const feedStatus = () => (filters.status === "confirmed" ? "confirmed" : "all");

  function connect() {
    if (state.source) state.source.close();
    state.feedStatus = feedStatus();
    const feed = new URLSearchParams({ status: state.feedStatus });
    if (MAX_ITEMS !== null) feed.set("max_items", String(MAX_ITEMS));
    const source = new EventSource("picture/events?" + feed.toString());
    source.addEventListener("snapshot", (e) => take(JSON.parse(e.data)));
    source.onerror = () => connection("state-down", "reconnecting");
    state.source = source;
  }

  window.setInterval(() => {
    if (state.lastEvent && Date.now() - state.lastEvent > STALE_S * 1000) connection("state-wait", "stale");
  }, 1000);

  // -- interaction ---------------------------------------------------------------------------
  let addressDue = 0;
  function viewMoved() {
    state.userView = true;
    window.clearTimeout(addressDue);
    addressDue = window.setTimeout(writeAddress, 250); // not on every frame of a drag
    schedule();
  }

  wrap.addEventListener(
    "wheel",
    (e) => {
      if (!state.view) return;
      e.preventDefault();
      const r = wrap.getBoundingClientRect();
      const sx = e.clientX - r.left;
      const sy = e.clientY - r.top;
      const [x, y] = world(sx, sy);
      const k = Math.exp(-e.deltaY * 0.0015);
      state.view.scale = Math.min(2000, Math.max(0.01, state.view.scale * k));
      const [x2, y2] = world(sx, sy);
      state.view.cx += x - x2;
      state.view.cy += y - y2;
      viewMoved();
    },
    { passive: false },
  );
  let drag = null;
  wrap.addEventListener("pointerdown", (e) => {
    if (!state.view) return;
    drag = { x: e.clientX, y: e.clientY, cx: state.view.cx, cy: state.view.cy, moved: false };
    wrap.setPointerCapture(e.pointerId);
    wrap.classList.add("dragging");
  });
  wrap.addEventListener("pointermove", (e) => {
    if (!drag) return;
    if (!drag.moved && Math.hypot(e.clientX - drag.x, e.clientY - drag.y) < CLICK_PX) return;
    drag.moved = true;
    state.view.cx = drag.cx - (e.clientX - drag.x) / state.view.scale;
    state.view.cy = drag.cy + (e.clientY - drag.y) / state.view.scale;
    viewMoved();
  });
  wrap.addEventListener("pointerup", (e) => {
    if (drag && !drag.moved && state.data) {
      const r = wrap.getBoundingClientRect();
      select(pick(e.clientX - r.left, e.clientY - r.top));
    }
    drag = null;
    wrap.classList.remove("dragging");
  });
  wrap.addEventListener("pointercancel", () => {
    drag = null;
    wrap.classList.remove("dragging");
  });
  wrap.addEventListener("dblclick", () => {
    fit();
    viewMoved();
  });
  window.addEventListener("resize", schedule);
  $("layers").addEventListener("change", (e) => {
    show[e.target.name] = e.target.checked;
    writeAddress();
    schedule();
  });
  form.addEventListener("submit", (e) => e.preventDefault());
  form.addEventListener("input", (e) => {
    if (e.target.name === "q" || e.target.type === "number") {
      readForm();
      refilter();
    }
  });
  form.addEventListener("change", () => {
    readForm();
    refilter();
  });
  // rows and links that name a track select it (the list, the selection's members and pairs)
  const onSelect = (e) => {
    const target = e.target.closest("[data-select]");
    if (!target) return;
    e.preventDefault();
    select(readSelection(target.dataset.select));
  };
  $("track-list").addEventListener("click", onSelect);
  $("selection-body").addEventListener("click", onSelect);
  $("unselect").addEventListener("click", () => select(null));

  // for the tests and the curious: where a track is drawn (px from the map's top left corner)
  window.topofusionPicture = {
    drawnAt(id) {
      if (!state.ix) return null;
      const { S, T } = state.ix;
      const sys = state.drawn.system.find((s) => s[2][S.id] === id);
      if (sys) return [sys[0], sys[1]];
      const trk = state.drawn.tracks.find((t) => `${t[2]}/${t[3][T.id]}` === id);
      return trk ? [trk[0], trk[1]] : null;
    },
    highlighted: () => state.drawn.highlighted.map((s) => s.slice()),
    drawnSystemIds: () => (state.ix ? state.drawn.system.map((s) => s[2][state.ix.S.id]) : []),
  };

  $("range-km").textContent = String(RANGE_KM);
  $("leader-s").textContent = String(LEADER_S);
  fillForm();
  writeAddress();
  loadBasemap();
  connect();
})();
