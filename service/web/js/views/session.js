// A session, live: progress from the server-sent events, residuals so far, device state, time
// remaining; pause, resume and abort with a confirmation; the reason when it stops.

import { can, download, get, post, sessionEvents } from "../api.js";
import { COLORS, chart, sizes } from "../plots.js";
import { sessionKinds } from "./cells.js";
import { add, address, badge, busy, card, clear, put, confirmDialog, duration, h, kv, notify, num, when, whenSeconds } from "../ui.js";

const TERMINAL = ["completed", "failed", "aborted"];
// The devices of a session's device_state, in order, with what to call them.
const DEVICE_LABELS = [["robot", "Robot"], ["tracker", "Laser tracker"], ["cmm", "CMM"], ["encoder", "Reference encoders"]];

export async function live(ctx, id) {
  let s = await get(`/sessions/${id}`);
  const [cell, kindList] = await Promise.all([get(`/cells/${s.cell_id}/summary`), sessionKinds()]);
  // how the page names the kind and whether the request chose its instrument: the kind's own say (GET /kinds)
  const kind = kindList.find((k) => k.name === s.kind) || { heading: s.kind, device_choice: true };
  if (!ctx.alive()) return;
  ctx.crumbs([["Cells", "#/"], [cell.name, `#/cells/${cell.id}`], [`Session ${id}`, null]]);
  const unit = cell.unit;

  const title = h("h1", {}, `${kind.heading} ${id}`);
  const stateEl = h("span", { id: "state" });
  const banner = h("div", { id: "banner" });
  const bar = h("div", { class: "bar-fill" });
  const progressText = h("div", { class: "progress-text", id: "progress" });
  const remaining = h("span", { id: "remaining" }, "–");
  const pace = h("span", {}, "–");
  const controls = h("div", { class: "actions", id: "controls" });
  const resid = h("div", { id: "residuals" });
  const devices = h("div", { id: "device-state" });
  const outcome = h("div", { id: "outcome" });

  put(ctx.root, 
    h("div", { class: "page-head" }, h("div", {}, title,
      h("p", { class: "muted" }, `${cell.name} · ${s.device}${s.target ? ` · target ${s.target}` : ""} · started by `
        + `${s.created_by} ${when(s.created_at)}`)), stateEl),
    banner,
    card("Progress",
      h("div", { class: "bar", role: "progressbar", "aria-label": "poses measured" }, bar), progressText,
      kv([["Time remaining", remaining], ["Pace", pace]]), controls,
      // the measurements so far, as the CSV `recal identify --data` reads (in the cell's units)
      h("p", { class: "small" }, h("button", { class: "secondary", id: "download-measurements",
        onclick: (e) => busy(e.target, () => download(`/sessions/${id}/measurements.csv`, `session-${id}-measurements.csv`)) },
        "Download the measurements (CSV)"))),
    outcome,
    h("div", { class: "two wide-first" }, card("Residuals so far", resid), card("Devices", devices)));

  let lastLive = 0, pending = null;
  async function refreshLive(force = false) {
    const now = Date.now();
    if (!force && now - lastLive < 900) {
      if (!pending) pending = setTimeout(() => { pending = null; refreshLive(true); }, 900 - (now - lastLive));
      return;
    }
    lastLive = now;
    try {
      const l = await get(`/sessions/${id}/live`);
      if (!ctx.alive()) return;
      showLive(l);
    } catch (e) { /* the next event retries */ }
  }

  // One count of the poses measured, from the live snapshot the chart and "Last reading" are
  // drawn from (the server counts them once, from the rows it charts); the session's own count
  // only until the first snapshot arrives. A paused session said "7 of 60 poses" beside a chart
  // and a last reading ending at pose 6: two counts read at different times (the live one from
  // the service's page cache, and never read again once the session had paused).
  function showProgress() {
    const measured = lastL ? lastL.measured : s.measured;
    const planned = s.planned;
    const pct = planned ? Math.round((100 * measured) / planned) : 0;
    bar.style.width = `${pct}%`;
    progressText.textContent = `${measured} of ${planned} poses measured (${pct} %)`;
  }

  let lastL = null;
  function showLive(l) {
    lastL = l;
    showProgress();
    remaining.textContent = TERMINAL.includes(s.state) ? "–"
      : s.state === "paused" || s.state === "interrupted" ? `${l.remaining_s != null ? `about ${duration(l.remaining_s)} ` : ""}once resumed`
      : l.remaining_s != null ? `about ${duration(l.remaining_s)}` : "estimating…";
    pace.textContent = l.seconds_per_pose != null ? `${num(l.seconds_per_pose, 2)} s per pose, ${duration(l.elapsed_s)} so far` : "–";
    const r = l.residuals;
    clear(resid);
    if (r && r.norm.length) {
      const isDeg = r.unit === "deg";
      add(resid, 
        chart([{ x: r.pose, y: r.norm, type: "bars", color: COLORS.after, label: isDeg ? "deviation (deg)" : `position error (${unit})` }],
          { xLabel: "pose", yLabel: isDeg ? "deg" : unit, integerX: true, height: 230, width: sizes().wide, xName: "pose", legend: false,
            title: "residuals against pose", zeroLine: true }),
        h("p", { class: "small muted" }, `${r.model}. RMS ${num(r.stats.rms, 3)}, max ${num(r.stats.max, 3)} ${isDeg ? "deg" : unit}.`));
    } else {
      add(resid, h("p", { class: "muted" }, !l.measured ? "No measurement yet."
        : r ? r.model : "No residuals for this kind of session."));
    }
    showDevices();
    // The live answer may be up to a second older than the session's state (the service keeps
    // the page's polled answers that long): until they agree, ask again. A paused session sends no
    // further events, and its page stayed at the older answer.
    if (l.measured !== s.measured || l.state !== s.state) refreshLive();
  }

  function showDevices() {
    const l = lastL || {};
    clear(devices);
    const last = l.last;
    const robots = cell.devices.filter((d) => d === "rtde" || d === "modbus");
    const where = { robot: robots.map((d, i) => [i ? ", " : "", `${d} `, address(cell.devices_doc[d])]),
                    tracker: trackerAddress(), cmm: address(cell.devices_doc.cmm),
                    encoder: "CANopen" };
    const ds = s.device_state;
    let rows;
    if (ds && DEVICE_LABELS.some(([k]) => ds[k])) {
      // a detail that only repeats the reason in the banner above is left out
      const detail = (k) => (ds[k].detail && ds[k].detail !== s.reason ? ` — ${ds[k].detail}` : "");
      rows = DEVICE_LABELS.filter(([k]) => ds[k]).map(([k, label]) => [label, h("span", { class: "device-state", "data-device": k },
        h("span", { class: `state state-${String(ds[k].state || "").replace(/\s+/g, "-")}` }, ds[k].state || "–"),
        detail(k), h("br"), h("span", { class: "small muted" }, where[k] || ""))]);
      if (s.state === "interrupted") { // the devices' state from before the service stopped: only the last known
        rows.unshift(["Now", "not connected: the service stopped while the session ran; below, what the devices "
          + "last reported"]);
        if (ds.at) rows.push(["Last known at", whenSeconds(ds.at)]);
      } else if (ds.at) rows.push(["As of", whenSeconds(ds.at)]);
    } else {
      rows = [["Robot", robots.length ? where.robot : "–"],
              ["Instrument", !kind.device_choice ? "reference encoders (CAN)"
                : [`${s.device} `, s.device === "tracker" ? trackerAddress() : address(cell.devices_doc[s.device] || "")]],
              ["State", deviceState(s)]];
    }
    if (s.beam_recoveries) rows.push(["Beam recoveries", h("span", { id: "beam-recoveries" },
      `${s.beam_recoveries}: the beam broke and the tracker found the reflector where the model puts it`)]);
    if (last) {
      rows.push(["Last reading", `pose ${last.pose} at ${whenSeconds(last.at)}`]);
      rows.push(["Joints (deg)", last.q_deg.map((v) => num(v, 4)).join(", ")]);
      if (kind.device_choice) rows.push(["Measured point", `${last.position.map((v) => num(v, 6)).join(", ")} ${unit}`
        + (last.sigma ? ` ± ${num(last.sigma, 2)}` : "")]);
      if (last.reference_deg != null) rows.push(["Reference encoder", `${num(last.reference_deg, 6)} deg`]);
    }
    add(devices, kv(rows));
  }

  // The tracker sessions use: Leica emScon when the cell has one, else the line protocol.
  function trackerAddress() {
    const e = cell.devices_doc.emscon;
    if (e) return address(`emScon ${typeof e === "object" ? `${e.host}:${e.port || 700}` : e}`);
    return address(cell.devices_doc.tracker || "");
  }

  function deviceState(x) {
    if (x.state === "running") return "connected: moving and measuring";
    if (x.state === "planned") return "opening the devices…";
    if (x.state === "paused") return "stopped (paused)";
    if (x.state === "interrupted") return "not connected (the service stopped)";
    return "closed";
  }

  function show(snap) {
    s = snap;
    if (asking && !APPLIES[asking.what](s.state)) { // e.g. "Pause the session?" while it completed
      const { what, controller } = asking;
      asking = null;
      controller.abort();
      notify(`The session is ${s.state} now: nothing to ${what}.`, "ok");
    }
    put(stateEl, badge(s.state));
    showProgress();
    clear(banner);
    if (s.state === "paused" || s.state === "interrupted" || s.state === "failed" || s.state === "aborted") {
      const kind = s.state === "failed" ? "error" : "warn";
      const heading = { paused: "Paused", interrupted: "Interrupted", failed: "Failed", aborted: "Aborted" }[s.state];
      add(banner, h("div", { class: `banner banner-${kind}`, role: "alert", id: "stop-banner" },
        h("strong", {}, `${heading}: `), s.reason || "no reason given",
        s.state === "paused" || s.state === "interrupted"
          ? h("div", { class: "small" }, "Nothing moves until someone resumes the session. Measurements taken so far are kept; "
            + "it continues with the first pose not yet measured.") : null));
    }
    const controllerWarning = s.plan_info?.controller_model?.warning;
    if (controllerWarning) {  // the UR controller's own kinematics changed (or could not be read)
      add(banner, h("div", { class: "banner banner-warn", id: "controller-model-banner" },
        h("strong", {}, "Controller kinematics: "), controllerWarning));
    }
    clear(controls);
    if (can("run")) {
      if (s.state === "running" || s.state === "planned") {
        add(controls, h("button", { class: "secondary", id: "pause", onclick: (e) => act(e.target, "pause") }, "Pause"));
      }
      if (s.state === "paused" || s.state === "interrupted") {
        add(controls, h("button", { class: "primary", id: "resume", onclick: (e) => act(e.target, "resume") }, "Resume"));
      }
      if (!TERMINAL.includes(s.state)) {
        add(controls, h("button", { class: "danger", id: "abort", onclick: (e) => act(e.target, "abort") }, "Abort"));
      }
    }
    if (TERMINAL.includes(s.state)) showOutcome();
    if (lastL) showLive(lastL);
    else showDevices();
  }

  const ASK = {
    pause: ["Pause the session?", "The robot stops after the current pose. Measurements taken so far are kept.", "Pause", false],
    resume: ["Resume the session?", "The robot will move again. Make sure nobody is inside the cell.", "Resume", false],
    abort: ["Abort the session?", "The robot stops now and the session ends; it cannot be resumed. Measurements taken so "
      + "far are kept but no calibration is made from them.", "Abort", true],
  };

  // Whether a control still applies to the session's state (its button is shown for it).
  const APPLIES = {
    pause: (state) => state === "running" || state === "planned",
    resume: (state) => state === "paused" || state === "interrupted",
    abort: (state) => !TERMINAL.includes(state),
  };
  let asking = null; // {what, controller}: the question open, withdrawn when the session moves on

  async function act(button, what) {
    const [t, m, c, danger] = ASK[what];
    const controller = new AbortController();
    asking = { what, controller };
    const yes = await confirmDialog(t, m, { confirm: c, danger, signal: controller.signal });
    if (asking?.controller === controller) asking = null;
    if (!yes) return;
    await busy(button, async () => {
      show(await post(`/sessions/${id}/${what}`));
      if (what === "resume") listen();
    });
  }

  let outcomeShown = false;
  async function showOutcome() {
    if (outcomeShown) return;
    outcomeShown = true;
    clear(outcome);
    if (s.state !== "completed") return;
    if (s.calibration_id) {
      // a later calibration does not replace the one in use: it waits for a verify session or an activation
      const now = await get(`/cells/${s.cell_id}/summary`).catch(() => null);
      const waits = now && now.current && now.current.id !== s.calibration_id;
      add(outcome, h("div", { class: "banner banner-ok", id: "done-banner" },
        h("strong", {}, "Calibrated. "), `The robot was measured at ${s.measured} poses and its true geometry worked out `
        + `(calibration ${s.calibration_id}). `
        + (waits ? `It is not in use yet: the cell still works with calibration ${now.current.id}. A verify session next `
          + "measures both and puts the new one in use if it is at least as accurate; or activate it on the cell's page. "
          : "A verify session next measures how accurate it now is. "),
        h("a", { class: "button primary", href: `#/calibrations/${s.calibration_id}`, id: "open-result" }, "Open the result")));
    } else if (s.plan_info && s.plan_info.verify) {
      add(outcome, card("Verification result", verifyBanner(s.plan_info.verify)));
    } else {
      add(outcome, h("div", { class: "banner banner-ok", id: "done-banner" }, h("strong", {}, "Done. "), s.reason || ""));
    }
  }

  let es = null;
  let retries = 0;
  let done = TERMINAL.includes(s.state);
  async function listen() {
    if (es) es.close();
    if (done || !ctx.alive()) return;
    let stream;
    try {
      stream = await sessionEvents(id);
    } catch (e) {
      return retry();
    }
    if (!ctx.alive()) return stream.close();
    es = stream;
    es.addEventListener("progress", (ev) => {
      if (!ctx.alive()) return es.close();
      retries = 0;
      const snap = JSON.parse(ev.data);
      const moved = snap.state !== s.state;
      show(snap);
      // a session that stops (pauses, completes) is shown as it stopped at once, not a second later
      refreshLive(moved || snap.state !== "running");
      if (TERMINAL.includes(snap.state)) { done = true; es.close(); }
    });
    es.onerror = () => {
      // A ticket serves one connection: the browser's own reconnection would be refused, so
      // open a new stream with a new ticket instead.
      stream.close();
      if (!done) retry();
    };
  }
  function retry() {
    retries += 1;
    if (retries === 5) notify("Lost the connection to the service; trying again.");
    setTimeout(listen, Math.min(10000, 500 * retries));
  }
  ctx.onLeave(() => { done = true; if (es) es.close(); if (pending) clearTimeout(pending); });
  show(s);
  refreshLive(true);
  listen();
}

