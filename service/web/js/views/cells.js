// Cells: the overview, one cell (devices and their connection test, accuracy trend, sessions,
// calibrations), registering and editing a cell, and starting a session (plan first, then confirm).

import { can, get, me, patch, post } from "../api.js";
import { COLORS, chart, jointRanges, sizes, sparkline } from "../plots.js";
import { address, badge, busy, card, put, confirmDialog, duration, epochMs, h, kv, notify, num, table, when,
         whenShort } from "../ui.js";

// How the page names a device: the service's device registry (x-devices of GET /schemas/devices)
// names each device; the other keys of the document are named here.
const SETTING_NAMES = { encoders: "reference encoders", resolvers: "resolvers", cmm_ball_radius_m: "CMM tooling ball radius" };

async function deviceNames() {
  const schema = await deviceSchema();
  return { ...SETTING_NAMES, ...Object.fromEntries((schema["x-devices"] || []).map((e) => [e.key, e.label])) };
}

// A length in metres (the API's) as the page shows it, in mm; and back (rounded to 12 digits so
// that 12.5 mm is 0.0125 m, not 0.012500000000000001).
const mmOf = (m) => (m == null || m === "" ? "" : +(Number(m) * 1000).toPrecision(12));
const mOf = (mm) => +(Number(mm) / 1000).toPrecision(12);

function robotLine(r) {
  return `${r.name} · ${r.joints} joints · ${r.convention}`;
}

function activeLink(a) {
  if (!a) return null;
  return h("a", { class: `active-session state-${a.state}`, href: `#/sessions/${a.id}` },
    badge(a.state), ` ${a.kind} session ${a.id}: ${a.measured}/${a.planned} measured`);
}

// --------------------------------------------------------------------------- overview

const PAGE = 30; // cells per page of the overview

// What the cell card's accuracy figure is: a verification of the current calibration on fresh
// configurations, never the calibration's own residual (how well it fits the data it came from).
function accuracyNote(c) {
  const a = c.accuracy, cur = c.current, waits = c.candidate ? `; calibration ${c.candidate.id} not in use yet` : "";
  if (a) return `accuracy: RMS error on ${a.n} fresh configurations (verified ${whenShort(a.created_at)})${waits}`;
  if (cur) return `calibrated ${whenShort(cur.created_at)}, not verified yet: run a verify session${waits}`;
  return c.last ? `no calibration in use${waits}` : "not calibrated yet";
}

export async function overview(ctx, page = 1) {
  ctx.crumbs([["Cells", null]]);
  page = Math.max(1, page || 1);
  const [data, DEVICE_NAMES] = await Promise.all([get(`/overview?limit=${PAGE}&offset=${(page - 1) * PAGE}`), deviceNames()]);
  if (!ctx.alive()) return;
  const grid = h("div", { class: "cell-grid" });
  for (const c of data.cells) {
    const last = c.last;
    grid.appendChild(h("article", { class: "card cell-card", "data-cell": c.id },
      h("h2", {}, h("a", { href: `#/cells/${c.id}` }, c.name)),
      h("p", { class: "muted" }, `site ${c.site}`),
      h("p", {}, robotLine(c.robot)),
      h("p", { class: "chips" }, c.devices.map((d) => h("span", { class: "chip" }, DEVICE_NAMES[d] || d))),
      h("div", { class: "accuracy" },
        h("div", { class: "big" }, c.accuracy ? `${num(c.accuracy.rms, 3)} ${c.unit}` : "—"),
        h("div", { class: "muted small" }, accuracyNote(c)),
        c.verified.length > 1 ? sparkline(c.verified.map((t) => t.rms), { width: 260, height: 40,
                                                                         title: "verified accuracy (RMS) over time" }) : null),
      activeLink(c.active_session),
      h("a", { class: "button", href: `#/cells/${c.id}` }, "Open")));
  }
  put(ctx.root, 
    h("div", { class: "page-head" },
      h("h1", {}, "Cells"),
      can("cells") ? h("a", { class: "button primary", href: "#/cells/new", id: "register-cell" }, "Register a cell") : null),
    data.cells.length ? grid : data.total ? card("No cells on this page", h("a", { href: "#/" }, "Back to the first page"))
      : card("No cells yet",
      h("p", {}, can("cells") ? "Register the first robot cell: its robot model and the address of each device."
        : "A technician registers cells; there are none yet.")),
    data.total > PAGE ? overviewPager(page, data.total) : null,
    howTo(data.cells.length === 0));
}

function overviewPager(page, total) {
  const pages = Math.ceil(total / PAGE);
  const first = (page - 1) * PAGE + 1;
  return h("nav", { class: "pager", id: "overview-pager", "aria-label": "pages of cells" },
    page > 1 ? h("a", { class: "button secondary", href: page === 2 ? "#/" : `#/page/${page - 1}`, id: "prev-page" }, "‹ Previous")
      : null,
    h("span", { class: "muted" }, `cells ${first}–${Math.min(total, first + PAGE - 1)} of ${total} (page ${page} of ${pages})`),
    page < pages ? h("a", { class: "button secondary", href: `#/page/${page + 1}`, id: "next-page" }, "Next ›") : null);
}

function howTo(open) {
  return h("details", { class: "card howto", open, id: "how-to" }, h("summary", {}, "How to calibrate a cell"),
    h("ol", {},
      h("li", {}, "Open the cell (or register it: its robot model and the address of each device) and press ",
        h("strong", {}, "Test connections"), ": every device should answer OK."),
      h("li", {}, h("strong", {}, "Start a session"), ", choose ", h("strong", {}, "Calibrate"), " and ",
        h("strong", {}, "Show the plan"), ". Nothing moves yet: check the number of poses, the joint ranges and the "
        + "predicted accuracy, then start. The robot moves only after you confirm."),
      h("li", {}, "Watch the poses being measured. You can pause, resume or abort; if a device faults the session "
        + "pauses and says why. When it completes, open the result."),
      h("li", {}, "The result shows the accuracy before and after and what changed. Download the model (or URDF, "
        + "DH table), compensate your robot programs, and print the certificate."),
      h("li", {}, "Now and then run a ", h("strong", {}, "Verify"), " session: it measures fresh poses and tells how "
        + "accurate the current calibration still is.")));
}

// --------------------------------------------------------------------------- one cell

