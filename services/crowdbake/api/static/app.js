// crowdbake's page: follows bakes, shows their cycle reports, lists bundles and previews impostor atlases.
// Vanilla JS against the JSON API; nothing is built or fetched from elsewhere.
//
// The key the user types is kept in localStorage and sent as a bearer token. A link may carry it and a
// selection in its fragment (#key=cbk_...&bake=bk_...&bundle=name/version): the fragment never reaches
// the server, and the key is moved into localStorage and removed from the address bar at once.
"use strict";

const KEY_STORAGE = "crowdbake.key";
const JOBS_POLL_MS = 2000;       // bake progress is written at most every 0.5 s; 2 s is plenty for eyes
const BUNDLES_POLL_MS = 15000;   // bundles change only when a bake publishes
const FINAL_STATES = new Set(["succeeded", "failed", "cancelled"]);
const ATLAS_DISPLAY_WIDTH = 1024;  // px the atlas viewer magnifies small atlases up to
const STAGE_SHORT = { validate: "val", cycle: "cyc", poses: "pos", impostors: "imp", pack: "pak", publish: "pub" };

const state = {
  key: localStorage.getItem(KEY_STORAGE) || "",
  bakeId: null,        // the bake shown in detail
  reportFor: null,     // the bake whose cycle report is loaded (or loading)
  bundle: null,        // {name, version} shown in the atlas viewer
  manifest: null,
  atlasUrl: null,      // object URL of the current preview, revoked when replaced
  atlasRequest: 0,     // the newest preview request; older answers are dropped
};

const $ = (id) => document.getElementById(id);

function el(tag, props = {}, ...children) {
  const node = document.createElement(tag);
  for (const [name, value] of Object.entries(props)) {
    if (name === "class") node.className = value;
    else if (name === "dataset") Object.assign(node.dataset, value);
    else if (name.startsWith("on")) node.addEventListener(name.slice(2), value);
    else node.setAttribute(name, value);
  }
  for (const child of children) node.append(child instanceof Node ? child : document.createTextNode(String(child)));
  return node;
}

// ------------------------------------------------------------------------------------------- API

class ApiError extends Error {
  constructor(status, detail) { super(detail); this.status = status; }
}

async function api(path, kind = "json") {
  const headers = state.key ? { Authorization: `Bearer ${state.key}` } : {};
  const response = await fetch(path, { headers, cache: "no-cache" });
  if (!response.ok) {
    let detail = `${response.status} ${response.statusText}`;
    try { detail = (await response.json()).detail || detail; } catch (_) { /* not a problem document */ }
    throw new ApiError(response.status, detail);
  }
  if (kind === "json") return response.json();
  if (kind === "text") return response.text();
  return response.blob();
}

function blobToDataUrl(blob) {
  return new Promise((resolve, reject) => {
    const reader = new FileReader();
    reader.onload = () => resolve(reader.result);
    reader.onerror = () => reject(reader.error);
    reader.readAsDataURL(blob);
  });
}

// ------------------------------------------------------------------------------------ formatting

function bytes(n) {
  const units = ["B", "KiB", "MiB", "GiB", "TiB"];
  let value = n, unit = 0;
  while (value >= 1024 && unit < units.length - 1) { value /= 1024; unit += 1; }
  return `${unit ? value.toFixed(value < 10 ? 2 : 1) : value} ${units[unit]}`;
}

function when(iso) {
  return iso ? new Date(iso).toLocaleString() : "";
}

function seconds(value) {
  return value === null || value === undefined ? "" : `${value.toFixed(value < 10 ? 2 : 1)} s`;
}

function stateLabel(value) {
  return el("span", { class: `state state-${value}` }, value);
}

function explain(error, scope) {
  if (error.status === 401) return `Enter a key with the ${scope} scope (${error.message}).`;
  if (error.status === 403) return `This key lacks the ${scope} scope.`;
  return `Could not load: ${error.message}`;
}

// ------------------------------------------------------------------------------------------ bakes

