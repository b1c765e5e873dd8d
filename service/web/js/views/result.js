// A calibration's result: parameters and their standard errors, what the data could not
// determine, errors before and after (histograms, per pose), residuals against pose, predicted
// accuracy over the workspace, comparison with the previous calibration, downloads, and
// compensating a task file.

import { api, can, download, get, saveBlob } from "../api.js";
import { COLORS, chart, colorMap, histogram, sizes } from "../plots.js";
import { add, badge, busy, card, clear, put, h, kv, notify, num, table, when } from "../ui.js";

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
    h("a", { class: "button", href: `#/calibrations/${id}/certificate`, id: "open-certificate" }, "Certificate"));

  const head = h("div", { class: "page-head" },
    h("div", {}, h("h1", {}, `Calibration ${id}`),
      h("p", { class: "muted" }, `${r.cell.name} · ${r.robot} · ${when(r.created_at)}`
        + (r.session ? ` · session ${r.session.id} by ${r.session.created_by}` : ""))),
    rep.success === false ? badge("failed") : badge("completed"));

  const summary = h("div", { class: "stats", id: "summary" },
    e ? stat("Before", `${num(e.before.stats.rms, 3)} ${unit}`, `RMS, max ${num(e.before.stats.max, 3)}`, "before") : null,
    stat("After", `${num(e ? e.after.stats.rms : r.rms, 3)} ${unit}`, e ? `RMS, max ${num(e.after.stats.max, 3)}` : "residual RMS", "after"),
    ws ? stat("Predicted (95 %)", `${num(ws.stats95.mean, 3)} ${unit}`, `over the workspace, max ${num(ws.stats95.max, 3)}`) : null,
    stat("Poses", String(rep.rows ?? "–"), `${(rep.outliers || []).length} outlier(s)`),
    stat("Parameters", String((rep.parameters || []).length), `${(rep.unidentifiable || []).length} not determinable`));

  const parts = [head, summary, card("Files", downloads, h("p", { class: "muted small" },
    "The model file works with every recal command; URDF for ROS; the DH table for the robot controller or a report."))];

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
          colorMap(p.map((v) => v[0]), p.map((v) => v[1]), ws.radius95, { xLabel: `x (${unit})`, yLabel: `y (${unit})`,
                                                                           unit, equal: true, title: "workspace map from above" })),
        h("div", {}, h("h3", {}, "Seen from the side"),
          colorMap(p.map((v) => Math.hypot(v[0] - avg(p, 0), v[1] - avg(p, 1))), p.map((v) => v[2]), ws.radius95,
            { xLabel: `distance from the centre (${unit})`, yLabel: `z (${unit})`, unit, title: "workspace map from the side" }))),
      histogram([{ values: ws.radius95, color: COLORS.after }], { xLabel: `95 % radius (${unit})`, yLabel: "configurations",
                                                                   height: 180, legend: false,
                                                                   min: Math.min(...ws.radius95) * 0.95 }),
      h("p", { class: "small muted" }, `${ws.note}. ${ws.samples} random configurations inside the allowed joint ranges`
        + `${ws.target ? `, target ${ws.target}` : ""}: mean ${num(ws.stats95.mean, 3)}, 95th percentile ${num(ws.stats95.p95, 3)}, `
        + `max ${num(ws.stats95.max, 3)} ${unit}.`)));
  }

  // parameters
  const params = rep.parameters || [];
  if (params.length) {
    parts.push(card("Identified parameters",
      table(["Parameter", "Value", "Change", "Std. error", "Unit"],
        params.map((p) => h("tr", { class: significant(p) ? "" : "muted" },
          h("td", {}, p.name), h("td", { class: "num" }, num(p.value, 8)), h("td", { class: "num" }, num(p.change, 4)),
          h("td", { class: "num" }, num(p.std_error, 3)), h("td", {}, p.unit))), { class: "params" }),
      h("p", { class: "small muted" }, "Change: how far the calibration moved the parameter from where it started. "
        + "base.* and tool.* are small displacements of those frames (their value is 0 by definition). "
        + "Greyed rows moved less than twice their standard error.")));
  }
  const un = rep.unidentifiable || [];
  if (un.length) {
    parts.push(card("Parameters the data could not determine",
      table(["Parameter", "Why"], un.map((u) => [u.name, u.reason]), { class: "unidentifiable" }),
      h("p", { class: "small muted" }, "These keep their starting values. It is normal for some (a joint offset and the base "
        + "rotation are the same motion); others need more varied poses or another target.")));
  }
  if ((rep.notes || []).length) parts.push(card("Notes", h("ul", {}, rep.notes.map((n) => h("li", {}, n)))));

  // comparison with the previous calibration
  const cmpBox = h("div", { id: "compare" }, h("p", { class: "muted" }, r.previous_id ? "Loading…" : "This is the cell's first calibration."));
  parts.push(card("Compared with the previous calibration", cmpBox));
  if (r.previous_id) {
    get(`/calibrations/${r.previous_id}/compare/${id}`).then((c) => showCompare(cmpBox, c, r.previous_id, unit))
      .catch((err) => { put(cmpBox, h("p", { class: "error-text" }, err.message)); });
  }

  // compensation
  parts.push(compensationCard(id, r));
  parts.push(card("Identification details", kv([
    ["Converged", rep.message || "–"], ["Condition number", num(rep.condition_number, 4)],
    ["Residual RMS", `${num(rep.residuals?.rms, 4)} ${unit} (per axis ${(rep.residuals?.rms_per_axis || []).map((v) => num(v, 3)).join(", ")})`],
    ["χ² / dof", rep.residuals ? `${num(rep.residuals.chi2, 4)} / ${rep.residuals.dof}` : "–"],
    ["Instrument noise assumed", rep.settings?.sigma != null ? `${num(rep.settings.sigma, 3)} ${unit} per axis` : "–"],
    ["Prior", rep.prior ? `calibration ${rep.prior.calibration_id} (${rep.prior.parameters} parameters)` : "none (first calibration)"],
    ["Plan", r.session?.plan_method || "–"]])));
  put(ctx.root, ...parts);
}