export async function detail(ctx, id) {
  const [c, DEVICE_NAMES] = await Promise.all([get(`/cells/${id}/summary`), deviceNames()]);
  if (!ctx.alive()) return;
  ctx.crumbs([["Cells", "#/"], [c.name, null]]);
  const unit = c.unit;
  const active = c.active_session;
  const head = h("div", { class: "page-head" },
    h("div", {}, h("h1", {}, c.name), h("p", { class: "muted" }, `site ${c.site} · registered ${when(c.created_at)}`)),
    h("div", { class: "actions" },
      can("run") ? h("a", { class: "button primary", href: `#/cells/${id}/start`, id: "start-session" },
        "Start a session") : null,
      can("cells") ? h("a", { class: "button", href: `#/cells/${id}/edit`, id: "edit-cell" }, "Edit") : null));
  const banner = active ? h("div", { class: `banner banner-${active.state === "running" || active.state === "planned" ? "info" : "warn"}` },
    activeLink(active), active.reason ? h("span", {}, ` — ${active.reason}`) : null) : null;

  // robot
  const r = c.robot;
  const robotCard = card("Robot", kv([
    ["Model", r.name], ["Convention", r.convention], ["Joints", String(r.joints)],
    ["Units", `${r.units?.length}, ${r.units?.angle}`], ["Targets", r.targets.join(", ") || "none (tool origin)"],
    ["Drift threshold", c.drift_threshold ? `${c.drift_threshold} ${unit}` : "–"],
    ["Allowed region", c.allowed_region ? c.allowed_region.map((p) => `[${p.join(", ")}]`).join(" ") : "the model's joint limits"]]));

  // devices + connection test
  const results = h("div", { id: "device-results" });
  const testBtn = can("run") ? h("button", { class: "primary", id: "test-devices" }, "Test connections") : null;
  const devRows = Object.entries(c.devices_doc || {}).filter(([k]) => k !== "ready")
    .map(([k, v]) => [DEVICE_NAMES[k] || k, k === "cmm_ball_radius_m" ? `${mmOf(v)} mm`
      : k.endsWith("_sigma_um") ? `${v} µm` : describeAddress(k, v)]);
  const devCard = card("Devices", c.devices_error ? h("p", { class: "error-text", id: "devices-error" },
      `This cell's devices cannot be used: ${c.devices_error}. Edit the cell to correct them.`) : null,
    table(["Device", "Address"], devRows),
    h("p", { class: "muted small" }, "The test opens each device, asks it something harmless and shows what it "
      + "answered. Nothing moves."), testBtn, results);
  if (testBtn) testBtn.addEventListener("click", () => busy(testBtn, async () => {
    testBtn.textContent = "Testing…";
    const res = await post(`/cells/${id}/devices/test`);
    showTest(results, { at: new Date().toISOString(), by: me.name, results: res.results });
  }));
  get(`/cells/${id}/devices/test`).then((t) => { if (t.last && !results.firstChild) showTest(results, t.last, true); })
    .catch(() => {});

  // accuracy over time: each verification of a calibration (RMS error on fresh configurations),
  // against the date; the calibration it checked in the tooltip
  const trend = c.verified;
  const trendCard = card("Accuracy over time",
    trend.length ? chart([{ x: trend.map((t) => epochMs(t.created_at)), y: trend.map((t) => t.rms), type: "line",
                            color: COLORS.after, label: `verified RMS error (${unit})`,
                            titles: trend.map((t) => `calibration ${t.calibration_id}, verified ${whenShort(t.created_at)} `
                              + `on ${t.n} configurations: RMS ${num(t.rms, 3)} ${unit}, max ${num(t.max, 3)} ${unit}`),
                            onclick: (x, y, i) => ctx.go(`#/sessions/${trend[i].session_id}`) }],
      { xLabel: "date", yLabel: unit, xTime: true, height: 220, title: "accuracy trend", width: sizes().half })
      : h("p", { class: "muted" }, c.last ? "Not verified yet: a verify session measures the calibrated robot at "
        + "fresh configurations and gives its accuracy." : "No calibration yet."),
    c.current ? h("p", {}, "Current calibration: ", h("a", { href: `#/calibrations/${c.current.id}`, id: "last-calibration" },
      `calibration ${c.current.id}`), `, ${when(c.current.created_at)}`,
      c.accuracy && c.accuracy.calibration_id === c.current.id ? `; accuracy ${num(c.accuracy.rms, 3)} ${unit} RMS, `
        + `max ${num(c.accuracy.max, 3)} ${unit} on ${c.accuracy.n} fresh configurations` : "; not verified yet") : null,
    candidateNote(c, ctx.reload));

  // a UR controller computes with its own kinematics (factory calibration): the cell keeps a copy
  const cm = c.controller_model;
  const controllerCard = cm || (c.devices_doc || {}).rtde ? card("Controller kinematics", cm
    ? kv([["Model", `${cm.name}, version ${cm.version}`], ["Read", `${when(cm.read_at || cm.created_at)}`
          + (cm.session_id ? ` (session ${cm.session_id})` : " (uploaded)")],
          cm.from_registers
            ? ["Fitted to the TCP-pose registers", cm.check_um == null ? "–" : `to ${num(cm.check_um, 2)} µm (0.1 mm registers)`]
            : ["Reproduces the controller", cm.check_um == null ? "–"
              : cm.check_um < 0.1 ? "exactly (to within 0.1 µm)" : `to ${num(cm.check_um, 2)} µm`],
          ["Last change", cm.moved_mm == null ? (cm.version > 1 ? "none" : "first read")
            : `the flange moved up to ${num(cm.moved_mm, 3)} mm`]])
    : h("p", { class: "muted", id: "controller-model-none" }, "Not read yet: the next session reads it from the "
        + "controller (over RTDE nothing moves; over Modbus from the TCP-pose registers at the poses it measures), "
        + "or upload the file `recal controller-model` writes."),
  h("p", { class: "muted small" }, "Targets mode, URScript pose targets and compensation use it, not the published "
    + "DH table.")) : null;

  const sessionsBox = h("div", {});
  const calsBox = h("div", {});
  put(ctx.root, head, banner,
    h("div", { class: "two" }, robotCard, trendCard),
    devCard, controllerCard,
    h("div", { class: "two" }, card("Sessions", sessionsBox), card("Calibrations", calsBox)));
  pagedSessions(sessionsBox, id, 0);
  pagedCalibrations(calsBox, id, 0, unit, ctx.reload);
}

function describeAddress(key, v) {
  if ((key === "encoders" || key === "resolvers") && v && typeof v === "object") {
    return Object.entries(v).map(([j, node]) => `joint ${j}: CANopen node ${node}`).join(", ");
  }
  if (key === "can" && v && typeof v === "object") {
    return address(`${v.interface || "?"} ${v.channel || ""}${v.host ? ` at ${v.host}:${v.port}` : ""}`);
  }
  return address(v);
}

// What a device answered, for people: an encoder's or resolver's angle first, its counts,
// resolution and node state as detail.
function answerOf(r) {
  const d = r.details || {};
  if (r.ok !== false && d.angle_deg != null) {
    const detail = [`${d.counts} counts`, d.resolution_deg ? `${num(d.resolution_deg, 3)}° per count` : null,
                    d.pole_pairs > 1 ? `${d.pole_pairs} pole pairs` : null, `CANopen node ${d.node_id}`].filter(Boolean);
    return h("span", {}, h("strong", { class: "angle" }, `${d.angle_deg.toFixed(4)}°`),
      h("span", { class: "muted" }, " on the device's own scale"),
      h("div", { class: "small muted" }, detail.join(" · ")),
      d.state ? h("div", { class: `small ${d.status === "operational" ? "muted" : "warn-text"}` }, `Node ${d.state}`) : null);
  }
  return h("span", { class: r.ok === false ? "error-text" : "" }, r.answer || r.error || "");
}

function showTest(box, t, old = false) {
  const rows = t.results.map((r) => [
    r.device,
    r.skipped ? h("span", { class: "badge state-paused" }, "not tested") : r.ok
      ? h("span", { class: "badge state-completed" }, "OK") : h("span", { class: "badge state-failed" }, "ERROR"),
    answerOf(r),
    r.elapsed_ms != null ? h("span", { class: "nowrap" }, `${Math.round(r.elapsed_ms)} ms`) : ""]);
  put(box, 
    h("p", { class: "muted small" }, `${old ? "Last test" : "Tested"} ${when(t.at)} by ${t.by || "?"}`),
    table(["Device", "Result", "What it answered", "Time"], rows, { class: "device-test" }));
}

