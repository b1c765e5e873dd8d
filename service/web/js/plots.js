// Plots drawn as inline SVG: axes with nice ticks (linear or log), lines, points, bars,
// histograms, colour maps, sparklines and joint-range bars. No external library.

const NS = "http://www.w3.org/2000/svg";

export const COLORS = { before: "#d9822b", after: "#1f77b4", x: "#d62728", y: "#2ca02c", z: "#1f77b4",
                        grey: "#8a94a6", limit: "#dfe4ea", used: "#4c8bf5", bad: "#c0392b" };

// Drawing widths (px) that match the page's columns, so that text in the plots keeps its size:
// full (a card across the page), half (a card in a two-column row), wide (the wider of 3:2).
export function sizes() {
  const vw = Math.min(window.innerWidth || 1024, 1280);
  const full = Math.max(300, vw - 82);
  const two = vw > 900;
  return { full, half: two ? Math.floor((vw - 40 - 18) / 2) - 42 : full,
           wide: two ? Math.floor(((vw - 40 - 18) * 3) / 5) - 42 : full,
           inner: two ? Math.floor((full - 18) / 2) : full };
}

function s(tag, attrs = {}, ...children) {
  const el = document.createElementNS(NS, tag);
  for (const [k, v] of Object.entries(attrs)) if (v !== null && v !== undefined) el.setAttribute(k, v);
  for (const c of children) if (c !== null && c !== undefined) el.appendChild(typeof c === "string" ? document.createTextNode(c) : c);
  return el;
}

function fmt(v) {
  if (v === 0) return "0";
  const a = Math.abs(v);
  if (a >= 1e5 || a < 1e-3) return v.toExponential(0).replace("e+", "e");
  return String(+v.toPrecision(4));
}

// A round step (1, 2 or 5 times a power of ten) that cuts ``span`` into about ``count`` parts,
// no finer than ``minStep``.
function niceStep(span, count, minStep = 0) {
  const step0 = Math.max(span / Math.max(count, 1), minStep);
  const mag = 10 ** Math.floor(Math.log10(step0));
  const err = step0 / mag;
  return Math.max((err >= 7.5 ? 10 : err >= 3.5 ? 5 : err >= 1.5 ? 2 : 1) * mag, minStep);
}

// Ticks at round values inside [lo, hi]; ``minStep``: no finer than this (1 for counts such as
// pose numbers). Each tick is computed from its index, so 1.2 + 0.2 + ... never misses 2.
export function niceTicks(lo, hi, count = 5, minStep = 0) {
  if (!(hi > lo)) { hi = lo + 1; lo = lo - 1; }
  const step = niceStep(hi - lo, count, minStep);
  const ticks = [];
  for (let k = Math.ceil(lo / step - 1e-9); k * step <= hi + step * 1e-9; k++) {
    ticks.push(k === 0 ? 0 : +(k * step).toPrecision(12));
  }
  return ticks;
}

// Ticks of a time axis (x in ms since the epoch) at round local times: seconds, minutes, hours,
// days or months, about ``count`` of them; with the label format that fits the step.
const SECOND = 1000, MINUTE = 60 * SECOND, HOUR = 60 * MINUTE, DAY = 24 * HOUR;
const TIME_STEPS = [SECOND, 2 * SECOND, 5 * SECOND, 10 * SECOND, 15 * SECOND, 30 * SECOND, MINUTE, 2 * MINUTE,
                    5 * MINUTE, 10 * MINUTE, 15 * MINUTE, 30 * MINUTE, HOUR, 2 * HOUR, 3 * HOUR, 6 * HOUR, 12 * HOUR,
                    DAY, 2 * DAY, 7 * DAY];

