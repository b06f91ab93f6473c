// ScanStation web page: start scans, follow them live (Server-Sent Events over fetch, so the
// bearer token can ride along), view the mesh in 3D and re-mesh it with a λ slider.
import {
  AmbientLight, Box3, Color, DirectionalLight, DoubleSide, GridHelper, Mesh,
  MeshStandardMaterial, OrbitControls, PerspectiveCamera, PLYLoader, Scene, Vector3,
  WebGLRenderer,
} from "./vendor/three-viewer.min.js";

const $ = (id) => document.getElementById(id);
const TOKEN_KEY = "scanstation-token";
const ACTIVE = new Set(["queued", "starting", "idle", "running", "paused", "stopping", "processing"]);
const ENDED = new Set(["done", "failed", "interrupted"]);
const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));
// "quick preview": one small hidden layer per patch, few epochs, three sectors and never an atlas
// (seconds, not minutes; good enough to check the framing and coverage before a full scan)
const PREVIEW = { max_layers: 1, max_neurons: 8, max_epochs: 5, final_epochs: 20, n_sectors: 3,
                  update_every: 0, min_patch_points: 100, surface: "sectors" };

let selected = null;      // id of the scan shown
let current = null;       // its last known JSON
let stream = null;        // AbortController of its event stream
let meshShown = null;     // "id:version" of the mesh in the viewer
let meshRequest = 0;      // newest mesh load wins

// -- API ---------------------------------------------------------------------------------------
class ApiError extends Error {
  constructor(status, detail) { super(detail); this.status = status; }
}

function headers(extra = {}) {
  const token = sessionStorage.getItem(TOKEN_KEY);
  return token ? { ...extra, Authorization: `Bearer ${token}` } : extra;
}

async function api(path, { method = "GET", body } = {}) {
  const options = { method, headers: headers(body ? { "Content-Type": "application/json" } : {}) };
  if (body !== undefined) options.body = JSON.stringify(body);
  const response = await fetch(`/api/v1${path}`, options);
  if (response.status === 401) askToken();
  if (!response.ok) {
    let detail = `${response.status} ${response.statusText}`;
    try { detail = (await response.json()).detail || detail; } catch (_) { /* not JSON */ }
    throw new ApiError(response.status, detail);
  }
  return response.status === 204 ? null : response.json();
}

function askToken() {
  $("token-form").hidden = false;
  $("token").focus();
}

// -- 3D viewer ---------------------------------------------------------------------------------
const canvas = $("canvas");
const renderer = new WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
const scene = new Scene();
scene.background = new Color(0x20242c);
const camera = new PerspectiveCamera(35, 1, 1, 20000);
camera.up.set(0, 0, 1);  // scans are in the table frame: z up the turntable axis, mm
const light = new DirectionalLight(0xffffff, 2.0);
light.position.set(0.5, -1, 1.5);
camera.add(light);
scene.add(camera, new AmbientLight(0xffffff, 0.7));
const grid = new GridHelper(300, 12, 0x556070, 0x394050);
grid.rotation.x = Math.PI / 2;
scene.add(grid);
const controls = new OrbitControls(camera, canvas);
controls.addEventListener("change", render);
let mesh = null;

function render() { renderer.render(scene, camera); }

function resize() {
  const { clientWidth: w, clientHeight: h } = canvas.parentElement;
  renderer.setSize(w, h, false);
  camera.aspect = w / Math.max(h, 1);
  camera.updateProjectionMatrix();
  render();
}
new ResizeObserver(resize).observe(canvas.parentElement);

function frame(object) {
  const box = new Box3().setFromObject(object);
  const center = box.getCenter(new Vector3());
  const size = Math.max(...box.getSize(new Vector3()).toArray(), 1);
  camera.position.set(center.x + 1.2 * size, center.y - 2.0 * size, center.z + 1.0 * size);
  controls.target.copy(center);
  controls.update();
}

async function loadMesh(scanId, version) {
  const request = ++meshRequest;
  const response = await fetch(`/api/v1/scans/${scanId}/mesh?format=ply`, { headers: headers() });
  if (request !== meshRequest) return;
  if (!response.ok) { $("viewer-note").textContent = "no mesh yet"; return; }
  const geometry = new PLYLoader().parse(await response.arrayBuffer());
  if (request !== meshRequest) return;
  geometry.computeVertexNormals();
  const first = !meshShown || !meshShown.startsWith(`${scanId}:`);
  if (mesh) { scene.remove(mesh); mesh.geometry.dispose(); }
  mesh = new Mesh(geometry, new MeshStandardMaterial({
    color: 0xd8c3a0, roughness: 0.65, side: DoubleSide }));
  scene.add(mesh);
  if (first) frame(mesh);
  render();
  meshShown = `${scanId}:${version}`;
  const faces = geometry.index ? geometry.index.count / 3 : geometry.attributes.position.count / 3;
  $("viewer-note").textContent = `mesh v${version}: ${faces} faces`;
  document.body.dataset.meshVersion = String(version);
}

