// The maxfs-ps job page: plain JavaScript, no build step, no third-party code.
// The token lives in this tab's sessionStorage and goes out only as an Authorization header
// (previews and downloads are fetched with it and shown through blob: URLs), never in a URL.
"use strict";

const TOKEN_KEY = "maxfs-token";
const POLL_MS = 1000; // job list refresh
const PREVIEW_MS = 2000; // at most one preview reload per this while a job runs
const FINAL = ["done", "failed", "cancelled"];
const DOWNLOADS = [
  ["results.zip", "results.zip", "the whole result: results.zarr, previews, record"],
  ["normal.npy", "results/normal.npy", "(H, W, 3) float32 unit normals, NaN where unsolved"],
  ["albedo.npy", "results/albedo.npy", "(H, W) float32"],
  ["inlier_count.npy", "results/inlier_count.npy", "(H, W) uint16"],
  ["optimal.npy", "results/optimal.npy", "(H, W) bool: optimum proved"],
  ["mask.npy", "results/mask.npy", "(H, W) bool"],
  ["depth.npy", "results/depth.npy", "(H, W) float32, after the job is done"],
  ["inliers.npy", "results/inliers.npy", "(k, H, W) bool: large; may need results.zip"],
];

const $ = (sel) => document.querySelector(sel);
const page = {
  token: sessionStorage.getItem(TOKEN_KEY),
  auth: true,
  jobs: [],
  selected: location.hash.startsWith("#job=") ? location.hash.slice(5) : null,
  timer: null,
  canDelete: false,
  previews: { key: null, at: 0, busy: false, job: null },
  depthMissing: new Set(),
};

class ApiError extends Error {
  constructor(status, error, detail) {
    super(detail);
    this.status = status;
    this.error = error;
  }
}

async function api(path, options = {}) {
  const headers = new Headers(options.headers || {});
  if (page.token) headers.set("Authorization", "Bearer " + page.token);
  const r = await fetch(path, { ...options, headers, cache: "no-store" });
  if (!r.ok) {
    let body = {};
    try {
      body = await r.json();
    } catch (e) {
      body = { error: "HTTPError", detail: r.statusText };
    }
    throw new ApiError(r.status, body.error || "HTTPError", body.detail || r.statusText);
  }
  return r;
}

// -- formatting -------------------------------------------------------------------------------
// a certified share means little when the calibration checks found the lights or mask suspect
function suspect(job) {
  return job.calibration && job.calibration.length ? " (calibration suspect)" : "";
}

function pct(x) {
  return x === null || x === undefined ? "–" : (100 * x).toFixed(1) + " %";
}
function rate(x) {
  if (!x) return "–";
  return x >= 1e6 ? (x / 1e6).toFixed(2) + " M" : x >= 1e3 ? (x / 1e3).toFixed(1) + " k" : x.toFixed(0);
}
function hms(s) {
  if (s === null || s === undefined) return "–";
  s = Math.max(0, Math.round(s));
  const h = Math.floor(s / 3600), m = Math.floor((s % 3600) / 60), sec = s % 60;
  return (h ? h + ":" + String(m).padStart(2, "0") : String(m)) + ":" + String(sec).padStart(2, "0");
}
function when(t) {
  return t ? new Date(t * 1000).toLocaleString() : "–";
}
function tiles(p) {
  return `${p.tiles_done} / ${p.tiles_total}`;
}

// -- sign in and out --------------------------------------------------------------------------
function show(section) {
  $("#sign-in").hidden = section !== "sign-in";
  $("#jobs").hidden = section !== "jobs";
  $("#who").hidden = section !== "jobs" || !page.auth;
  if (section !== "jobs") $("#detail").hidden = true;
}

function signOut(message) {
  page.token = null;
  sessionStorage.removeItem(TOKEN_KEY);
  clearTimeout(page.timer);
  page.jobs = [];
  $("#job-table tbody").replaceChildren();
  $("#sign-in-error").textContent = message || "";
  show("sign-in");
  $("#token").focus();
}

