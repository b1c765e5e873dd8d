// A calibration's result: parameters and their standard errors, what the data could not
// determine, errors before and after (histograms, per pose), residuals against pose, predicted
// accuracy over the workspace, comparison with the previous calibration, downloads, and
// compensating a task file.

import { api, can, download, get, saveBlob } from "../api.js";
import { COLORS, chart, colorMap, histogram, sizes } from "../plots.js";
import { add, badge, busy, card, clear, put, h, kv, length, num, paramLabel, table, when } from "../ui.js";

// Above this the page explains the identification's (scaled) condition number in plain words (the certificate
// judges conditioning by the predicted accuracy over the workspace, not by this number).
const CONDITION_LIMIT = 1000;

export async function show(ctx, id) {
  const r = await get(`/calibrations/${id}/result`);
  if (!ctx.alive()) return;
  ctx.crumbs([["Cells", "#/"], [r.cell.name, `#/cells/${r.cell.id}`], [`Calibration ${id}`, null]]);
  const unit = r.units.length;
  const rep = r.report;
  const e = r.errors && r.errors.available ? r.errors : null;
  const ws = r.workspace && r.workspace.available ? r.workspace : null;

  const downloads = h("div", { class: "actions wrap", id: "downloads" },
    dl("Model (JSON)", `/calibrations/${id}/download/model`, "model.json", "download-model"),
    dl("URDF", `/calibrations/${id}/download/urdf`, "robot.urdf", "download-urdf"),
    dl("DH table (CSV)", `/calibrations/${id}/download/dh-csv`, "dh.csv", "download-dh"),
    dl("DH table (Markdown)", `/calibrations/${id}/download/dh-md`, "dh.md", "download-dh-md"),
    dl("UR calibration (YAML)", `/calibrations/${id}/download/ur-calibration`, "ur-calibration.yaml",
      "download-ur-calibration"),
    h("a", { class: "button", href: `#/calibrations/${id}/certificate`, id: "open-certificate" }, "Certificate"));

  const head = h("div", { class: "page-head" },
    h("div", {}, h("h1", {}, `Calibration ${id}`),
      h("p", { class: "muted" }, `${r.cell.name} · ${r.robot} · ${when(r.created_at)}`
        + (r.session ? ` · session ${r.session.id} by ${r.session.created_by}` : ""))),
    rep.success === false ? badge("failed") : badge("completed"));

  const pred = ws ? ws.stats_rms : null;
  const summary = h("div", { class: "stats", id: "summary" },
    e ? stat("Before", num(e.before.stats.rms, 3), unit, `RMS, max ${num(e.before.stats.max, 3)}`, "before") : null,
    stat("After (fitted poses)", num(e ? e.after.stats.rms : r.rms, 3), unit,
      e ? `RMS, max ${num(e.after.stats.max, 3)}` : "residual RMS", "after"),
    pred ? stat("Predicted error", num(pred.p95, 3), unit,
      `95th percentile at random configurations; RMS ${num(pred.rms, 3)}`, "predicted") : null,
    stat("Poses", String(rep.rows ?? "–"), "", `${(rep.outliers || []).length} outlier(s)`),
    stat("Parameters", String((rep.parameters || []).length), "", `${(rep.unidentifiable || []).length} not determinable`));
  const summaryNote = h("p", { class: "small muted", id: "summary-note" },
    "After: residuals on the measurements the model was fitted to (in-sample, optimistic). ",
    pred ? `Predicted: the position error the calibrated model is expected to have at ${ws.samples} random `
      + "configurations inside the allowed joint ranges, from its parameters' uncertainty — the same quantity the "
      + "plan predicted before the session. " : "",
    "A verify session measures fresh configurations: the accuracy to quote (the certificate uses it).");

  const parts = [head, summary, summaryNote, numericalNotes(rep, unit),
    card("Files", downloads, h("p", { class: "muted small" },
      "The model file works with every recal command; URDF for ROS and MoveIt (rooted at base_link); the UR "
      + "calibration YAML for UR's ROS driver (kinematics_params_file, six-joint arms); the DH table for the robot "
      + "controller or a report."))];

  if (e) {
    parts.push(h("div", { class: "two" },
      card("Errors before calibration",
        histogram([{ values: e.before.norm, color: COLORS.before, label: "before" }], { xLabel: `position error (${unit})`, height: 220, legend: false, title: "histogram of errors before", width: sizes().half }),
        h("p", { class: "small muted" }, `${e.before.model}. `
          + `(As it stood, before placing its base: RMS ${num(e.before.raw_rms, 4)} ${unit}.)`)),
      card("Errors after calibration",
        histogram([{ values: e.after.norm, color: COLORS.after, label: "after" }], { xLabel: `position error (${unit})`, height: 220, legend: false, title: "histogram of errors after", width: sizes().half }),
        h("p", { class: "small muted" }, `${e.after.model}.`))));
    parts.push(card("Per-pose errors, before and after",
      chart([{ x: e.pose, y: e.before.norm, type: "points", color: COLORS.before, label: `before (${unit})` },
             { x: e.pose, y: e.after.norm, type: "points", color: COLORS.after, label: `after (${unit})` }],
        { xLabel: "pose", yLabel: `${unit} (log scale)`, logY: true, integerX: true, height: 260, xName: "pose",
          title: "per-pose errors before and after" })));
    const xyz = e.after.xyz;
    parts.push(card("Residuals against pose (after calibration)",
      chart([{ x: e.pose, y: xyz.map((v) => v[0]), type: "line", color: COLORS.x, label: "x" },
             { x: e.pose, y: xyz.map((v) => v[1]), type: "line", color: COLORS.y, label: "y" },
             { x: e.pose, y: xyz.map((v) => v[2]), type: "line", color: COLORS.z, label: "z" },
             { x: e.pose, y: e.after.norm, type: "points", color: COLORS.grey, label: "|e|" }],
        { xLabel: "pose", yLabel: unit, zeroLine: true, integerX: true, height: 260, xName: "pose",
          hlines: rep.settings?.sigma ? [{ y: 3 * rep.settings.sigma, label: "3σ instrument", color: COLORS.grey },
                                         { y: -3 * rep.settings.sigma, color: COLORS.grey }] : [],
          title: "residuals against pose" }),
      e.outlier_poses.length ? h("p", { class: "small" }, `Outliers (down-weighted): poses ${e.outlier_poses.join(", ")}`) : null));
  } else if (r.errors && r.errors.reason) {
    parts.push(card("Errors", h("p", { class: "muted" }, r.errors.reason)));
  }

  if (ws) {
    const p = ws.points;
    parts.push(card("Predicted accuracy over the workspace",
      h("div", { class: "two" },
        h("div", {}, h("h3", {}, "Seen from above"),
          colorMap(p.map((v) => v[0]), p.map((v) => v[1]), ws.rms, { xLabel: `x (${unit})`, yLabel: `y (${unit})`,
                                                                     unit, equal: true, title: "workspace map from above" })),
        h("div", {}, h("h3", {}, "Seen from the side"),
          colorMap(p.map((v) => Math.hypot(v[0] - avg(p, 0), v[1] - avg(p, 1))), p.map((v) => v[2]), ws.rms,
            { xLabel: `distance from the centre (${unit})`, yLabel: `z (${unit})`, unit, title: "workspace map from the side" }))),
      histogram([{ values: ws.rms, color: COLORS.after }], { xLabel: `predicted position error (${unit})`,
                                                             yLabel: "configurations", height: 180, legend: false,
                                                             title: "histogram of predicted errors" }),
      h("p", { class: "small muted" }, `Each dot: where the ${ws.target ? `target ${ws.target}` : "tool"} is at one of `
        + `${ws.samples} random configurations inside the allowed joint ranges, coloured by the position error the `
        + `calibrated model is predicted to have there (1σ, 3-D, from the identified parameters' covariance; the `
        + `instrument's own noise is not included). RMS over the configurations ${num(ws.stats_rms.rms, 3)}, 95th `
        + `percentile ${num(ws.stats_rms.p95, 3)}, max ${num(ws.stats_rms.max, 3)} ${unit}. (As a 95 % uncertainty `
        + `radius, ${num(ws.stats95.mean, 3)} ${unit} on average.)`)));
  }

  // joint compliance under gravity: the rigid and the compliant model, cross-validated on the same data
  const comp = rep.compliance;
  // the residual correction (issue 28): chosen by nested cross-validation among families, kept where it helps
  const rmap = rep.residual_map;
  const mapNote = residualNote(rmap, unit);
  const mapKept = rmap && (rmap.families ? rmap.chosen && rmap.chosen !== "none" : rmap.kept);
  if (comp && comp.cv_rms_rigid != null) {
    parts.push(card("Rigid against compliant",
      table(["Model", `Cross-validated RMS (${unit})`],
        [["Rigid (geometric parameters only)", num(comp.cv_rms_rigid, 4)],
         [`Compliant (joints ${(comp.joints || []).join(", ")} sag under gravity)`, num(comp.cv_rms_compliant, 4)]],
        { class: "compliance", id: "rigid-compliant" }),
      h("p", { class: "small muted" }, `${comp.folds}-fold cross-validation: each model identified on all folds but `
        + "one and tested on that one. This calibration is the compliant model"
        + (comp.gain > 0 ? `: ${num(100 * comp.gain, 3)} % lower error than rigid.` : "; here it does no better than rigid.")),
      mapNote));
  } else if (mapNote && (mapKept || rmap.families)) {  // an old map-only report left out: no news
    parts.push(card("Beyond the geometric model", mapNote));
  }

  // parameters
  const params = rep.parameters || [];
  if (params.length) {
    const labelled = params.some((p) => paramLabel(p));
    parts.push(card("Identified parameters",
      table(["Parameter", "Value", "Change", "Std. error", "Unit", labelled ? "Note" : null].filter(Boolean),
        params.map((p) => h("tr", { class: significant(p) ? "" : "muted" },
          h("td", {}, p.name), h("td", { class: "num" }, num(p.value, 8)), h("td", { class: "num" }, num(p.change, 4)),
          h("td", { class: "num" }, num(p.std_error, 3)), h("td", {}, p.unit),
          labelled ? h("td", { class: "small" }, paramLabel(p)) : null)), { class: "params" }),
      h("p", { class: "small muted" }, "Change: how far the calibration moved the parameter from where it started. "
        + "base.* and tool.* are small displacements of those frames (their value is 0 by definition). "
        + "Greyed rows moved less than twice their standard error."
        + (labelled ? " Note: what the identification says about the parameter (\u201cfrom the prior\u201d: these "
          + "measurements did not determine it; its value and uncertainty come from the previous calibration)." : ""))));
  }
  const un = rep.unidentifiable || [];
  if (un.length) {
    parts.push(card("Parameters the data could not determine",
      table(["Parameter", "Why"], un.map((u) => [u.name, [u.reason, paramLabel(u) ? ` (${paramLabel(u)})` : ""]]),
        { class: "unidentifiable" }),
      h("p", { class: "small muted" }, "These keep their starting values. It is normal for some (a joint offset and the base "
        + "rotation are the same motion); others need more varied poses or another target.")));
  }

  // comparison with the previous calibration
  const cmpBox = h("div", { id: "compare" }, h("p", { class: "muted" }, r.previous_id ? "Loading…" : "This is the cell's first calibration."));
  parts.push(card("Compared with the previous calibration", cmpBox));
  if (r.previous_id) {
    get(`/calibrations/${id}/comparison?previous=${r.previous_id}`).then((c) => showCompare(cmpBox, c, r.previous_id, unit))
      .catch((err) => { put(cmpBox, h("p", { class: "error-text" }, err.message)); });
  }

  // compensation
  parts.push(compensationCard(id, r));
  if (can("compensate")) parts.push(backupCard(id));
  // The identification's own terms (its stopping rule, χ²/dof, model conventions) for whoever
  // checks the mathematics, folded away from the technician's reading.
  parts.push(h("details", { class: "card details", id: "details" },
    h("summary", {}, "Details for specialists (how the identification went)"),
    kv([
      ["Converged", rep.message || "–"], ["Condition number", num(rep.condition_number, 4)],
      ["Residual RMS", `${num(rep.residuals?.rms, 4)} ${unit} (per axis ${(rep.residuals?.rms_per_axis || []).map((v) => num(v, 3)).join(", ")})`],
      ["χ² / dof", rep.residuals ? `${num(rep.residuals.chi2, 4)} / ${rep.residuals.dof}` : "–"],
      ["Instrument noise assumed", rep.settings?.sigma != null ? `${num(rep.settings.sigma, 3)} ${unit} per axis` : "–"],
      ["Prior", rep.prior ? `calibration ${rep.prior.calibration_id} (${rep.prior.parameters} parameters)` : "none (first calibration)"],
      ["Plan", r.session?.plan_method || "–"]]),
    (rep.notes || []).length ? h("div", { id: "notes" }, h("h3", {}, "Notes"), h("ul", {}, rep.notes.map((n) => h("li", {}, n))))
      : null));
  put(ctx.root, ...parts);
}