function clearMesh() {
  if (mesh) { scene.remove(mesh); mesh.geometry.dispose(); mesh = null; }
  meshShown = null;
  delete document.body.dataset.meshVersion;
  $("viewer-note").textContent = "no mesh yet";
  render();
}

// -- scan list and detail ----------------------------------------------------------------------
async function refreshList() {
  const { scans } = await api("/scans");
  const list = $("scans");
  list.replaceChildren(...scans.map((scan) => {
    const item = document.createElement("li");
    item.dataset.id = scan.id;
    item.classList.toggle("selected", scan.id === selected);
    const when = new Date(scan.created * 1000).toLocaleString();
    const p = scan.progress || {};
    item.innerHTML = `<code></code> <span class="badge ${scan.state}">${scan.state}</span>
      <br><small>${when} · ${p.views_done ?? 0}/${p.views_total ?? "?"} views</small>`;
    item.querySelector("code").textContent = scan.id;
    item.addEventListener("click", () => select(scan.id));
    return item;
  }));
}

function showScan(scan) {
  current = scan;
  $("empty").hidden = true;
  $("scan").hidden = false;
  $("scan-id").textContent = scan.id;
  const badge = $("scan-state");
  badge.textContent = scan.state;
  badge.className = `badge ${scan.state}`;
  document.body.dataset.scanState = scan.state;
  const p = scan.progress || {};
  $("progress").value = p.fraction ?? 0;
  $("progress-text").textContent = `${p.views_done ?? 0} / ${p.views_total ?? "?"} views`;
  $("scan-reason").textContent = scan.reason || "";
  const files = scan.files || {};
  const can = {
    pause: scan.state === "running",
    resume: scan.state === "paused" || scan.state === "interrupted",
    cancel: ["queued", "starting", "idle", "running", "paused"].includes(scan.state),
    reprocess: ENDED.has(scan.state) && files.recording_segments > 0,
    delete: !ACTIVE.has(scan.state),
  };
  for (const button of document.querySelectorAll("[data-action]")) {
    button.disabled = !can[button.dataset.action];
  }
  const refinable = ENDED.has(scan.state) && files.mesh;
  $("lam").disabled = $("depth").disabled = !refinable;
  const params = scan.mesh_params || {};
  if (params.lam != null && !refineBusy) {
    $("lam").value = params.lam;
    $("lam-value").textContent = params.lam;
  }
  if (params.depth != null && !refineBusy) $("depth").value = params.depth;
}

async function select(scanId) {
  selected = scanId;
  clearMesh();
  $("log").replaceChildren();
  for (const item of $("scans").children) item.classList.toggle("selected", item.dataset.id === scanId);
  const scan = await api(`/scans/${scanId}`);
  showScan(scan);
  if (scan.files && scan.files.mesh) loadMesh(scanId, scan.mesh_version);
  follow(scanId);
}

async function refreshScan() {
  if (!selected) return;
  const scan = await api(`/scans/${selected}`);
  if (scan.id === selected) showScan(scan);
  return scan;
}

// -- live events -------------------------------------------------------------------------------
function onDocument(scanId, doc) {
  if (scanId !== selected) return;
  const entry = document.createElement("li");
  entry.textContent = summary(doc);
  $("log").prepend(entry);
  if (doc.kind === "progress") {
    $("progress").value = doc.fraction;
    $("progress-text").textContent = `${doc.views_done} / ${doc.views_total} views`;
  } else if (doc.kind === "mesh" || doc.kind === "refined") {
    refreshScan().then((scan) => scan && loadMesh(scan.id, scan.mesh_version));
  } else if (["state", "paused", "resumed", "stop", "error"].includes(doc.kind)) {
    refreshScan().catch(() => {});
    refreshList().catch(() => {});
  }
}

function summary(doc) {
  const time = doc.time ? new Date(doc.time * 1000).toLocaleTimeString() : "";
  const skip = new Set(["kind", "time", "seq", "plan", "calibration", "station", "figures"]);
  const fields = Object.entries(doc).filter(([k]) => !skip.has(k))
    .map(([k, v]) => `${k}=${typeof v === "object" ? JSON.stringify(v) : v}`);
  return `${time} ${doc.kind} ${fields.join(" ")}`;
}