export function timeTicks(t0, t1, count = 5) {
  const want = (t1 - t0) / Math.max(count, 1);
  const step = TIME_STEPS.find((s) => s >= want);
  const ticks = [];
  let label;
  if (step === undefined) { // months: the first of a month, every 1, 3, 6 or 12 months
    const months = [1, 3, 6, 12, 24, 60].find((m) => m * 30 * DAY >= want) || 120;
    const d = new Date(t0);
    d.setHours(0, 0, 0, 0);
    d.setDate(1);
    d.setMonth(Math.ceil(d.getMonth() / months) * months);
    for (; d.getTime() <= t1; d.setMonth(d.getMonth() + months)) if (d.getTime() >= t0) ticks.push(d.getTime());
    label = (t) => new Date(t).toLocaleDateString(undefined, { month: "short", year: "numeric" });
  } else if (step >= DAY) { // local midnights
    const d = new Date(t0);
    d.setHours(0, 0, 0, 0);
    if (d.getTime() < t0) d.setDate(d.getDate() + 1);
    const days = step / DAY;
    for (; d.getTime() <= t1; d.setDate(d.getDate() + days)) ticks.push(d.getTime());
    label = (t) => new Date(t).toLocaleDateString(undefined, { month: "short", day: "numeric" });
  } else {
    const off = new Date(t0).getTimezoneOffset() * MINUTE; // round in local time
    for (let t = Math.ceil((t0 - off) / step) * step + off; t <= t1; t += step) ticks.push(t);
    const days = new Date(t0).toDateString() !== new Date(t1).toDateString();
    const opts = { hour: "2-digit", minute: "2-digit", ...(step < MINUTE ? { second: "2-digit" } : {}),
                   ...(days ? { month: "short", day: "numeric" } : {}) };
    label = (t) => new Date(t).toLocaleString(undefined, opts);
  }
  return { ticks, label };
}

function logTicks(lo, hi) {
  const out = [];
  for (let e = Math.floor(Math.log10(lo)); e <= Math.ceil(Math.log10(hi)); e++) {
    for (const m of [1, 2, 5]) {
      const v = m * 10 ** e;
      if (v >= lo * 0.999 && v <= hi * 1.001) out.push(v);
    }
  }
  return out.length > 8 ? out.filter((v) => Math.abs(Math.log10(v) % 1) < 1e-9) : out;
}