// What the identification's numbers mean when they look alarming: a large condition number,
// parameters the data could not determine, parameters kept from the prior. Null when none.
function numericalNotes(rep, unit) {
  const items = [];
  const cond = rep.condition_number;
  if (cond != null && cond > CONDITION_LIMIT) {
    items.push(h("li", { id: "note-condition" }, h("strong", {}, `Condition number ${num(cond, 3)}. `),
      "Some combinations of parameters are only weakly told apart by these poses, so those parameters' individual "
      + "values are uncertain (their standard errors say how much). This does not make the model inaccurate: "
      + `the position errors on this page (in ${unit}) are what count. More varied poses lower it.`));
  }
  const un = rep.unidentifiable || [];
  if (un.length) {
    items.push(h("li", { id: "note-undetermined" }, h("strong", {}, `${un.length} parameter(s) not determined. `),
      "These measurements cannot tell them apart from other parameters (see the list below, with the reason); they "
      + "keep their starting values and the others absorb their effect, so positions are still predicted "
      + "correctly. This is normal for a robot measured at one point of its tool."));
  }
  const labels = {};
  for (const p of rep.parameters || []) {
    const l = paramLabel(p);
    if (l) (labels[l] ||= []).push(p.name);
  }
  for (const [label, names] of Object.entries(labels)) {
    const prior = /prior/i.test(label);
    items.push(h("li", { class: "note-label" }, h("strong", {}, `${names.length} parameter(s) ${label}: `),
      `${names.slice(0, 8).join(", ")}${names.length > 8 ? ` and ${names.length - 8} more` : ""}. `,
      prior ? "These measurements did not determine them; their values and uncertainties come from the previous "
        + `calibration${rep.prior ? `, ${rep.prior.calibration_id}` : ""}, which is as it should be for a short `
        + "update session." : ""));
  }
  if (!items.length) return null;
  return h("section", { class: "card notes-card", id: "numerical-notes" }, h("h2", {}, "Reading these numbers"),
    h("ul", {}, items));
}

