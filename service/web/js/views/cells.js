// Cells: the overview, one cell (devices and their connection test, accuracy trend, sessions,
// calibrations), registering and editing a cell, and starting a session (plan first, then confirm).

import { can, get, me, patch, post } from "../api.js";
import { COLORS, chart, jointRanges, sizes, sparkline } from "../plots.js";
import { add, badge, busy, card, clear, put, confirmDialog, duration, h, kv, notify, num, table, when, whenShort } from "../ui.js";

const DEVICE_NAMES = { rtde: "robot (UR RTDE)", modbus: "robot (Modbus TCP)", tracker: "laser tracker",
                       cmm: "CMM (I++ DME)", can: "CAN bus", encoders: "reference encoders", resolvers: "resolvers" };

function robotLine(r) {
  return `${r.name} · ${r.joints} joints · ${r.convention}`;
}

function activeLink(a) {
  if (!a) return null;
  return h("a", { class: `active-session state-${a.state}`, href: `#/sessions/${a.id}` },
    badge(a.state), ` ${a.kind} session ${a.id}: ${a.measured}/${a.planned} measured`);
}

// --------------------------------------------------------------------------- overview

export async function overview(ctx) {
  ctx.crumbs([["Cells", null]]);
  const data = await get("/overview?limit=200");
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
        h("div", { class: "big" }, last ? `${num(last.rms, 3)} ${c.unit}` : "—"),
        h("div", { class: "muted small" }, last ? `residual RMS of calibration ${last.id}, ${whenShort(last.created_at)}`
          : "not calibrated yet"),
        c.trend.length > 1 ? sparkline(c.trend.map((t) => t.rms), { width: 260, height: 40,
                                                                   title: "accuracy trend (RMS of the last calibrations)" }) : null),
      activeLink(c.active_session),
      h("a", { class: "button", href: `#/cells/${c.id}` }, "Open")));
  }
  put(ctx.root, 
    h("div", { class: "page-head" },
      h("h1", {}, "Cells"),
      can("cells") ? h("a", { class: "button primary", href: "#/cells/new", id: "register-cell" }, "Register a cell") : null),
    data.cells.length ? grid : card("No cells yet",
      h("p", {}, can("cells") ? "Register the first robot cell: its robot model and the address of each device."
        : "A technician registers cells; there are none yet.")),
    data.total > data.cells.length ? h("p", { class: "muted" }, `${data.cells.length} of ${data.total} cells shown`) : null,
    howTo(data.cells.length === 0));
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
  const c = await get(`/cells/${id}/summary`);
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
    .map(([k, v]) => [DEVICE_NAMES[k] || k, h("code", {}, address(k, v))]);
  const devCard = card("Devices", table(["Device", "Address"], devRows),
    h("p", { class: "muted small" }, "The test opens each device, asks it something harmless and shows what it "
      + "answered. Nothing moves."), testBtn, results);
  if (testBtn) testBtn.addEventListener("click", () => busy(testBtn, async () => {
    testBtn.textContent = "Testing…";
    const res = await post(`/cells/${id}/devices/test`);
    showTest(results, { at: new Date().toISOString(), by: me.name, results: res.results });
  }));
  get(`/cells/${id}/devices/test`).then((t) => { if (t.last && !results.firstChild) showTest(results, t.last, true); })
    .catch(() => {});

  // accuracy trend
  const trend = c.trend;
  const trendCard = card("Accuracy over time",
    trend.length ? chart([{ x: trend.map((t) => t.id), y: trend.map((t) => t.rms), type: "line", color: COLORS.after,
                            label: `residual RMS (${unit})`, onclick: (x) => ctx.go(`#/calibrations/${x}`) }],
      { xLabel: "calibration", yLabel: unit, integerX: true, height: 220, title: "accuracy trend", width: sizes().half })
      : h("p", { class: "muted" }, "No calibration yet."),
    c.last ? h("p", {}, "Last calibration: ", h("a", { href: `#/calibrations/${c.last.id}`, id: "last-calibration" },
      `calibration ${c.last.id}`), `, RMS ${num(c.last.rms, 3)} ${unit}, ${when(c.last.created_at)}`) : null);

  const sessionsBox = h("div", {});
  const calsBox = h("div", {});
  put(ctx.root, head, banner,
    h("div", { class: "two" }, robotCard, trendCard),
    devCard,
    h("div", { class: "two" }, card("Sessions", sessionsBox), card("Calibrations", calsBox)));
  pagedSessions(sessionsBox, id, 0);
  pagedCalibrations(calsBox, id, 0, unit);
}