async function signIn(event) {
  event.preventDefault();
  const value = $("#token").value.trim();
  if (!value) return;
  page.token = value;
  $("#sign-in-error").textContent = "";
  try {
    await api("/jobs");
  } catch (e) {
    page.token = null;
    $("#sign-in-error").textContent = e.message;
    return;
  }
  sessionStorage.setItem(TOKEN_KEY, value);
  $("#token").value = "";
  start();
}

function start() {
  show("jobs");
  refresh();
}

// -- the job list -----------------------------------------------------------------------------
async function refresh() {
  clearTimeout(page.timer);
  try {
    const r = await api("/jobs");
    page.jobs = (await r.json()).reverse(); // newest first
    const who = r.headers.get("X-Maxfs-User");
    if (who) $("#who-text").textContent = page.auth ? "Signed in as " + who : who;
    $("#list-error").textContent = "";
    $("#updated").textContent = "updated " + new Date().toLocaleTimeString();
    renderTable();
    renderDetail();
  } catch (e) {
    if (e.status === 401) {
      signOut("Signed out: " + e.message);
      return;
    }
    $("#list-error").textContent = "cannot reach the server: " + e.message;
  }
  page.timer = setTimeout(refresh, POLL_MS);
}

function cell(row, i) {
  while (row.cells.length <= i) row.insertCell();
  return row.cells[i];
}

function renderTable() {
  const body = $("#job-table tbody");
  const rows = new Map([...body.rows].map((r) => [r.dataset.job, r]));
  const order = [];
  for (const job of page.jobs) {
    let row = rows.get(job.id);
    if (!row) {
      row = document.createElement("tr");
      row.dataset.job = job.id;
      row.tabIndex = 0;
      row.addEventListener("click", () => select(job.id));
      row.addEventListener("keydown", (e) => e.key === "Enter" && select(job.id));
    }
    const p = job.progress;
    const idCell = cell(row, 0);
    idCell.textContent = job.name ? `${job.name} (${job.id.slice(0, 8)})` : job.id.slice(0, 8);
    idCell.title = job.id;
    cell(row, 1).textContent = job.owner;
    const st = cell(row, 2);
    st.textContent = job.state;
    st.className = "state state-" + job.state;
    const t = cell(row, 3);
    t.className = "tiles";
    t.replaceChildren(miniBar(p.fraction), document.createTextNode(tiles(p)));
    cell(row, 4).textContent = rate(p.pixels_per_second);
    cell(row, 5).textContent = job.state === "running" || job.state === "queued" ? hms(p.eta_seconds) : "–";
    cell(row, 6).textContent = pct(p.solved_share);
    cell(row, 7).textContent = pct(p.certified_share) + suspect(job);
    cell(row, 8).textContent = when(job.created_at);
    row.classList.toggle("selected", job.id === page.selected);
    order.push(row);
  }
  body.replaceChildren(...order);
  $("#no-jobs").hidden = page.jobs.length > 0;
}

function miniBar(fraction) {
  const outer = document.createElement("span");
  outer.className = "mini";
  const inner = document.createElement("span");
  inner.style.width = (100 * (fraction || 0)).toFixed(1) + "%";
  outer.append(inner);
  return outer;
}

function select(id) {
  page.selected = id;
  history.replaceState(null, "", "#job=" + id);
  page.previews.key = null;
  $("#d-action-error").textContent = "";
  renderTable();
  renderDetail();
}