function avg(p, k) {
  return p.reduce((a, v) => a + v[k], 0) / (p.length || 1);
}

function significant(p) {
  return p.std_error == null || Math.abs(p.change || 0) > 2 * p.std_error;
}

// What each residual-correction family is (calibration.residual_choice.FAMILIES).
const FAMILY_TITLES = {
  none: "none: the geometric model alone",
  map: "smooth map of the joint angles",
  transmission: "joint transmission (per-joint gear harmonics)",
  trees: "boosted trees on the joint angles",
};

// The residual correction's figures (report.residual_map, the shape `recal identify --residual-map auto`
// reports): each family's cross-validated RMS, the one kept and the learning curve; a calibration made
// before every family was tried has the smooth map's alone (rms_without, rms_with, kept). null: none.
function residualNote(rmap, unit) {
  if (!rmap) return null;
  if (!rmap.families) {
    return rmap.rms_without == null ? null : h("p", { class: "small", id: "residual-map" },
      h("strong", {}, "Residual map: "), `a smooth correction of what the model leaves, as a function of the joints, `
        + `${rmap.folds}-fold cross-validated: RMS ${num(rmap.rms_without, 4)} ${unit} without it, `
        + `${num(rmap.rms_with, 4)} ${unit} with it. `
        + (rmap.kept ? "Kept: stored with this calibration and applied when compensating task files and robot "
          + "programs, inside the joint region this session measured; outside it, the model alone."
          : `Left out: it did not lower the error by ${num(100 * rmap.min_gain, 2)} % or more (what remains is noise, `
            + "or too sparse to map)."));
  }
  const kept = rmap.chosen && rmap.chosen !== "none";
  const rows = Object.entries(rmap.families).map(([name, f]) => h("tr", { class: name === rmap.chosen ? "chosen" : "",
                                                                       "data-family": name },
    h("td", {}, FAMILY_TITLES[name] || name), h("td", { class: "num" }, num(f.rms, 4)),
    h("td", {}, name === rmap.chosen ? "chosen" : "")));
  const curve = rmap.learning_curve || [];
  const notTried = Object.entries(rmap.not_tried || {}).map(([name, why]) => `${FAMILY_TITLES[name] || name}: not tried (${why}). `);
  return h("div", { id: "residual-map" },
    table(["Correction of what the model leaves", `Cross-validated RMS (${unit})`, ""], rows,
      { class: "families", id: "residual-families" }),
    h("p", { class: "small" }, h("strong", {}, "Residual correction: "),
      `${rmap.folds}-fold cross-validated over ${rmap.cv_poses ?? rmap.cv_rows} poses, nested (the geometric model `
        + "identified on each training fold, each family fitted to what it leaves there, tested on the held-out fold). "
        + (kept ? `Kept: ${FAMILY_TITLES[rmap.chosen] || rmap.chosen}, ${num(100 * rmap.gain, 2)} % lower error than `
          + "none. Stored with this calibration and applied, inside the joint region this session measured, when "
          + "compensating task files and robot programs, in verify sessions, the certificate and the errors above; "
          + "outside that region, the model alone. "
          : `Left out: no family lowered the error by ${num(100 * rmap.min_gain, 2)} % or more (what remains is noise, `
            + "or too sparse to learn). ") + notTried.join("")),
    curve.length ? h("p", { class: "small muted", id: "residual-learning-curve" },
      `Learning curve (${rmap.best ? FAMILY_TITLES[rmap.best] || rmap.best : "best family"}, held-out RMS against the `
        + `number of poses): ${curve.map((p) => `${p.poses} poses ${num(p.rms, 3)}`).join(", ")} ${unit}.`) : null);
}

