// crowdbake's page: uploads a character, its cloth (one cache, a cache of several clips with its timeline,
// or a cache per clip) and textures and starts a bake; follows bakes (cancel, retry, publish, download),
// shows their cycle reports, lists bundles and shows impostor atlases at full size with a zoom. Vanilla
// JS against the JSON API; nothing is built or fetched from elsewhere.
//
// The key the user types is kept in sessionStorage (it lasts as long as the tab) and sent as a bearer
// token. A link may carry it and a selection in its fragment (#key=cbk_...&bake=bk_...&bundle=name/version):
// the fragment never reaches the server, and the key is moved into sessionStorage and removed from the
// address bar at once.
"use strict";

const KEY_STORAGE = "crowdbake.key";
const JOBS_POLL_MS = 2000;       // bake progress is written at most every 0.5 s; 2 s is plenty for eyes
const BUNDLES_POLL_MS = 15000;   // bundles change only when a bake publishes
const FINAL_STATES = new Set(["succeeded", "failed", "cancelled"]);
const PREFLIGHT_ASSET = "preflight-no-such-asset";  // an asset id that never exists (see preflight)
const ARCHIVE_URL_LIFETIME_MS = 60000;  // the downloaded zip's object URL is revoked after this
const STAGE_SHORT = { validate: "val", loops: "lps", cycle: "cyc", probes: "prb", poses: "pos", impostors: "imp", pack: "pak", publish: "pub" };

// Earlier versions of the page kept the key in localStorage, where it outlived the browser session.
localStorage.removeItem(KEY_STORAGE);

const state = {
  key: sessionStorage.getItem(KEY_STORAGE) || "",
  files: { character: null, cloth: null, clothMesh: null, timeline: null, textures: new Map() },  // chosen for the next bake
  clips: [],           // the per-clip rows ({clip, cache, mesh}), in the order the clips join
  notice: "",          // the note on files not used, shown until the user acts
  detail: null,        // the bake record shown in detail
  bakeId: null,        // the bake shown in detail
  reportFor: null,     // the bake whose cycle report is loaded (or loading)
  bundle: null,        // {name, version} shown in the atlas viewer
  manifest: null,
  params: null,        // the server's bake parameter table (GET /v1/params), which the form is built from
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
  constructor(status, detail, problem = null) { super(detail); this.status = status; this.problem = problem; }
}