async function pagedSessions(box, id, offset) {
  const page = await get(`/cells/${id}/session-list?limit=8&offset=${offset}`);
  const rows = page.items.map((s) => [h("a", { href: `#/sessions/${s.id}` }, `#${s.id}`), s.kind, badge(s.state),
    `${s.measured}/${s.planned}`,
    h("span", {}, h("span", { class: "nowrap" }, whenShort(s.created_at)), h("br"), h("span", { class: "small muted" }, s.created_by))]);
  put(box, rows.length ? table(["", "Kind", "State", "Poses", "Started"], rows, { class: "sessions" })
    : h("p", { class: "muted" }, "No sessions yet."),
    pager(page.total, offset, 8, (o) => pagedSessions(box, id, o)));
}

// A newer calibration than the current one waits: a verify session that passes it makes it
// current, or a technician activates it here (issue 27: activated, not overwritten).
function candidateNote(c, reload) {
  const k = c.candidate;
  if (!k) return null;
  return h("p", { id: "candidate" }, h("a", { href: `#/calibrations/${k.id}` }, `Calibration ${k.id}`),
    ` (${when(k.created_at)}) is not in use yet: a verify session that finds it at least as accurate as the `
    + `${c.current ? `current calibration ${c.current.id}` : "nominal model"} makes it current, or activate it now. `,
    can("cells") ? calibrationButton(k.id, "activate", reload, "activate-candidate") : null);
}

const CHANGES = {
  activate: ["Activate", "Make calibration {id} the cell's current calibration?", "Compensation, verify sessions and "
    + "the next calibration then use it. The calibration in use now is kept and can be activated again."],
  retire: ["Retire", "Retire calibration {id}?", "It is kept and can still be read and compared, but no longer "
    + "serves as the cell's calibration; the one activated before it does (or the nominal model)."],
};

function calibrationButton(id, what, reload, elId = `${what}-${id}`) {
  const [label, title, text] = CHANGES[what];
  const b = h("button", { class: what === "activate" ? "primary" : "secondary", id: elId }, label);
  b.addEventListener("click", async () => {
    if (!await confirmDialog(title.replace("{id}", id), text, { confirm: label, danger: what === "retire" })) return;
    await busy(b, async () => {
      await post(`/calibrations/${id}/${what}`);
      notify(`Calibration ${id}: ${what === "activate" ? "now the cell's current calibration" : "retired"}.`, "ok");
      reload();
    });
  });
  return b;
}

const STATUS_WORDS = { current: "in use", candidate: "not in use yet", superseded: "earlier", retired: "retired" };

async function pagedCalibrations(box, id, offset, unit, reload) {
  const page = await get(`/cells/${id}/history?limit=10&offset=${offset}`);
  const rows = page.items.map((c) => [h("a", { href: `#/calibrations/${c.id}` }, `#${c.id}`), c.kind,
    h("span", { class: `status status-${c.status}`, "data-calibration": c.id }, STATUS_WORDS[c.status] || c.status || "–"),
    c.rms != null ? num(c.rms, 3) : "–", h("span", { class: "nowrap" }, whenShort(c.created_at)),
    can("cells") && c.kind === "pose" ? h("span", { class: "actions" },
      c.status !== "current" ? calibrationButton(c.id, "activate", reload) : null,
      c.status !== "retired" ? calibrationButton(c.id, "retire", reload) : null) : ""]);
  put(box, rows.length ? table(["", "Kind", "Status", `Fit residual RMS (${unit})`, "Date", ""], rows, { class: "calibrations" })
    : h("p", { class: "muted" }, "No calibrations yet."),
    pager(page.total, offset, 10, (o) => pagedCalibrations(box, id, o, unit, reload)));
}

function pager(total, offset, size, go) {
  if (total <= size) return null;
  const prev = h("button", { class: "secondary", disabled: offset <= 0, onclick: () => go(Math.max(0, offset - size)) }, "‹ Newer");
  const next = h("button", { class: "secondary", disabled: offset + size >= total, onclick: () => go(offset + size) }, "Older ›");
  return h("div", { class: "pager" }, prev, h("span", { class: "muted" }, `${offset + 1}–${Math.min(total, offset + size)} of ${total}`), next);
}

// --------------------------------------------------------------------------- register / edit

// The devices document is described by its JSON Schema (GET /schemas/devices, the service's
// one parser): the form's labels, help, placeholders and checks come from it, so a field is
// refused here with the words the service would use.
const CAN_KEYS = ["interface", "channel", "host", "port"];
let deviceSchemaPromise = null;

export function deviceSchema() {
  deviceSchemaPromise ||= get("/schemas/devices").catch((e) => { deviceSchemaPromise = null; throw e; });
  return deviceSchemaPromise;
}

// The schema of `name` in `obj` (an object's schema): references followed, and of an optional
// field (anyOf [..., null]) the branch that is not null; of a string-or-object field (emscon)
// the branch of `type` when asked for.
function schemaOf(root, obj, name, type) {
  const resolve = (s) => (s && s.$ref ? root.$defs[s.$ref.split("/").pop()] : s);
  let s = resolve(obj?.properties?.[name]) || {};
  const meta = { title: s.title, description: s.description, default: s.default };
  for (let k = 0; k < 3 && (s.anyOf || s.oneOf); k++) {
    const branches = (s.anyOf || s.oneOf).map(resolve).filter((b) => b.type !== "null");
    s = branches.find((b) => !type || b.type === type) || branches[0] || {};
  }
  return { ...s, ...Object.fromEntries(Object.entries(meta).filter(([, v]) => v !== undefined)),
           description: meta.description ?? s.description };
}

// What is wrong with `text` for a field of schema `s` ("" when nothing): the service's words
// ("expected ...") from the schema's x-expected, pattern and range.
function schemaCheck(s) {
  const re = s.pattern ? new RegExp(s.pattern) : null;
  return (text) => {
    if (!text) return "";
    if (s.type === "integer" || s.type === "number") {
      const v = Number(text);
      const ok = text.trim() !== "" && Number.isFinite(v) && (s.type === "number" || Number.isInteger(v))
        && (s.minimum === undefined || v >= s.minimum) && (s.maximum === undefined || v <= s.maximum)
        && (s.exclusiveMinimum === undefined || v > s.exclusiveMinimum);
      const range = s.minimum !== undefined && s.maximum !== undefined ? ` (${s.minimum}–${s.maximum})` : "";
      return ok ? "" : `expected ${s.type === "integer" ? "a whole number" : "a number"}${range}`;
    }
    return !re || re.test(text) ? "" : `expected ${s["x-expected"] || `text matching ${s.pattern}`}`;
  };
}

function placeholderOf(s) {
  if (s.examples?.length) return `e.g. ${s.examples[0]}`;
  return s.default != null ? String(s.default) : "";
}

// One input with its label, help and the place for its error message.
function field(label, input, help) {
  const id = input.id || `f${Math.random().toString(36).slice(2)}`;
  input.id = id;
  const err = h("p", { class: "field-error", id: `${id}-error`, role: "alert" });
  input.setAttribute("aria-describedby", `${id}-error`);
  return h("div", { class: "field" }, h("label", { for: id }, label), input, help ? h("p", { class: "help" }, help) : null, err);
}

// A field labelled and explained by its schema (title, description).
function schemaField(input, s) {
  return field(s.title || input.id, input, s.description);
}