// -- one job ----------------------------------------------------------------------------------
function renderDetail() {
  const job = page.jobs.find((j) => j.id === page.selected);
  $("#detail").hidden = !job;
  if (!job) return;
  const p = job.progress;
  $("#d-id").textContent = job.name ? `${job.name} · ${job.id}` : job.id;
  const st = $("#d-state");
  st.textContent = job.state;
  st.className = "state state-" + job.state;
  $("#d-bar").style.width = (100 * p.fraction).toFixed(1) + "%";
  const stats = [
    ["Owner", job.owner],
    ["Tiles", tiles(p)],
    ["Pixels solved", `${p.pixels_done + (p.pixels_running || 0)} / ${p.pixels_total}`],
    ["Pixels/s", rate(p.pixels_per_second)],
    ["ETA", job.state === "running" || job.state === "queued" ? hms(p.eta_seconds) : "–"],
    ["Solved", pct(p.solved_share)],
    ["Certified", pct(p.certified_share) + suspect(job)],
    ["eps", job.eps === null || job.eps === undefined ? "–" : job.eps.toPrecision(4)],
    ["Raw step", job.raw_step ? String(job.raw_step) : "–"],
    ["Created", when(job.created_at)],
    ["Started", when(job.started_at)],
    ["Finished", when(job.finished_at)],
  ];
  const dl = $("#d-stats");
  dl.replaceChildren();
  for (const [k, v] of stats) {
    const div = document.createElement("div");
    const dt = document.createElement("dt");
    const dd = document.createElement("dd");
    dt.textContent = k;
    dd.textContent = v;
    dd.dataset.stat = k.toLowerCase().replace("/", "-");
    div.append(dt, dd);
    dl.append(div);
  }
  $("#d-error").textContent = job.error ? "Error: " + job.error : "";
  $("#d-warnings").replaceChildren(
    ...(job.warnings || []).map((w) => Object.assign(document.createElement("li"), { textContent: w }))
  );
  // a failed job would fail the same way: nothing can be changed from this page (results.resumable)
  const resumable = !job.results || job.results.resumable !== false;
  $("#d-start").hidden = !resumable;
  $("#d-start").disabled = !resumable || !["created", "uploading", "cancelled", "failed"].includes(job.state);
  $("#d-start").textContent = job.state === "cancelled" ? "Resume" : "Start";
  $("#d-cancel").disabled = FINAL.includes(job.state);
  $("#d-delete").hidden = !page.canDelete;
  $("#d-delete").disabled = !FINAL.includes(job.state);
  const available = job.results && job.results.available;
  $("#d-no-results").textContent = (job.results && job.results.note) || "";
  $("#d-no-results").hidden = !(job.results && job.results.note);
  $("#d-previews").hidden = !available;
  $("#d-partial").textContent = available && job.results.partial ? "partial: the job is not done" : "";
  renderDownloads(job, available);
  if (available) maybeLoadPreviews(job);
}

function renderDownloads(job, available) {
  const box = $("#d-downloads");
  if (box.dataset.job === job.id && box.dataset.available === String(available)) return;
  box.dataset.job = job.id;
  box.dataset.available = String(available);
  if (!available) {
    box.replaceChildren(Object.assign(document.createElement("span"), { className: "note", textContent: "none yet" }));
    return;
  }
  box.replaceChildren(
    ...DOWNLOADS.map(([label, path, what]) => {
      const a = document.createElement("a");
      a.href = `/jobs/${job.id}/${path}`; // the API address; the click fetches it with the token
      a.textContent = label;
      a.title = what;
      a.dataset.download = label;
      a.addEventListener("click", (e) => {
        e.preventDefault();
        download(a, job.id, label);
      });
      return a;
    })
  );
}

async function download(a, id, label) {
  $("#d-action-error").textContent = "";
  a.classList.add("busy");
  try {
    const r = await api(a.getAttribute("href"));
    const partial = r.headers.get("X-Maxfs-Partial") === "true";
    const blob = await r.blob();
    const url = URL.createObjectURL(blob);
    const save = document.createElement("a");
    save.href = url;
    save.download = `${id.slice(0, 8)}-${partial ? "partial-" : ""}${label}`;
    document.body.append(save);
    save.click();
    save.remove();
    setTimeout(() => URL.revokeObjectURL(url), 60000);
  } catch (e) {
    $("#d-action-error").textContent = `${label}: ${e.message}`;
  } finally {
    a.classList.remove("busy");
  }
}