async function refreshJobs() {
  try {
    const page = await api("/v1/bakes?limit=50");
    renderJobs(page.data);
    $("jobs-status").textContent = page.count ? "" : "No bakes yet.";
    $("jobs-updated").textContent = `updated ${new Date().toLocaleTimeString()}`;
  } catch (error) {
    $("jobs-status").textContent = explain(error, "bake");
    $("jobs-table").tBodies[0].replaceChildren();
  }
  if (state.bakeId) await refreshDetail();
}

function renderJobs(bakes) {
  const rows = bakes.map((bake) => {
    const stages = el("span", { class: "stages" }, ...bake.stages.map((stage) =>
      el("span", { class: `stage state-${stage.state}`, title: `${stage.stage}: ${stage.state} ${stage.done}/${stage.total} ${seconds(stage.seconds)}` },
        STAGE_SHORT[stage.stage] || stage.stage)));
    const percent = Math.round(bake.progress * 100);
    return el("tr", { class: `selectable${bake.id === state.bakeId ? " selected" : ""}`, dataset: { bake: bake.id, state: bake.state },
                      onclick: () => selectBake(bake.id) },
      el("td", {}, el("code", {}, bake.id)),
      el("td", { class: "job-name" }, `${bake.name} ${bake.version}`),
      el("td", { class: "job-state", title: bake.error ? `${bake.error.stage}: ${bake.error.detail}` : "" }, stateLabel(bake.state)),
      el("td", {}, el("progress", { max: "100", value: String(percent) }), ` ${percent}%`),
      el("td", {}, stages),
      el("td", {}, when(bake.created_at)));
  });
  $("jobs-table").tBodies[0].replaceChildren(...rows);
}

function selectBake(id) {
  state.bakeId = id;
  for (const row of $("jobs-table").tBodies[0].rows) row.classList.toggle("selected", row.dataset.bake === id);
  setFragment();
  refreshDetail();
}

async function refreshDetail() {
  const id = state.bakeId;
  let bake;
  try {
    bake = await api(`/v1/bakes/${encodeURIComponent(id)}`);
  } catch (error) {
    $("bake-detail").hidden = false;
    $("detail-title").textContent = id;
    $("detail-summary").textContent = explain(error, "bake");
    return;
  }
  if (id !== state.bakeId) return;  // another bake was chosen meanwhile
  $("bake-detail").hidden = false;
  $("bake-detail").dataset.bake = bake.id;
  $("bake-detail").dataset.state = bake.state;
  $("detail-title").textContent = `${bake.name} ${bake.version} (${bake.id})`;
  const summary = [`${bake.state}, ${Math.round(bake.progress * 100)}% done, attempt ${bake.attempt}`];
  if (bake.started_at && bake.finished_at) {
    summary.push(`took ${seconds((new Date(bake.finished_at) - new Date(bake.started_at)) / 1000)}`);
  }
  $("detail-summary").replaceChildren(summary.join(", "));
  if (bake.bundle_url) {
    const [, , , name, version] = bake.bundle_url.split("/");
    $("detail-summary").append(" — bundle ", el("button", { class: "link", type: "button", onclick: () => selectBundle(name, version) },
      `${name}/${version}`));
  }
  $("detail-error").hidden = !bake.error;
  $("detail-error").textContent = bake.error ? `${bake.error.stage}: ${bake.error.title}: ${bake.error.detail}` : "";
  $("detail-stages").tBodies[0].replaceChildren(...bake.stages.map((stage) => el("tr", {},
    el("td", {}, stage.stage), el("td", {}, stateLabel(stage.state)),
    el("td", { class: "number" }, `${stage.done}/${stage.total}`),
    el("td", { class: "number" }, seconds(stage.seconds)), el("td", { class: "number" }, stage.retries))));
  $("detail-log").textContent = bake.log.map((line) => `${line.at} ${line.level.padEnd(7)} ${(line.stage || "-").padEnd(9)} ${line.message}`).join("\n");
  const cycle = bake.stages.find((stage) => stage.stage === "cycle");
  if (cycle && cycle.state === "succeeded" && state.reportFor !== bake.id) loadReport(bake.id);
  if (!cycle || cycle.state !== "succeeded") {
    $("report").hidden = true;
    state.reportFor = null;
    $("report-status").textContent = "The report appears when the cycle stage has finished.";
  }
}