// Show (or clear) an input's error message; returns whether it is valid.
function mark(input, message) {
  const err = document.getElementById(`${input.id}-error`);
  input.classList.toggle("invalid", !!message);
  if (message) input.setAttribute("aria-invalid", "true");
  else input.removeAttribute("aria-invalid");
  if (err) err.textContent = message || "";
  return !message;
}

// The devices and allowed-region part of the cell form: fields for the robot controller, the
// instrument, the CAN bus with its encoder and resolver nodes per joint, and the allowed joint
// ranges; a shortcut that fills them from the endpoint line `recal fake-cell` prints; checks
// each field as it is left and all of them on `read()` (which returns {devices, allowed_region}
// or null when a field is wrong, with the messages shown at the fields).
// Python difflib's SequenceMatcher(None, a, b).ratio() (no junk: the keys are short), so that the
// page suggests the key the API would ("did you mean 'emscon'?", service/device_config.py).
function matchRatio(a, b) {
  const b2j = {};
  [...b].forEach((c, j) => (b2j[c] ||= []).push(j));
  function longest(alo, ahi, blo, bhi) {
    let best = [alo, blo, 0], j2len = {};
    for (let i = alo; i < ahi; i++) {
      const next = {};
      for (const j of b2j[a[i]] || []) {
        if (j < blo) continue;
        if (j >= bhi) break;
        const k = next[j] = (j2len[j - 1] || 0) + 1;
        if (k > best[2]) best = [i - k + 1, j - k + 1, k];
      }
      j2len = next;
    }
    return best;
  }
  function matched(alo, ahi, blo, bhi) {
    const [i, j, k] = longest(alo, ahi, blo, bhi);
    return k ? k + matched(alo, i, blo, j) + matched(i + k, ahi, j + k, bhi) : 0;
  }
  const total = a.length + b.length;
  return total ? (2 * matched(0, a.length, 0, b.length)) / total : 1;
}

// difflib.get_close_matches(word, known, n=1, cutoff=0.6)[0], or null: the largest (ratio, key).
function closeMatch(word, known) {
  let best = null, bestScore = -1;
  for (const k of known) {
    const score = matchRatio(k, word);
    if (score >= 0.6 && (score > bestScore || (score === bestScore && k > best))) [best, bestScore] = [k, score];
  }
  return best;
}

// Fields two by two.
function pairs(fields) {
  const out = [];
  for (let i = 0; i < fields.length; i += 2) out.push(h("div", { class: "pair" }, fields.slice(i, i + 2)));
  return out;
}