function maybeLoadPreviews(job) {
  const pv = page.previews;
  const key = `${job.id}:${job.state}:${job.progress.tiles_done}`;
  const now = Date.now();
  if (pv.busy || key === pv.key) return;
  if (pv.job === job.id && !FINAL.includes(job.state) && now - pv.at < PREVIEW_MS) return;
  pv.key = key;
  pv.at = now;
  pv.job = job.id;
  loadPreviews(job);
}

async function loadPreviews(job) {
  const pv = page.previews;
  pv.busy = true;
  try {
    const names = ["normal", "albedo", "inlier_count"];
    const depth = document.querySelector('figure[data-preview="depth"]');
    const wantDepth = job.state === "done" && !page.depthMissing.has(job.id);
    if (wantDepth) names.push("depth");
    else depth.hidden = true;
    await Promise.all(names.map((name) => loadPreview(job.id, name)));
  } finally {
    pv.busy = false;
  }
}

async function loadPreview(id, name) {
  const fig = document.querySelector(`figure[data-preview="${name}"]`);
  const img = fig.querySelector("img");
  try {
    const r = await api(`/jobs/${id}/previews/${name}.png`);
    const url = URL.createObjectURL(await r.blob());
    if (page.selected !== id) return URL.revokeObjectURL(url);
    const old = img.dataset.url;
    img.onload = () => old && URL.revokeObjectURL(old);
    img.src = url;
    img.dataset.url = url;
    img.dataset.job = id;
    fig.hidden = false;
  } catch (e) {
    if (name === "depth" && e.status === 404) {
      page.depthMissing.add(id); // no depth for this job (not integrated): do not ask again
      fig.hidden = true;
    } else if (e.status !== 409) {
      $("#d-action-error").textContent = `preview ${name}: ${e.message}`;
    }
  }
}

async function act(what) {
  const id = page.selected;
  if (!id) return;
  $("#d-action-error").textContent = "";
  const calls = {
    start: () => api(`/jobs/${id}/start`, { method: "POST" }),
    cancel: () => api(`/jobs/${id}`, { method: "DELETE" }),
    delete: () => api(`/jobs/${id}?purge=true`, { method: "DELETE" }),
  };
  if (what === "delete" && !confirm(`Delete job ${id} and its results for good?`)) return;
  try {
    await calls[what]();
    if (what === "delete") {
      page.selected = null;
      history.replaceState(null, "", location.pathname);
    }
  } catch (e) {
    $("#d-action-error").textContent = `${what}: ${e.message}`;
  }
  page.previews.key = null;
  refresh();
}

// -- what this server can do ------------------------------------------------------------------
async function discover() {
  try {
    const h = await (await fetch("/health", { cache: "no-store" })).json();
    page.auth = h.auth !== false;
  } catch (e) {
    page.auth = true;
  }
  try {
    // deleting a finished job for good: offered only where the server documents it
    const doc = await (await fetch("/openapi.json", { cache: "no-store" })).json();
    const del = ((doc.paths || {})["/jobs/{job_id}"] || {}).delete || {};
    page.canDelete = (del.parameters || []).some((p) => p.name === "purge");
  } catch (e) {
    page.canDelete = false;
  }
}

document.addEventListener("DOMContentLoaded", async () => {
  $("#sign-in-form").addEventListener("submit", signIn);
  $("#sign-out").addEventListener("click", () => signOut(""));
  $("#d-start").addEventListener("click", () => act("start"));
  $("#d-cancel").addEventListener("click", () => act("cancel"));
  $("#d-delete").addEventListener("click", () => act("delete"));
  await discover();
  if (!page.auth || page.token) start();
  else show("sign-in");
});