// A chart of `series` ({x, y, type: "line"|"points"|"bars", color, label, width, titles,
// onclick(x, y, i)}) with axes; `titles[i]`: the tooltip of point i.
// Options: xLabel, yLabel, logY, yMin, yMax, xMin, xMax, zeroLine, width, height, legend,
// hlines ([{y, label, color}]), title (accessible name), integerX, integerY (ticks on whole numbers),
// xTime (x in ms since the epoch: ticks at round local times), barWidth (x units, default 1),
// xTicks and xFormat (ticks and their labels chosen by the caller).
export function chart(series, o = {}) {
  const W = o.width || sizes().full, H = o.height || 260;
  const m = { l: 64, r: 14, t: o.legend === false ? 12 : 28, b: 44 };
  const xs = series.flatMap((d) => d.x).filter(Number.isFinite);
  let ys = series.flatMap((d) => d.y).filter(Number.isFinite);
  if (o.logY) ys = ys.filter((v) => v > 0);
  for (const hl of o.hlines || []) if (Number.isFinite(hl.y)) ys.push(hl.y);
  let x0 = o.xMin ?? Math.min(...xs), x1 = o.xMax ?? Math.max(...xs);
  if (!xs.length) { x0 = 0; x1 = 1; }
  const bars = series.some((d) => d.type === "bars");
  const barWidth = o.barWidth || 1;
  const padL = bars && o.xMin === undefined ? barWidth / 2 : 0, padR = bars && o.xMax === undefined ? barWidth / 2 : 0;
  x0 -= padL;
  x1 += padR;
  if (o.xTime) { // room around the points; an hour either side of a single one
    const pad = x1 > x0 ? (x1 - x0) * 0.04 : 3600e3;
    x0 -= pad; x1 += pad;
  }
  if (x1 === x0) { x0 -= 1; x1 += 1; }
  let y0, y1;
  if (o.logY) {
    y0 = o.yMin ?? Math.min(...ys) / 1.5;
    y1 = o.yMax ?? Math.max(...ys) * 1.5;
    if (!ys.length) { y0 = 1e-3; y1 = 1; }
  } else {
    y0 = o.yMin ?? Math.min(0, ...ys);
    y1 = o.yMax ?? Math.max(...ys, 0);
    if (!ys.length) { y0 = 0; y1 = 1; }
    if (y1 === y0) { y1 = y0 + 1; }
    const pad = (y1 - y0) * 0.06;
    if (o.yMax === undefined) y1 += pad;
    if (o.yMin === undefined && y0 < 0) y0 -= pad;
  }
  const px = (v) => m.l + ((v - x0) / (x1 - x0)) * (W - m.l - m.r);
  const py = o.logY
    ? (v) => H - m.b - ((Math.log10(v) - Math.log10(y0)) / (Math.log10(y1) - Math.log10(y0))) * (H - m.t - m.b)
    : (v) => H - m.b - ((v - y0) / (y1 - y0)) * (H - m.t - m.b);
  const svg = s("svg", { viewBox: `0 0 ${W} ${H}`, class: "plot", role: "img", "aria-label": o.title || o.yLabel || "plot" });
  const g = s("g", { class: "axes" });
  svg.appendChild(g);
  const yt = o.logY ? logTicks(y0, y1) : niceTicks(y0, y1, 5, o.integerY ? 1 : 0);
  for (const t of yt) {
    if (t < y0 - 1e-12 || t > y1 + 1e-12) continue;
    g.appendChild(s("line", { x1: m.l, x2: W - m.r, y1: py(t), y2: py(t), class: "grid" }));
    g.appendChild(s("text", { x: m.l - 6, y: py(t) + 4, "text-anchor": "end" }, fmt(t)));
  }
  const nx = Math.max(2, Math.floor((W - m.l) / (o.xTime ? 110 : 80)));
  let xt = o.xTicks, xf = o.xFormat || fmt;
  if (!xt && o.xTime) ({ ticks: xt, label: xf } = timeTicks(x0, x1, nx));
  if (!xt) xt = niceTicks(x0 + padL, x1 - padR, nx, o.integerX ? 1 : 0);
  for (const t of xt) {
    if (t < x0 - 1e-12 || t > x1 + 1e-12) continue;
    g.appendChild(s("line", { x1: px(t), x2: px(t), y1: H - m.b, y2: H - m.b + 5, class: "tick" }));
    g.appendChild(s("text", { x: px(t), y: H - m.b + 18, "text-anchor": "middle" }, xf(t)));
  }
  g.appendChild(s("line", { x1: m.l, x2: W - m.r, y1: H - m.b, y2: H - m.b, class: "axis" }));
  g.appendChild(s("line", { x1: m.l, x2: m.l, y1: m.t, y2: H - m.b, class: "axis" }));
  if (o.xLabel) g.appendChild(s("text", { x: (m.l + W - m.r) / 2, y: H - 6, "text-anchor": "middle", class: "label" }, o.xLabel));
  if (o.yLabel) g.appendChild(s("text", { x: 14, y: (m.t + H - m.b) / 2, "text-anchor": "middle", class: "label",
                                          transform: `rotate(-90 14 ${(m.t + H - m.b) / 2})` }, o.yLabel));
  if (o.zeroLine && !o.logY && y0 < 0 && y1 > 0)
    g.appendChild(s("line", { x1: m.l, x2: W - m.r, y1: py(0), y2: py(0), class: "zero" }));
  for (const hl of o.hlines || []) {
    if (!Number.isFinite(hl.y)) continue;
    g.appendChild(s("line", { x1: m.l, x2: W - m.r, y1: py(hl.y), y2: py(hl.y), stroke: hl.color || COLORS.grey,
                              "stroke-dasharray": "5 4", "stroke-width": 1.3 }));
    if (hl.label) g.appendChild(s("text", { x: W - m.r - 4, y: py(hl.y) - 4, "text-anchor": "end", class: "hl" }, hl.label));
  }
  const nb = series.filter((d) => d.type === "bars").length;
  let bi = 0;
  const plot = s("g", { class: "data" });
  svg.appendChild(plot);
  for (const d of series) {
    const color = d.color || COLORS.after;
    if (d.type === "bars") {
      const slot = Math.min((px(barWidth) - px(0)) * 0.8, o.barWidth ? Infinity : 60); // a lone pose: no slab
      const bw = Math.max(1, slot / nb);
      const base = o.logY ? y0 : Math.max(y0, Math.min(0, y1));
      d.x.forEach((xv, i) => {
        const yv = d.y[i];
        if (!Number.isFinite(yv) || (o.logY && yv <= 0)) return;
        const xa = px(xv) - slot / 2 + bi * bw;
        const ya = py(Math.max(yv, base)), yb = py(Math.min(yv, base));
        const r = s("rect", { x: xa, y: Math.min(ya, yb), width: Math.max(bw - 1, 1), height: Math.max(Math.abs(yb - ya), 0.5),
                              fill: color, opacity: d.opacity ?? 0.85 });
        r.appendChild(s("title", {}, d.titles?.[i] ?? `${d.label ? d.label + ": " : ""}${o.xName || "x"} ${fmt(xv)}, ${fmt(yv)}`));
        plot.appendChild(r);
      });
      bi += 1;
    } else {
      const pts = d.x.map((xv, i) => [xv, d.y[i], i]).filter(([a, b]) => Number.isFinite(a) && Number.isFinite(b) && (!o.logY || b > 0));
      if (d.type !== "points" && pts.length > 1) {
        plot.appendChild(s("polyline", { points: pts.map(([a, b]) => `${px(a).toFixed(1)},${py(b).toFixed(1)}`).join(" "),
                                         fill: "none", stroke: color, "stroke-width": d.width || 1.8,
                                         "stroke-dasharray": d.dash || null }));
      }
      if (d.type !== "line" || pts.length < 30) {
        for (const [a, b, i] of pts) {
          const c = s("circle", { cx: px(a), cy: py(b), r: d.r || (d.type === "points" ? 3.2 : 2.4), fill: color });
          c.appendChild(s("title", {}, d.titles?.[i] ?? `${d.label ? d.label + ": " : ""}${o.xName || "x"} ${fmt(a)}, ${fmt(b)}`));
          if (d.onclick) { c.style.cursor = "pointer"; c.addEventListener("click", () => d.onclick(a, b, i)); }
          plot.appendChild(c);
        }
      }
    }
  }
  if (o.legend !== false) {
    let lx = m.l;
    for (const d of series.filter((d) => d.label)) {
      svg.appendChild(s("rect", { x: lx, y: 8, width: 12, height: 12, fill: d.color || COLORS.after, rx: 2 }));
      const t = s("text", { x: lx + 16, y: 18, class: "legend" }, d.label);
      svg.appendChild(t);
      lx += 26 + d.label.length * 7;
    }
  }
  return svg;
}