function deviceForm(doc, region, schema) {
  doc = doc || {};
  const can = typeof doc.can === "object" && doc.can ? doc.can : {};
  const canSchema = schemaOf(schema, schema, "can");
  const prop = (name, type) => schemaOf(schema, schema, name, type);
  const canProp = (name) => schemaOf(schema, canSchema, name);
  const input = (id, value, s, attrs = {}) => h("input", { id, value: value ?? "", spellcheck: "false", autocomplete: "off",
                                                           placeholder: placeholderOf(s), ...attrs });
  // One text field per device of the registry entered as text (x-devices: its key, role, label,
  // kind of field), in the registry's order; a device written as an object of settings (emScon:
  // host, reflector, environment, …) is kept as it is.
  const entries = (schema["x-devices"] || []).filter((e) => e.page === "text" || e.page === "text-or-settings");
  const texts = entries.map((e) => {
    const v = doc[e.key], kept = e.page === "text-or-settings" && v && typeof v === "object";
    return { entry: e, s: prop(e.key, "string"),
             input: input(`dev-${e.key}`, typeof v === "string" ? v : "", prop(e.key, "string"),
                          kept ? { placeholder: `${v.host} (settings kept)` } : {}) };
  });
  // the tooling balls' radius is in metres in the API and in mm on the page, as every length here
  const ballM = prop("cmm_ball_radius_m");
  const ballS = { ...ballM, title: ballM.title.replace("(m)", "(mm)"), minimum: mmOf(ballM.minimum),
                  maximum: mmOf(ballM.maximum), default: mmOf(ballM.default),
                  description: `radius of the tool's tooling balls the CMM probes, every ball alike, mm (${mmOf(ballM.minimum)} to ${mmOf(ballM.maximum)})` };
  const ball = input("dev-cmm-ball", mmOf(doc.cmm_ball_radius_m), ballS, { inputmode: "decimal" });
  // each instrument's own noise figure (x-instrument: its device's key), in µm as the API takes it
  const sigmas = Object.entries(schema.properties).filter(([, p]) => p["x-instrument"]).map(([key]) => {
    const s = prop(key, "number");
    return { key, s, input: input(`dev-${key.replaceAll("_", "-")}`, doc[key], s, { inputmode: "decimal", placeholder: "the driver's default" }) };
  });
  const canIf = input("dev-can-interface", can.interface, canProp("interface"), { placeholder: canProp("interface").default, list: "can-interfaces" });
  const canCh = input("dev-can-channel", can.channel, canProp("channel"), { placeholder: "e.g. vcan0, can0" });
  const canHost = input("dev-can-host", can.host, canProp("host"), { placeholder: "socketcand only" });
  const canPort = input("dev-can-port", can.port, canProp("port"), { placeholder: "e.g. 29536", inputmode: "numeric" });
  const nodeSchema = Object.values(prop("encoders").patternProperties || {})[0] || { type: "integer", minimum: 1, maximum: 127 };
  const line = h("textarea", { id: "endpoint-line", rows: 3, spellcheck: "false",
                               placeholder: '{"ready": true, "rtde": "127.0.0.2", "modbus": "127.0.0.2:502", "tracker": "socket://127.0.0.2:10001", …}' });
  const fill = h("button", { type: "button", class: "secondary", id: "fill-from-line" }, "Fill in the fields");
  const lineErr = h("p", { class: "field-error", id: "endpoint-line-error", role: "alert" });
  const lineOk = h("p", { class: "small ok-text", id: "endpoint-line-status", role: "status" });
  const jointsBox = h("div", { id: "joint-devices" });
  const regionBox = h("div", { id: "region-fields" });
  let joints = [];
  let units = { length: "mm", angle: "deg" };
  let nodes = { encoders: { ...(doc.encoders || {}) }, resolvers: { ...(doc.resolvers || {}) } };
  let regionRows = Array.isArray(region) ? region.map((r) => [...r]) : [];
  // The document's keys: those the schema knows and the form has no field for (an emScon object)
  // are kept as they are; keys it does not know (registered before the service checked them) are
  // left out when saved, and said so.
  const known = Object.keys(schema.properties);
  const FORM_KEYS = [...(schema["x-devices"] || []).map((e) => e.key), "cmm_ball_radius_m", ...sigmas.map((g) => g.key), "encoders", "resolvers", "ready"];
  const keptAsIs = entries.filter((e) => e.page === "text-or-settings").map((e) => e.key);
  const extra = Object.fromEntries(Object.entries(doc).filter(([k, v]) => known.includes(k) && (!FORM_KEYS.includes(k)
    || (keptAsIs.includes(k) && v && typeof v === "object"))));
  const unknown = Object.keys(doc).filter((k) => !known.includes(k));
  const unknownNote = unknown.length ? h("p", { class: "help", id: "devices-unknown" }, `Not device settings, left out `
    + `when saved: ${unknown.join(", ")} (the service knows ${known.filter((k) => k !== "ready").join(", ")}).`) : null;
  const canExtra = Object.fromEntries(Object.entries(can).filter(([k]) => !CAN_KEYS.includes(k)));
  const nodeInputs = [], regionInputs = [];
  const checkNode = schemaCheck(nodeSchema);

  const checks = [
    ...texts.map((t) => [t.input, schemaCheck(t.s)]),
    [ball, schemaCheck(ballS)],
    ...sigmas.map((g) => [g.input, schemaCheck(g.s)]),
    [canIf, (v) => !v && usesCan() ? "the reference encoders and resolvers need the CAN interface (socketcand, socketcan, pcan, …)" : ""],
    [canCh, (v) => !v && (canIf.value.trim() || usesCan()) ? "expected the CAN channel, e.g. vcan0 or can0" : ""],
    [canHost, (v) => {
      if (canIf.value.trim() !== "socketcand") return schemaCheck(canProp("host"))(v);
      return v ? schemaCheck(canProp("host"))(v) : "socketcand needs the host of the socketcand server";
    }],
    [canPort, (v) => {
      if (canIf.value.trim() !== "socketcand" && !v) return "";
      return v ? schemaCheck(canProp("port"))(v) : "socketcand needs the port of the socketcand server, e.g. 29536";
    }],
  ];
  const checkOne = (inp) => {
    const c = checks.find(([i]) => i === inp);
    return c ? mark(inp, c[1](inp.value.trim())) : true;
  };
  for (const [inp] of checks) inp.addEventListener("change", () => checkOne(inp));

  function usesCan() {
    return nodeInputs.some((i) => i.value.trim());
  }

  function checkNodes() {
    let ok = true;
    const seen = {};
    for (const inp of nodeInputs) {
      const v = inp.value.trim();
      let msg = "";
      if (v && checkNode(v)) msg = `${checkNode(v)}: a CANopen node id`;
      else if (v && seen[v]) msg = `node ${v} is already the ${seen[v]}`;
      if (v && !msg) seen[v] = inp.dataset.what;
      ok = mark(inp, msg) && ok;
    }
    return ok;
  }

  function checkRegion() {
    let ok = true;
    joints.forEach((j, i) => {
      const [lo, hi] = regionInputs[i];
      const a = lo.value.trim(), b = hi.value.trim();
      let msgLo = "", msgHi = "";
      if (a && !Number.isFinite(+a)) msgLo = "expected a number";
      if (b && !Number.isFinite(+b)) msgHi = "expected a number";
      if (!msgLo && !msgHi && (a || b)) {
        const l = a ? +a : j.lower, u = b ? +b : j.upper;
        if (l != null && u != null && !(l < u)) msgHi = `must be above the lower end (${l})`;
        else if (j.lower != null && j.upper != null && (u <= j.lower || l >= j.upper)) {
          msgHi = `[${l}, ${u}] lies outside the joint's limits [${j.lower}, ${j.upper}]: no motion left`;
        }
      }
      ok = mark(lo, msgLo) && ok;
      ok = mark(hi, msgHi) && ok;
    });
    return ok;
  }

  // The per-joint inputs (encoder and resolver nodes, allowed range) for the model's joints,
  // keeping what was typed.
  function setJoints(js, u) {
    remember();
    joints = (js || []).map((j, i) => ({ name: j.name || `j${i + 1}`, prismatic: j.type === "prismatic",
                                         lower: j.lower ?? null, upper: j.upper ?? null }));
    units = u || units;
    render();
  }

  function render() {
    nodeInputs.length = 0;
    regionInputs.length = 0;
    const nodeRows = joints.map((j, i) => {
      const n = String(i + 1);
      const enc = input(`enc-${n}`, nodes.encoders[n], { inputmode: "numeric", placeholder: "–", "aria-label": `joint ${n} reference encoder node id` });
      const res = input(`res-${n}`, nodes.resolvers[n], { inputmode: "numeric", placeholder: "–", "aria-label": `joint ${n} resolver node id` });
      enc.dataset.what = `joint ${n} reference encoder`;
      res.dataset.what = `joint ${n} resolver`;
      nodeInputs.push(enc, res);
      for (const x of [enc, res]) x.addEventListener("change", () => { checkNodes(); checkOne(canIf); checkOne(canCh); });
      return h("tr", {}, h("th", {}, `${n} (${j.name})`), h("td", {}, enc, errorOf(enc)), h("td", {}, res, errorOf(res)));
    });
    put(jointsBox, joints.length ? h("div", { class: "table-wrap" }, h("table", { class: "joint-fields" },
      h("thead", {}, h("tr", {}, h("th", {}, "Joint"), h("th", {}, "Reference encoder node"), h("th", {}, "Resolver node"))),
      h("tbody", {}, nodeRows))) : h("p", { class: "muted small" }, "Choose the robot model first."));
    const unitOf = (j) => (j.prismatic ? units.length : units.angle);
    const same = joints.every((j) => unitOf(j) === unitOf(joints[0]));
    const rows = joints.map((j, i) => {
      // a bound equal to the joint's limit is shown empty (its placeholder says the limit)
      const r = (regionRows[i] || []).map((v, k) => (v !== "" && v != null && +v === [j.lower, j.upper][k] ? "" : v));
      const lo = input(`region-lo-${i + 1}`, r[0], { inputmode: "decimal", placeholder: j.lower ?? "", "aria-label": `joint ${i + 1} lowest allowed` });
      const hi = input(`region-hi-${i + 1}`, r[1], { inputmode: "decimal", placeholder: j.upper ?? "", "aria-label": `joint ${i + 1} highest allowed` });
      regionInputs.push([lo, hi]);
      for (const x of [lo, hi]) x.addEventListener("change", checkRegion);
      return h("tr", {}, h("th", {}, `${i + 1} (${j.name})${same ? "" : `, ${unitOf(j)}`}`), h("td", {}, lo, errorOf(lo)),
        h("td", {}, hi, errorOf(hi)));
    });
    const unit = same && joints.length ? ` (${unitOf(joints[0])})` : "";
    put(regionBox, joints.length ? h("div", { class: "table-wrap" }, h("table", { class: "joint-fields" },
      h("thead", {}, h("tr", {}, h("th", {}, "Joint"), h("th", {}, `From${unit}`), h("th", {}, `To${unit}`))),
      h("tbody", {}, rows))) : null);
  }

  function errorOf(inp) {
    const err = h("p", { class: "field-error", id: `${inp.id}-error`, role: "alert" });
    inp.setAttribute("aria-describedby", err.id);
    return err;
  }

  // What was typed in the per-joint inputs, so that rebuilding them keeps it.
  function remember() {
    if (!joints.length) return;
    nodes = { encoders: {}, resolvers: {} };
    nodeInputs.forEach((inp) => {
      const [kind, n] = inp.id.split("-");
      if (inp.value.trim()) nodes[kind === "enc" ? "encoders" : "resolvers"][n] = inp.value.trim();
    });
    regionRows = regionInputs.map(([lo, hi]) => [lo.value.trim(), hi.value.trim()]);
  }

  fill.addEventListener("click", () => {
    lineErr.textContent = lineOk.textContent = "";
    let d;
    try {
      d = JSON.parse(line.value.trim());
      if (!d || typeof d !== "object" || Array.isArray(d)) throw new Error("expected a JSON object");
    } catch (e) {
      lineErr.textContent = `Not an endpoint line: ${e.message}. Paste the one line of JSON that recal fake-cell printed.`;
      return;
    }
    // A key the service does not know is refused, in the API's words (POST /cells answers 422
    // with the same message), and nothing is filled in: a typo is not silently dropped.
    const strange = Object.keys(d).filter((k) => !known.includes(k));
    if (strange.length) {
      const near = closeMatch(strange[0], known);
      lineErr.textContent = `The line's ${JSON.stringify(strange[0])}: unknown key`
        + (near ? `; did you mean '${near}'?` : "") + ` (expected one of ${known.join(", ")}). Nothing was filled in.`;
      return;
    }
    const named = Object.keys(d).filter((k) => known.includes(k) && k !== "ready");
    if (!named.length) {
      lineErr.textContent = `This JSON names no device (expected ${known.filter((k) => k !== "ready").join(", ")}).`;
      return;
    }
    for (const t of texts) t.input.value = typeof d[t.entry.key] === "string" ? d[t.entry.key] : "";
    ball.value = mmOf(d.cmm_ball_radius_m);
    for (const g of sigmas) g.input.value = d[g.key] ?? "";
    const c = d.can && typeof d.can === "object" ? d.can : {};
    canIf.value = c.interface ?? ""; canCh.value = c.channel ?? ""; canHost.value = c.host ?? ""; canPort.value = c.port ?? "";
    Object.keys(canExtra).forEach((k) => delete canExtra[k]);
    Object.assign(canExtra, Object.fromEntries(Object.entries(c).filter(([k]) => !CAN_KEYS.includes(k))));
    remember();
    nodes = { encoders: { ...(d.encoders || {}) }, resolvers: { ...(d.resolvers || {}) } };
    render();
    const missing = Object.keys(d.encoders || {}).concat(Object.keys(d.resolvers || {})).filter((n) => +n > joints.length);
    if (missing.length) lineErr.textContent = `The line names joint(s) ${missing.join(", ")}, which this robot does not have.`;
    read(true);
    lineOk.textContent = `Filled in from the line: ${named.join(", ")}. Check the fields below, then save.`;
  });

  // {devices, allowed_region} from the fields, or null (the errors shown at the fields).
  function read(quiet = false) {
    let ok = checkNodes();
    for (const [inp] of checks) ok = checkOne(inp) && ok;
    ok = checkRegion() && ok;
    if (!ok) {
      if (!quiet) document.querySelector("[aria-invalid=true]")?.focus();
      return null;
    }
    remember();
    const devices = { ...extra };
    const v = (x) => x.value.trim();
    for (const t of texts) if (v(t.input)) devices[t.entry.key] = v(t.input);
    if (v(ball)) devices.cmm_ball_radius_m = mOf(v(ball));
    for (const g of sigmas) if (v(g.input)) devices[g.key] = Number(v(g.input));
    if (v(canIf)) {
      devices.can = { interface: v(canIf), channel: v(canCh), ...canExtra };
      if (v(canHost)) devices.can.host = v(canHost);
      if (v(canPort)) devices.can.port = Number(v(canPort));
    }
    for (const key of ["encoders", "resolvers"]) {
      const m = Object.fromEntries(Object.entries(nodes[key]).map(([j, n]) => [j, Number(n)]));
      if (Object.keys(m).length) devices[key] = m;
    }
    let allowed = null;
    if (regionRows.some(([a, b]) => a || b)) {
      allowed = joints.map((j, i) => [regionRows[i][0] ? +regionRows[i][0] : j.lower, regionRows[i][1] ? +regionRows[i][1] : j.upper]);
    }
    return { devices, allowed_region: allowed };
  }

  const element = h("div", { class: "device-form" },
    h("fieldset", {}, h("legend", {}, "Devices"),
      h("div", { class: "paste" },
        h("label", { for: "endpoint-line" }, "Shortcut: paste the simulated cell's endpoint line"),
        h("p", { class: "help" }, "The one line of JSON that ", h("code", {}, "recal fake-cell"),
          " prints once its devices are ready; the fields below are filled from it."),
        line, h("div", { class: "actions wrap" }, fill), lineErr, lineOk),
      h("h3", {}, "Robot controller"),
      pairs(texts.filter((t) => t.entry.role === "robot").map((t) => schemaField(t.input, prop(t.entry.key)))),
      h("h3", {}, "Instrument"),
      pairs([...texts.filter((t) => t.entry.role !== "robot").map((t) => schemaField(t.input, prop(t.entry.key))),
             schemaField(ball, ballS), ...sigmas.map((g) => schemaField(g.input, g.s))]),
      h("h3", {}, "CAN bus (reference encoders and resolvers)"),
      h("datalist", { id: "can-interfaces" }, (canProp("interface").examples || []).map((x) => h("option", { value: x }))),
      h("div", { class: "pair" }, schemaField(canIf, canProp("interface")), schemaField(canCh, canProp("channel"))),
      h("div", { class: "pair" }, schemaField(canHost, canProp("host")), schemaField(canPort, canProp("port"))),
      h("p", { class: "help" }, "CANopen node id (1–127) of the reference encoder and of the resolver on each joint; "
        + "leave empty where there is none."),
      jointsBox, unknownNote),
    h("fieldset", {}, h("legend", {}, "Allowed region"),
      h("p", { class: "help" }, "The joint ranges sessions may use, in the model's units; empty: the joint's limits "
        + "(shown greyed)."), regionBox));
  return { element, read, setJoints };
}

