// The service's REST API from the page: same origin, the token from the login (kept in this
// browser's session storage, or local storage when "remember" was ticked).

const KEY = "recal.token";

export function getToken() {
  return sessionStorage.getItem(KEY) || localStorage.getItem(KEY) || "";
}

export function setToken(token, remember) {
  sessionStorage.setItem(KEY, token);
  if (remember) localStorage.setItem(KEY, token);
  else localStorage.removeItem(KEY);
}

export function clearToken() {
  sessionStorage.removeItem(KEY);
  localStorage.removeItem(KEY);
}

export class ApiError extends Error {
  constructor(status, detail) {
    super(describe(detail) || `HTTP ${status}`);
    this.status = status;
    this.detail = detail;
  }
}

// The service names request fields as "body.count", "query.mode" or "body" (the whole body, whose
// message names the file, row and column itself): a person reads "count: ..." or the message alone.
function fieldName(field) {
  return String(field).replace(/^(?:body|query|path)(?:\.|$)/, "");
}

function describe(detail) {
  if (detail == null) return "";
  if (typeof detail === "string") return detail.replace(/(^|; )(?:body|query|path)(?:\.|: )/g, "$1");
  if (Array.isArray(detail)) return detail.map(describe).join("; ");
  if (detail.field && detail.message) {
    const name = fieldName(detail.field);
    return name ? `${name}: ${detail.message}` : detail.message;
  }
  if (detail.message) return detail.message;
  return JSON.stringify(detail);
}

// A request to /api/v1 + path. `body`: an object (sent as JSON), a string (sent as text), a
// FormData (multipart) or a Blob/File (its bytes).
// Returns the parsed JSON, or {text, headers} for other answers; raises ApiError.
export async function api(method, path, body, { raw = false, token = null } = {}) {
  const headers = { Authorization: `Bearer ${token || getToken()}` };
  let data;
  if (typeof body === "string") {
    headers["Content-Type"] = "text/plain; charset=utf-8";
    data = body;
  } else if (body instanceof FormData) {
    data = body; // the browser writes the multipart Content-Type with its boundary
  } else if (body instanceof Blob) {
    headers["Content-Type"] = "text/plain"; // no charset: the file's bytes as they are (a program need not be UTF-8)
    data = body;
  } else if (body !== undefined) {
    headers["Content-Type"] = "application/json";
    data = JSON.stringify(body);
  }
  let resp;
  try {
    resp = await fetch(`/api/v1${path}`, { method, headers, body: data });
  } catch (e) {
    throw new ApiError(0, `the service cannot be reached (${e.message})`);
  }
  const type = resp.headers.get("content-type") || "";
  if (!resp.ok) {
    let detail = `${resp.status} ${resp.statusText}`;
    try {
      detail = type.includes("json") ? (await resp.json()).detail : await resp.text();
    } catch (_) { /* keep the status line */ }
    if (resp.status === 401) window.dispatchEvent(new CustomEvent("recal:unauthorized"));
    throw new ApiError(resp.status, detail);
  }
  if (raw) return resp;
  if (type.includes("application/json")) return resp.json();
  return { text: await resp.text(), headers: resp.headers };
}

export const get = (path) => api("GET", path);
export const post = (path, body) => api("POST", path, body === undefined ? {} : body);
export const patch = (path, body) => api("PATCH", path, body);

// Fetch a file with the token and hand it to the browser as a download.
export async function download(path, fallbackName) {
  const resp = await api("GET", path, undefined, { raw: true });
  const blob = await resp.blob();
  const cd = resp.headers.get("content-disposition") || "";
  const m = /filename="?([^";]+)"?/.exec(cd);
  saveBlob(blob, m ? m[1] : fallbackName);
}

export function saveBlob(blob, name) {
  const url = URL.createObjectURL(blob);
  const a = document.createElement("a");
  a.href = url;
  a.download = name;
  document.body.appendChild(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

// Server-sent events of a session. EventSource cannot send an Authorization header, and a token
// in a URL ends up in logs and history: the page asks for a single-use ticket (good for 30 s, for
// this session's stream only) and puts that in the URL instead. A ticket serves one connection,
// so the caller opens a new stream (with a new ticket) when one drops.
export async function sessionEvents(id) {
  const { ticket } = await api("POST", `/sessions/${id}/events/ticket`);
  return new EventSource(`/api/v1/sessions/${id}/events?ticket=${encodeURIComponent(ticket)}`);
}

// What each role may do (service/api/deps.py PERMISSIONS).
const PERMISSIONS = {
  read: ["viewer", "technician", "job", "admin"],
  run: ["technician", "job", "admin"],
  compensate: ["technician", "job", "admin"],
  cells: ["technician", "admin"],
  admin: ["admin"],
};

export const me = { name: "", role: "" };

export function can(permission) {
  return (PERMISSIONS[permission] || []).includes(me.role);
}