async function follow(scanId) {
  if (stream) stream.abort();
  const controller = new AbortController();
  stream = controller;
  let lastId = 0;
  while (!controller.signal.aborted) {
    try {
      const response = await fetch(`/api/v1/scans/${scanId}/events?after=${lastId}`,
        { headers: headers(), signal: controller.signal });
      if (response.status === 401) { askToken(); return; }
      if (!response.ok) return;
      const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
      let buffer = "";
      for (;;) {
        const { value, done } = await reader.read();
        if (done) break;
        buffer += value;
        let cut;
        while ((cut = buffer.indexOf("\n\n")) >= 0) {
          const block = buffer.slice(0, cut);
          buffer = buffer.slice(cut + 2);
          let data = "";
          for (const line of block.split("\n")) {
            if (line.startsWith("id:")) lastId = Number(line.slice(3));
            else if (line.startsWith("data:")) data += line.slice(5);
          }
          if (data) onDocument(scanId, JSON.parse(data));
        }
      }
    } catch (error) {
      if (controller.signal.aborted) return;
    }
    // The stream ended: the scan ended (done), or the connection dropped (try again).
    const scan = await api(`/scans/${scanId}`).catch(() => null);
    if (controller.signal.aborted) return;
    if (scan && selected === scanId) showScan(scan);
    if (!scan || !ACTIVE.has(scan.state)) return;
    await sleep(1000);
  }
}

// -- actions -----------------------------------------------------------------------------------
$("new-scan").addEventListener("submit", async (event) => {
  event.preventDefault();
  const form = event.target;
  const views = Number(form.views.value);
  const body = { plan: {
    angles: Array.from({ length: views }, (_, i) => (360 * i) / views),
    frames_per_view: Number(form.frames.value),
  } };
  if (form.reconstruction.value === "preview") body.plan.reconstruction = PREVIEW;
  if (form.reconstruction.value === "none") body.plan.reconstruction = null;
  for (const name of ["object", "camera_url", "turntable_url"]) {
    if (form[name].value.trim()) body[name] = form[name].value.trim();
  }
  $("form-error").textContent = "";
  try {
    const scan = await api("/scans", { method: "POST", body });
    await refreshList();
    await select(scan.id);
  } catch (error) {
    $("form-error").textContent = error.message;
  }
});

for (const button of document.querySelectorAll("[data-action]")) {
  button.addEventListener("click", async () => {
    const action = button.dataset.action;
    try {
      if (action === "delete") {
        await api(`/scans/${selected}`, { method: "DELETE" });
        selected = null;
        $("scan").hidden = true;
        $("empty").hidden = false;
        if (stream) stream.abort();
      } else {
        const scan = await api(`/scans/${selected}/${action}`, { method: "POST" });
        showScan({ ...current, ...scan });
        if (action === "resume" || action === "reprocess") follow(selected);
      }
      await refreshList();
    } catch (error) {
      $("scan-reason").textContent = error.message;
    }
  });
}

let refineWanted = null;
let refineBusy = false;

function requestRefine() {
  refineWanted = { lam: Number($("lam").value), depth: Number($("depth").value) };
  if (!refineBusy) runRefines();
}

async function runRefines() {
  refineBusy = true;
  while (refineWanted) {  // only the newest wish is sent once the previous answer is back
    const params = refineWanted;
    refineWanted = null;
    $("refine-status").textContent = `re-meshing (λ ${params.lam}, depth ${params.depth})…`;
    try {
      const scan = await api(`/scans/${selected}/refine`, { method: "POST", body: params });
      await loadMesh(scan.id, scan.mesh_version);
      $("refine-status").textContent = `mesh v${scan.mesh_version}: λ ${scan.mesh_params.lam}, ` +
        `depth ${scan.mesh_params.depth}`;
      current = scan;
    } catch (error) {
      $("refine-status").textContent = error.message;
    }
  }
  refineBusy = false;
}

$("lam").addEventListener("input", () => {
  $("lam-value").textContent = $("lam").value;
  requestRefine();
});
$("depth").addEventListener("change", requestRefine);

for (const link of document.querySelectorAll("[data-file]")) {
  link.href = "#";
  link.addEventListener("click", async (event) => {  // fetch, so the token is sent
    event.preventDefault();
    const response = await fetch(`/api/v1/scans/${selected}/${link.dataset.file}`,
      { headers: headers() });
    if (!response.ok) { $("scan-reason").textContent = `${link.textContent}: not available`; return; }
    const disposition = response.headers.get("Content-Disposition") || "";
    const name = (disposition.match(/filename="?([^";]+)"?/) || [])[1] || link.textContent;
    const url = URL.createObjectURL(await response.blob());
    const anchor = Object.assign(document.createElement("a"), { href: url, download: name });
    anchor.click();
    setTimeout(() => URL.revokeObjectURL(url), 10000);
  });
}

$("token-form").addEventListener("submit", (event) => {
  event.preventDefault();
  sessionStorage.setItem(TOKEN_KEY, $("token").value.trim());
  $("token-form").hidden = true;
  refreshList().catch(() => {});
});

async function health() {
  try {
    const response = await fetch("/healthz");
    const ok = response.ok;
    $("health").textContent = ok ? "daemon up" : `daemon: ${response.status}`;
    $("health").className = `badge ${ok ? "ok" : "down"}`;
  } catch (_) {
    $("health").textContent = "daemon unreachable";
    $("health").className = "badge down";
  }
}

health();
setInterval(health, 10000);
refreshList().catch(() => {});
setInterval(() => refreshList().catch(() => {}), 5000);
resize();
document.body.dataset.ready = "1";