function avg(p, k) {
  return p.reduce((a, v) => a + v[k], 0) / (p.length || 1);
}

function significant(p) {
  return p.std_error == null || Math.abs(p.change || 0) > 2 * p.std_error;
}

function stat(label, value, sub, cls = "") {
  return h("div", { class: `stat ${cls}` }, h("div", { class: "label" }, label), h("div", { class: "value" }, value),
    h("div", { class: "sub" }, sub));
}

function dl(label, path, name, id) {
  const b = h("button", { class: "secondary", id });
  b.textContent = label;
  b.addEventListener("click", () => busy(b, () => download(path, name)));
  return b;
}

function showCompare(box, c, prevId, unit) {
  const moved = c.parameters.filter((p) => p.moved);
  const rows = c.parameters.slice(0, 40).map((p) => h("tr", { class: p.moved ? "moved" : "" },
    h("td", {}, p.name), h("td", { class: "num" }, num(p.from, 8)), h("td", { class: "num" }, num(p.to, 8)),
    h("td", { class: "num" }, num(p.change, 3)), h("td", { class: "num" }, p.change_sigmas == null ? "–" : `${num(p.change_sigmas, 2)} σ`),
    h("td", {}, p.unit), h("td", {}, p.moved ? "moved" : "")));
  put(box, 
    h("p", {}, "Against ", h("a", { href: `#/calibrations/${prevId}` }, `calibration ${prevId}`),
      `: RMS ${num(c.rms_from, 3)} → ${num(c.rms_to, 3)} ${unit}. `,
      h("strong", { id: "moved-count" }, moved.length ? `${moved.length} parameter(s) moved beyond their uncertainty (more than 2σ).`
        : "No parameter moved beyond its uncertainty.")),
    rows.length ? table(["Parameter", "Before", "Now", "Change", "In σ", "Unit", ""], rows, { class: "compare" }) : null,
    h("p", { class: "small muted" }, "σ: the combined standard uncertainty of the two values. Sorted by how far each moved."));
}

