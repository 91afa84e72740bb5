// TopoFusion operator picture: plain JavaScript, no library, nothing loaded from elsewhere.
//
// Data: server-sent events from picture/events (one JSON snapshot about every second; see
// service/api/picture.py for its fields).  Map: a local equirectangular projection around the
// mean of the radar sites (x east, y north, in km; distances are true near the centre, which
// is what a radar network's few hundred km need), drawn as SVG; wheel zooms about the
// pointer, drag pans, double-click fits the sites and their coverage.
//
// Page options (query string of /picture): range_km (coverage ring radius, default 250),
// leader_s (velocity leader length in seconds, default 60), status=all (tentative tracks
// too), max_items (the feed's cap per kind, default 2000).
"use strict";
(() => {
  const params = new URLSearchParams(window.location.search);
  const positive = (v, fallback) => {
    const x = Number(v);
    return v !== null && Number.isFinite(x) && x > 0 ? x : fallback;
  };
  const RANGE_KM = positive(params.get("range_km"), 250);
  const LEADER_S = positive(params.get("leader_s"), 60);
  const EARTH_KM = 6371.0088;
  const RAD = Math.PI / 180;
  const PALETTE = ["#6ab0ff", "#7be0a8", "#ff9f6a", "#c79bff", "#5fd6e0", "#f2e06b", "#ff7aa8", "#a8c46a"];
  const GRATICULE_STEPS = [0.05, 0.1, 0.25, 0.5, 1, 2, 5, 10, 20];
  const BIAS_SCALES = [1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000];
  const BIAS_MAX_PX = 90;
  const RATE_WINDOW_S = 5;
  const STALE_S = 5;

  const $ = (id) => document.getElementById(id);
  const svg = $("map");
  const layer = {
    graticule: $("layer-graticule"),
    coverage: $("layer-coverage"),
    links: $("layer-links"),
    tracks: $("layer-tracks"),
    system: $("layer-system"),
    sites: $("layer-sites"),
    biases: $("layer-biases"),
  };
  const show = { coverage: true, tracks: true, links: true, system: true, labels: true, biases: true };

  const state = {
    data: null,
    centre: null, // [lat0, lon0] of the projection
    siteKey: "",
    view: null, // {cx, cy} world km at the middle of the map, scale px/km
    history: [], // [{wall, counters: {radar: [plots, batches]}}], for rates
    colours: {},
    updates: 0,
    lastEvent: 0,
    pending: false,
  };

  $("range-km").textContent = String(RANGE_KM);
  $("leader-s").textContent = String(LEADER_S);

  // -- helpers -----------------------------------------------------------------------------
  const esc = (s) =>
    String(s).replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[c]);
  const f = (x, digits = 0) => (Number.isFinite(x) ? x.toFixed(digits) : "-");
  const signed = (x, digits) => (x >= 0 ? "+" : "\u2212") + Math.abs(x).toFixed(digits);

  function duration(s) {
    if (!Number.isFinite(s)) return "-";
    const a = Math.abs(s);
    const sign = s < 0 ? "\u2212" : "";
    if (a < 100) return sign + a.toFixed(1) + " s";
    if (a < 2 * 3600) return sign + (a / 60).toFixed(1) + " min";
    if (a < 2 * 86400) return sign + (a / 3600).toFixed(1) + " h";
    return sign + (a / 86400).toFixed(1) + " d";
  }

  function utc(t) {
    if (!Number.isFinite(t)) return "-";
    return new Date(t * 1000).toISOString().replace("T", " ").replace(/\.\d+Z$/, "Z");
  }

  function colour(radar) {
    if (!(radar in state.colours)) {
      state.colours[radar] = PALETTE[Object.keys(state.colours).length % PALETTE.length];
    }
    return state.colours[radar];
  }

  // -- projection ----------------------------------------------------------------------------
  function project(lat, lon) {
    const [lat0, lon0] = state.centre;
    let dlon = lon - lon0;
    if (dlon > 180) dlon -= 360;
    if (dlon < -180) dlon += 360;
    return [EARTH_KM * dlon * RAD * Math.cos(lat0 * RAD), EARTH_KM * (lat - lat0) * RAD];
  }

  function unproject(x, y) {
    const [lat0, lon0] = state.centre;
    return [lat0 + y / (EARTH_KM * RAD), lon0 + x / (EARTH_KM * RAD * Math.cos(lat0 * RAD))];
  }

  function size() {
    const r = svg.getBoundingClientRect();
    return [Math.max(r.width, 1), Math.max(r.height, 1)];
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
    let pts = sites.map((s) => [s.latitude_deg, s.longitude_deg]);
    if (!pts.length) pts = data.system_tracks.map((t) => [t[1], t[2]]);
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
    const pts = state.data.sites.map((s) => project(s.latitude_deg, s.longitude_deg));
    const pad = pts.length ? RANGE_KM * 1.05 : 50;
    if (!pts.length) state.data.system_tracks.forEach((t) => pts.push(project(t[1], t[2])));
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

  function drawGraticule() {
    const [w, h] = size();
    const corners = [world(0, 0), world(w, 0), world(0, h), world(w, h)].map(([x, y]) => unproject(x, y));
    const lats = corners.map((c) => c[0]);
    const lons = corners.map((c) => c[1]);
    const pxPerDegLat = EARTH_KM * RAD * state.view.scale;
    const step = GRATICULE_STEPS.find((s) => s * pxPerDegLat >= 70) || GRATICULE_STEPS[GRATICULE_STEPS.length - 1];
    const digits = step < 0.1 ? 2 : step < 1 ? (step === 0.5 ? 1 : 2) : 0;
    const out = [];
    const latMin = Math.max(-89, Math.floor(Math.min(...lats) / step) * step);
    const latMax = Math.min(89, Math.max(...lats));
    for (let lat = latMin; lat <= latMax; lat += step) {
      const [, sy] = screen(...project(lat, state.centre[1]));
      if (sy < 16 || sy > h) continue;
      const label = Math.abs(lat).toFixed(digits) + "\u00b0" + (lat >= 0 ? "N" : "S");
      out.push(`<line x1="0" y1="${f(sy, 1)}" x2="${f(w, 1)}" y2="${f(sy, 1)}"></line>`);
      out.push(`<text x="4" y="${f(sy - 3, 1)}">${label}</text>`);
    }
    const lonMin = Math.floor(Math.min(...lons) / step) * step;
    const lonMax = Math.max(...lons);
    for (let lon = lonMin; lon <= lonMax; lon += step) {
      const [sx] = screen(...project(state.centre[0], lon));
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

  function drawCoverage(sites) {
    if (!show.coverage) return "";
    return sites
      .map((s) => {
        const pts = [];
        for (let b = 0; b <= 360; b += 5) {
          const [la, lo] = destination(s.latitude_deg, s.longitude_deg, b, RANGE_KM);
          const [sx, sy] = screen(...project(la, lo));
          pts.push(`${f(sx, 1)},${f(sy, 1)}`);
        }
        return `<path d="M${pts.join("L")}Z" stroke="${colour(s.radar_id)}"></path>`;
      })
      .join("");
  }

  function drawSites(sites) {
    return sites
      .map((s) => {
        const [sx, sy] = screen(...project(s.latitude_deg, s.longitude_deg));
        const c = colour(s.radar_id);
        return (
          `<g class="site" data-radar-id="${esc(s.radar_id)}">` +
          `<path d="M${f(sx, 1)},${f(sy - 8, 1)}l7,12h-14z" fill="${c}"></path>` +
          `<text x="${f(sx + 9, 1)}" y="${f(sy + 4, 1)}">${esc(s.radar_id)}</text></g>`
        );
      })
      .join("");
  }

  function drawTracks(tracks) {
    if (!show.tracks) return "";
    const out = [];
    for (const [radar, rows] of Object.entries(tracks)) {
      const c = colour(radar);
      for (const [, lat, lon, confirmed] of rows) {
        const [sx, sy] = screen(...project(lat, lon));
        if (!onScreen(sx, sy)) continue;
        const cls = confirmed ? "" : ' class="tentative"';
        out.push(`<circle cx="${f(sx, 1)}" cy="${f(sy, 1)}" r="2.5" fill="${c}"${cls}></circle>`);
      }
    }
    return out.join("");
  }

  function drawLinks(links) {
    if (!show.links) return "";
    const out = [];
    for (const [, , la1, lo1, la2, lo2, st] of links) {
      const [x1, y1] = screen(...project(la1, lo1));
      const [x2, y2] = screen(...project(la2, lo2));
      if (!onScreen(x1, y1) && !onScreen(x2, y2)) continue;
      const cls = st === "t" ? ' class="tentative"' : "";
      out.push(`<line x1="${f(x1, 1)}" y1="${f(y1, 1)}" x2="${f(x2, 1)}" y2="${f(y2, 1)}"${cls}></line>`);
    }
    return out.join("");
  }

  function drawSystem(rows) {
    // Every system track gets its element (with its id), on the map or not: the list is capped
    // by the feed, and the ids are what a reader of the page's DOM looks for.
    return rows
      .map(([id, lat, lon, ve, vn, sigma, members, confirmed]) => {
        const [x, y] = project(lat, lon);
        const [sx, sy] = screen(x, y);
        const [lx, ly] = screen(x + (ve * LEADER_S) / 1000, y + (vn * LEADER_S) / 1000);
        const label = show.labels ? `<text x="${f(sx + 7, 1)}" y="${f(sy - 6, 1)}">${esc(id)}</text>` : "";
        const cls = confirmed ? "system-track" : "system-track tentative";
        const title = `${id}: ${members} member(s), \u03c3 ${f(sigma)} m, ${f(Math.hypot(ve, vn))} m/s`;
        return (
          `<g class="${cls}" data-track-id="${esc(id)}"><title>${esc(title)}</title>` +
          `<line x1="${f(sx, 1)}" y1="${f(sy, 1)}" x2="${f(lx, 1)}" y2="${f(ly, 1)}"></line>` +
          `<rect x="${f(sx - 4, 1)}" y="${f(sy - 4, 1)}" width="8" height="8"></rect>${label}</g>`
        );
      })
      .join("");
  }

  function drawBiases(biases, sites) {
    const at = Object.fromEntries(sites.map((s) => [s.radar_id, s]));
    const known = biases.filter((b) => b.radar_id in at);
    // displacement (m) of a plot on the ring due north of the radar: east = azimuth, north = range
    const vec = (b) => [RANGE_KM * 1000 * b.azimuth_deg * RAD, b.range_m];
    const sig = (b) => [RANGE_KM * 1000 * b.azimuth_sigma_deg * RAD, b.range_sigma_m];
    const longest = Math.max(1, ...known.map((b) => Math.hypot(...vec(b)) + Math.max(...sig(b))));
    const mPerPx = BIAS_SCALES.find((s) => longest / s <= BIAS_MAX_PX) || BIAS_SCALES[BIAS_SCALES.length - 1];
    $("bias-scale").textContent = String(mPerPx);
    if (!show.biases) return "";
    return known
      .map((b) => {
        const s = at[b.radar_id];
        const [sx, sy] = screen(...project(s.latitude_deg, s.longitude_deg));
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

  function draw() {
    const d = state.data;
    if (!d || !state.centre || !state.view) return;
    drawGraticule();
    layer.coverage.innerHTML = drawCoverage(d.sites);
    layer.links.innerHTML = drawLinks(d.links);
    layer.tracks.innerHTML = drawTracks(d.tracks);
    layer.system.innerHTML = show.system ? drawSystem(d.system_tracks) : "";
    layer.sites.innerHTML = drawSites(d.sites);
    layer.biases.innerHTML = drawBiases(d.biases, d.sites);
  }

  // -- panels --------------------------------------------------------------------------------
  function rates(d) {
    const counters = {};
    for (const r of d.health.radars) counters[r.radar_id] = [r.plots, r.batches];
    state.history.push({ wall: d.wall_s, counters });
    while (state.history.length > 2 && d.wall_s - state.history[0].wall > RATE_WINDOW_S) state.history.shift();
    const first = state.history[0];
    const dt = d.wall_s - first.wall;
    const out = {};
    for (const [radar, [plots, batches]] of Object.entries(counters)) {
      const old = first.counters[radar];
      out[radar] = dt > 0 && old ? [(plots - old[0]) / dt, (batches - old[1]) / dt] : null;
    }
    return out;
  }

  function panels(d) {
    const rate = rates(d);
    $("health").tBodies[0].innerHTML = d.health.radars
      .map((r) => {
        const lag = r.last_time_s === null ? NaN : d.wall_s - r.last_time_s;
        const lagClass = r.expired ? "bad" : Math.abs(lag) > 10 ? "warn" : "";
        const rt = rate[r.radar_id];
        const rateText = rt ? `${f(rt[0])}/s (${f(rt[1], 1)} b/s)` : "-";
        const rejClass = r.rejected + r.lost_batches > 0 ? "warn" : "";
        return (
          `<tr data-radar-id="${esc(r.radar_id)}"><td><span class="swatch" style="background:${colour(r.radar_id)}">` +
          `</span>${esc(r.radar_id)}${r.expired ? " (expired)" : ""}</td><td>${rateText}</td>` +
          `<td class="${lagClass}">${duration(lag)}</td>` +
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
    const c = d.health.correlation;
    const q = d.health.queue || {};
    const items = [
      ["method", esc(d.health.method)],
      ["latency p50 / p99", `${f(c.p50_ms, 1)} / ${f(c.p99_ms, 1)} ms`],
      ["last update", `${f(c.last_ms, 1)} ms`],
      ["updates", String(c.updates)],
      ["pairs", `${d.health.pairs_confirmed} confirmed, ${d.health.pairs_tentative} tentative`],
      ["ingest queue", `${q.depth ?? "-"} / ${q.capacity ?? "-"} (dropped ${q.dropped ?? 0})`],
    ];
    if (d.health.missing_partitions.length) items.push(["missing workers", d.health.missing_partitions.join(", ")]);
    $("correlation").innerHTML = items.map(([k, v]) => `<dt>${k}</dt><dd>${v}</dd>`).join("");
    const rej = Object.entries(d.health.rejected);
    $("rejections").innerHTML = rej.length
      ? rej.map(([k, v]) => `<li>${esc(k)}: ${v}</li>`).join("")
      : "<li>none</li>";
    const nTracks = Object.values(d.tracks).reduce((a, r) => a + r.length, 0);
    $("summary").textContent =
      `data time ${utc(d.time_s)} \u00b7 ${d.sites.length} radars \u00b7 ` +
      `${d.system_tracks.length} system tracks \u00b7 ${nTracks} radar tracks \u00b7 ${d.links.length} links`;
    const t = d.truncated;
    const cut = Object.entries(t).filter(([, v]) => v > 0);
    $("truncated").hidden = !cut.length;
    $("truncated").textContent = cut.length
      ? `Not drawn (over ${d.max_items} per kind): ` + cut.map(([k, v]) => `${v} ${k.replace("_", " ")}`).join(", ")
      : "";
  }

  // -- live data -----------------------------------------------------------------------------
  function connection(cls, text) {
    const el = $("connection");
    el.className = cls;
    el.textContent = text;
  }

  function take(d) {
    state.data = d;
    state.updates += 1;
    state.lastEvent = Date.now();
    document.body.dataset.updates = String(state.updates);
    document.body.dataset.timeS = d.time_s === null ? "" : String(d.time_s);
    connection("state-live", "live");
    if (setCentre(d) || !state.view) fit();
    panels(d);
    schedule();
  }

  function connect() {
    const feed = new URLSearchParams();
    for (const k of ["status", "max_items"]) if (params.has(k)) feed.set(k, params.get(k));
    const q = feed.toString();
    const source = new EventSource("picture/events" + (q ? "?" + q : ""));
    source.addEventListener("snapshot", (e) => take(JSON.parse(e.data)));
    source.onerror = () => connection("state-down", "reconnecting");
  }

  window.setInterval(() => {
    if (state.lastEvent && Date.now() - state.lastEvent > STALE_S * 1000) connection("state-wait", "stale");
  }, 1000);

  // -- interaction ---------------------------------------------------------------------------
  svg.addEventListener(
    "wheel",
    (e) => {
      if (!state.view) return;
      e.preventDefault();
      const r = svg.getBoundingClientRect();
      const sx = e.clientX - r.left;
      const sy = e.clientY - r.top;
      const [x, y] = world(sx, sy);
      const k = Math.exp(-e.deltaY * 0.0015);
      state.view.scale = Math.min(2000, Math.max(0.01, state.view.scale * k));
      const [x2, y2] = world(sx, sy);
      state.view.cx += x - x2;
      state.view.cy += y - y2;
      schedule();
    },
    { passive: false },
  );
  let drag = null;
  svg.addEventListener("pointerdown", (e) => {
    if (!state.view) return;
    drag = { x: e.clientX, y: e.clientY, cx: state.view.cx, cy: state.view.cy };
    svg.setPointerCapture(e.pointerId);
    svg.classList.add("dragging");
  });
  svg.addEventListener("pointermove", (e) => {
    if (!drag) return;
    state.view.cx = drag.cx - (e.clientX - drag.x) / state.view.scale;
    state.view.cy = drag.cy + (e.clientY - drag.y) / state.view.scale;
    schedule();
  });
  const endDrag = () => {
    drag = null;
    svg.classList.remove("dragging");
  };
  svg.addEventListener("pointerup", endDrag);
  svg.addEventListener("pointercancel", endDrag);
  svg.addEventListener("dblclick", fit);
  window.addEventListener("resize", schedule);
  $("layers").addEventListener("change", (e) => {
    show[e.target.name] = e.target.checked;
    schedule();
  });

  connect();
})();
