// The page: sign-in with a token, then a hash router over the views.

import { ApiError, clearToken, get, getToken, me, setToken } from "./api.js";
import { clear, h, notify } from "./ui.js";
import * as cells from "./views/cells.js";
import * as session from "./views/session.js";
import * as result from "./views/result.js";
import * as certificate from "./views/certificate.js";

const routes = [
  [/^#?\/?$/, cells.overview],
  [/^#\/page\/(\d+)$/, cells.overview],
  [/^#\/cells\/new$/, cells.register],
  [/^#\/cells\/(\d+)$/, cells.detail],
  [/^#\/cells\/(\d+)\/edit$/, cells.edit],
  [/^#\/cells\/(\d+)\/start$/, cells.start],
  [/^#\/sessions\/(\d+)$/, session.live],
  [/^#\/calibrations\/(\d+)$/, result.show],
  [/^#\/calibrations\/(\d+)\/certificate$/, certificate.show],
];

const root = document.getElementById("view");
let generation = 0;
let cleanups = [];

function setCrumbs(items) {
  const nav = clear(document.getElementById("crumbs"));
  items.forEach(([label, href], i) => {
    if (i) nav.appendChild(h("span", { class: "sep" }, "›"));
    nav.appendChild(href ? h("a", { href }, label) : h("span", {}, label));
  });
}

function showWho() {
  const who = clear(document.getElementById("who"));
  if (!me.role) return;
  who.appendChild(h("span", { class: "me", title: `signed in as ${me.name}` }, me.name, " ",
    h("span", { class: `role role-${me.role}`, id: "role" }, me.role)));
  who.appendChild(h("button", { class: "link", onclick: signOut }, "Sign out"));
}

function signOut() {
  clearToken();
  me.name = me.role = "";
  showWho();
  login();
}

async function route() {
  const gen = ++generation;
  for (const fn of cleanups.splice(0)) {
    try { fn(); } catch (_) { /* ignore */ }
  }
  document.body.classList.remove("printing");
  if (!me.role) return login();
  const hash = location.hash || "#/";
  for (const [re, view] of routes) {
    const m = re.exec(hash);
    if (!m) continue;
    clear(root).appendChild(h("p", { class: "loading" }, "Loading…"));
    const ctx = {
      root,
      crumbs: setCrumbs,
      alive: () => gen === generation,
      onLeave: (fn) => cleanups.push(fn),
      go: (href) => { location.hash = href; },
      reload: () => route(),
    };
    try {
      await view(ctx, ...m.slice(1).map(Number));
    } catch (e) {
      if (gen !== generation) return;
      clear(root).appendChild(h("section", { class: "card" }, h("h2", {}, "This page could not be shown"),
        h("p", { class: "error-text" }, e.message || String(e)), h("a", { href: "#/" }, "Back to the cells")));
    }
    window.scrollTo(0, 0);
    return;
  }
  clear(root).appendChild(h("section", { class: "card" }, h("h2", {}, "No such page"), h("a", { href: "#/" }, "Back to the cells")));
}

function login(message) {
  setCrumbs([["Sign in", null]]);
  const input = h("input", { type: "password", id: "token", name: "token", autocomplete: "current-password",
                             placeholder: "rc_…", required: true, spellcheck: "false" });
  const remember = h("input", { type: "checkbox", id: "remember" });
  const err = h("p", { class: "error-text", role: "alert" }, message || "");
  const form = h("form", { class: "card login", onsubmit: async (e) => {
    e.preventDefault();
    const ok = await tryToken(input.value.trim(), remember.checked, err);
    if (ok) route();
  } },
    h("h1", {}, "Sign in to Recal"),
    h("p", {}, "Recal calibrates robots: it measures a robot with a laser tracker or a CMM, works out its true "
      + "geometry and corrects its programs. Sign in with your API token."),
    h("label", { for: "token" }, "Token"), input,
    h("label", { class: "check" }, remember, " Remember me on this device"),
    err,
    h("button", { type: "submit", class: "primary", id: "sign-in" }, "Sign in"),
    h("details", {}, h("summary", {}, "Where do I get a token?"),
      h("p", {}, "Ask whoever runs the service: ", h("code", {}, "recal token create --role technician"),
        " prints one. ", h("code", {}, "make demo"), " prints the technician's token and keeps it in ",
        h("code", {}, "demo-output/tokens.txt"), " (the demo's RECAL_HOME). Viewers can watch and read; technicians also register cells, "
        + "run sessions and compensate programs.")));
  clear(root).appendChild(form);
  input.focus();
}

async function tryToken(token, remember, errEl) {
  if (!token) return false;
  setToken(token, remember);
  try {
    const who = await get("/me");
    me.name = who.name;
    me.role = who.role;
    showWho();
    return true;
  } catch (e) {
    clearToken();
    if (errEl) errEl.textContent = e instanceof ApiError && e.status === 401
      ? "This token is not valid (unknown or revoked)." : e.message;
    return false;
  }
}

window.addEventListener("recal:unauthorized", () => {
  if (!me.role) return;
  clearToken();
  me.name = me.role = "";
  showWho();
  login("Your token is no longer valid; sign in again.");
});

window.addEventListener("hashchange", route);

async function start() {
  const m = /^#token=([^&]+)/.exec(location.hash);
  if (m) {
    const tok = decodeURIComponent(m[1]);
    history.replaceState(null, "", location.pathname + "#/");
    await tryToken(tok, false, null);
  } else if (getToken()) {
    const ok = await tryToken(getToken(), !!localStorage.getItem("recal.token"), null);
    if (!ok) notify("The saved token is no longer valid; sign in again.");
  }
  route();
}

start();