// Histograms of several datasets on common bins of a round width (bars side by side). The
// bins start at a round number at or below the smallest value (not at 0), so no bar is empty
// for lack of small values; each bar's tooltip gives its bin and count. ``o.bins``: about how
// many bins.
export function histogram(datasets, o = {}) {
  const all = datasets.flatMap((d) => d.values).filter(Number.isFinite);
  if (!all.length) return chart([], o);
  const mn = Math.min(...all), mx = Math.max(...all);
  const nbins = o.bins || Math.min(20, Math.max(6, Math.round(Math.sqrt(all.length))));
  const w = niceStep(Math.max(mx - mn, Math.abs(mx) * 1e-6, 1e-12), nbins);
  const lo = Math.floor(mn / w + 1e-9) * w;
  const n = Math.max(1, Math.floor((mx - lo) / w + 1e-9) + 1);
  const series = datasets.map((d) => {
    const counts = new Array(n).fill(0);
    for (const v of d.values) if (Number.isFinite(v)) counts[Math.min(n - 1, Math.max(0, Math.floor((v - lo) / w + 1e-9)))]++;
    const x = counts.map((_, i) => lo + (i + 0.5) * w);
    return { type: "bars", x, y: counts, color: d.color, label: d.label,
             titles: counts.map((c, i) => `${fmt(+(lo + i * w).toPrecision(6))} to ${fmt(+(lo + (i + 1) * w).toPrecision(6))}: ${c}`) };
  });
  return chart(series, { ...o, barWidth: w, xMin: lo, xMax: lo + n * w, xName: "bin", integerY: true,
                         yLabel: o.yLabel || "poses" });
}

// Colour scale from blue (low) through green and yellow to red (high).
export function heat(t) {
  t = Math.max(0, Math.min(1, t));
  const stops = [[49, 54, 149], [69, 117, 180], [116, 173, 209], [171, 217, 233], [254, 224, 144], [253, 174, 97],
                 [244, 109, 67], [215, 48, 39]];
  const f = t * (stops.length - 1), i = Math.min(stops.length - 2, Math.floor(f)), r = f - i;
  const c = stops[i].map((v, k) => Math.round(v + (stops[i + 1][k] - v) * r));
  return `rgb(${c[0]},${c[1]},${c[2]})`;
}