export async function register(ctx) {
  ctx.crumbs([["Cells", "#/"], ["Register a cell", null]]);
  if (!can("cells")) {
    put(ctx.root, card("Register a cell", h("p", {}, `Your role (${me.role}) cannot register cells.`)));
    return;
  }
  const library = await get("/library/robots");
  if (!ctx.alive()) return;
  const docs = {};
  let fileModel = null;
  const name = h("input", { id: "cell-name", required: true, placeholder: "e.g. line 3 welding robot" });
  const site = h("input", { id: "cell-site", value: "default" });
  // No robot is chosen for the technician (the first of the library, alphabetically, is no default)
  const src = h("select", { id: "model-source" },
    h("option", { value: "", selected: true, disabled: true }, "choose the robot…"),
    library.map((r) => h("option", { value: `lib:${r.name}` }, `${r.name} (library, ${r.joints} joints)`)),
    h("option", { value: "file" }, "a model file (recal.model/1 JSON)…"));
  const file = h("input", { type: "file", id: "model-file", accept: ".json,application/json" });
  const fileRow = h("div", { class: "field", hidden: true }, h("label", { for: "model-file" }, "Model file"), file);
  const modelInfo = h("p", { class: "muted small", id: "model-info" });
  const devs = deviceForm({}, null, await deviceSchema());
  async function model() {
    if (!src.value) return null;
    if (src.value === "file") return fileModel;
    const key = src.value.slice(4);
    docs[key] ||= await get(`/library/robots/${encodeURIComponent(key)}`);
    return docs[key];
  }
  async function describeModel() {
    const m = await model().catch(() => null);
    devs.setJoints(m?.joints || [], m?.units);
    if (!src.value) {
      modelInfo.textContent = "Choose the robot: a library robot's published model, or a model file.";
    } else if (src.value === "file") {
      modelInfo.textContent = fileModel ? `${fileModel.name || "model"}: ${fileModel.joints?.length} joints, `
        + `${fileModel.convention}, units ${fileModel.units?.length}/${fileModel.units?.angle}, targets: `
        + `${Object.keys(fileModel.targets || {}).join(", ") || "none"}` : "Choose the robot's nominal model file.";
    } else {
      const r = library.find((x) => `lib:${x.name}` === src.value);
      modelInfo.textContent = r ? `${r.name}: ${r.joints} joints, ${r.convention}, units ${r.units.length}/${r.units.angle}; `
        + "no targets: a tracker measures the tool flange origin (use a model file to name reflectors and tooling balls)" : "";
    }
  }
  src.addEventListener("change", () => { fileRow.hidden = src.value !== "file"; describeModel(); });
  file.addEventListener("change", async () => {
    fileModel = null;
    const f = file.files[0];
    if (f) {
      try {
        fileModel = JSON.parse(await f.text());
      } catch (e) {
        notify(`${f.name}: not valid JSON (${e.message})`);
      }
    }
    describeModel();
  });
  const drift = h("input", { id: "cell-drift", type: "number", step: "any", min: "0", placeholder: "optional" });
  const submit = h("button", { type: "submit", class: "primary", id: "save-cell" }, "Register the cell");
  const formErr = h("p", { class: "error-text", id: "form-error", role: "alert" });
  const form = h("form", { class: "card form", novalidate: true },
    h("h1", {}, "Register a cell"),
    field("Name", name), field("Site", site),
    field("Robot model", src), fileRow, modelInfo,
    devs.element,
    field("Drift threshold", drift, "in the model's length unit: the nightly job recalibrates beyond it"),
    formErr,
    h("div", { class: "actions" }, h("a", { class: "button secondary", href: "#/" }, "Cancel"), submit));
  name.addEventListener("change", () => mark(name, name.value.trim() ? "" : "give the cell a name"));
  form.addEventListener("submit", (e) => {
    e.preventDefault();
    formErr.textContent = "";
    busy(submit, async () => {
      const m = await model();
      const okName = mark(name, name.value.trim() ? "" : "give the cell a name");
      const d = devs.read();
      if (!okName || !d || !m) {
        formErr.textContent = !m ? (src.value === "file" ? "Choose the robot's model file first."
          : "Choose the robot first (Robot model).") : "Some fields need attention (marked in red).";
        if (!okName) name.focus();
        return;
      }
      const body = { name: name.value.trim(), site: site.value.trim() || "default", model: m, devices: d.devices };
      if (drift.value) body.drift_threshold = Number(drift.value);
      if (d.allowed_region) body.allowed_region = d.allowed_region;
      const cell = await post("/cells", body);
      notify(`Cell ${cell.name} registered.`, "ok");
      ctx.go(`#/cells/${cell.id}`);
    });
  });
  put(ctx.root, form);
  await describeModel();
}