// The report's plots are fetched with the key and inlined as data URLs, so the report can sit in a
// sandboxed frame (no scripts, no access to this page) and still show every picture.
async function loadReport(id) {
  state.reportFor = id;
  const frame = $("report");
  $("report-status").textContent = "Loading the cycle report…";
  try {
    const html = await api(`/v1/bakes/${encodeURIComponent(id)}/cycle/report.html`, "text");
    const doc = new DOMParser().parseFromString(html, "text/html");
    for (const node of doc.querySelectorAll("script, link, iframe, object, embed")) node.remove();
    for (const image of doc.querySelectorAll("img")) {
      const src = image.getAttribute("src") || "";
      if (/^[A-Za-z0-9][A-Za-z0-9_./-]*\.png$/.test(src) && !src.includes("..")) {
        image.src = await blobToDataUrl(await api(`/v1/bakes/${encodeURIComponent(id)}/cycle/${src}`, "blob"));
      } else {
        image.remove();
      }
    }
    if (state.reportFor !== id) return;
    frame.srcdoc = `<!doctype html>${doc.documentElement.outerHTML}`;
    frame.hidden = false;
    frame.dataset.bake = id;
    frame.dataset.loaded = "true";
    $("report-status").textContent = `${doc.title}`;
  } catch (error) {
    state.reportFor = null;
    frame.hidden = true;
    $("report-status").textContent = explain(error, "bake");
  }
}

// ---------------------------------------------------------------------------------------- bundles

async function refreshBundles() {
  let names;
  try {
    names = (await api("/v1/bundles")).names;
  } catch (error) {
    $("bundles-status").textContent = explain(error, "read");
    return;
  }
  const rows = [];
  for (const name of names) {
    let listing;
    try {
      listing = await api(`/v1/bundles/${encodeURIComponent(name)}`);
    } catch (_) {
      continue;  // not readable with this key
    }
    for (const bundle of listing.versions) {
      rows.push(el("tr", { dataset: { bundle: `${bundle.name}/${bundle.version}` } },
        el("td", { class: "bundle-name" }, bundle.name),
        el("td", { class: "bundle-version" }, bundle.version, bundle.version === listing.latest ? " (latest)" : ""),
        el("td", { class: "number bundle-size", dataset: { bytes: String(bundle.size) } }, bytes(bundle.size)),
        el("td", { class: "number" }, bundle.file_count),
        el("td", {}, bundle.public ? "public" : "private"),
        el("td", {}, when(bundle.published_at)),
        el("td", {}, el("button", { type: "button", onclick: () => selectBundle(bundle.name, bundle.version) }, "atlas"))));
    }
  }
  $("bundles-table").tBodies[0].replaceChildren(...rows);
  $("bundles-status").textContent = rows.length ? "" : (state.key ? "No bundles published yet." : "No public bundles; enter a key with the read scope to see private ones.");
}

function options(select, items) {
  const previous = select.value;
  select.replaceChildren(...items.map(([value, label]) => el("option", { value }, label)));
  if (items.some(([value]) => value === previous)) select.value = previous;
}

async function selectBundle(name, version) {
  state.bundle = { name, version };
  setFragment();
  $("atlas").hidden = false;
  $("atlas-title").textContent = `${name}/${version}`;
  $("atlas-status").textContent = "Loading the manifest…";
  try {
    state.manifest = await api(`/v1/bundles/${encodeURIComponent(name)}/${encodeURIComponent(version)}/manifest.json`);
  } catch (error) {
    $("atlas-status").textContent = explain(error, "read");
    return;
  }
  const impostor = state.manifest.impostor;
  options($("atlas-frame"), impostor.frame_indices.map((frame, k) => [String(k), `${k}: cycle frame ${frame}`]));
  options($("atlas-azimuth"), [["", "all"], ...impostor.azimuths_deg.map((deg, a) => [String(a), `${a}: ${deg}°`])]);
  options($("atlas-elevation"), [["", "all"], ...impostor.elevations_deg.map((deg, e) => [String(e), `${e}: ${deg}°`])]);
  await loadAtlas();
}