// Points coloured by a value, with a colour bar: {x, y, c} arrays.
export function colorMap(x, y, c, o = {}) {
  const W = o.width || sizes().inner, H = o.height || 360;
  const m = { l: 58, r: 70, t: 14, b: 44 };
  const finite = (a) => a.filter(Number.isFinite);
  let x0 = Math.min(...finite(x)), x1 = Math.max(...finite(x)), y0 = Math.min(...finite(y)), y1 = Math.max(...finite(y));
  if (o.equal) { // same scale on both axes
    const span = Math.max(x1 - x0, y1 - y0) / 2, cx = (x0 + x1) / 2, cy = (y0 + y1) / 2;
    x0 = cx - span; x1 = cx + span; y0 = cy - span; y1 = cy + span;
  }
  const cw = W - m.l - m.r, ch = H - m.t - m.b;
  const px = (v) => m.l + ((v - x0) / (x1 - x0 || 1)) * cw;
  const py = (v) => H - m.b - ((v - y0) / (y1 - y0 || 1)) * ch;
  const c0 = Math.min(...finite(c)), c1 = Math.max(...finite(c));
  const svg = s("svg", { viewBox: `0 0 ${W} ${H}`, class: "plot", role: "img", "aria-label": o.title || "map" });
  const g = s("g", { class: "axes" });
  svg.appendChild(g);
  for (const t of niceTicks(x0, x1, 4)) {
    g.appendChild(s("line", { x1: px(t), x2: px(t), y1: m.t, y2: H - m.b, class: "grid" }));
    g.appendChild(s("text", { x: px(t), y: H - m.b + 18, "text-anchor": "middle" }, fmt(t)));
  }
  for (const t of niceTicks(y0, y1, 4)) {
    g.appendChild(s("line", { x1: m.l, x2: m.l + cw, y1: py(t), y2: py(t), class: "grid" }));
    g.appendChild(s("text", { x: m.l - 6, y: py(t) + 4, "text-anchor": "end" }, fmt(t)));
  }
  g.appendChild(s("rect", { x: m.l, y: m.t, width: cw, height: ch, class: "frame" }));
  if (o.xLabel) g.appendChild(s("text", { x: m.l + cw / 2, y: H - 6, "text-anchor": "middle", class: "label" }, o.xLabel));
  if (o.yLabel) g.appendChild(s("text", { x: 14, y: m.t + ch / 2, "text-anchor": "middle", class: "label",
                                          transform: `rotate(-90 14 ${m.t + ch / 2})` }, o.yLabel));
  const order = c.map((_, i) => i).sort((a, b) => c[a] - c[b]); // largest drawn last, on top
  for (const i of order) {
    if (!Number.isFinite(x[i]) || !Number.isFinite(y[i])) continue;
    const t = (c[i] - c0) / (c1 - c0 || 1);
    const dot = s("circle", { cx: px(x[i]), cy: py(y[i]), r: 3.4, fill: heat(t), opacity: 0.9 });
    dot.appendChild(s("title", {}, `${fmt(x[i])}, ${fmt(y[i])}: ${fmt(c[i])}${o.unit ? " " + o.unit : ""}`));
    svg.appendChild(dot);
  }
  // colour bar
  const bx = W - m.r + 16, bh = ch;
  const grad = s("linearGradient", { id: `g${Math.random().toString(36).slice(2)}`, x1: 0, y1: 1, x2: 0, y2: 0 });
  for (let k = 0; k <= 8; k++) grad.appendChild(s("stop", { offset: `${k * 12.5}%`, "stop-color": heat(k / 8) }));
  svg.appendChild(s("defs", {}, grad));
  svg.appendChild(s("rect", { x: bx, y: m.t, width: 12, height: bh, fill: `url(#${grad.getAttribute("id")})` }));
  for (const t of niceTicks(c0, c1, 4)) {
    if (t < c0 || t > c1) continue;
    const yy = m.t + bh - ((t - c0) / (c1 - c0 || 1)) * bh;
    svg.appendChild(s("text", { x: bx + 16, y: yy + 4, class: "small" }, fmt(t)));
  }
  if (o.unit) svg.appendChild(s("text", { x: bx, y: H - m.b + 18, class: "small" }, o.unit));
  return svg;
}

