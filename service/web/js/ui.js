// Small DOM helpers: element builder, formatting, dialogs, notices.

export function h(tag, attrs, ...children) {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === null || v === undefined || v === false) continue;
    if (k === "class") el.className = v;
    else if (k === "style" && typeof v === "object") Object.assign(el.style, v);
    else if (k.startsWith("on") && typeof v === "function") el.addEventListener(k.slice(2), v);
    else if (k === "dataset") Object.assign(el.dataset, v);
    else if (v === true) el.setAttribute(k, "");
    else el.setAttribute(k, v);
  }
  append(el, children);
  return el;
}

function append(el, children) {
  for (const c of children) {
    if (c === null || c === undefined || c === false) continue;
    if (Array.isArray(c)) append(el, c);
    else if (c instanceof Node) el.appendChild(c);
    else el.appendChild(document.createTextNode(String(c)));
  }
}

export function clear(el) {
  while (el.firstChild) el.removeChild(el.firstChild);
  return el;
}

// Replace an element's children (null, false and undefined children are left out).
export function put(el, ...children) {
  clear(el);
  append(el, children);
  return el;
}

// Add children to an element (null, false and undefined are left out).
export function add(el, ...children) {
  append(el, children);
  return el;
}

// Numbers: `digits` significant digits, no exponent for ordinary sizes.
export function num(v, digits = 4) {
  if (v === null || v === undefined || Number.isNaN(v)) return "–";
  if (v === 0) return "0";
  const a = Math.abs(v);
  if (a >= 1e6 || a < 1e-5) return v.toExponential(digits - 1);
  const d = Math.max(0, digits - 1 - Math.floor(Math.log10(a)));
  return v.toFixed(Math.min(d, 8));
}

// A length for a person, in `unit` (mm, m, in, µm), `digits` significant digits; anything below
// 0.1 µm, far below what any instrument measures (what is left is rounding), is said as such
// ("below 0.0001 mm") rather than as 2.69e-7 mm.
const METRES_PER = { "µm": 1e-6, mm: 1e-3, m: 1, in: 0.0254 };
export const FLOOR_M = 1e-7;
export function length(v, unit, digits = 4) {
  if (v === null || v === undefined || Number.isNaN(v)) return "–";
  const floor = FLOOR_M / (METRES_PER[unit] || 1e-3);
  if (v !== 0 && Math.abs(v) < floor) return `below ${num(floor, 1)} ${unit}`;
  return `${num(v, digits)} ${unit}`;
}

function parseTime(iso) {
  return new Date(iso.endsWith("Z") || /[+-]\d\d:\d\d$/.test(iso) ? iso : iso + "Z");
}

export function when(iso) {
  if (!iso) return "–";
  return parseTime(iso).toLocaleString(undefined, { year: "numeric", month: "short", day: "numeric", hour: "2-digit",
                                                    minute: "2-digit" });
}

// A time to the second (readings, device states): the date only when it is not today.
export function whenSeconds(iso) {
  if (!iso) return "–";
  const t = parseTime(iso);
  const opts = { hour: "2-digit", minute: "2-digit", second: "2-digit" };
  if (t.toDateString() !== new Date().toDateString()) Object.assign(opts, { year: "numeric", month: "short", day: "numeric" });
  return t.toLocaleString(undefined, opts);
}

// Milliseconds since the epoch of an ISO time from the service (UTC when it names no zone).
export function epochMs(iso) {
  return parseTime(iso).getTime();
}

// Compact date and time for tables: the year only when it is not this year.
export function whenShort(iso) {
  if (!iso) return "–";
  const t = parseTime(iso);
  const opts = { month: "short", day: "numeric", hour: "2-digit", minute: "2-digit" };
  if (t.getFullYear() !== new Date().getFullYear()) opts.year = "numeric";
  return t.toLocaleString(undefined, opts);
}