// `init` may carry method and body (a FormData, or an object sent as JSON).
async function api(path, kind = "json", init = {}) {
  const headers = state.key ? { Authorization: `Bearer ${state.key}` } : {};
  let body = init.body;
  if (body && !(body instanceof FormData)) {
    headers["Content-Type"] = "application/json";
    body = JSON.stringify(body);
  }
  const response = await fetch(path, { method: init.method || "GET", headers, body, cache: "no-cache" });
  if (!response.ok) {
    let detail = `${response.status} ${response.statusText}`, problem = null;
    try { problem = await response.json(); detail = problem.detail || detail; } catch (_) { /* not a problem document */ }
    throw new ApiError(response.status, detail, problem);
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

// One line from a problem document: its title, detail and the errors with the field they concern.
function problemText(error) {
  const problem = error.problem;
  if (!problem) return error.message;
  const errors = (problem.errors || []).map((item) => `${item.field || "?"}${item.where ? ` (${item.where})` : ""}: ${item.message}`);
  return `${problem.title}: ${problem.detail}${errors.length ? ` [${errors.join("; ")}]` : ""}`;
}

// ------------------------------------------------------------------------------- upload and bake

// Which input a dropped or chosen file is. The cloth forms are those POST /v1/assets/cloth takes: a .pc2
// or .mdd cache with its .obj rest mesh, an Alembic .abc or a .zip of OBJ frames alone. A .json is a
// timeline when its content reads as one (timelineProblem), whatever its name.
const CLOTH_SUFFIXES = [".pc2", ".mdd", ".abc", ".zip"];
const TEXTURE_SUFFIXES = [".png", ".jpg", ".jpeg"];
// A timeline holds about 130 bytes a cache frame (robot_clips: 94 KB for 717 frames); a JSON larger than
// this is not read into the tab to look for segments.
const TIMELINE_READ_LIMIT = 64 * 1024 * 1024;
const GLB_MAGIC = 0x46546c67;  // "glTF": the first word of a .glb (glTF 2.0, "GLB File Format Specification")
const FILE_INPUTS = { character: "file-character", cloth: "file-cloth", clothMesh: "file-cloth-mesh", timeline: "file-timeline", textures: "file-textures" };
const INPUT_LABELS = { character: "character", cloth: "cloth", clothMesh: "cloth mesh", timeline: "timeline", textures: "textures" };
// The modes of crowdbake.ingest.input_modes the page bakes (a body alone and a chosen cycle are crowdbake submit's).
const MODE_LABELS = { cloth: "one cloth cache, its cycle searched", timeline: "a timeline: one cloth cache playing several clips",
                      clip_cloth: "one cloth cache per clip" };
const NOTICE_PENDING = "some files were not used (see the note above): dismiss it to bake without them";
const hasSuffix = (file, suffixes) => suffixes.some((suffix) => file.name.toLowerCase().endsWith(suffix));
const clothNeedsMesh = (cloth) => hasSuffix(cloth, [".pc2", ".mdd"]);

// Why a .json is not a timeline, or null when it reads as one: an object listing its `segments`
// (crowdbake.ingest.timeline). The server checks the rest when it is uploaded.
async function timelineProblem(file) {
  if (file.size > TIMELINE_READ_LIMIT) return `over ${bytes(TIMELINE_READ_LIMIT)}, too large to read as a timeline`;
  let parsed;
  try {
    parsed = JSON.parse(await file.text());
  } catch (_) {
    return "not JSON";
  }
  const segments = parsed && parsed.segments;
  return Array.isArray(segments) && segments.length ? null : "a JSON without segments, so not a timeline";
}

// {kind} of a file (a key of FILE_INPUTS), or {why} it is not an input of a bake.
async function classify(file) {
  if (hasSuffix(file, [".glb", ".gltf"])) return { kind: "character" };
  if (hasSuffix(file, CLOTH_SUFFIXES)) return { kind: "cloth" };
  if (hasSuffix(file, [".obj"])) return { kind: "clothMesh" };
  if (hasSuffix(file, TEXTURE_SUFFIXES)) return { kind: "textures" };
  if (hasSuffix(file, [".json"])) {
    const why = await timelineProblem(file);
    return why ? { why } : { kind: "timeline" };
  }
  return { why: "not an input of a bake" };
}

// The multipart fields of the cloth upload for a cache (and mesh).
function clothUploadFields(cloth, clothMesh) {
  if (hasSuffix(cloth, [".zip"])) return { sequence: cloth };
  return clothNeedsMesh(cloth) ? { cache: cloth, mesh: clothMesh } : { cache: cloth };
}

// The animation names of a character, offered as the clip rows' names: the JSON chunk of a .glb, the
// document of a .gltf. Anything unreadable offers none; the server says what is wrong when it is uploaded.
async function animationNames(file) {
  let json = "";
  if (hasSuffix(file, [".gltf"])) {
    json = await file.text();
  } else {
    const header = new DataView(await file.slice(0, 20).arrayBuffer());  // magic, version, length; JSON chunk length, type
    if (header.byteLength === 20 && header.getUint32(0, true) === GLB_MAGIC) json = await file.slice(20, 20 + header.getUint32(12, true)).text();
  }
  try {
    return (JSON.parse(json).animations || []).map((animation) => animation.name).filter(Boolean);
  } catch (_) {
    return [];
  }
}

async function offerClipNames(character) {
  const names = character ? await animationNames(character) : [];
  $("character-clips").replaceChildren(...names.map((name) => el("option", { value: name })));
}

// A note on files the page did not use stays until the user acts on it: chooses files again or dismisses
// it. A bake's progress has its own line (#bake-form-status), so no later status hides the note.
function showNotice(text) {
  state.notice = text;
  $("input-notice-text").textContent = text;
  $("input-notice").hidden = !text;
}

// The line under the form: a bake's progress, or (refused) why it did not start, which stays until the user acts.
function showBakeStatus(text, refused = false) {
  $("bake-form-status").textContent = text;
  $("bake-form-status").classList.toggle("error", refused);
}

// The inputs changed: a refusal of the earlier ones no longer applies.
function inputsChanged() {
  showBakeStatus("");
  renderChosen();
}

async function chooseFiles(files) {
  if (!files.length) return;  // a file dialog closed without a choice changes nothing
  const ignored = [];
  for (const file of files) {
    const { kind, why } = await classify(file);
    if (kind === "textures") state.files.textures.set(file.name, file);
    else if (kind) state.files[kind] = file;
    else ignored.push(`${file.name} (${why})`);
    if (kind === "character") await offerClipNames(file);
  }
  showNotice(ignored.length ? `Not used: ${ignored.join("; ")}.` : "");
  inputsChanged();
}

function forgetInput(kind) {
  if (kind === "textures") state.files.textures.clear();
  else state.files[kind] = null;
  $(FILE_INPUTS[kind]).value = "";
  if (kind === "character") offerClipNames(null);
  inputsChanged();
}

// One row per clip of the per-clip mode (REST clip_cloth, `crowdbake submit --clip-cloth NAME=CACHE[,MESH]`):
// the clip's name, its cache and, for a .pc2 or .mdd, its mesh (default: the cloth mesh above, as --cloth-mesh).
function addClipRow() {
  const row = { clip: "", cache: null, mesh: null };
  const node = el("div", { class: "clip-row" },
    el("label", {}, "clip ", el("input", { class: "clip-name", list: "character-clips", placeholder: "Walking", spellcheck: "false",
                                          oninput: (event) => { row.clip = event.target.value.trim(); inputsChanged(); } })),
    el("label", {}, "cache ", el("input", { class: "clip-cache", type: "file", accept: CLOTH_SUFFIXES.join(","),
                                           onchange: (event) => chooseClipFiles(row, [...event.target.files]) })),
    el("label", {}, "mesh ", el("input", { class: "clip-mesh", type: "file", accept: ".obj", onchange: (event) => chooseClipFiles(row, [...event.target.files]) })),
    el("button", { type: "button", onclick: () => removeClipRow(row, node) }, "Remove"));
  acceptDrops(node, (files) => chooseClipFiles(row, files));
  state.clips.push(row);
  $("clip-rows").append(node);
  inputsChanged();
}

function removeClipRow(row, node) {
  state.clips = state.clips.filter((other) => other !== row);
  node.remove();
  inputsChanged();
}

function chooseClipFiles(row, files) {
  if (!files.length) return;
  const ignored = [];
  for (const file of files) {
    if (hasSuffix(file, CLOTH_SUFFIXES)) row.cache = file;
    else if (hasSuffix(file, [".obj"])) row.mesh = file;
    else ignored.push(file.name);
  }
  showNotice(ignored.length ? `Not used (a clip takes a cloth cache and its .obj mesh): ${ignored.join(", ")}.` : "");
  inputsChanged();
}

const filledClipRows = () => state.clips.filter((row) => row.clip || row.cache || row.mesh);

// The bake's mode, named as crowdbake.ingest.input_modes names it: a filled clip row makes it one cache per clip.
function inputMode() {
  if (filledClipRows().length) return "clip_cloth";
  return state.files.timeline ? "timeline" : "cloth";
}

// What keeps the chosen inputs from making a bake of `mode` with `params`, each a phrase; none when they make
// one. The conflicts are crowdbake.ingest.input_modes', told here before anything is uploaded.
function inputProblems(mode, params) {
  const { character, cloth, clothMesh, timeline } = state.files;
  const problems = character ? [] : ["choose a character (.glb)"];
  if (mode === "clip_cloth") {
    if (cloth) problems.push(`one cache per clip stands alone: remove the cloth ${cloth.name}, or the clips`);
    if (timeline) problems.push(`each clip's cache is a simulation of its own: remove the timeline ${timeline.name}, or the clips`);
    problems.push(...filledClipRows().flatMap((row, k) => clipRowProblems(row, k, clothMesh)));
  } else if (!cloth) {
    problems.push(`choose a cloth cache (.pc2, .mdd, .abc) or a zip of OBJ frames${mode === "timeline" ? " for the timeline" : ""}`);
  } else if (clothNeedsMesh(cloth) && !clothMesh) {
    problems.push("choose the cloth's mesh (.obj)");
  }
  if (mode !== "cloth" && params.cycle_frames !== undefined) {
    problems.push(`leave cycle frames empty: ${mode === "timeline" ? "the timeline gives each clip's period" : "each clip's period is its animation's"}`);
  }
  return problems;
}

function clipRowProblems(row, k, sharedMesh) {
  if (!row.clip) return [`name the clip of row ${k + 1} (one of the character's animations)`];
  if (!row.cache) return [`choose the cloth cache of ${row.clip}`];
  if (clothNeedsMesh(row.cache) && !(row.mesh || sharedMesh)) return [`choose the mesh (.obj) of ${row.clip}, or one cloth mesh above for every clip`];
  return [];
}

function chosenItem(kind, text) {
  const remove = el("button", { type: "button", title: `do not use the ${INPUT_LABELS[kind]}`, onclick: () => forgetInput(kind) }, "remove");
  return el("li", { dataset: { input: kind } }, `${INPUT_LABELS[kind]}: `, ...(text ? [text, remove] : [el("span", { class: "muted" }, "none")]));
}

const fileText = (file) => file && `${file.name} (${bytes(file.size)})`;

function clipText(row, sharedMesh) {
  const mesh = row.mesh || (row.cache && clothNeedsMesh(row.cache) ? sharedMesh : null);
  const files = [row.cache, mesh].filter(Boolean).map((file) => file.name);
  return `${row.clip || "(no name)"}: ${files.length ? files.join(" + ") : "no cache"}`;
}

function renderChosen() {
  const mode = inputMode();
  const { character, cloth, clothMesh, timeline, textures } = state.files;
  const clips = filledClipRows();
  const items = [el("li", { dataset: { input: "mode" } }, `bake: ${MODE_LABELS[mode]}`), chosenItem("character", fileText(character))];
  if (mode !== "clip_cloth" || cloth) items.push(chosenItem("cloth", fileText(cloth)));
  if (!cloth || clothNeedsMesh(cloth) || clothMesh) items.push(chosenItem("clothMesh", fileText(clothMesh)));
  if (mode !== "clip_cloth" || timeline) items.push(chosenItem("timeline", fileText(timeline)));
  if (clips.length) items.push(el("li", { dataset: { input: "clips" } }, `clips: ${clips.map((row) => clipText(row, clothMesh)).join("; ")}`));
  items.push(chosenItem("textures", [...textures.keys()].sort().join(", ")));
  $("chosen-files").dataset.mode = mode;
  $("chosen-files").replaceChildren(...items);
}

// The bake form's parameter fields come from the server's own table (GET /v1/params, crowdbake.params.PARAMS),
// so their defaults, choices and bounds are the ones it bakes with. An empty field leaves the server's default.
function paramField(spec) {
  const id = `param-${spec.name}`;
  const title = `${spec.help} (default: ${spec.default_text})`;
  const data = { param: spec.name, kind: spec.kind, default: JSON.stringify(spec.default) };
  let input;
  if (spec.kind === "bool") {
    input = el("input", { id, type: "checkbox", title, dataset: data });
    input.checked = Boolean(spec.default);
  } else if (spec.kind === "str") {
    input = el("select", { id, title, dataset: data },
      el("option", { value: "" }, `default (${spec.default_text})`), ...spec.choices.map((choice) => el("option", { value: choice }, choice)));
  } else {
    const numeric = spec.kind === "int" || spec.kind === "float";
    input = el("input", { id, title, placeholder: spec.default_text, dataset: data, type: numeric ? "number" : "text" });
    if (numeric) {
      if (spec.minimum !== null) input.min = String(spec.minimum);
      if (spec.maximum !== null) input.max = String(spec.maximum);
      input.step = spec.multiple_of ? String(spec.multiple_of) : spec.kind === "int" ? "1" : "any";
    }
  }
  const label = spec.name.replaceAll("_", " ");
  return spec.kind === "bool" ? el("label", { title }, input, ` ${label}`) : el("label", { title }, `${label} `, input);
}

async function loadParamFields() {
  try {
    state.params = await api("/v1/params");
    $("param-fields").replaceChildren(...state.params.map(paramField));
  } catch (error) {
    $("param-fields").replaceChildren(el("span", { class: "error" }, `Cannot load the bake parameters: ${error.message}`));
  }
}

function bakeParams() {
  const params = {};
  for (const spec of state.params || []) {
    const input = $(`param-${spec.name}`);
    if (spec.kind === "bool") {
      if (input.checked !== spec.default) params[spec.name] = input.checked;
      continue;
    }
    const value = input.value.trim();
    if (!value) continue;
    if (spec.kind === "int" || spec.kind === "float") params[spec.name] = Number(value);
    else if (spec.kind === "floats") params[spec.name] = value.split(",").map((item) => Number(item.trim()));
    else if (spec.kind === "name_or_index") params[spec.name] = /^\d+$/.test(value) ? Number(value) : value;
    else params[spec.name] = value;
  }
  return params;
}

async function upload(endpoint, fields, what) {
  const form = new FormData();
  for (const [field, value] of Object.entries(fields)) form.append(field, value);
  showBakeStatus(`Uploading ${what}…`);
  return api(endpoint, "json", { method: "POST", body: form });
}

// The bake request's inputs for `mode` (the fields of POST /v1/bakes), each asset from `convert(endpoint,
// fields, what)`: an upload's id, or the preflight's placeholder. One description of what a mode uploads.
async function requestAssets(mode, params, convert) {
  const { character, cloth, clothMesh, timeline, textures } = state.files;
  const assets = { character: await convert("/v1/assets/characters", { file: character }, character.name), textures: {} };
  if (mode === "clip_cloth") {
    assets.clip_cloth = [];
    for (const row of filledClipRows()) {
      const id = await convert("/v1/assets/cloth", clothUploadFields(row.cache, row.mesh || clothMesh), `${row.clip}: ${row.cache.name}`);
      assets.clip_cloth.push({ clip: row.clip, cloth: id });
    }
  } else {
    const period = params.cycle_frames ? { cycle_frames: String(params.cycle_frames) } : {};
    assets.cloth = await convert("/v1/assets/cloth", { ...clothUploadFields(cloth, clothMesh), ...period }, cloth.name);
  }
  if (mode === "timeline") assets.timeline = await convert("/v1/assets/timelines", { timeline }, timeline.name);
  for (const [name, file] of [...textures.entries()].sort()) assets.textures[name] = await convert("/v1/assets/textures", { file }, name);
  return assets;
}

function bakeRequest(assets, params) {
  return { name: $("bake-name").value.trim(), version: $("bake-version").value.trim(), ...assets, params,
           publish: $("bake-publish").checked, public: $("bake-public").checked };
}

// A refusal for want of an asset (crowdbake.api.bake_inputs.find_assets), as crowdbake submit's is_missing_asset.
function isMissingAsset(item) {
  const field = String(item.field);
  return (["character", "cloth", "timeline"].includes(field) || field.startsWith("textures.") || /^clip_cloth\.\d+\.cloth$/.test(field))
    && String(item.message).startsWith("no ");
}

// Before uploading, the server checks the key, the name, version and parameters: a bake request naming
// assets that do not exist starts nothing and is refused only for them (as crowdbake submit does).
async function preflight(mode, params) {
  try {
    await api("/v1/bakes", "json", { method: "POST", body: bakeRequest(await requestAssets(mode, params, async () => PREFLIGHT_ASSET), params) });
  } catch (error) {
    const errors = (error.problem && error.problem.errors) || [];
    if (!(error.status === 422 && errors.length && errors.every(isMissingAsset))) throw error;
  }
}

async function startBake(event) {
  event.preventDefault();
  const params = bakeParams();
  const mode = inputMode();
  const problems = [...(state.notice ? [NOTICE_PENDING] : []), ...inputProblems(mode, params)];
  if (problems.length) {
    showBakeStatus(`Not baking: ${problems.join("; ")}.`, true);
    return;
  }
  const button = $("start-bake");
  button.disabled = true;
  try {
    showBakeStatus("Checking the bake request…");
    await preflight(mode, params);
    const assets = await requestAssets(mode, params, async (endpoint, fields, what) => (await upload(endpoint, fields, what)).id);
    showBakeStatus("Starting the bake…");
    const bake = await api("/v1/bakes", "json", { method: "POST", body: bakeRequest(assets, params) });
    showBakeStatus(`Bake ${bake.id} ${bake.state}.`);
    $("bake-form-status").dataset.bake = bake.id;
    selectBake(bake.id);
    await refreshJobs();
  } catch (error) {
    showBakeStatus(error.status === 401 || error.status === 403 ? explain(error, "upload and bake") : problemText(error), true);
  } finally {
    button.disabled = false;
  }
}

function acceptDrops(zone, onFiles) {
  for (const name of ["dragenter", "dragover"]) {
    zone.addEventListener(name, (event) => { event.preventDefault(); zone.classList.add("dragging"); });
  }
  zone.addEventListener("dragleave", () => zone.classList.remove("dragging"));
  zone.addEventListener("drop", (event) => {
    event.preventDefault();
    zone.classList.remove("dragging");
    onFiles([...event.dataTransfer.files]);  // copied at once: a drop's data is gone when its event ends
  });
}

function setUpInputs() {
  acceptDrops($("drop-zone"), chooseFiles);
  for (const id of Object.values(FILE_INPUTS)) $(id).addEventListener("change", (event) => chooseFiles([...event.target.files]));
  $("add-clip").addEventListener("click", () => addClipRow());
  $("dismiss-notice").addEventListener("click", () => { showNotice(""); inputsChanged(); });
  renderChosen();
}

// ---------------------------------------------------------------------------------- bake actions

async function bakeAction(action) {
  const id = state.bakeId;
  $("action-status").textContent = `${action}…`;
  try {
    const bake = await api(`/v1/bakes/${encodeURIComponent(id)}/${action}`, "json", { method: "POST" });
    $("action-status").textContent = `${action}: bake is ${bake.state}`;
  } catch (error) {
    $("action-status").textContent = error.status === 401 || error.status === 403 ? explain(error, action === "publish" ? "publish" : "bake") : problemText(error);
  }
  await refreshJobs();
}

async function downloadBundle() {
  const [, , , name, version] = state.detail.bundle_url.split("/");
  $("action-status").textContent = `Downloading ${name}/${version}…`;
  try {
    const blob = await api(`/v1/bundles/${encodeURIComponent(name)}/${encodeURIComponent(version)}/archive.zip`, "blob");
    const url = URL.createObjectURL(blob);
    const link = el("a", { href: url, download: `${name}-${version}.zip` });
    document.body.append(link);
    link.click();
    link.remove();
    setTimeout(() => URL.revokeObjectURL(url), ARCHIVE_URL_LIFETIME_MS);
    $("action-status").textContent = `Downloaded ${name}-${version}.zip (${bytes(blob.size)})`;
    $("action-status").dataset.downloaded = `${name}/${version}`;
  } catch (error) {
    $("action-status").textContent = explain(error, "read");
  }
}

function showActions(bake) {
  const active = bake.state === "queued" || bake.state === "running";
  $("action-cancel").hidden = !active;
  $("action-retry").hidden = !(bake.state === "failed" || bake.state === "cancelled");
  $("action-publish").hidden = !(bake.state === "succeeded" && !bake.bundle_url);
  $("action-download").hidden = !bake.bundle_url;
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
  if (id !== state.bakeId) $("action-status").textContent = "";
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
  state.detail = bake;
  showActions(bake);
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

// The three.js crowd preview of a bundle's engine export (docs/export.md). It opens in this tab, so it
// reads the key from this tab's sessionStorage as the page does: the key never goes into the link.
function previewLink(bundle) {
  const href = `/ui/preview/index.html?export=${encodeURIComponent(bundle.export_url)}`;
  return el("a", { class: "preview-link", href, title: "draw a crowd of this bundle with three.js" }, "Preview crowd");
}

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
        el("td", {}, el("button", { type: "button", onclick: () => selectBundle(bundle.name, bundle.version) }, "atlas"),
          bundle.export_url ? previewLink(bundle) : "")));
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
  // The maps this bundle stores (detail maps only when baked with --detail-map).
  const mapLabels = { uv: "UV map (u red, v green)", normal: "normal map", detail: "detail map" };
  options($("atlas-map"), Object.entries(mapLabels).filter(([kind]) => kind in impostor.maps));
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
    applyZoom();
    const impostor = state.manifest.impostor;
    $("atlas-status").textContent = `${kind} map, layer ${query.get("frame")} of ${impostor.frame_indices.length}: `
      + `${image.naturalWidth}×${image.naturalHeight} texels (tiles of ${impostor.tile_size}²`
      + `${impostor.crop ? `, stored cropped to ${impostor.crop.width}×${impostor.crop.height}` : ""}, `
      + `${impostor.azimuths_deg.length} azimuths × ${impostor.elevations_deg.length} elevations), ${bytes(blob.size)} PNG`;
  };
  image.src = state.atlasUrl;
}