function stat(label, value, unit, sub, cls = "") {
  return h("div", { class: `stat ${cls}` }, h("div", { class: "label" }, label),
    h("div", { class: "value" }, h("span", { class: "figure" }, value), unit ? [" ", h("span", { class: "unit" }, unit)] : null),
    h("div", { class: "sub" }, sub));
}

function dl(label, path, name, id) {
  const b = h("button", { class: "secondary", id });
  b.textContent = label;
  b.addEventListener("click", () => busy(b, () => download(path, name)));
  return b;
}

const STATUS = {
  both: "",
  new: "new: estimated now, not in the previous calibration",
  "not estimated": "not estimated now: kept its value",
  "from the prior": "from the prior: these measurements did not determine it",
  fixed: "not estimated in either",
};

function showCompare(box, c, prevId, unit) {
  const rows = c.parameters;
  const moved = rows.filter((p) => p.moved);
  const frame = (p) => p.group === "base" || p.group === "tool" || p.group === "home";
  const tr = (p) => h("tr", { class: [p.moved ? "moved" : "", p.status !== "both" ? "partial" : ""].join(" ").trim(),
                              "data-status": p.status },
    h("td", {}, p.name), h("td", { class: "num" }, frame(p) ? "–" : num(p.from, 8)),
    h("td", { class: "num" }, frame(p) ? "–" : num(p.to, 8)),
    h("td", { class: "num" }, num(p.change, 3)), h("td", { class: "num" }, p.change_sigmas == null ? "–" : `${num(p.change_sigmas, 2)} σ`),
    h("td", {}, p.unit),
    h("td", { class: "small" }, [p.moved ? h("strong", {}, "moved") : null, p.moved && STATUS[p.status] ? "; " : null,
                                 STATUS[p.status]]));
  const list = h("div", {});
  const LIMIT = 40;
  const showRows = (all) => put(list, table(["Parameter", "Before", "Now", "Change", "In σ", "Unit", ""],
    (all ? rows : rows.slice(0, LIMIT)).map(tr), { class: "compare" }),
    !all && rows.length > LIMIT ? h("button", { class: "secondary", onclick: () => showRows(true) },
      `Show all ${rows.length} parameters`) : null);
  const n = c.counts || {};
  put(box,
    h("p", {}, "Against ", h("a", { href: `#/calibrations/${prevId}` }, `calibration ${prevId}`),
      `: RMS ${num(c.rms_from, 3)} → ${num(c.rms_to, 3)} ${unit}. `,
      h("strong", { id: "moved-count" }, moved.length ? `${moved.length} parameter(s) moved beyond their uncertainty (more than 2σ): `
        + `${moved.slice(0, 6).map((p) => p.name).join(", ")}${moved.length > 6 ? ", …" : ""}.`
        : "No parameter moved beyond its uncertainty."),
      n.new || n["not estimated"] ? ` ${n.new || 0} estimated only now (new), ${n["not estimated"] || 0} only before.` : ""),
    rows.length ? list : null,
    h("p", { class: "small muted" }, "σ: the combined standard uncertainty of the two values (or the one calibration's, "
      + "for a parameter estimated in only one). base.* and tool.*: how far the robot's base (as seen from the instrument) "
      + "and its tool frame moved, along and about their own axes; the base moves when the robot or the instrument was "
      + "moved. Moved parameters first, then by how far each moved."));
  if (rows.length) showRows(false);
}