export async function edit(ctx, id) {
  const [c, schema] = await Promise.all([get(`/cells/${id}/summary`), deviceSchema()]);
  if (!ctx.alive()) return;
  ctx.crumbs([["Cells", "#/"], [c.name, `#/cells/${id}`], ["Edit", null]]);
  if (!can("cells")) {
    put(ctx.root, card("Edit", h("p", {}, `Your role (${me.role}) cannot edit cells.`)));
    return;
  }
  const name = h("input", { id: "cell-name", value: c.name, required: true });
  const site = h("input", { id: "cell-site", value: c.site });
  const devs = deviceForm(c.devices_doc, c.allowed_region, schema);
  devs.setJoints(c.model.joints, c.model.units);
  const drift = h("input", { id: "cell-drift", type: "number", step: "any", min: "0", value: c.drift_threshold ?? "" });
  const submit = h("button", { type: "submit", class: "primary", id: "save-cell" }, "Save");
  const formErr = h("p", { class: "error-text", id: "form-error", role: "alert" });
  const form = h("form", { class: "card form", novalidate: true }, h("h1", {}, `Edit ${c.name}`),
    field("Name", name), field("Site", site), devs.element,
    field("Drift threshold", drift, `in ${c.unit}`),
    h("p", { class: "muted small" }, "The robot model cannot be changed: register a new cell for another robot."),
    formErr,
    h("div", { class: "actions" }, h("a", { class: "button secondary", href: `#/cells/${id}` }, "Cancel"), submit));
  form.addEventListener("submit", (e) => {
    e.preventDefault();
    formErr.textContent = "";
    busy(submit, async () => {
      const okName = mark(name, name.value.trim() ? "" : "give the cell a name");
      const d = devs.read();
      if (!okName || !d) {
        formErr.textContent = "Some fields need attention (marked in red).";
        return;
      }
      const body = { name: name.value.trim(), site: site.value.trim() || "default", devices: d.devices,
                     allowed_region: d.allowed_region, drift_threshold: drift.value ? Number(drift.value) : null };
      await patch(`/cells/${id}`, body);
      notify("Saved.", "ok");
      ctx.go(`#/cells/${id}`);
    });
  });
  put(ctx.root, form);
}

// --------------------------------------------------------------------------- start a session

// [label, what it does, default count, most the service accepts (service/models.py MAX_COUNT)]
// The kinds of session come from the service (GET /kinds: service/kinds/, each kind's name, words,
// count and instruments); nothing here names one.
let kindsPromise = null;

export function sessionKinds() {
  kindsPromise ||= get("/kinds").catch((e) => { kindsPromise = null; throw e; });
  return kindsPromise;
}