async function loadAtlas() {
  if (!state.bundle) return;
  const { name, version } = state.bundle;
  const query = new URLSearchParams({ frame: $("atlas-frame").value || "0" });
  if ($("atlas-azimuth").value) query.set("azimuth", $("atlas-azimuth").value);
  if ($("atlas-elevation").value) query.set("elevation", $("atlas-elevation").value);
  const kind = $("atlas-map").value;
  const request = ++state.atlasRequest;
  $("atlas-status").textContent = "Decoding…";
  let blob;
  try {
    blob = await api(`/v1/bundles/${encodeURIComponent(name)}/${encodeURIComponent(version)}/preview/${kind}?${query}`, "blob");
  } catch (error) {
    $("atlas-status").textContent = explain(error, "read");
    return;
  }
  if (request !== state.atlasRequest) return;
  const image = $("atlas-image");
  if (state.atlasUrl) URL.revokeObjectURL(state.atlasUrl);
  state.atlasUrl = URL.createObjectURL(blob);
  image.onload = () => {
    image.dataset.loaded = "true";
    image.dataset.kind = kind;
    image.dataset.width = String(image.naturalWidth);
    image.dataset.height = String(image.naturalHeight);
    // Small atlases are magnified by a whole factor (nearest texel, see style.css), large ones shown as they are.
    const zoom = Math.max(1, Math.floor(ATLAS_DISPLAY_WIDTH / image.naturalWidth));
    image.style.width = `${zoom * image.naturalWidth}px`;
    const impostor = state.manifest.impostor;
    $("atlas-status").textContent = `${kind} map, layer ${query.get("frame")} of ${impostor.frame_indices.length}: `
      + `${image.naturalWidth}×${image.naturalHeight} texels (tiles of ${impostor.tile_size}², `
      + `${impostor.azimuths_deg.length} azimuths × ${impostor.elevations_deg.length} elevations), ${bytes(blob.size)} PNG`;
  };
  image.src = state.atlasUrl;
}

// ------------------------------------------------------------------------------- key and fragment

function showKeyState() {
  $("key-state").textContent = state.key ? `key ${state.key.split("_")[1] || ""} in use` : "no key: public bundles only";
}

function setFragment() {
  const parts = new URLSearchParams();
  if (state.bakeId) parts.set("bake", state.bakeId);
  if (state.bundle) parts.set("bundle", `${state.bundle.name}/${state.bundle.version}`);
  history.replaceState(null, "", `${location.pathname}${location.search}${parts.toString() ? `#${parts}` : ""}`);
}

function readFragment() {
  const parts = new URLSearchParams(location.hash.slice(1));
  if (parts.get("key")) {
    state.key = parts.get("key");
    localStorage.setItem(KEY_STORAGE, state.key);
  }
  state.bakeId = parts.get("bake") || state.bakeId;
  const bundle = parts.get("bundle");
  setFragment();  // the key leaves the address bar (and the history) at once
  return bundle ? bundle.split("/") : null;
}

function useKey(key) {
  state.key = key;
  if (key) localStorage.setItem(KEY_STORAGE, key); else localStorage.removeItem(KEY_STORAGE);
  $("key").value = "";
  showKeyState();
  state.reportFor = null;
  refreshJobs();
  refreshBundles();
  if (state.bundle) selectBundle(state.bundle.name, state.bundle.version);
}

async function poll(task, interval) {
  try { await task(); } finally { setTimeout(() => poll(task, interval), interval); }
}

function start() {
  const bundle = readFragment();
  showKeyState();
  $("key-form").addEventListener("submit", (event) => { event.preventDefault(); useKey($("key").value.trim()); });
  $("forget-key").addEventListener("click", () => useKey(""));
  for (const id of ["atlas-map", "atlas-frame", "atlas-azimuth", "atlas-elevation"]) $(id).addEventListener("change", loadAtlas);
  poll(refreshJobs, JOBS_POLL_MS);
  poll(refreshBundles, BUNDLES_POLL_MS);
  if (bundle && bundle.length === 2) selectBundle(bundle[0], bundle[1]);
}

document.addEventListener("DOMContentLoaded", start);
