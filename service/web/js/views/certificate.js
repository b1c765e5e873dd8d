// The calibration certificate: a printable page (the browser's Print gives a PDF too) and the
// service's own PDF.

import { download, get } from "../api.js";
import { busy, h, num, paramLabel, put, when } from "../ui.js";

export async function show(ctx, id) {
  const c = await get(`/calibrations/${id}/certificate`);
  if (!ctx.alive()) return;
  ctx.crumbs([["Cells", "#/"], [c.cell.name, `#/cells/${c.cell.id}`], [`Calibration ${id}`, `#/calibrations/${id}`],
              ["Certificate", null]]);
  const unit = c.units.length;
  const pdf = h("button", { class: "secondary", id: "download-pdf" }, "Download PDF");
  pdf.addEventListener("click", () => busy(pdf, () => download(`/calibrations/${id}/certificate.pdf`, `${c.number}.pdf`)));
  const tools = h("div", { class: "actions no-print" },
    h("a", { class: "button secondary", href: `#/calibrations/${id}` }, "Back to the result"),
    pdf, h("button", { class: "primary", id: "print", onclick: () => window.print() }, "Print"));

  const inst = c.instrument;
  const acc = c.accuracy;
  const figs = [["n", "Poses"], ["mean", "Mean error"], ["std", "Std. dev. S"], ["mean_plus_3sigma", "Mean + 3 S"],
                ["rms", "RMS"], ["p95", "95th percentile"], ["max", "Maximum"]];
  const accRows = acc.rows.map((f) => h("tr", { class: f === acc.rows.at(-1) && acc.holdout ? "holdout" : "" },
    h("th", {}, f.label), figs.map(([k]) => h("td", { class: "num" }, k === "n" ? String(f.n) : num(f[k], 4)))));
  const w = acc.predicted_workspace;
  const notRun = c.not_run || [];

  const doc = h("article", { class: "certificate", id: "certificate" },
    h("header", {},
      h("div", {}, h("div", { class: "cert-title" }, c.title), h("div", { class: "muted" }, `Certificate ${c.number}`)),
      h("div", { class: `cert-verdict ${c.passed ? "pass" : "fail"}`, id: "verdict" },
        c.passed ? "All checks that were run passed" : "Not all checks passed",
        notRun.length ? h("div", { class: "small" }, `Not run: ${notRun.join("; ")}`) : null)),
    h("table", { class: "cert-kv" }, h("tbody", {},
      row("Cell", `${c.cell.name} (site ${c.cell.site}, id ${c.cell.id})`),
      row("Robot", `${c.robot.model}, ${c.robot.joints} joints, nominal convention ${c.robot.convention}`
        + (c.robot.identified_convention && c.robot.identified_convention !== c.robot.convention ? ` (identified as ${c.robot.identified_convention})` : "")),
      row("Instrument", `${inst.kind} at ${inst.address || "–"}` + (inst.identity ? `; ${inst.identity}` : "")
        + (inst.noise != null ? `; noise ${num(inst.noise, 3)} ${unit} per axis` : "") + (inst.target ? `; target ${inst.target}` : "")),
      row("Date of calibration", when(c.calibration.date)),
      row("Operator", c.operator || "–"),
      row("Poses used", `${c.poses.measured} measured of ${c.poses.planned} planned`
        + (c.poses.plan_method ? ` (${c.poses.plan_method})` : "") + `; ${c.poses.outliers} outlier(s)`),
      row("Method", c.calibration.method),
      row("Issued", when(c.issued_at)))),
    h("h2", {}, `Accuracy (${unit})`),
    h("table", { class: "grid" }, h("thead", {}, h("tr", {}, h("th", {}, ""), figs.map(([, l]) => h("th", {}, l)))),
      h("tbody", {}, accRows)),
    h("p", { class: "small" }, `Before: ${acc.before_model || "–"}. After, ${acc.after_kind}. `,
      acc.holdout ? h("strong", {}, `Hold-out: ${acc.holdout_model}. `)
        : h("strong", {}, "No hold-out check yet: run a verify session on this cell to measure fresh configurations. "),
      `${acc.note}.`),
    w ? h("p", { class: "small", id: "cert-predicted" }, `Predicted: ${w.what}: RMS ${num(w.rms, 3)} ${unit}, `
      + `95th percentile ${num(w.p95, 3)} ${unit}, max ${num(w.max, 3)} ${unit}.`) : null,
    h("h2", {}, "Checks"),
    h("table", { class: "grid checks" }, h("tbody", {}, c.checks.map((k) => h("tr", {},
      h("td", { class: k.passed ? "pass" : k.passed === null ? "na" : "fail" }, k.passed ? "✓ passed" : k.passed === null ? "– not run" : "✗ failed"),
      h("th", {}, k.name), h("td", {}, k.detail))))),
    h("h2", {}, "Identified parameters"),
    h("table", { class: "grid params" },
      h("thead", {}, h("tr", {}, ["Parameter", "Value", "Change", "Std. uncertainty u", "U (k = 2)", "Unit"].map((t) => h("th", {}, t)))),
      h("tbody", {}, c.parameters.map((p) => h("tr", {}, h("td", {}, p.name, paramLabel(p) ? ` (${paramLabel(p)})` : ""),
        h("td", { class: "num" }, num(p.value, 9)),
        h("td", { class: "num" }, num(p.change, 4)), h("td", { class: "num" }, num(p.std_error, 3)),
        h("td", { class: "num" }, num(p.expanded_uncertainty, 3)), h("td", {}, p.unit))))),
    h("p", { class: "small" }, "base.* and tool.* are small displacements of those frames about the calibrated model: their value "
      + "is 0 by definition, the change is what the calibration moved. U: expanded uncertainty, coverage factor k = 2 (about 95 %)."),
    c.unidentifiable.length ? [h("h2", {}, "Parameters the data could not determine"),
      h("table", { class: "grid" }, h("tbody", {}, c.unidentifiable.map((u) => h("tr", {}, h("th", {}, u.name), h("td", {}, u.reason)))))] : null,
    h("div", { class: "signatures" }, h("div", {}, "Operator signature"), h("div", {}, "Reviewed by")));
  put(ctx.root, tools, doc);
}

function row(k, v) {
  return h("tr", {}, h("th", {}, k), h("td", {}, v));
}