// What each compensation flag means (calibration/compensation.py FLAGS).
const FLAG_TEXT = {
  joint_limit: "outside the joint limits",
  near_singular: "near a singular configuration: small position changes need large joint moves",
  outside_calibrated_region: "outside the joint ranges the calibration measured: the correction is extrapolated",
  no_convergence: "the correction did not reach the tolerance",
  branch_change: "the correction changed the arm's configuration (branch) or is unusually large",
  unreachable: "the pose is out of the robot's reach",
};

function compensationCard(id, r) {
  const box = h("div", { id: "compensation-result" });
  if (!can("compensate")) {
    return card("Compensate a program", h("p", { class: "muted" }, "Your role cannot compensate programs."));
  }
  const file = h("input", { type: "file", id: "task-file", multiple: true,
    accept: ".csv,.script,.urscript,.txt,.mod,.modx,.prg,.src,.dat,.ls" });
  const mode = h("select", { id: "comp-mode" },
    h("option", { value: "joints" }, "joints — new joint commands"),
    h("option", { value: "targets" }, "targets — corrected poses (for a nominal controller)"));
  // a model with joint compliance sags under the task's payload (the route's ?payload=KG[,X,Y,Z])
  const payload = r.compliant ? h("input", { type: "text", id: "comp-payload", placeholder: "e.g. 10,0,0,100" }) : null;
  const go = h("button", { class: "primary", id: "compensate" }, "Compensate");
  go.addEventListener("click", () => busy(go, async () => {
    const chosen = [...file.files];
    if (!chosen.length) throw new Error("choose a task file (CSV) or a robot program first");
    let name, text, encoding, extras = [], compId;
    const query = `mode=${mode.value}`
      + (payload && payload.value.trim() ? `&payload=${encodeURIComponent(payload.value.replace(/\s+/g, ""))}` : "");
    if (chosen.length > 1) {
      // a program of several files (KUKA: the .src and its .dat): one multipart request
      const form = new FormData();
      chosen.forEach((f) => form.append("file", f, f.name));
      const resp = await api("POST", `/calibrations/${id}/compensate?${query}`, form, { raw: true });
      compId = resp.headers.get("x-recal-compensation");
      const files = (await resp.json()).files || [];
      ({ name, text, encoding } = files[0]);
      extras = files.slice(1);
    } else {
      const f = chosen[0];
      name = f.name;
      if (name.toLowerCase().endsWith(".src")) throw new Error("a KUKA program needs its .src and its .dat: choose both");
      const path = `/calibrations/${id}/compensate?${query}&name=${encodeURIComponent(name)}`;
      if (name.toLowerCase().endsWith(".csv")) { // a task CSV is UTF-8 text (contracts §5)
        const resp = await api("POST", path, await f.text());
        compId = resp.headers.get("x-recal-compensation");
        text = resp.text;
      } else {
        // a program as its bytes, not f.text(): one in Windows-1252 (KUKA, ABB) comes back byte for byte
        const resp = await api("POST", path, f, { raw: true });
        compId = resp.headers.get("x-recal-compensation");
        encoding = /charset=iso-8859-1/i.test(resp.headers.get("content-type") || "") ? "iso-8859-1" : "utf-8";
        text = bytesAsText(new Uint8Array(await resp.arrayBuffer()), encoding);
      }
    }
    let report = {};
    if (compId) {
      try { report = (await get(`/compensations/${compId}/report`)).report || {}; } catch (_) { /* shown without */ }
    }
    showCompensation(box, name, text, report, r.units.length, extras, encoding);
  }));
  return card("Compensate a program",
    h("p", {}, "Upload a task file (CSV with x, y, z, qw, qx, qy, qz and/or q1…qN) or a robot program: URScript, "
      + "ABB RAPID (.mod, .modx, .prg), Fanuc TP (.ls), or a KUKA KRL .src together with its .dat (choose both; "
      + "add $config.dat for the TOOL_DATA and BASE_DATA it selects). Download it with every point corrected for "
      + "this robot's real geometry, every other character as it was."),
    h("div", { class: "row" }, h("div", { class: "field" }, h("label", { for: "task-file" }, "Task file"), file),
      h("div", { class: "field" }, h("label", { for: "comp-mode" }, "Mode"), mode),
      payload ? h("div", { class: "field" }, h("label", { for: "comp-payload" }, "Payload (optional)"), payload) : null,
      go),
    payload ? h("p", { class: "help" }, `Payload: kg, or kg,x,y,z with its centre of gravity in the tool frame `
      + `(${r.units.length}), what the robot carries during the task. This calibration has joint compliance: the arm `
      + "sags under the payload, and the points are corrected for it. Empty: no payload.") : null,
    box);
}