export function duration(s) {
  if (s === null || s === undefined) return "–";
  s = Math.max(0, Math.round(s));
  if (s < 60) return `${s} s`;
  const m = Math.floor(s / 60), r = s % 60;
  if (m < 60) return `${m} min ${r ? r + " s" : ""}`.trim();
  return `${Math.floor(m / 60)} h ${m % 60} min`;
}

export function badge(state) {
  return h("span", { class: `badge state-${state}` }, state);
}

export function card(title, ...children) {
  return h("section", { class: "card" }, title ? h("h2", {}, title) : null, ...children);
}

export function kv(rows) {
  return h("dl", { class: "kv" }, rows.filter(Boolean).map(([k, v]) => [h("dt", {}, k), h("dd", {}, v)]));
}

export function table(head, rows, attrs = {}) {
  return h("div", { class: "table-wrap" },
    h("table", attrs, h("thead", {}, h("tr", {}, head.map((c) => h("th", {}, c)))),
      h("tbody", {}, rows.map((r) => (r instanceof Node ? r : h("tr", {}, r.map((c) => h("td", {}, c))))))));
}

// What a report says about where a parameter's value came from, when it is not simply these
// measurements: "from the prior" (kept from the previous calibration), or a label it gives; "".
export function paramLabel(p) {
  if (p.source === "prior") return "from the prior";
  for (const k of ["label", "status", "note"]) if (typeof p[k] === "string" && p[k]) return p[k];
  return "";
}

// A notice: errors stay (at the bottom of the screen, over the page) until closed; others
// appear above the page's content, pushing it down (never covering a button), and fade.
export function notify(message, kind = "error") {
  const box = document.getElementById(kind === "error" ? "toasts" : "notices");
  if (kind !== "error") clear(box); // the latest success only
  const el = h("div", { class: `notice notice-${kind}`, role: kind === "error" ? "alert" : "status" },
    h("span", {}, message), h("button", { class: "close", "aria-label": "close", onclick: () => el.remove() }, "×"));
  box.appendChild(el);
  if (kind !== "error") setTimeout(() => el.remove(), 5000);
  return el;
}

// A modal confirmation; resolves true when confirmed. `signal` (an AbortSignal) withdraws the
// question (false): what it asked about no longer applies (a session that ended meanwhile).
export function confirmDialog(title, message, { confirm = "Confirm", cancel = "Cancel", danger = false, signal } = {}) {
  return new Promise((resolve) => {
    const dlg = h("dialog", { class: "confirm" },
      h("h2", {}, title),
      typeof message === "string" ? h("p", {}, message) : message,
      h("div", { class: "actions" },
        h("button", { class: "secondary", "data-action": "cancel", onclick: () => done(false) }, cancel),
        h("button", { class: danger ? "danger" : "primary", "data-action": "confirm", onclick: () => done(true) },
          confirm)));
    let answered = false;
    function done(v) {
      if (answered) return;
      answered = true;
      dlg.close();
      dlg.remove();
      resolve(v);
    }
    dlg.addEventListener("cancel", (e) => { e.preventDefault(); done(false); });
    signal?.addEventListener("abort", () => done(false));
    document.body.appendChild(dlg);
    dlg.showModal();
  });
}

// Run an async action from a button: disabled while it runs, errors shown as notices.
export async function busy(button, fn) {
  const label = button.textContent;
  button.disabled = true;
  button.classList.add("busy");
  try {
    return await fn();
  } catch (e) {
    notify(e.message || String(e));
    return undefined;
  } finally {
    button.disabled = false;
    button.classList.remove("busy");
    button.textContent = label;
  }
}

// A device address as code that wraps only at its natural breaks (after "//", before ":port",
// after ", "), never in the middle of a number.
export function address(v) {
  const text = v == null ? "" : typeof v === "object" ? JSON.stringify(v) : String(v);
  const el = h("code", { class: "address" });
  text.split(/(?<=\/\/)|(?=:\d)|(?<=, )/).forEach((part, i) => {
    if (i) el.appendChild(h("wbr"));
    el.appendChild(document.createTextNode(part));
  });
  return el;
}