// A small trend line (no axes); `values` oldest first; highlights the last point.
export function sparkline(values, o = {}) {
  const W = o.width || 140, H = o.height || 36;
  const v = values.filter(Number.isFinite);
  const svg = s("svg", { viewBox: `0 0 ${W} ${H}`, class: "spark", role: "img", "aria-label": o.title || "trend",
                         width: W, height: H, preserveAspectRatio: "none" });
  if (v.length === 0) {
    svg.appendChild(s("text", { x: 4, y: H / 2 + 4, class: "small" }, "no calibrations yet"));
    return svg;
  }
  const lo = Math.min(...v), hi = Math.max(...v);
  const px = (i) => 4 + (v.length === 1 ? (W - 8) / 2 : (i / (v.length - 1)) * (W - 8));
  const py = (y) => H - 5 - ((y - lo) / (hi - lo || 1)) * (H - 10) * (hi > lo ? 1 : 0) - (hi > lo ? 0 : (H - 10) / 2);
  if (v.length > 1) svg.appendChild(s("polyline", { points: v.map((y, i) => `${px(i)},${py(y)}`).join(" "), fill: "none",
                                                     stroke: COLORS.after, "stroke-width": 1.6 }));
  svg.appendChild(s("circle", { cx: px(v.length - 1), cy: py(v[v.length - 1]), r: 3, fill: COLORS.before }));
  return svg;
}

// Joint ranges: the allowed limits (grey), the range the plan uses (blue), each configuration (ticks).
export function jointRanges(joints, o = {}) {
  const W = o.width || sizes().full, row = 34, H = 20 + joints.length * row + 24;
  const m = { l: 64, r: 16 };
  const svg = s("svg", { viewBox: `0 0 ${W} ${H}`, class: "plot", role: "img", "aria-label": "joint ranges" });
  joints.forEach((j, k) => {
    const lo = Math.min(j.limit[0], j.used[0]), hi = Math.max(j.limit[1], j.used[1]);
    const span = hi - lo || 1;
    const px = (v) => m.l + ((v - lo) / span) * (W - m.l - m.r);
    const y = 14 + k * row;
    svg.appendChild(s("text", { x: m.l - 8, y: y + 14, "text-anchor": "end" }, j.name));
    svg.appendChild(s("rect", { x: px(j.limit[0]), y: y + 4, width: px(j.limit[1]) - px(j.limit[0]), height: 14,
                                fill: COLORS.limit, rx: 3 }));
    const bad = j.used[0] < j.limit[0] || j.used[1] > j.limit[1];
    svg.appendChild(s("rect", { x: px(j.used[0]), y: y + 7, width: Math.max(2, px(j.used[1]) - px(j.used[0])), height: 8,
                                fill: bad ? COLORS.bad : COLORS.used, opacity: 0.55, rx: 2 }));
    for (const v of j.values || []) svg.appendChild(s("line", { x1: px(v), x2: px(v), y1: y + 3, y2: y + 19,
                                                                stroke: bad && (v < j.limit[0] || v > j.limit[1]) ? COLORS.bad : "#1b3f8b",
                                                                "stroke-width": 1 }));
    svg.appendChild(s("text", { x: px(j.limit[0]), y: y + 30, class: "small" }, `${fmt(j.limit[0])}`));
    svg.appendChild(s("text", { x: px(j.limit[1]), y: y + 30, class: "small", "text-anchor": "end" }, `${fmt(j.limit[1])} ${j.unit}`));
  });
  svg.appendChild(s("rect", { x: m.l, y: H - 16, width: 12, height: 10, fill: COLORS.limit }));
  svg.appendChild(s("text", { x: m.l + 16, y: H - 7, class: "small" }, "allowed range"));
  svg.appendChild(s("rect", { x: m.l + 120, y: H - 16, width: 12, height: 10, fill: COLORS.used, opacity: 0.55 }));
  svg.appendChild(s("text", { x: m.l + 136, y: H - 7, class: "small" }, "range the plan uses (ticks: configurations)"));
  return svg;
}