// A controller backup (KUKA archive, ABB backup, folder of Fanuc .ls programs) as a zip: sent
// as its bytes, the zip of the same layout (with the report) back, to download as it came.
function backupCard(id) {
  const box = h("div", { id: "backup-result" });
  const file = h("input", { type: "file", id: "backup-file", accept: ".zip,application/zip" });
  const go = h("button", { class: "primary", id: "compensate-backup" }, "Compensate the backup");
  go.addEventListener("click", () => busy(go, async () => {
    const f = file.files[0];
    if (!f) throw new Error("choose a zip of the controller's backup folder first");
    const path = `/calibrations/${id}/compensate-backup?name=${encodeURIComponent(f.name)}`;
    const resp = await api("POST", path, f, { raw: true });
    const short = Number(resp.headers.get("x-recal-not-compensated") || 0);
    const blob = new Blob([await resp.arrayBuffer()], { type: "application/zip" });
    const name = `${f.name.replace(/\.zip$/i, "")}-compensated.zip`;
    const save = h("button", { class: "primary", id: "download-backup" }, `Download ${name}`);
    save.addEventListener("click", () => saveBlob(blob, name));
    clear(box);
    add(box, h("div", { class: `banner banner-${short ? "warn" : "ok"}`, id: "backup-compensated" },
      h("strong", {}, "Compensated. "),
      short ? `${short} target(s) were left as written or did not converge: the report in the zip `
        + "(recal-compensation-report.json) names them. " : "Every target was compensated. ", save));
  }));
  return card("Compensate a controller backup",
    h("p", {}, "Upload a controller's backup folder as a zip: a KUKA archive (KRC/R1/… with $config.dat), an ABB "
      + "backup (RAPID/TASK1/PROGMOD, SYSMOD) or a folder of Fanuc .ls programs. You get back a zip of the same "
      + "folders with every program corrected and every other file as it was, plus a report of every point."),
    h("div", { class: "row" }, h("div", { class: "field" }, h("label", { for: "backup-file" }, "Backup (.zip)"), file),
      go),
    box);
}