// The atlas at full size (1×: one texel per pixel, scrolled in its viewport) or magnified by a whole
// factor (nearest texel, see style.css); "fit" scales it to the page's width.
function applyZoom() {
  const image = $("atlas-image");
  if (!image.naturalWidth) return;
  const zoom = $("atlas-zoom").value;
  const width = zoom === "fit" ? Math.min(image.naturalWidth, $("atlas-viewport").clientWidth - 2) : Number(zoom) * image.naturalWidth;
  image.style.width = `${width}px`;
  image.dataset.zoom = zoom;
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
    sessionStorage.setItem(KEY_STORAGE, state.key);
  }
  state.bakeId = parts.get("bake") || state.bakeId;
  const bundle = parts.get("bundle");
  setFragment();  // the key leaves the address bar (and the history) at once
  return bundle ? bundle.split("/") : null;
}

function useKey(key) {
  state.key = key;
  if (key) sessionStorage.setItem(KEY_STORAGE, key); else sessionStorage.removeItem(KEY_STORAGE);
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
  $("atlas-zoom").addEventListener("change", applyZoom);
  setUpInputs();
  loadParamFields();
  $("bake-form").addEventListener("submit", startBake);
  $("action-cancel").addEventListener("click", () => bakeAction("cancel"));
  $("action-retry").addEventListener("click", () => bakeAction("retry"));
  $("action-publish").addEventListener("click", () => bakeAction("publish"));
  $("action-download").addEventListener("click", downloadBundle);
  poll(refreshJobs, JOBS_POLL_MS);
  poll(refreshBundles, BUNDLES_POLL_MS);
  if (bundle && bundle.length === 2) selectBundle(bundle[0], bundle[1]);
}

document.addEventListener("DOMContentLoaded", start);
