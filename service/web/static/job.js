/* A job's page: state while it runs, then the block's map (Leaflet, canvas, local metres),
   the per-row and block summaries, the changes since the block's previous capture (a
   capture of an orchard block: trees coloured by growth, removed / new / replanted trees,
   lagging rows, a tree's history on click), and the sortable per-tree table. The same script
   drives report.html, where the data is inlined in the page. */
(function () {
  "use strict";
  const O = window.Orchard;
  const el = O.el;
  const POLL_MS = 2000;
  const PAGE = 200; // table rows per page: 5,000 rows at once would make the page sluggish

  const LABELS = {
    tree_id: ["Tree", 0], row: ["Row", 0], position: ["Position", 0], young: ["Young", 0],
    trunk_x: ["Trunk x", 2], trunk_y: ["Trunk y", 2], trunk_z: ["Trunk z", 2],
    height_m: ["Height [m]", 2], crown_diameter_m: ["Crown diameter [m]", 2], crown_area_m2: ["Crown area [m²]", 2],
    crown_volume_m3: ["Crown volume [m³]", 2], trunk_diameter_m: ["Trunk diameter [m]", 3], n_points: ["Points", 0],
    wood_fraction: ["Wood fraction", 2], tree_key: ["Tree key", 0], status: ["Status", 0],
    height_change_m: ["Height change [m]", 2], crown_volume_change_m3: ["Crown volume change [m³]", 2],
    trunk_diameter_change_m: ["Trunk diameter change [m]", 3], days_since_previous: ["Days since previous", 0],
  };
  const NOT_METRICS = new Set(["tree_id", "tree_key", "trunk_x", "trunk_y", "trunk_z", "row", "position"]);
  // growth: shrank red, no change pale yellow, grew green (ColorBrewer RdYlGn, readable by most colour-blind eyes)
  const DIVERGING = ["#a50026", "#d73027", "#f46d43", "#fdae61", "#fee08b", "#d9ef8b", "#a6d96a", "#66bd63", "#1a9850", "#006837"];
  const isChange = (name) => /_change_/.test(name);
  // a row lags when its trees' mean growth is below the block's by more than this share of it (and 1 cm)
  const LAG_SHARE = 0.2;
  const SVG = "http://www.w3.org/2000/svg";
  // viridis: ordered, readable by the colour-blind, prints in grey
  const RAMP = ["#440154", "#482878", "#3e4989", "#31688e", "#26828e", "#1f9e89", "#35b779", "#6ece58", "#b5de2b", "#fde725"];
  const NO_VALUE = "#bdbdbd";

  function label(name) { return (LABELS[name] || [name])[0]; }
  function digits(name) { return LABELS[name] ? LABELS[name][1] : 2; }

  function rgb(hex) { return [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16)); }
  const RAMP_RGB = RAMP.map(rgb), DIVERGING_RGB = DIVERGING.map(rgb);
  function rampColour(t, ramp) {
    const stops = ramp || RAMP_RGB;
    const x = Math.min(Math.max(t, 0), 1) * (stops.length - 1);
    const i = Math.min(Math.floor(x), stops.length - 2), f = x - i;
    const a = stops[i], b = stops[i + 1];
    return "rgb(" + a.map((v, k) => Math.round(v + (b[k] - v) * f)).join(",") + ")";
  }

  /* "12/37", "row 12 tree 37", "r12 p37", "12 37" → {row, position}; "row 12", "r12" →
     {row}; "37", "tree 37", "id 37", "#37" → {id}. */
  function parseQuery(text) {
    const q = text.trim().toLowerCase().replace(/\s+/g, " ");
    let m = q.match(/^(?:row|r) ?(\d+)$/);
    if (m) return { row: +m[1] };
    m = q.match(/^(?:row|r)? ?(\d+) ?(?:\/|,|\s|,? ?(?:tree|t|position|pos|p)) ?(\d+)$/);
    if (m && /\D/.test(q)) return { row: +m[1], position: +m[2] };
    m = q.match(/^(?:tree|id|#)? ?(\d+)$/);
    if (m) return { id: +m[1], bare: /^\d+$/.test(q) };
    return null;
  }

  /* A table or details cell: young as yes/no, numbers with the column's digits. */
  function cell(name, v) {
    if (name === "young" && v !== null && v !== undefined) return v ? "yes" : "no";
    return O.fmt(v, digits(name));
  }

  /* The table's columns: the address first, then the id and the measures; the trunk's
     height (in the details) left out so that the table fits the page. */
  function tableKeys(cols) {
    const first = ["row", "position", "tree_id"].filter((k) => k in cols);
    const last = ["young", "trunk_x", "trunk_y"].filter((k) => k in cols);
    const rest = Object.keys(cols).filter((k) => !first.includes(k) && !last.includes(k) && k !== "trunk_z");
    return first.concat(rest, last);
  }

  const MARK = "#e8590c";

  function insidePolygon(ring, x, y) {
    let inside = false;
    for (let a = 0, b = ring.length - 2; a < ring.length; b = a, a += 2) {
      const xa = ring[a], ya = ring[a + 1], xb = ring[b], yb = ring[b + 1];
      if (ya > y !== yb > y && x < ((xb - xa) * (y - ya)) / (yb - ya) + xa) inside = !inside;
    }
    return inside;
  }

  /* One canvas over the map (with a margin, so a pan shows trees before it ends), drawn
     by the view after each move or zoom; scaled by CSS during the zoom animation. */
  const TreeCanvas = L.Layer.extend({
    PAD: 0.3,
    initialize(view) { this.view = view; },
    onAdd(map) {
      this.canvas = L.DomUtil.create("canvas", "leaflet-zoom-animated");
      map.getPanes().overlayPane.appendChild(this.canvas);
      map.on("moveend viewreset resize", this.redraw, this);
      map.on("zoomanim", this.animateZoom, this);
      this.redraw();
    },
    onRemove(map) {
      L.DomUtil.remove(this.canvas);
      map.off("moveend viewreset resize", this.redraw, this);
      map.off("zoomanim", this.animateZoom, this);
    },
    scale() { return this._map.getZoomScale(this._map.getZoom(), 0); }, // pixels per metre
    animateZoom(e) {
      const offset = this._map._latLngBoundsToNewLayerBounds(this.bounds, e.zoom, e.center).min;
      L.DomUtil.setTransform(this.canvas, offset, this._map.getZoomScale(e.zoom));
    },
    redraw() {
      const map = this._map, size = map.getSize(), dpr = window.devicePixelRatio || 1;
      const px = Math.round(size.x * this.PAD), py = Math.round(size.y * this.PAD);
      const w = size.x + 2 * px, h = size.y + 2 * py;
      this.bounds = L.latLngBounds(map.containerPointToLatLng([-px, size.y + py]), map.containerPointToLatLng([size.x + px, -py]));
      L.DomUtil.setPosition(this.canvas, map.containerPointToLayerPoint([-px, -py]));
      this.canvas.width = Math.round(w * dpr);
      this.canvas.height = Math.round(h * dpr);
      this.canvas.style.width = w + "px";
      this.canvas.style.height = h + "px";
      const ctx = this.canvas.getContext("2d");
      ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
      const origin = map.latLngToContainerPoint([0, 0]);
      this.view.paint(ctx, { ox: origin.x + px, oy: origin.y + py, s: this.scale(), w, h });
    },
  });

  class JobView {
    constructor(data, options) {
      this.d = data;
      this.opts = options || {};
      this.n = data.n_trees;
      this.cols = data.columns;
      this.metrics = Object.keys(this.cols).filter((k) => !NOT_METRICS.has(k));
      this.text = data.text || {};
      // a capture with a previous one opens coloured by growth
      const grown = (this.cols.height_change_m || []).some((v) => v !== null);
      this.metric = grown ? "height_change_m" : this.metrics.includes("height_m") ? "height_m" : this.metrics[0];
      this.sort = { key: "tree_id", dir: 1 };
      this.page = 0;
      this.selected = -1;
      this.mark = null; // what a find or a click outlines: {tree: i}, {gap: g} or {row: r, idx: [i...]}; one at a time
      this.byId = new Map();
      (this.cols.tree_id || []).forEach((id, i) => this.byId.set(id, i));
    }

    draw() {
      document.getElementById("mapsection").hidden = false;
      document.getElementById("tree-count").textContent = O.fmt(this.n);
      this.fillMetricChoice();
      this.recolour();
      this.drawMap();
      this.summaries();
      this.changes();
      this.table();
      document.getElementById("searchform").addEventListener("submit", (ev) => {
        ev.preventDefault();
        this.search(document.getElementById("search").value);
      });
      // the first frame with every tree on it: what bench/webpage.py times
      requestAnimationFrame(() => requestAnimationFrame(() => {
        window.orchardFirstDraw = performance.now();
        document.body.dataset.drawn = String(this.n);
      }));
    }

    drawMap() {
      const d = this.d;
      const map = (this.map = L.map("map", {
        crs: L.CRS.Simple, minZoom: -6, maxZoom: 7, zoomSnap: 0.25, attributionControl: false,
      }));
      L.control.scale({ imperial: false, metric: true, maxWidth: 160 }).addTo(map);
      // each tree's shape once, in local metres: its footprint, or a circle of its crown
      this.shape = new Array(this.n);
      this.box = new Float64Array(4 * this.n).fill(NaN);
      const crownD = this.cols.crown_diameter_m || [];
      const bounds = L.latLngBounds([]);
      for (let i = 0; i < this.n; i++) {
        const x = d.x[i], y = d.y[i];
        if (x === null || y === null) continue;
        const o = d.outlines ? d.outlines[i] : null;
        let x0, y0, x1, y1;
        if (o && o.length >= 6) {
          this.shape[i] = Float64Array.from(o);
          x0 = x1 = x; y0 = y1 = y;
          for (let k = 0; k < o.length; k += 2) { x0 = Math.min(x0, o[k]); x1 = Math.max(x1, o[k]); y0 = Math.min(y0, o[k + 1]); y1 = Math.max(y1, o[k + 1]); }
        } else {
          const r = Math.max((crownD[i] || 1) / 2, 0.2);
          this.shape[i] = r;
          x0 = x - r; x1 = x + r; y0 = y - r; y1 = y + r;
        }
        this.box.set([x0, y0, x1, y1], 4 * i);
        bounds.extend([[y0, x0], [y1, x1]]);
      }
      (d.gaps || []).forEach((g) => { if (g.x !== undefined && g.x !== null) bounds.extend([g.y, g.x]); });
      if (bounds.isValid()) map.fitBounds(bounds.pad(0.05));
      else map.setView([0, 0], 0);
      this.rowLabels = this.rowStarts();
      this.layer = new TreeCanvas(this).addTo(map);
      map.on("click", (e) => this.clicked(e.latlng.lng, e.latlng.lat));
    }

    /* Draw every visible tree on the canvas: one path per colour, one for the outlines,
       one for the trunks (a path per tree would take seconds with 5,000 trees). */
    paint(ctx, t) {
      const { ox, oy, s, w, h } = t;
      const X = (x) => ox + x * s, Y = (y) => oy - y * s;
      const xmin = -ox / s, xmax = (w - ox) / s, ymin = (oy - h) / s, ymax = oy / s;
      const visible = (i) => { const b = 4 * i; return this.box[b] <= xmax && this.box[b + 2] >= xmin && this.box[b + 1] <= ymax && this.box[b + 3] >= ymin; };
      const trace = (i) => {
        const sh = this.shape[i];
        if (typeof sh === "number") {
          ctx.moveTo(X(this.d.x[i] + sh), Y(this.d.y[i]));
          ctx.arc(X(this.d.x[i]), Y(this.d.y[i]), sh * s, 0, 2 * Math.PI);
        } else {
          ctx.moveTo(X(sh[0]), Y(sh[1]));
          for (let k = 2; k < sh.length; k += 2) ctx.lineTo(X(sh[k]), Y(sh[k + 1]));
          ctx.closePath();
        }
      };
      ctx.clearRect(0, 0, w, h);
      const shown = [];
      for (let i = 0; i < this.n; i++) if (this.shape[i] !== undefined && visible(i)) shown.push(i);
      if (this.d.rows) {
        ctx.beginPath();
        for (const r of this.d.rows) {
          if (!r.line || r.line.length < 4) continue;
          ctx.moveTo(X(r.line[0]), Y(r.line[1]));
          for (let k = 2; k < r.line.length; k += 2) ctx.lineTo(X(r.line[k]), Y(r.line[k + 1]));
        }
        ctx.setLineDash([6, 4]); ctx.strokeStyle = "#8a7f62"; ctx.lineWidth = 1.5; ctx.stroke(); ctx.setLineDash([]);
      }
      ctx.globalAlpha = 0.8;
      for (let b = 0; b < this.binColour.length; b++) {
        ctx.beginPath();
        let any = false;
        for (const i of shown) if (this.bin[i] === b) { trace(i); any = true; }
        if (any) { ctx.fillStyle = this.binColour[b]; ctx.fill(); }
      }
      ctx.globalAlpha = 1;
      // strokes cost most: outlines and round trunks once they can be told apart
      // (a few metres across the screen's pixels, or fewer trees in view)
      const few = shown.length <= 1500;
      if (s >= 6 || few) {
        ctx.beginPath(); for (const i of shown) trace(i);
        ctx.strokeStyle = "#333"; ctx.lineWidth = 1; ctx.stroke();
      }
      if (few) {
        ctx.beginPath();
        const r = Math.min(Math.max(s * 0.1, 2), 5);
        for (const i of shown) { ctx.moveTo(X(this.d.x[i]) + r, Y(this.d.y[i])); ctx.arc(X(this.d.x[i]), Y(this.d.y[i]), r, 0, 2 * Math.PI); }
        ctx.fillStyle = "#2b1a0e"; ctx.fill(); ctx.strokeStyle = "#fff"; ctx.stroke();
      } else if (s >= 5) { // below that a trunk would hide its crown
        ctx.fillStyle = "#2b1a0e";
        for (const i of shown) ctx.fillRect(X(this.d.x[i]) - 1, Y(this.d.y[i]) - 1, 3, 3);
      }
      if (this.d.gaps && this.d.gaps.length) {
        ctx.beginPath();
        for (const g of this.d.gaps) if (g.x !== null && g.x !== undefined) { ctx.moveTo(X(g.x) + Math.max(0.5 * s, 3), Y(g.y)); ctx.arc(X(g.x), Y(g.y), Math.max(0.5 * s, 3), 0, 2 * Math.PI); }
        ctx.setLineDash([3, 3]); ctx.strokeStyle = "#b3261e"; ctx.lineWidth = 1.5; ctx.stroke(); ctx.setLineDash([]);
      }
      this.paintRowLabels(ctx, X, Y, w, h);
      this.paintMark(ctx, trace, X, Y, s);
      this.drawn = shown.length;
    }

    /* Where each row begins: beyond its first tree (position 1 end), away from the
       second, in local metres; from the trees' addresses (and the empty slots). */
    rowStarts() {
      const r = this.cols.row, p = this.cols.position;
      if (!r || !p) return [];
      const byRow = new Map();
      const add = (row, pos, x, y, rad) => {
        if (row === null || pos === null || x === null || x === undefined || y === null || y === undefined) return;
        if (!byRow.has(row)) byRow.set(row, []);
        byRow.get(row).push({ pos, x, y, rad });
      };
      for (let i = 0; i < this.n; i++) add(r[i], p[i], this.d.x[i], this.d.y[i], typeof this.shape[i] === "number" ? this.shape[i] : 1.5);
      (this.d.gaps || []).forEach((g) => add(g.row, g.position, g.x, g.y, 1));
      const out = [];
      for (const [row, pts] of byRow) {
        pts.sort((a, b) => a.pos - b.pos);
        const a = pts[0], b = pts[1];
        let ux = -1, uy = 0;
        if (b) { const len = Math.hypot(b.x - a.x, b.y - a.y) || 1; ux = (a.x - b.x) / len; uy = (a.y - b.y) / len; }
        out.push({ row, x: a.x, y: a.y, ux, uy, rad: a.rad });
      }
      return out.sort((a, b) => a.row - b.row);
    }

    /* Row numbers at the rows' starts; a label that would overlap one drawn already is left out. */
    paintRowLabels(ctx, X, Y, w, h) {
      if (!this.rowLabels || !this.rowLabels.length) return;
      const s = this.layer ? this.layer.scale() : 1, placed = [];
      ctx.font = "bold 12px system-ui, sans-serif"; ctx.textAlign = "center"; ctx.textBaseline = "middle";
      ctx.lineJoin = "round"; ctx.lineWidth = 3; ctx.strokeStyle = "#fff"; ctx.fillStyle = "#4a3f22";
      this.labelsDrawn = 0;
      for (const l of this.rowLabels) {
        const off = l.rad * s + 12;
        const px = X(l.x) + l.ux * off, py = Y(l.y) - l.uy * off;
        if (px < -20 || py < -20 || px > w + 20 || py > h + 20) continue;
        if (placed.some(([qx, qy]) => Math.abs(qx - px) < 22 && Math.abs(qy - py) < 13)) continue;
        placed.push([px, py]);
        ctx.strokeText(String(l.row), px, py); ctx.fillText(String(l.row), px, py);
        this.labelsDrawn++;
      }
    }

    /* The one thing found or clicked: a tree's outline, an empty slot's ring, a row's trees. */
    paintMark(ctx, trace, X, Y, s) {
      const m = this.mark;
      if (!m) return;
      ctx.beginPath();
      if (m.tree !== undefined && this.shape[m.tree] !== undefined) trace(m.tree);
      else if (m.gap) { const r = Math.max(0.9 * s, 9); ctx.moveTo(X(m.gap.x) + r, Y(m.gap.y)); ctx.arc(X(m.gap.x), Y(m.gap.y), r, 0, 2 * Math.PI); }
      else if (m.idx) for (const i of m.idx) if (this.shape[i] !== undefined) trace(i);
      // a white halo under the orange: it stands out on every colour of the ramp
      ctx.strokeStyle = "#fff"; ctx.lineWidth = 7; ctx.stroke();
      ctx.strokeStyle = MARK; ctx.lineWidth = 4; ctx.stroke();
    }

    /* Zoom so that the box (local metres) fills a good part of the map, a tree with its
       neighbours around it: a tree of a 1,000-tree block is a few pixels when the whole block shows. */
    zoomTo(x0, y0, x1, y1) {
      const m = Math.max(4, 0.1 * Math.max(x1 - x0, y1 - y0));
      this.map.fitBounds([[y0 - m, x0 - m], [y1 + m, x1 + m]], { animate: false, maxZoom: 6 });
      this.layer.redraw();
    }

    /* Clear what was outlined before (on the map and in the tables). */
    unmark() {
      this.mark = null;
      this.selected = -1;
      document.querySelectorAll("#treestable tr.selected").forEach((r) => r.classList.remove("selected"));
    }

    selectRow(row) {
      const r = this.cols.row;
      const idx = [];
      for (let i = 0; i < this.n; i++) if (r[i] === row) idx.push(i);
      const gaps = (this.d.gaps || []).filter((g) => g.row === row);
      if (!idx.length && !gaps.length) return false;
      this.unmark();
      this.mark = { row, idx };
      let x0 = Infinity, y0 = Infinity, x1 = -Infinity, y1 = -Infinity;
      for (const i of idx) if (this.shape[i] !== undefined) { const b = 4 * i; x0 = Math.min(x0, this.box[b]); y0 = Math.min(y0, this.box[b + 1]); x1 = Math.max(x1, this.box[b + 2]); y1 = Math.max(y1, this.box[b + 3]); }
      for (const g of gaps) if (g.x !== null && g.x !== undefined) { x0 = Math.min(x0, g.x); y0 = Math.min(y0, g.y); x1 = Math.max(x1, g.x); y1 = Math.max(y1, g.y); }
      if (x0 <= x1) this.zoomTo(x0, y0, x1, y1); else this.layer.redraw();
      const young = this.cols.young ? idx.filter((i) => this.cols.young[i]).length : null;
      const facts = [["Trees", O.fmt(idx.length)]];
      if (this.d.gaps) facts.push(["Empty slots", O.fmt(gaps.length)]);
      if (young !== null) facts.push(["Young", O.fmt(young)]);
      document.getElementById("details").replaceChildren(el("h3", { id: "selected-row", text: "Row " + row }),
        el("dl", {}, facts.flatMap(([k, v]) => [el("dt", { text: k }), el("dd", { text: v })])));
      idx.forEach((i) => { const tr = document.querySelector(`#treestable tr[data-i="${i}"]`); if (tr) tr.classList.add("selected"); });
      return true;
    }

    /* The tree under a click: the crowns holding the point, the one whose trunk is nearest. */
    clicked(x, y) {
      const tol = 4 / this.layer.scale(); // a few pixels, in metres
      let best = -1, bestD = Infinity;
      for (let i = 0; i < this.n; i++) {
        const b = 4 * i, sh = this.shape[i];
        if (sh === undefined || x < this.box[b] - tol || x > this.box[b + 2] + tol || y < this.box[b + 1] - tol || y > this.box[b + 3] + tol) continue;
        const dx = x - this.d.x[i], dy = y - this.d.y[i], dist = Math.hypot(dx, dy);
        const inside = typeof sh === "number" ? dist <= sh + tol : dist <= tol || insidePolygon(sh, x, y);
        if (inside && dist < bestD) { best = i; bestD = dist; }
      }
      if (best >= 0) { this.select(best, false); return; }
      const gap = (this.d.gaps || []).find((g) => Math.hypot(g.x - x, g.y - y) <= 0.5 + tol);
      if (gap) this.showGap(gap, false);
    }

    fillMetricChoice() {
      const sel = document.getElementById("metric");
      sel.replaceChildren(...this.metrics.map((m) => el("option", { value: m, text: label(m) })));
      sel.value = this.metric;
      sel.addEventListener("change", () => { this.metric = sel.value; this.recolour(); });
    }

    recolour() {
      const v = this.cols[this.metric] || [];
      let lo = Infinity, hi = -Infinity;
      for (const x of v) if (x !== null) { lo = Math.min(lo, x); hi = Math.max(hi, x); }
      const diverging = isChange(this.metric) && lo <= hi;
      if (diverging) { const m = Math.max(Math.abs(lo), Math.abs(hi)) || 1; lo = -m; hi = m; } // no change in the middle
      const span = hi > lo ? hi - lo : 1;
      const binary = !diverging && v.every((x) => x === null || x === 0 || x === 1);
      // colours in bins: one fill per bin when drawing
      const BINS = 48;
      const ramp = diverging ? DIVERGING_RGB : RAMP_RGB;
      this.binColour = binary ? [NO_VALUE, RAMP[2], RAMP[8]] : [NO_VALUE].concat([...Array(BINS).keys()].map((k) => rampColour(k / (BINS - 1), ramp)));
      this.bin = new Uint8Array(this.n);
      for (let i = 0; i < this.n; i++) {
        const x = v[i];
        this.bin[i] = x === null || x === undefined ? 0 : binary ? 1 + (x ? 1 : 0) : 1 + Math.round(((x - lo) / span) * (BINS - 1));
      }
      document.body.dataset.metric = this.metric;
      if (this.layer) this.layer.redraw();
      const legend = document.getElementById("legend");
      const parts = [el("strong", { text: label(this.metric) })];
      if (binary) {
        parts.push(el("span", { class: "swatch", style: "background:" + RAMP[2] }), "no",
                   el("span", { class: "swatch", style: "background:" + RAMP[8] }), "yes");
      } else if (lo <= hi) {
        const colours = diverging ? DIVERGING : RAMP;
        const stops = colours.map((c, k) => c + " " + Math.round((100 * k) / (colours.length - 1)) + "%").join(",");
        parts.push((diverging ? "shrank " : "") + O.fmt(lo, digits(this.metric)),
                   el("span", { class: "ramp", style: "background:linear-gradient(to right," + stops + ")" }),
                   (diverging ? "+" : "") + O.fmt(hi, digits(this.metric)) + (diverging ? " grew" : ""));
      }
      parts.push(el("span", { class: "swatch", style: "background:" + NO_VALUE }), diverging ? "no previous measure" : "not measured");
      if (this.d.gaps && this.d.gaps.length) parts.push(el("span", { class: "swatch", style: "border:1.5px dashed #b3261e;border-radius:50%" }), "empty slot");
      if (this.d.rows && this.d.rows.length) parts.push(el("span", { class: "swatch", style: "border:0;border-top:2px dashed #8a7f62;height:2px" }), "row");
      if (this.cols.row && this.cols.position) parts.push(el("strong", { text: "7", style: "color:#4a3f22" }), "row number, at its first tree");
      legend.replaceChildren(...parts);
    }

    details(i) {
      const items = [];
      for (const k of Object.keys(this.cols)) items.push(el("dt", { text: label(k) }), el("dd", { text: cell(k, this.cols[k][i]) }));
      for (const k of Object.keys(this.text)) items.push(el("dt", { text: label(k) }), el("dd", { text: O.fmt(this.text[k][i]) }));
      return el("dl", {}, items);
    }

    /* The rows of one tree in the block's history, oldest first (the file's order). */
    historyOf(key) {
      const h = this.d.history;
      if (!h || key === null || key === undefined) return [];
      if (!this.histIndex) {
        this.histIndex = new Map();
        h.tree_key.forEach((k, j) => { if (!this.histIndex.has(k)) this.histIndex.set(k, []); this.histIndex.get(k).push(j); });
      }
      return (this.histIndex.get(key) || []).map((j) => ({
        capture: h.captures[h.capture[j]], date: h.dates[h.capture[j]], status: h.status ? h.status[j] : null,
        row: h.row ? h.row[j] : null, position: h.position ? h.position[j] : null,
        height_m: h.height_m ? h.height_m[j] : null, crown_volume_m3: h.crown_volume_m3 ? h.crown_volume_m3[j] : null,
        trunk_diameter_m: h.trunk_diameter_m ? h.trunk_diameter_m[j] : null,
      }));
    }

    /* A tree's history: its height over the captures (a small line chart) and a table. */
    historyBlock(key) {
      const rows = this.historyOf(key);
      if (!rows.length) return null;
      const parts = [el("h4", { text: "History (" + rows.length + " capture" + (rows.length > 1 ? "s" : "") + ")" })];
      const pts = rows.map((r, k) => [k, r.height_m]).filter(([, v]) => v !== null);
      if (pts.length >= 2) {
        const W = 230, H = 70, P = 6;
        const vs = pts.map(([, v]) => v), lo = Math.min(...vs), hi = Math.max(...vs), span = hi > lo ? hi - lo : 1;
        // along time when every capture has a date (captures weeks or months apart), else evenly
        const t = rows.map((r) => Date.parse(r.date || ""));
        const byTime = t.every((v) => !Number.isNaN(v)) && t[t.length - 1] > t[0];
        const at = (k) => (byTime ? (t[k] - t[0]) / (t[t.length - 1] - t[0]) : k / Math.max(rows.length - 1, 1));
        const X = (k) => P + at(k) * (W - 2 * P), Y = (v) => H - P - ((v - lo) * (H - 2 * P)) / span;
        const svg = document.createElementNS(SVG, "svg");
        svg.setAttribute("viewBox", `0 0 ${W} ${H}`); svg.setAttribute("class", "sparkline");
        svg.setAttribute("role", "img"); svg.setAttribute("aria-label", "height over the captures");
        const line = document.createElementNS(SVG, "polyline");
        line.setAttribute("points", pts.map(([k, v]) => X(k).toFixed(1) + "," + Y(v).toFixed(1)).join(" "));
        svg.appendChild(line);
        for (const [k, v] of pts) {
          const c = document.createElementNS(SVG, "circle");
          c.setAttribute("cx", X(k).toFixed(1)); c.setAttribute("cy", Y(v).toFixed(1)); c.setAttribute("r", "2.5");
          svg.appendChild(c);
        }
        parts.push(svg);
      }
      const head = el("tr", {}, ["Captured", "Status", "Height [m]", "Crown volume [m³]", "Trunk diameter [m]"].map((t) => el("th", { text: t })));
      const body = rows.map((r) => el("tr", {}, [
        el("td", { class: "text", text: r.date || r.capture }), el("td", { class: "text", text: r.status || "–" }),
        el("td", { text: O.fmt(r.height_m, 2) }), el("td", { text: O.fmt(r.crown_volume_m3, 2) }), el("td", { text: O.fmt(r.trunk_diameter_m, 3) }),
      ]));
      parts.push(el("table", { class: "data history", id: "tree-history" }, [el("thead", {}, [head]), el("tbody", {}, body)]));
      return el("div", { class: "treehistory" }, parts);
    }

    /* Changes since the block's previous capture: removed, new and replanted trees, and
       the rows whose trees grew less than the block's (shown only for a capture of an
       orchard block that had a previous one). */
    changes() {
      const section = document.getElementById("changes");
      const status = this.text.status, growth = this.cols.height_change_m;
      const removed = (this.d.gaps || []).filter((g) => g.tree_key !== null && g.tree_key !== undefined);
      const hadPrevious = (this.d.capture && this.d.capture.previous_capture_id) || removed.length ||
        (growth || []).some((v) => v !== null) || (status || []).some((v) => v && v !== "new");
      if (!section || !status) return;
      section.hidden = false;
      if (!hadPrevious) {
        section.replaceChildren(el("h2", { text: "Changes" }),
          el("p", { id: "firstcapture", class: "small", text: "The block's first capture: every tree has its key now; growth, and removed, new and replanted trees, show from the next capture." }));
        return;
      }
      const treeItem = (i) => el("li", {}, [el("a", { href: "#", text: "Tree " + this.cols.tree_id[i] + this.address(i) + this.keyText(i),
        onclick: (ev) => { ev.preventDefault(); this.select(i, true); } })]);
      const listOf = (id, title, items, none) => el("div", { class: "changelist" }, [el("h3", { text: title + " (" + items.length + ")" }),
        items.length ? el("ul", { id }, items) : el("p", { id, class: "small", text: none })]);
      const byStatus = (s) => [...Array(this.n).keys()].filter((i) => status[i] === s);
      const gone = removed.map((g) => el("li", {}, [el("a", { href: "#",
        text: (g.row !== null && g.row !== undefined ? `row ${g.row} tree ${g.position}` : "slot") + ` (key ${g.tree_key}), last seen ${this.captureName(g.since)}`,
        onclick: (ev) => { ev.preventDefault(); this.showGap(g); } })]));
      const lists = [
        listOf("removedtrees", "Removed", gone, "No tree is gone."),
        listOf("newtrees", "New", byStatus("new").map(treeItem), "No new tree."),
        listOf("replantedtrees", "Replanted", byStatus("replanted").map(treeItem), "No replanting."),
      ];
      const lag = this.laggingRows();
      if (lag) {
        const items = lag.rows.map((r) => el("li", {}, [
          el("strong", { text: "Row " + r.row }), `: ${O.fmt(r.mean, 2)} m mean height change over ${r.n} tree${r.n > 1 ? "s" : ""} (block ${O.fmt(lag.block, 2)} m)`]));
        lists.push(listOf("laggingrows", "Rows that lag", items, `No row grew less than the block's mean (${O.fmt(lag.block, 2)} m) by more than ${Math.round(LAG_SHARE * 100)} %.`));
      }
      const reg = this.d.capture && this.d.capture.registration;
      const intro = [el("h2", { text: "Changes since the previous capture" })];
      if (reg) intro.push(el("p", { class: "small", id: "registration", text: `Registered to the previous capture: shift ${O.fmt(reg.dx, 2)}, ${O.fmt(reg.dy, 2)} m, ` +
        `rotation ${O.fmt(reg.rotation_deg, 2)}°, residual ${O.fmt(reg.residual_m * 100, 1)} cm over ${O.fmt(reg.n_matched)} trees.` }));
      section.replaceChildren(...intro, el("div", { class: "changes" }, lists));
    }

    /* Rows whose mean height change is below the block's by more than LAG_SHARE of it
       (and 1 cm), most lagging first; null without growth figures. */
    laggingRows() {
      const g = this.cols.height_change_m, r = this.cols.row;
      if (!g || !r) return null;
      const per = new Map();
      let sum = 0, n = 0;
      g.forEach((v, i) => {
        if (v === null || r[i] === null) return;
        sum += v; n += 1;
        const e = per.get(r[i]) || { row: r[i], sum: 0, n: 0 };
        e.sum += v; e.n += 1; per.set(r[i], e);
      });
      if (!n) return null;
      const block = sum / n, margin = Math.max(LAG_SHARE * Math.abs(block), 0.01);
      const rows = [...per.values()].map((e) => ({ row: e.row, n: e.n, mean: e.sum / e.n }))
        .filter((e) => e.mean < block - margin).sort((a, b) => a.mean - b.mean);
      return { block, rows };
    }

    keyText(i) { return this.cols.tree_key && this.cols.tree_key[i] !== null ? ` (key ${this.cols.tree_key[i]})` : ""; }

    captureName(id) {
      const h = this.d.history;
      const k = h ? h.captures.indexOf(id) : -1;
      return k >= 0 && h.dates[k] ? h.dates[k] : id || "–";
    }

    address(i) {
      const r = this.cols.row, p = this.cols.position;
      return r && p && r[i] !== null && p[i] !== null ? ` (row ${r[i]} tree ${p[i]})` : "";
    }

    select(i, pan) {
      this.unmark();
      this.selected = i;
      this.mark = { tree: i };
      if (this.shape[i] !== undefined) {
        if (pan) { const b = 4 * i; this.zoomTo(this.box[b], this.box[b + 1], this.box[b + 2], this.box[b + 3]); }
        else this.layer.redraw();
      }
      const box = document.getElementById("details");
      const key = this.cols.tree_key ? this.cols.tree_key[i] : null;
      box.replaceChildren(el("h3", { id: "selected-tree", text: "Tree " + this.cols.tree_id[i] + this.address(i) }), this.details(i),
                          ...[this.historyBlock(key)].filter((b) => b));
      document.querySelectorAll("#treestable tr.selected").forEach((r) => r.classList.remove("selected"));
      const row = document.querySelector(`#treestable tr[data-i="${i}"]`);
      if (row) row.classList.add("selected");
    }

    showGap(g, zoom = true) {
      const items = [];
      for (const [k, v] of Object.entries(g)) if (k !== "line" && k !== "x" && k !== "y") items.push(el("dt", { text: label(k) }), el("dd", { text: O.fmt(v) }));
      this.unmark();
      this.mark = { gap: g };
      const removed = g.tree_key !== null && g.tree_key !== undefined;
      const where = g.row !== undefined && g.position !== undefined ? ` (row ${g.row} tree ${g.position})` : "";
      // a removed tree's slot keeps the tree's heading (its key and history follow)
      const heading = removed ? el("h3", { id: "selected-tree", text: `Removed tree (key ${g.tree_key})` })
                              : el("h3", { id: "selected-slot", text: "Empty slot" + where });
      document.getElementById("details").replaceChildren(heading, el("dl", {}, items),
                                                         ...[removed ? this.historyBlock(g.tree_key) : null].filter((b) => b));
      if (zoom && g.x !== null && g.x !== undefined) this.zoomTo(g.x - 1, g.y - 1, g.x + 1, g.y + 1);
      else this.layer.redraw();
    }

    search(text) {
      const out = document.getElementById("searchresult");
      const q = parseQuery(text);
      let i;
      if (!q) { out.textContent = "Type a tree id (12, tree 12), an address (row 5 tree 3, 5/3, r5 p3) or a row (row 5)."; return; }
      if (q.id !== undefined) i = this.byId.get(q.id);
      else if (q.position === undefined) {
        if (!this.cols.row) { out.textContent = "This job's trees have no row addresses; search by tree id."; return; }
        const found = this.selectRow(q.row);
        const n = found ? this.mark.idx.length : 0;
        out.textContent = found ? `Row ${q.row}: ${n} tree${n === 1 ? "" : "s"}.` : `No row ${q.row}.`;
        return;
      } else if (this.cols.row && this.cols.position) {
        i = this.cols.row.findIndex((r, k) => r === q.row && this.cols.position[k] === q.position);
        if (i < 0) {
          const gap = (this.d.gaps || []).find((g) => g.row === q.row && g.position === q.position);
          if (gap) { out.textContent = `Row ${q.row} tree ${q.position} is an empty slot.`; this.showGap(gap); return; }
        }
      } else { out.textContent = "This job's trees have no row addresses; search by tree id."; return; }
      if (i === undefined || i < 0) { out.textContent = "No such tree."; return; }
      // a bare number is an id: say how to ask for a row, which a grower may have meant
      const hint = q.bare && this.cols.row ? ` For row ${q.id}, type "row ${q.id}".` : "";
      out.textContent = "Found tree " + this.cols.tree_id[i] + this.address(i) + "." + hint;
      this.select(i, true);
    }

    summaries() {
      const c = this.cols, n = this.n;
      const vals = (k) => (c[k] || []).filter((v) => v !== null);
      const mean = (a) => (a.length ? a.reduce((s, v) => s + v, 0) / a.length : null);
      const sum = (a) => a.reduce((s, v) => s + v, 0);
      const median = (a) => { if (!a.length) return null; const s = [...a].sort((x, y) => x - y); const m = s.length >> 1; return s.length % 2 ? s[m] : (s[m - 1] + s[m]) / 2; };
      const facts = [["Trees", O.fmt(n)]];
      if (c.height_m) facts.push(["Height, mean / median [m]", O.fmt(mean(vals("height_m"))) + " / " + O.fmt(median(vals("height_m")))]);
      if (c.crown_diameter_m) facts.push(["Crown diameter, mean [m]", O.fmt(mean(vals("crown_diameter_m")))]);
      if (c.crown_area_m2) facts.push(["Crown area, total [m²]", O.fmt(sum(vals("crown_area_m2")), 1)]);
      if (c.crown_volume_m3) facts.push(["Crown volume, total [m³]", O.fmt(sum(vals("crown_volume_m3")), 1)]);
      if (c.young) facts.push(["Young trees", O.fmt(vals("young").filter((v) => v).length)]);
      if (this.d.gaps) facts.push(["Empty slots", O.fmt(this.d.gaps.length)]);
      if (this.d.rows) facts.push(["Rows", O.fmt(this.d.rows.length)]);
      const given = Object.entries(this.opts.facts || {});
      const all = given.concat(facts.filter(([k]) => !given.some(([g]) => g === k)));
      document.getElementById("blocksummary").replaceChildren(...all.flatMap(([k, v]) => [el("dt", { text: k }), el("dd", { text: v })]));
      if (!c.row) return;
      const groups = new Map();
      c.row.forEach((r, i) => { if (r === null) return; if (!groups.has(r)) groups.set(r, []); groups.get(r).push(i); });
      const gapsPerRow = new Map();  // row -> positions of its empty slots
      (this.d.gaps || []).forEach((g) => { if (!gapsPerRow.has(g.row)) gapsPerRow.set(g.row, []); gapsPerRow.get(g.row).push(g.position); });
      const pick = (k, idx) => idx.map((i) => (c[k] || [])[i]).filter((v) => v !== null && v !== undefined);
      const grew = c.height_change_m ? (idx) => mean(pick("height_change_m", idx)) : null;
      const head = ["Row", "Trees", "Young", "Empty slots", "Height, mean [m]", "Crown diameter, mean [m]", "Crown area, total [m²]"]
        .concat(grew ? ["Height change, mean [m]"] : [], ["Empty slots at"]);
      const rows = [...groups.keys()].sort((a, b) => a - b).map((r) => {
        const idx = groups.get(r);
        const empty = (gapsPerRow.get(r) || []).sort((a, b) => a - b);
        return el("tr", {}, [r, idx.length, c.young ? pick("young", idx).filter((v) => v).length : null, this.d.gaps ? empty.length : null,
          mean(pick("height_m", idx)), mean(pick("crown_diameter_m", idx)), sum(pick("crown_area_m2", idx))]
          .map((v, k) => el("td", { text: k < 4 ? O.fmt(v) : O.fmt(v, k === 6 ? 1 : 2) }))
          .concat(grew ? [el("td", { text: O.fmt(grew(idx), 2) })] : [], [el("td", { text: empty.length ? "tree " + empty.join(", ") : "" })]));
      });
      document.getElementById("rowstable").replaceChildren(el("thead", {}, [el("tr", {}, head.map((h) => el("th", { text: h })))]), el("tbody", {}, rows));
      document.getElementById("rowsection").hidden = false;
    }

    table() {
      const keys = tableKeys(this.cols).concat(Object.keys(this.text));
      const value = (k, i) => (k in this.cols ? this.cols[k] : this.text[k])[i];
      const order = [...Array(this.n).keys()];
      const col = this.cols[this.sort.key] || this.text[this.sort.key] || [];
      const dir = this.sort.dir;
      order.sort((a, b) => {
        const x = col[a], y = col[b];
        if (x === y) return a - b;
        if (x === null) return 1; // unmeasured last, whatever the direction
        if (y === null) return -1;
        return (x < y ? -1 : 1) * dir;
      });
      const pages = Math.max(1, Math.ceil(this.n / PAGE));
      this.page = Math.min(this.page, pages - 1);
      const shown = order.slice(this.page * PAGE, (this.page + 1) * PAGE);
      const head = el("tr", {}, keys.map((k) => el("th", {
        class: "sortable" + (k === this.sort.key ? (dir > 0 ? " sorted-asc" : " sorted-desc") : ""),
        "data-key": k, text: label(k), title: "sort",
        onclick: () => { this.sort = { key: k, dir: k === this.sort.key ? -dir : 1 }; this.page = 0; this.table(); },
      })));
      const marked = (i) => i === this.selected || (this.mark && this.mark.idx && this.cols.row[i] === this.mark.row);
      const body = shown.map((i) => el("tr", { "data-i": String(i), class: marked(i) ? "selected" : null, onclick: () => this.select(i, true) },
        keys.map((k) => el("td", { class: k in this.text ? "text" : null, text: cell(k, value(k, i)) }))));
      document.getElementById("treestable").replaceChildren(el("thead", {}, [head]), el("tbody", {}, body));
      const pager = document.getElementById("pager");
      const go = (p) => { this.page = p; this.table(); };
      pager.replaceChildren(
        el("button", { type: "button", class: "secondary", text: "‹ Previous", disabled: this.page === 0 ? "" : null, onclick: () => go(this.page - 1) }),
        el("span", { text: `${this.n ? this.page * PAGE + 1 : 0}–${Math.min((this.page + 1) * PAGE, this.n)} of ${this.n}` }),
        el("button", { type: "button", class: "secondary", text: "Next ›", disabled: this.page >= pages - 1 ? "" : null, onclick: () => go(this.page + 1) })
      );
    }
  }

  const DOWNLOADS = {
    "trees.csv": "Trees (CSV)", "trees.parquet": "Trees (GeoParquet)", "points.parquet": "Points (Parquet)",
    "rows.parquet": "Rows (GeoParquet)", "gaps.parquet": "Empty slots (GeoParquet)", "history.parquet": "Block history (Parquet)",
    report: "Report (HTML)", "map.png": "Map (PNG)",
  };
  const NOT_DOWNLOADS = new Set(["self", "page", "trees"]); // the resource, this page, the JSON of the table

  function showDownloads(links) {
    const known = Object.keys(DOWNLOADS).filter((k) => links[k]);
    const other = Object.keys(links).filter((k) => !NOT_DOWNLOADS.has(k) && !(k in DOWNLOADS)).sort();
    const parts = known.concat(other).map((k) => el("a", { class: "button secondary", href: links[k], download: "", text: DOWNLOADS[k] || k }));
    document.getElementById("downloads").replaceChildren(...(parts.length ? [el("strong", { text: "Downloads" }), ...parts] : []));
  }

  function showStatus(job) {
    const facts = [O.stateBadge(job), O.progress(job)];
    facts.push(el("span", { text: "block " + job.block_id }));
    if (job.capture) facts.push(el("span", { text: "capture " + job.capture }));
    const ob = job.orchard_block;
    if (ob) facts.push(el("span", { id: "orchardblock", text: `capture ${ob.seq} of orchard block ${ob.name}` + (ob.captured_at ? `, ${ob.captured_at}` : "") }));
    facts.push(el("span", { text: "submitted " + O.when(job.created_at) }));
    if (job.finished_at) facts.push(el("span", { text: "finished " + O.when(job.finished_at) }));
    if (job.n_trees !== null && job.n_trees !== undefined) facts.push(el("span", { text: O.fmt(job.n_trees) + " trees" }));
    if (job.error) facts.push(el("span", { class: "error", text: job.error }));
    document.getElementById("status").replaceChildren(...facts.filter((f) => f));
    if (job.partial) {
      const w = document.getElementById("warning");
      w.textContent = `Partial result: tile(s) ${job.failed_tiles.join(", ")} failed; trees standing in them are missing.`;
      w.hidden = false;
    }
  }

  /* The page in the service: follow the job until it is done, then draw it. */
  O.job = async function (cfg) {
    const path = "/v1/jobs/" + encodeURIComponent(cfg.jobId);
    let job, named = false;
    for (;;) {
      try {
        job = await O.api(path);
      } catch (err) {
        document.getElementById("status").textContent = "Could not load the job: " + err.message;
        await new Promise((r) => setTimeout(r, POLL_MS * 2));
        continue;
      }
      showStatus(job);
      showDownloads(job.links);
      if (!named) {
        named = true;
        O.api("/v1/blocks/" + encodeURIComponent(job.block_id)).then((b) => {
          const name = job.capture || b.filename || b.id;
          document.getElementById("title").textContent = name + " — job " + job.id.slice(0, 8);
          document.title = name + " — Orchard";
        }).catch(() => {});
      }
      if (job.state !== "queued" && job.state !== "running") break;
      await new Promise((r) => setTimeout(r, POLL_MS));
    }
    if (job.state !== "done") return;
    const data = await O.api("/web/jobs/" + encodeURIComponent(cfg.jobId) + "/map.json");
    window.orchardView = new JobView(data, {});
    window.orchardView.draw();
  };

  /* report.html: everything is in the page. */
  O.report = function () {
    const data = JSON.parse(document.getElementById("orchard-data").textContent);
    const cfg = JSON.parse(document.getElementById("orchard-report").textContent);
    if (cfg.warning) { const w = document.getElementById("warning"); w.textContent = cfg.warning; w.hidden = false; }
    showDownloads(cfg.downloads || {});
    window.orchardView = new JobView(data, { facts: cfg.facts });
    window.orchardView.draw();
  };

  O.parseQuery = parseQuery;

  // started by the page's data attributes, not an inline script (the served pages' CSP runs none)
  const page = document.body.dataset.page;
  if (page === "job") O.job({ jobId: document.body.dataset.jobId });
  else if (page === "report") O.report();
})();