function address(key, v) {
  if ((key === "encoders" || key === "resolvers") && v && typeof v === "object") {
    return Object.entries(v).map(([j, node]) => `joint ${j}: CANopen node ${node}`).join(", ");
  }
  if (key === "can" && v && typeof v === "object") {
    return `${v.interface || "?"} ${v.channel || ""}${v.host ? ` at ${v.host}:${v.port}` : ""}`;
  }
  return typeof v === "object" ? JSON.stringify(v) : String(v);
}

function showTest(box, t, old = false) {
  const rows = t.results.map((r) => [
    r.device,
    r.skipped ? h("span", { class: "badge state-paused" }, "not tested") : r.ok
      ? h("span", { class: "badge state-completed" }, "OK") : h("span", { class: "badge state-failed" }, "ERROR"),
    h("span", { class: r.ok ? "" : "error-text" }, r.answer || r.error || ""),
    r.elapsed_ms != null ? `${Math.round(r.elapsed_ms)} ms` : ""]);
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

async function pagedCalibrations(box, id, offset, unit) {
  const page = await get(`/cells/${id}/history?limit=10&offset=${offset}`);
  const rows = page.items.map((c) => [h("a", { href: `#/calibrations/${c.id}` }, `#${c.id}`), c.kind,
    c.rms != null ? num(c.rms, 3) : "–", h("span", { class: "nowrap" }, whenShort(c.created_at))]);
  put(box, rows.length ? table(["", "Kind", `RMS (${unit})`, "Date"], rows, { class: "calibrations" })
    : h("p", { class: "muted" }, "No calibrations yet."),
    pager(page.total, offset, 10, (o) => pagedCalibrations(box, id, o, unit)));
}

function pager(total, offset, size, go) {
  if (total <= size) return null;
  const prev = h("button", { class: "secondary", disabled: offset <= 0, onclick: () => go(Math.max(0, offset - size)) }, "‹ Newer");
  const next = h("button", { class: "secondary", disabled: offset + size >= total, onclick: () => go(offset + size) }, "Older ›");
  return h("div", { class: "pager" }, prev, h("span", { class: "muted" }, `${offset + 1}–${Math.min(total, offset + size)} of ${total}`), next);
}

// --------------------------------------------------------------------------- register / edit

function parseJson(text, what) {
  if (!text.trim()) return null;
  try {
    return JSON.parse(text);
  } catch (e) {
    throw new Error(`${what}: not valid JSON (${e.message})`);
  }
}

const DEVICES_EXAMPLE = '{"rtde": "127.0.0.2", "tracker": "socket://127.0.0.2:10001", "cmm": "socket://127.0.0.2:1294"}';

export async function register(ctx) {
  ctx.crumbs([["Cells", "#/"], ["Register a cell", null]]);
  if (!can("cells")) {
    put(ctx.root, card("Register a cell", h("p", {}, `Your role (${me.role}) cannot register cells.`)));
    return;
  }
  const library = await get("/library/robots");
  if (!ctx.alive()) return;
  let fileModel = null;
  const name = h("input", { id: "cell-name", required: true, placeholder: "e.g. line 3 welding robot" });
  const site = h("input", { id: "cell-site", value: "default" });
  const src = h("select", { id: "model-source" },
    library.map((r) => h("option", { value: `lib:${r.name}` }, `${r.name} (library, ${r.joints} joints)`)),
    h("option", { value: "file" }, "a model file (recal.model/1 JSON)…"));
  const file = h("input", { type: "file", id: "model-file", accept: ".json,application/json" });
  const fileRow = h("div", { class: "field", hidden: true }, h("label", { for: "model-file" }, "Model file"), file);
  const modelInfo = h("p", { class: "muted small", id: "model-info" });
  src.addEventListener("change", () => { fileRow.hidden = src.value !== "file"; describeModel(); });
  file.addEventListener("change", async () => {
    fileModel = null;
    const f = file.files[0];
    if (!f) return describeModel();
    try {
      fileModel = JSON.parse(await f.text());
    } catch (e) {
      notify(`${f.name}: not valid JSON (${e.message})`);
    }
    describeModel();
  });
  function describeModel() {
    if (src.value === "file") {
      modelInfo.textContent = fileModel ? `${fileModel.name || "model"}: ${fileModel.joints?.length} joints, `
        + `${fileModel.convention}, units ${fileModel.units?.length}/${fileModel.units?.angle}, targets: `
        + `${Object.keys(fileModel.targets || {}).join(", ") || "none"}` : "Choose the robot's nominal model file.";
    } else {
      const r = library.find((x) => `lib:${x.name}` === src.value);
      modelInfo.textContent = r ? `${r.name}: ${r.joints} joints, ${r.convention}, units ${r.units.length}/${r.units.angle}; `
        + "no targets: a tracker measures the tool flange origin (use a model file to name reflectors and tooling balls)" : "";
    }
  }
  describeModel();
  const devices = h("textarea", { id: "cell-devices", rows: 5, placeholder: DEVICES_EXAMPLE, spellcheck: "false" });
  const drift = h("input", { id: "cell-drift", type: "number", step: "any", min: "0", placeholder: "optional" });
  const region = h("textarea", { id: "cell-region", rows: 2, placeholder: "optional: [[-180, 180], [-150, 0], ...] one [low, high] per joint, model units" });
  const submit = h("button", { type: "submit", class: "primary", id: "save-cell" }, "Register the cell");
  const form = h("form", { class: "card form" },
    h("h1", {}, "Register a cell"),
    field("Name", name), field("Site", site),
    field("Robot model", src), fileRow, modelInfo,
    field("Devices", devices, "Paste the line `recal fake-cell` printed, or the same shape for real devices: "
      + "rtde (UR controller address) or modbus (HOST:PORT), tracker and cmm (socket://HOST:PORT or a serial port), "
      + "can with encoders / resolvers."),
    field(`Drift threshold`, drift, "in the model's length unit: the nightly job recalibrates beyond it"),
    field("Allowed region", region, "joint ranges the sessions may use"),
    h("div", { class: "actions" }, h("a", { class: "button secondary", href: "#/" }, "Cancel"), submit));
  form.addEventListener("submit", (e) => {
    e.preventDefault();
    busy(submit, async () => {
      let model;
      if (src.value === "file") {
        if (!fileModel) throw new Error("choose a model file first");
        model = fileModel;
      } else {
        model = await get(`/library/robots/${encodeURIComponent(src.value.slice(4))}`);
      }
      const body = { name: name.value.trim(), site: site.value.trim() || "default", model,
                     devices: parseJson(devices.value, "Devices") || {} };
      if (drift.value) body.drift_threshold = Number(drift.value);
      const reg = parseJson(region.value, "Allowed region");
      if (reg) body.allowed_region = reg;
      const cell = await post("/cells", body);
      notify(`Cell ${cell.name} registered.`, "ok");
      ctx.go(`#/cells/${cell.id}`);
    });
  });
  put(ctx.root, form);
}

function field(label, input, help) {
  const id = input.id || `f${Math.random().toString(36).slice(2)}`;
  input.id = id;
  return h("div", { class: "field" }, h("label", { for: id }, label), input, help ? h("p", { class: "help" }, help) : null);
}

export async function edit(ctx, id) {
  const c = await get(`/cells/${id}/summary`);
  if (!ctx.alive()) return;
  ctx.crumbs([["Cells", "#/"], [c.name, `#/cells/${id}`], ["Edit", null]]);
  if (!can("cells")) {
    put(ctx.root, card("Edit", h("p", {}, `Your role (${me.role}) cannot edit cells.`)));
    return;
  }
  const name = h("input", { id: "cell-name", value: c.name, required: true });
  const site = h("input", { id: "cell-site", value: c.site });
  const devices = h("textarea", { id: "cell-devices", rows: 6, spellcheck: "false" });
  devices.value = JSON.stringify(c.devices_doc || {}, null, 1);
  const drift = h("input", { id: "cell-drift", type: "number", step: "any", min: "0", value: c.drift_threshold ?? "" });
  const region = h("textarea", { id: "cell-region", rows: 3 });
  region.value = c.allowed_region ? JSON.stringify(c.allowed_region) : "";
  const submit = h("button", { type: "submit", class: "primary", id: "save-cell" }, "Save");
  const form = h("form", { class: "card form" }, h("h1", {}, `Edit ${c.name}`),
    field("Name", name), field("Site", site), field("Devices", devices),
    field("Drift threshold", drift, `in ${c.unit}`), field("Allowed region", region, "one [low, high] per joint, model units; empty: the joint limits"),
    h("p", { class: "muted small" }, "The robot model cannot be changed: register a new cell for another robot."),
    h("div", { class: "actions" }, h("a", { class: "button secondary", href: `#/cells/${id}` }, "Cancel"), submit));
  form.addEventListener("submit", (e) => {
    e.preventDefault();
    busy(submit, async () => {
      const body = { name: name.value.trim(), site: site.value.trim() || "default",
                     devices: parseJson(devices.value, "Devices") || {},
                     allowed_region: parseJson(region.value, "Allowed region") };
      body.drift_threshold = drift.value ? Number(drift.value) : null;
      await patch(`/cells/${id}`, body);
      notify("Saved.", "ok");
      ctx.go(`#/cells/${id}`);
    });
  });
  put(ctx.root, form);
}

// --------------------------------------------------------------------------- start a session

const KINDS = {
  pose: ["Calibrate", "measure the robot at planned poses and identify its true geometry", 40],
  verify: ["Verify", "measure fresh poses and report how accurate the current model is (changes nothing)", 20],
  joint: ["Joint encoders", "sweep joints against reference encoders: gains and gear eccentricity", 12],
  circle: ["Circle points", "sweep each joint alone to locate its axis", 12],
};

export async function start(ctx, id) {
  const c = await get(`/cells/${id}/summary`);
  if (!ctx.alive()) return;
  ctx.crumbs([["Cells", "#/"], [c.name, `#/cells/${id}`], ["Start a session", null]]);
  if (!can("run")) {
    put(ctx.root, card("Start a session", h("p", { id: "no-start" },
      `Your role (${me.role}) can watch sessions and read results, but not start sessions.`)));
    return;
  }
  const devs = c.devices;
  const kind = h("div", { class: "kinds", role: "radiogroup" });
  for (const [k, [label, text]] of Object.entries(KINDS)) {
    const needs = k === "joint" ? devs.includes("can") : devs.includes("tracker") || devs.includes("cmm");
    kind.appendChild(h("label", { class: `kind${needs ? "" : " disabled"}` },
      h("input", { type: "radio", name: "kind", value: k, checked: k === "pose", disabled: !needs }),
      h("span", {}, h("strong", {}, label), ` — ${text}`)));
  }
  const count = h("input", { type: "number", id: "count", min: 1, max: 2000, value: 40 });
  const device = h("select", { id: "device" },
    devs.includes("tracker") ? h("option", { value: "tracker" }, "laser tracker") : null,
    devs.includes("cmm") ? h("option", { value: "cmm" }, "CMM (tooling balls, full pose)") : null);
  const targets = c.robot.targets;
  const target = h("select", { id: "target" },
    targets.filter((t) => !t.startsWith("ball")).map((t) => h("option", { value: t }, t)),
    h("option", { value: "" }, "tool origin (no target)"));
  const targetField = field("Target (reflector)", target, "the point on the tool the tracker follows");
  const countHelp = h("p", { class: "help" });
  const deviceField = field("Instrument", device);
  function sync() {
    const k = kind.querySelector("input:checked").value;
    countHelp.textContent = k === "pose" || k === "verify" ? "number of robot configurations to measure"
      : "points per swept joint";
    deviceField.hidden = k === "joint";
    targetField.hidden = k === "joint" || device.value === "cmm";
  }
  kind.addEventListener("change", () => {
    count.value = KINDS[kind.querySelector("input:checked").value][2];
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
    deviceField, targetField,
    h("div", { class: "actions" }, h("a", { class: "button secondary", href: `#/cells/${id}` }, "Cancel"), planBtn));
  sync();
  form.addEventListener("submit", (e) => {
    e.preventDefault();
    busy(planBtn, async () => {
      planBtn.textContent = "Planning…";
      const k = kind.querySelector("input:checked").value;
      const body = { kind: k, count: Number(count.value), dry_run: true };
      if (k !== "joint") body.device = device.value || "tracker";
      if (k !== "joint" && device.value !== "cmm" && target.value) body.target = target.value;
      const dry = await post(`/cells/${id}/sessions`, body);
      let s = dry;
      for (let i = 0; i < 600 && !["completed", "failed", "aborted", "paused"].includes(s.state); i++) {
        await new Promise((r) => setTimeout(r, 200));
        s = await get(`/sessions/${dry.id}`);
      }
      const plan = await get(`/sessions/${dry.id}/plan`);
      if (!ctx.alive()) return;
      showPlan(ctx, planBox, plan, s, c);
      planBox.scrollIntoView({ behavior: "smooth", block: "start" });
    });
  });
  put(ctx.root, form, planBox);
}

function showPlan(ctx, box, plan, s, c) {
  const unit = c.unit;
  const ok = plan.check && plan.check.ok && s.state === "completed";
  const p = plan.predicted;
  const rows = [
    ["Configurations", `${plan.configurations}${plan.method ? ` (${plan.method})` : ""}`],
    ["Limit check (dry run)", h("span", { class: ok ? "ok-text" : "error-text", id: "plan-check" },
      ok ? `✓ ${plan.check.message}` : `✗ ${s.reason || plan.check?.message || "the plan failed"}`)],
    p && p.rms != null ? ["Predicted accuracy", h("span", { id: "predicted" },
      `RMS ${num(p.rms, 3)} ${unit}, 95 % of the workspace within ${num(p.p95, 3)} ${unit}`)] : null,
    p && p.identifiable ? ["Parameters", `${p.identifiable} identifiable, ${p.unidentifiable} that these poses cannot determine`]
      : p && p.unidentifiable != null ? ["Parameters", `${p.unidentifiable} that these poses cannot determine`
        + (p.unidentifiable_names ? ` (${p.unidentifiable_names.slice(0, 6).join(", ")}${p.unidentifiable > 6 ? ", …" : ""})` : "")] : null,
    p && p.note ? ["", h("span", { class: "muted small" }, p.note)] : null,
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