// A compensated file as the route sent it: UTF-8 text, or ISO-8859-1 (a program that was not
// UTF-8), one character per byte. The text keeps a character per byte; the blob is the bytes.
function bytesAsText(bytes, encoding) {
  if (encoding !== "iso-8859-1") return new TextDecoder("utf-8").decode(bytes);
  let s = "";
  for (let i = 0; i < bytes.length; i += 8192) s += String.fromCharCode(...bytes.subarray(i, i + 8192));
  return s;
}

function fileBlob(text, encoding) {
  if (encoding !== "iso-8859-1") return new Blob([text], { type: "text/plain" });
  return new Blob([Uint8Array.from(text, (c) => c.charCodeAt(0))], { type: "text/plain" });
}

function compensatedName(name) {
  const dot = name.lastIndexOf(".");
  return dot > 0 ? `${name.slice(0, dot)}-compensated${name.slice(dot)}` : `${name}-compensated`;
}

function showCompensation(box, name, text, report, unit, extras = [], encoding = "utf-8") {
  const points = report.points || [];
  const summary = report.summary || {};
  const angle = report.units?.angle || "deg";
  const flagged = points.filter((p) => (p.flags || []).length || p.converged === false);
  const save = h("button", { class: "primary", id: "download-compensated" }, `Download ${compensatedName(name)}`);
  save.addEventListener("click", () => saveBlob(fileBlob(text, encoding), compensatedName(name)));
  // a program's other files (KRL's .dat): saved under the same stem, so the .src still finds its .dat
  const saveExtras = extras.map((f, i) => {
    const b = h("button", { id: `download-compensated-${i + 1}` }, `Download ${compensatedName(f.name)}`);
    b.addEventListener("click", () => saveBlob(fileBlob(f.text, f.encoding), compensatedName(f.name)));
    return b;
  });
  const maxAbs = (a) => (Array.isArray(a) && a.length ? Math.max(...a.map((v) => Math.abs(v ?? 0))) : null);
  const rows = points.map((p, i) => h("tr", { class: (p.flags || []).length || p.converged === false ? "flagged" : "" },
    h("td", {}, String(p.row ?? i + 1)), h("td", {}, p.line != null ? String(p.line) : "–"),
    h("td", {}, p.move ? `${p.move}${p.kind ? ` (${p.kind}${p.variable ? ` ${p.variable}` : ""})` : ""}` : report.mode || ""),
    h("td", {}, p.converged === false ? "no" : p.converged ? "yes" : "–"),
    h("td", { class: "num" }, p.residual != null ? num(Math.abs(p.residual) < 1e-6 ? 0 : p.residual, 3) : "–"),
    h("td", { class: "num" }, maxAbs(p.correction) != null ? num(maxAbs(p.correction), 3) : "–"),
    h("td", { class: "flags" }, (p.flags || []).length
      ? (p.flags || []).map((f) => h("span", { class: "flag", title: FLAG_TEXT[f] || f }, f.replace(/_/g, " "))) : "—")));
  const skipped = report.uninterpreted || [];
  const counts = Object.entries(summary.flags || {}).filter(([, v]) => v);
  clear(box);
  add(box,
    h("div", { class: `banner banner-${flagged.length ? "warn" : "ok"}`, id: "compensated" },
      h("strong", {}, "Compensated. "), `${summary.points ?? points.length} point(s), ${summary.converged ?? "?"} converged, `
        + `${flagged.length} flagged${skipped.length ? `, ${skipped.length} line(s) left unchanged` : ""}. `, save,
      ...saveExtras),
    report.payload ? h("p", { class: "small", id: "compensated-payload" }, `Corrected for a payload of `
      + `${num(report.payload[0], 4)} kg at ${report.payload.slice(1).map((v) => num(v, 4)).join(", ")} ${unit} `
      + "(centre of gravity in the tool frame): the sag of the arm's joints under it is in the correction.") : null,
    h("p", { class: "small muted" }, `Largest remaining error ${length(summary.residual_max, unit, 3)}; largest joint `
      + `correction ${num(summary.correction_max, 3)} ${angle}`
      + (counts.length ? `; flags: ${counts.map(([k, v]) => `${k.replace(/_/g, " ")} ${v}`).join(", ")}` : "; no flags") + "."),
    counts.length ? h("ul", { class: "small", id: "flag-meanings" }, counts.map(([k]) =>
      h("li", {}, h("strong", {}, k.replace(/_/g, " ")), `: ${FLAG_TEXT[k] || ""}`))) : null,
    points.length ? table(["Point", "Line", "Move", "Converged", `Residual (${unit})`, `Largest joint correction (${angle})`, "Flags"],
      rows, { class: "compensation" }) : h("pre", { class: "preview" }, text.split("\n").slice(0, 30).join("\n")),
    skipped.length ? h("div", {}, h("h3", {}, "Left unchanged"),
      h("ul", {}, skipped.slice(0, 50).map((u) => h("li", {}, `${u.file ? `${u.file}, ` : ""}line ${u.line}: ${u.reason || ""}`,
        u.text ? h("code", {}, ` ${u.text}`) : null)))) : null);
}