export async function start(ctx, id) {
  const [c, kindList, schema] = await Promise.all([get(`/cells/${id}/summary`), sessionKinds(), deviceSchema()]);
  if (!ctx.alive()) return;
  ctx.crumbs([["Cells", "#/"], [c.name, `#/cells/${id}`], ["Start a session", null]]);
  const KINDS = Object.fromEntries(kindList.map((k) => [k.name, k]));
  // the roles of the cell's devices (the device registry's: robot, tracker, cmm, encoder)
  const roleOf = Object.fromEntries((schema["x-devices"] || []).map((e) => [e.key, e.role]));
  const roles = new Set(c.devices.map((d) => roleOf[d]));
  if (!can("run")) {
    put(ctx.root, card("Start a session", h("p", { id: "no-start" },
      `Your role (${me.role}) can watch sessions and read results, but not start sessions.`)));
    return;
  }
  const devs = c.devices;
  const kind = h("div", { class: "kinds", role: "radiogroup" });
  kindList.forEach((k, i) => {
    const needs = k.instruments.some((r) => roles.has(r));
    kind.appendChild(h("label", { class: `kind${needs ? "" : " disabled"}` },
      h("input", { type: "radio", name: "kind", value: k.name, checked: i === 0, disabled: !needs }),
      h("span", {}, h("strong", {}, k.title), ` — ${k.summary}`)));
  });
  const first = kindList[0];
  const count = h("input", { type: "number", id: "count", min: 1, max: first.max_count, value: first.default_count });
  const device = h("select", { id: "device" },
    roles.has("tracker") ? h("option", { value: "tracker" }, "laser tracker") : null,
    roles.has("cmm") ? h("option", { value: "cmm" }, "CMM (tooling balls, full pose)") : null);
  const targets = c.robot.targets;
  const target = h("select", { id: "target" },
    targets.filter((t) => !t.startsWith("ball")).map((t) => h("option", { value: t }, t)),
    h("option", { value: "" }, "tool origin (no target)"));
  const targetField = field("Target (reflector)", target, "the point on the tool the tracker follows");
  const countHelp = h("p", { class: "help" });
  const deviceField = field("Instrument", device);
  const payloads = h("input", { type: "text", id: "payloads", placeholder: "e.g. 0; 10,0,0,100" });
  const payloadField = field("Payloads (optional)", payloads, `kg or kg,x,y,z (centre of gravity in the tool frame, `
    + `${c.unit}), separated by ";": the plan is split between them, each set through the robot controller (UR). `
    + "Two payloads let a model with joint compliance tell the arm's own weight from the payload's.");
  function sync() {
    const k = KINDS[kind.querySelector("input:checked").value];
    countHelp.textContent = k.count_help;
    deviceField.hidden = !k.device_choice;
    targetField.hidden = !k.device_choice || device.value === "cmm";
    payloadField.hidden = !k.payloads;
  }
  kind.addEventListener("change", () => {
    const spec = KINDS[kind.querySelector("input:checked").value];
    count.value = spec.default_count;
    count.max = spec.max_count;
    sync();
  });
  device.addEventListener("change", sync);
  const planBtn = h("button", { type: "submit", class: "primary", id: "plan" }, "Show the plan (nothing moves)");
  const planBox = h("div", { id: "plan-box" });
  const form = h("form", { class: "card form" },
    h("h1", {}, `Start a session on ${c.name}`),
    c.active_session ? h("div", { class: "banner banner-warn" }, activeLink(c.active_session),
      " — only one session can drive a cell at a time.") : null,
    h("fieldset", {}, h("legend", {}, "What to do"), kind),
    h("div", { class: "field" }, h("label", { for: "count" }, "How many"), count, countHelp),
    deviceField, targetField, payloadField,
    h("div", { class: "actions" }, h("a", { class: "button secondary", href: `#/cells/${id}` }, "Cancel"), planBtn));
  sync();
  form.addEventListener("submit", (e) => {
    e.preventDefault();
    busy(planBtn, async () => {
      planBtn.textContent = "Planning…";
      const k = kind.querySelector("input:checked").value;
      const body = { kind: k, count: Number(count.value), dry_run: true };
      if (KINDS[k].device_choice) body.device = device.value || "tracker";
      if (KINDS[k].device_choice && device.value !== "cmm" && target.value) body.target = target.value;
      if (!payloadField.hidden && payloads.value.trim()) {  // "0; 10,0,0,100" -> [[0], [10, 0, 0, 100]]
        body.payloads = payloads.value.split(";").map((p) => p.split(",").map((v) => Number(v.trim())));
      }
      const dry = await post(`/cells/${id}/sessions`, body);
      let s = dry;
      for (let i = 0; i < 600 && !["completed", "failed", "aborted", "paused"].includes(s.state); i++) {
        await new Promise((r) => setTimeout(r, 200));
        s = await get(`/sessions/${dry.id}`);
      }
      const plan = await get(`/sessions/${dry.id}/plan`);
      if (!ctx.alive()) return;
      showPlan(ctx, planBox, plan, s, c);
      planBox.scrollIntoView({ block: "start" });
    });
  });
  put(ctx.root, form, planBox);
}

// How many more poses, or which kind of measurement, would determine what a plan cannot (issue 27):
// calibration.planning.shortfall, in plain words.
function shortfallText(sf) {
  const parts = [];
  if (sf.more_poses > 0) parts.push(`${sf.more_poses} more poses (${sf.poses_needed} planned in all) would determine the ${sf.identifiable} parameters these poses can reach.`);
  else if (sf.poses_needed != null) parts.push(`These ${sf.count} poses are enough for the ${sf.identifiable} parameters poses of this kind can reach.`);
  for (const k of sf.by_kind || []) {
    const names = k.parameters.slice(0, 4).join(", ") + (k.parameters.length > 4 ? ` and ${k.parameters.length - 4} more` : "");
    parts.push(k.harmless
      ? `${k.parameters.length} need nothing more (${names}): ${k.needs.replace(/^nothing: /, "")}.`
      : `${k.parameters.length} no number of these poses determines (${names}): ${k.needs} would.`);
  }
  return parts.join(" ");
}

function showPlan(ctx, box, plan, s, c) {
  const unit = c.unit;
  const ok = plan.check && plan.check.ok && s.state === "completed";
  const p = plan.predicted;
  const lc = plan.learning_curve;  // the accuracy the earlier calibration's learning curve predicts (issue 28)
  const rows = [
    ["Configurations", `${plan.configurations}${plan.method ? ` (${plan.method})` : ""}`],
    ["Limit check (dry run)", h("span", { class: ok ? "ok-text" : "error-text", id: "plan-check" },
      ok ? `✓ ${plan.check.message}` : `✗ ${s.reason || plan.check?.message || "the plan failed"}`)],
    p && p.rms != null ? ["Predicted error after calibration", h("span", {},
      h("span", { id: "predicted" }, `95th percentile ${num(p.p95, 3)} ${unit}, RMS ${num(p.rms, 3)} ${unit}`),
      h("span", { class: "muted small", id: "predicted-note", style: { display: "block" } }, "The position error the "
        + "calibrated model is expected to have at random configurations of the workspace, from how well these poses "
        + `determine its parameters (for an instrument with ${num(p.sigma, 2)} ${unit} noise per axis): 95 % of the `
        + "configurations within the first figure. The result page shows the same quantity for the calibration "
        + "actually obtained."))] : null,
    p && p.identifiable ? ["Parameters", `${p.identifiable} identifiable, ${p.unidentifiable} that these poses cannot determine`]
      : p && p.unidentifiable != null ? ["Parameters", `${p.unidentifiable} that these poses cannot determine`
        + (p.unidentifiable_names ? ` (${p.unidentifiable_names.slice(0, 6).join(", ")}${p.unidentifiable > 6 ? ` and ${p.unidentifiable - 6} more` : ""})` : "")] : null,
    lc && lc.available ? ["Predicted from earlier data", h("span", {},
      h("span", { id: "learning-curve" }, `hold-out RMS ${num(lc.rms, 3)} ${unit} with ${lc.poses} poses`),
      h("span", { class: "muted small", id: "learning-curve-note", style: { display: "block" } }, lc.note))] : null,
    p && p.shortfall ? ["What would determine the rest", h("span", { id: "plan-shortfall" }, shortfallText(p.shortfall))] : null,
    plan.estimated_duration_s != null ? ["Estimated robot time", `${duration(plan.estimated_duration_s)} (motion at `
      + `≤ ${num(plan.speed_caps?.joint_speed_deg_s, 3)} °/s, settling and measuring)`] : null,
  ];
  const startBtn = h("button", { class: "primary big", id: "confirm-start", disabled: !ok }, "Start — the robot will move");
  startBtn.addEventListener("click", async () => {
    const yes = await confirmDialog("Start the session?",
      h("div", {}, h("p", {}, `The robot in ${c.name} will move through ${plan.configurations} configurations.`),
        h("p", {}, "Make sure nobody is inside the cell and the instrument's line of sight is clear. "
          + "You can pause or abort at any time.")), { confirm: "Start", danger: false });
    if (!yes) return;
    await busy(startBtn, async () => {
      const run = await post(`/sessions/${plan.session_id}/run`);
      ctx.go(`#/sessions/${run.id}`);
    });
  });
  put(box, card("The plan",
    kv(rows),
    plan.joints.length ? h("div", {}, h("h3", {}, "Joint ranges"), jointRanges(plan.joints)) : null,
    h("div", { class: "actions" }, startBtn)));
}