function compensationCard(id, r) {
  const box = h("div", { id: "compensation-result" });
  if (!can("compensate")) {
    return card("Compensate a program", h("p", { class: "muted" }, "Your role cannot compensate programs."));
  }
  const file = h("input", { type: "file", id: "task-file", accept: ".csv,.script,.urscript,.txt" });
  const mode = h("select", { id: "comp-mode" },
    h("option", { value: "joints" }, "joints — new joint commands"),
    h("option", { value: "targets" }, "targets — corrected poses (for a nominal controller)"));
  const go = h("button", { class: "primary", id: "compensate" }, "Compensate");
  go.addEventListener("click", () => busy(go, async () => {
    const f = file.files[0];
    if (!f) throw new Error("choose a task file (CSV) or a URScript program first");
    const text = await f.text();
    const resp = await api("POST", `/calibrations/${id}/compensate?mode=${mode.value}&name=${encodeURIComponent(f.name)}`, text);
    const compId = resp.headers.get("x-recal-compensation");
    let report = {};
    if (compId) {
      try { report = (await get(`/compensations/${compId}/report`)).report || {}; } catch (_) { /* shown without */ }
    }
    showCompensation(box, f.name, resp.text, report, r.units.length);
  }));
  return card("Compensate a program",
    h("p", {}, "Upload a task file (CSV with x, y, z, qw, qx, qy, qz and/or q1…qN) or a URScript program; "
      + "download it with every point corrected for this robot's real geometry."),
    h("div", { class: "row" }, h("div", { class: "field" }, h("label", { for: "task-file" }, "Task file"), file),
      h("div", { class: "field" }, h("label", { for: "comp-mode" }, "Mode"), mode), go),
    box);
}

function compensatedName(name) {
  const dot = name.lastIndexOf(".");
  return dot > 0 ? `${name.slice(0, dot)}-compensated${name.slice(dot)}` : `${name}-compensated`;
}

function showCompensation(box, name, text, report, unit) {
  const points = report.points || [];
  const summary = report.summary || {};
  const angle = report.units?.angle || "deg";
  const flagged = points.filter((p) => (p.flags || []).length || p.converged === false);
  const save = h("button", { class: "primary", id: "download-compensated" }, `Download ${compensatedName(name)}`);
  save.addEventListener("click", () => saveBlob(new Blob([text], { type: "text/plain" }), compensatedName(name)));
  const maxAbs = (a) => (Array.isArray(a) && a.length ? Math.max(...a.map((v) => Math.abs(v ?? 0))) : null);
  const rows = points.map((p, i) => h("tr", { class: (p.flags || []).length || p.converged === false ? "flagged" : "" },
    h("td", {}, String(p.row ?? i + 1)), h("td", {}, p.line != null ? String(p.line) : "–"),
    h("td", {}, p.move ? `${p.move}${p.kind ? ` (${p.kind}${p.variable ? ` ${p.variable}` : ""})` : ""}` : report.mode || ""),
    h("td", {}, p.converged === false ? "no" : p.converged ? "yes" : "–"),
    h("td", { class: "num" }, p.residual != null ? num(p.residual, 3) : "–"),
    h("td", { class: "num" }, maxAbs(p.correction) != null ? num(maxAbs(p.correction), 3) : "–"),
    h("td", {}, (p.flags || []).join(", ") || "—")));
  const skipped = report.uninterpreted || [];
  const counts = Object.entries(summary.flags || {}).filter(([, v]) => v);
  clear(box);
  add(box,
    h("div", { class: "banner banner-ok", id: "compensated" },
      h("strong", {}, "Compensated. "), `${summary.points ?? points.length} point(s), ${summary.converged ?? "?"} converged, `
        + `${flagged.length} flagged${skipped.length ? `, ${skipped.length} line(s) left unchanged` : ""}. `, save),
    h("p", { class: "small muted" }, `Largest remaining error ${num(summary.residual_max, 3)} ${unit}; largest joint `
      + `correction ${num(summary.correction_max, 3)} ${angle}`
      + (counts.length ? `; flags: ${counts.map(([k, v]) => `${k.replace(/_/g, " ")} ${v}`).join(", ")}` : "; no flags") + "."),
    points.length ? table(["Point", "Line", "Move", "Converged", `Residual (${unit})`, `Largest joint correction (${angle})`, "Flags"],
      rows, { class: "compensation" }) : h("pre", { class: "preview" }, text.split("\n").slice(0, 30).join("\n")),
    skipped.length ? h("div", {}, h("h3", {}, "Left unchanged"),
      h("ul", {}, skipped.slice(0, 50).map((u) => h("li", {}, `line ${u.line}: ${u.reason || ""}`,
        u.text ? h("code", {}, ` ${u.text}`) : null)))) : null);
}