// What a verify session found, in a technician's words and with units: a calibration's accuracy
// (green), or the nominal model's error, led by the figure with the robot placed where it fits
// the instrument best (its own inaccuracy; where the instrument stands is not the robot's error).
function verifyBanner(v) {
  const u = v.unit;
  if (v.calibration_id) {
    const k = v.candidate, was = k && k.against.calibration_id ? `calibration ${k.against.calibration_id}` : "the nominal model";
    return h("div", { class: `banner banner-${k && !k.passed ? "warn" : "ok"}`, id: "done-banner" },
      h("strong", {}, "Checked. "), `Calibration ${v.calibration_id} is accurate to ${num(v.rms, 3)} ${u} RMS `
      + `(max ${num(v.max, 3)} ${u}; 95 % of points within ${num(v.p95, 3)} ${u}), measured at ${v.n} fresh configurations.`,
      k ? h("div", { id: "candidate-verdict" }, k.passed
        ? `It is at least as accurate as ${was} (${num(k.against.rms, 3)} ${u} RMS on the same configurations) and is now in use.`
        : `It is less accurate than ${was} (${num(k.against.rms, 3)} ${u} RMS on the same configurations), which stays in use; `
          + "it can still be activated on the cell's page.") : null);
  }
  const reg = v.registered;
  return h("div", { class: "banner banner-warn", id: "done-banner" },
    h("strong", {}, "Not calibrated yet. "),
    reg ? `With its nominal model the robot is off by ${num(reg.rms, 3)} ${u} RMS (max ${num(reg.max, 3)} ${u}) at `
      + `${v.n} fresh configurations, even placed where it fits the instrument best. `
      : `With its nominal model the robot is off by ${num(v.rms, 3)} ${u} RMS (max ${num(v.max, 3)} ${u}) at ${v.n} `
      + "fresh configurations. ",
    "A pose session calibrates it.",
    reg ? h("div", { class: "small" }, `Before its position in front of the instrument is known, points are `
      + `${num(v.rms, 3)} ${u} RMS off (max ${num(v.max, 3)} ${u}); a calibration finds that position too.`) : null);
}
