// The arcloud viewer: one map's objects, live. It reads GET v1/maps/{map}/events (server-sent events, read
// with fetch) and draws each object
// as its oriented box, coloured by class, with the devices' last cameras. A click on a box or its label shows
// the object's details (window.arcloudViewer.select(id) does the same). <body data-objects> is the number of
// boxes drawn (what the tests read; data-devices and data-voxels count cameras and point sets, data-points the
// points drawn, data-selected the id whose details show). Behind the boxes, the room: every object's voxels
// (tentative ones and those the filters hide included) as points in their mean colour.
// No key goes in a URL or in the page's storage: a viewer session's HttpOnly cookie authenticates every read. A
// ticket (from the URL's fragment, #ticket=T, which no server sees; or drawn with a key typed into the form, then
// forgotten) is traded once for that cookie. A label that would overlap a nearer one is hidden.
// See docs/service.md, "Web viewer".
import * as THREE from "three";
import { OrbitControls } from "three/addons/OrbitControls.js";
import { CSS2DObject, CSS2DRenderer } from "three/addons/CSS2DRenderer.js";

const CLASS_COLOURS = { chair: "#ff5a36", table: "#2f9bff", laptop: "#ffd21f", couch: "#34d399", tv: "#c86bff" };
const OTHER_COLOURS = ["#f472b6", "#a3e635", "#fb923c", "#22d3ee", "#e879f9"];
const DEVICE_COLOUR = "#7dd3fc";
const FRUSTUM_DEPTH_M = 0.3; // how deep a device's camera is drawn
const DEVICE_OLD_S = 30; // a device silent this long is drawn faded
const RETRY_MS = 2000; // between reconnections (the stream's `retry:` overrides it)
const MISSING_MAP_RETRY_MS = 5000; // a map with no frame yet: ask again this often
const VOXEL_FETCHES = 4; // voxel requests in flight at once
const MAX_POINTS = 200_000; // the room's points drawn in all: objects fetched past it are left out
const POINTS_PER_OBJECT = 20_000; // an object with more voxels is drawn with an even sample of them
const CLICK_SLOP_PX = 4; // a pointer that moved further between down and up dragged the view: no pick
const FACE_OPACITY = { confirmed: 0.2, tentative: 0.08, selected: 0.45 };

const $ = (id) => document.getElementById(id);

// --- what the page knows -------------------------------------------------------------------------------
const state = {
  map: "",
  objects: new Map(), // id -> object (every status: the tentative toggle filters)
  devices: new Map(), // device id -> its last frame
  hidden: new Set(), // classes unticked in the legend
  minScore: 0,
  showTentative: false,
  showLabels: true,
  showVoxels: true, // the room's points
  showCameras: true,
  selected: null, // id of the object whose details show
  labelVotes: new Map(), // id -> { asked, version, votes } of GET .../objects/{id}: the selected object's label votes
  userMoved: false, // the view follows the map until the user moves it
  connection: null, // AbortController of the open stream
};

// --- the scene (display frame: z up; `world` holds map coordinates) -------------------------------------
const container = $("scene");
const renderer = new THREE.WebGLRenderer({ antialias: true });
renderer.setPixelRatio(window.devicePixelRatio);
container.appendChild(renderer.domElement);
const labelRenderer = new CSS2DRenderer();
labelRenderer.domElement.className = "labels";
container.appendChild(labelRenderer.domElement);

const scene = new THREE.Scene();
scene.background = new THREE.Color("#15181d");
const world = new THREE.Group(); // its rotation takes the map's up to +z (the snapshot's world2gravity)
scene.add(world);
const boxes = new THREE.Group();
const voxels = new THREE.Group();
const cameras = new THREE.Group();
world.add(boxes, voxels, cameras);
const grid = new THREE.GridHelper(20, 20, 0x3a4048, 0x262a31);
grid.rotation.x = Math.PI / 2; // GridHelper lies in xz; the floor here is xy
scene.add(grid);

const camera = new THREE.PerspectiveCamera(50, 1, 0.01, 500);
camera.up.set(0, 0, 1);
camera.position.set(-2, -4, 3);
const controls = new OrbitControls(camera, labelRenderer.domElement);
controls.enableDamping = true;
controls.addEventListener("change", requestRender);
controls.addEventListener("start", () => (state.userMoved = true));

let renderQueued = false;
function requestRender() {
  if (renderQueued) return;
  renderQueued = true;
  requestAnimationFrame(() => {
    renderQueued = false;
    if (controls.update()) requestRender(); // still easing
    renderer.render(scene, camera);
    labelRenderer.render(scene, camera);
    declutterLabels();
  });
}

// A label whose screen rectangle meets a label kept before it is hidden (class "overlapped"); the selected
// object's label is kept first, then the nearer to the camera. The rectangles are all read before any is
// hidden: one layout a render.
function declutterLabels() {
  const labels = [];
  for (const group of [boxes, cameras]) {
    for (const child of group.children) {
      const label = child.userData.label;
      if (label?.visible && label.element.style.display !== "none") labels.push(label); // CSS2DRenderer hides those out of view
    }
  }
  const at = new THREE.Vector3();
  const order = labels.map((label) => ({
    label,
    first: label.parent.userData.id === state.selected, // a device's group has no id
    distance: label.getWorldPosition(at).distanceToSquared(camera.position),
    rect: label.element.getBoundingClientRect(),
  }));
  order.sort((a, b) => b.first - a.first || a.distance - b.distance);
  const kept = [];
  for (const { label, rect } of order) {
    const overlaps = kept.some((k) => rect.left < k.right && k.left < rect.right && rect.top < k.bottom && k.top < rect.bottom);
    label.element.classList.toggle("overlapped", overlaps);
    if (!overlaps) kept.push(rect);
  }
}

function resize() {
  const { clientWidth: w, clientHeight: h } = container;
  renderer.setSize(w, h);
  labelRenderer.setSize(w, h);
  camera.aspect = w / Math.max(1, h);
  camera.updateProjectionMatrix();
  requestRender();
}
window.addEventListener("resize", resize);

// --- drawing ---------------------------------------------------------------------------------------------
const colourCache = new Map();
function classColour(label) {
  if (CLASS_COLOURS[label]) return CLASS_COLOURS[label];
  if (!colourCache.has(label)) colourCache.set(label, OTHER_COLOURS[colourCache.size % OTHER_COLOURS.length]);
  return colourCache.get(label);
}

function shown(o) {
  return (
    (o.obb || o.aabb) &&
    !state.hidden.has(o.label) &&
    o.score >= state.minScore &&
    (state.showTentative || o.status === "confirmed")
  );
}

function disposeTree(root) {
  root.traverse((node) => {
    node.geometry?.dispose();
    node.material?.dispose();
    if (node.isCSS2DObject) node.element.remove();
  });
}

function clearGroup(group) {
  for (const child of [...group.children]) {
    group.remove(child);
    disposeTree(child);
  }
}

// {center, size, yaw} of the object's OBB, or of its AABB (yaw 0); null for an object with neither.
function boxShape(o) {
  if (o.obb) return { center: o.obb.center, size: o.obb.size, yaw: o.obb.yaw_rad };
  if (!o.aabb) return null;
  const { min, max } = o.aabb;
  return { center: min.map((v, i) => (v + max[i]) / 2), size: min.map((v, i) => max[i] - v), yaw: 0 };
}

// A box: faint faces and solid edges (dashed when tentative), centred on the OBB, turned by its yaw about up.
function boxObject(o) {
  const colour = new THREE.Color(classColour(o.label));
  const tentative = o.status !== "confirmed";
  const { center, size, yaw } = boxShape(o);
  const geometry = new THREE.BoxGeometry(...size);
  const group = new THREE.Group();
  const faces = new THREE.Mesh(
    geometry,
    new THREE.MeshBasicMaterial({ color: colour, transparent: true, opacity: FACE_OPACITY[o.status], depthWrite: false }),
  );
  const edgeMaterial = tentative
    ? new THREE.LineDashedMaterial({ color: colour, dashSize: 0.05, gapSize: 0.04 })
    : new THREE.LineBasicMaterial({ color: colour });
  const edges = new THREE.LineSegments(new THREE.EdgesGeometry(geometry), edgeMaterial);
  if (tentative) edges.computeLineDistances();
  group.add(faces, edges);
  group.position.set(...center);
  // box2world = world2gravity^T Rz(yaw); `world` applies world2gravity, so the box turns by the rest.
  const yawTurn = new THREE.Quaternion().setFromAxisAngle(new THREE.Vector3(0, 0, 1), yaw);
  group.quaternion.copy(world.quaternion).invert().multiply(yawTurn);
  const text = document.createElement("div");
  text.className = tentative ? "label tentative" : "label";
  text.dataset.id = o.id; // a click on the label picks the object
  text.textContent = `${o.label} ${o.score.toFixed(2)}${tentative ? " (tentative)" : ""}`;
  const label = new CSS2DObject(text);
  label.position.set(0, 0, size[2] / 2);
  label.visible = state.showLabels;
  group.add(label);
  group.userData = { id: o.id, version: o.version, status: o.status, faces, label };
  markSelected(group);
  return group;
}

// A device's camera: apex at its centre, a rectangle FRUSTUM_DEPTH_M ahead (OpenCV axes: z forward, y down).
function deviceObject(d) {
  const { fx, fy, cx, cy } = d.intrinsics;
  const z = FRUSTUM_DEPTH_M;
  const corner = (u, v) => new THREE.Vector3(((u - cx) / fx) * z, ((v - cy) / fy) * z, z);
  const [a, b, c, e] = [corner(0, 0), corner(d.width, 0), corner(d.width, d.height), corner(0, d.height)];
  const o = new THREE.Vector3();
  const points = [o, a, o, b, o, c, o, e, a, b, b, c, c, e, e, a];
  const old = Date.now() / 1000 - d.received_at_s > DEVICE_OLD_S;
  const lines = new THREE.LineSegments(
    new THREE.BufferGeometry().setFromPoints(points),
    new THREE.LineBasicMaterial({ color: DEVICE_COLOUR, transparent: old, opacity: old ? 0.35 : 1 }),
  );
  const group = new THREE.Group();
  group.add(lines);
  const pose = new THREE.Matrix4().set(...d.cam2world); // row-major, as sent
  pose.decompose(group.position, group.quaternion, group.scale);
  const text = document.createElement("div");
  text.className = "label device";
  text.textContent = d.device_id;
  const label = new CSS2DObject(text);
  label.visible = state.showLabels;
  group.add(label);
  group.userData = { label };
  return group;
}

function redrawObject(o) {
  const old = boxes.children.find((child) => child.userData.id === o.id);
  if (old) {
    boxes.remove(old);
    disposeTree(old);
  }
  if (shown(o)) boxes.add(boxObject(o));
}

function redrawAll() {
  clearGroup(boxes);
  for (const o of state.objects.values()) if (shown(o)) boxes.add(boxObject(o));
  redrawDevices();
}

function redrawDevices() {
  clearGroup(cameras);
  if (state.showCameras) for (const d of state.devices.values()) cameras.add(deviceObject(d));
}

// After any change: counts, legend, voxels, view.
function refresh() {
  document.body.dataset.objects = String(boxes.children.length);
  document.body.dataset.devices = String(cameras.children.length);
  countPoints();
  $("drawn").textContent = boxes.children.length;
  $("known").textContent = state.objects.size;
  renderLegend();
  showDetails();
  syncVoxels();
  if (!state.userMoved) fitView();
  requestRender();
}

function renderLegend() {
  const counts = new Map();
  for (const o of state.objects.values()) {
    if (!state.showTentative && o.status !== "confirmed") continue;
    counts.set(o.label, (counts.get(o.label) || 0) + 1);
  }
  const list = $("legend");
  list.replaceChildren();
  for (const label of [...new Set([...counts.keys(), ...state.hidden])].sort()) {
    const item = document.createElement("li");
    const row = document.createElement("label");
    const box = document.createElement("input");
    box.type = "checkbox";
    box.checked = !state.hidden.has(label);
    box.dataset.label = label;
    box.addEventListener("change", () => {
      if (box.checked) state.hidden.delete(label);
      else state.hidden.add(label);
      redrawAll();
      refresh();
    });
    const swatch = document.createElement("span");
    swatch.className = "swatch";
    swatch.style.background = classColour(label);
    const name = document.createElement("span");
    name.textContent = label;
    const count = document.createElement("span");
    count.className = "count";
    count.textContent = counts.get(label) || 0;
    row.append(box, swatch, name, count);
    item.append(row);
    list.append(item);
  }
}

function fitView() {
  const bounds = new THREE.Box3();
  for (const group of [boxes, cameras]) if (group.children.length) bounds.expandByObject(group);
  if (bounds.isEmpty()) bounds.set(new THREE.Vector3(-2, -2, 0), new THREE.Vector3(2, 2, 1));
  const centre = bounds.getCenter(new THREE.Vector3());
  const radius = Math.max(0.5, bounds.getSize(new THREE.Vector3()).length() / 2);
  const distance = (radius / Math.sin(THREE.MathUtils.degToRad(camera.fov / 2))) * 1.1;
  const direction = new THREE.Vector3(-0.4, -1, 1).normalize();
  camera.position.copy(centre).addScaledVector(direction, distance);
  camera.near = distance / 100;
  camera.far = distance * 10;
  camera.updateProjectionMatrix();
  controls.target.copy(centre);
  controls.update();
}

// --- the selected object: its details, from the events (the fields of GET v1/maps/{map}/objects/{id}), and its
// label votes, which the events do not carry: read from that route for each version the details show -----------
function select(id) {
  state.selected = state.objects.has(id) ? id : null;
  for (const group of boxes.children) markSelected(group);
  showDetails();
  requestRender();
  return state.selected !== null;
}

function markSelected(group) {
  const { id, status, faces, label } = group.userData;
  faces.material.opacity = FACE_OPACITY[id === state.selected ? "selected" : status];
  label.element.classList.toggle("selected", id === state.selected);
}

function showDetails() {
  if (!state.objects.has(state.selected)) state.selected = null; // removed, or another map
  const o = state.objects.get(state.selected);
  document.body.dataset.selected = o ? String(o.id) : "";
  $("details").hidden = !o;
  if (!o) return;
  $("details-label").textContent = o.label;
  $("details-id").textContent = `#${o.id}`;
  const size = boxShape(o)?.size;
  const fields = [
    ["score", o.score.toFixed(2)],
    ["status", o.status],
    ["frames", o.n_frames],
    ["devices", o.n_devices],
    ["voxels", o.n_voxels],
    ["box (m)", size ? size.map((v) => v.toFixed(2)).join(" × ") : "none"],
    ["votes", labelVotesText(o)],
    ["version", o.version],
    ["updated", o.updated_at ?? "unknown"],
  ];
  $("details-fields").replaceChildren(
    ...fields.flatMap(([name, value]) => {
      const term = document.createElement("dt");
      term.textContent = name;
      const text = document.createElement("dd");
      text.textContent = value;
      text.dataset.field = name;
      return [term, text];
    }),
  );
}

// Each class's share of the object's label votes, most first ("chair 0.92, table 0.08"); "…" while they are read.
function labelVotesText(o) {
  const entry = state.labelVotes.get(o.id);
  if (!entry || (entry.version < o.version && !(entry.loading && entry.asked === o.version))) loadLabelVotes(o);
  if (!entry?.votes) return entry?.failed ? "unavailable" : "…";
  const total = Object.values(entry.votes).reduce((sum, v) => sum + v, 0);
  const shares = Object.entries(entry.votes).map(([name, v]) => `${name} ${(v / total).toFixed(2)}`);
  return shares.join(", ") || "none";
}

async function loadLabelVotes(o) {
  const previous = state.labelVotes.get(o.id);
  state.labelVotes.set(o.id, { ...previous, asked: o.version, version: previous?.version ?? -1, loading: true });
  try {
    const response = await fetch(`v1/maps/${encodeURIComponent(state.map)}/objects/${o.id}`, { cache: "no-store" });
    if (!response.ok) throw new Error(`label votes of object ${o.id}: HTTP ${response.status}`);
    const detail = await response.json(); // its version may be newer than the events' yet: kept until they catch up
    state.labelVotes.set(o.id, { asked: o.version, version: detail.version, votes: detail.label_votes });
  } catch (error) {
    console.warn(error);
    state.labelVotes.set(o.id, { asked: o.version, version: o.version, failed: true }); // asked again when it changes
  }
  if (state.selected === o.id) showDetails();
}

// A click (a pointer that went down and up in place) on a label picks its object, else the nearest box face
// under it; on nothing, it clears the selection. OrbitControls captures the pointer, so the label is the
// target of pointerdown, not of pointerup.
const raycaster = new THREE.Raycaster();
let pointerDown = null;
labelRenderer.domElement.addEventListener("pointerdown", (event) => {
  pointerDown = { x: event.clientX, y: event.clientY, target: event.target };
});
labelRenderer.domElement.addEventListener("pointerup", (event) => {
  const down = pointerDown;
  pointerDown = null;
  if (!down || Math.hypot(event.clientX - down.x, event.clientY - down.y) > CLICK_SLOP_PX) return;
  const label = down.target.closest?.(".label[data-id]");
  if (label) return select(Number(label.dataset.id));
  const rect = labelRenderer.domElement.getBoundingClientRect();
  const pointer = new THREE.Vector2(((event.clientX - rect.left) / rect.width) * 2 - 1, 1 - ((event.clientY - rect.top) / rect.height) * 2);
  raycaster.setFromCamera(pointer, camera);
  const [hit] = raycaster.intersectObjects(boxes.children.map((group) => group.userData.faces), false);
  select(hit ? hit.object.parent.userData.id : null);
});

// --- the room's points: each object's voxels (GET v1/maps/{map}/objects/{id}?voxels=true, once a version) ---
const voxelState = new Map(); // id -> {version, points} drawn, {version, loading: true} or {version, failed: true}
let voxelFetches = 0;
let voxelPauseUntil = 0; // after a 429: no voxel request before this (ms), as Retry-After says
let pointCount = 0; // points drawn, of every object

// 0-255 sRGB -> the renderer's linear working space (vertex colours are taken as linear).
const LINEAR = Float32Array.from({ length: 256 }, (_, v) => new THREE.Color().setRGB(v / 255, v / 255, v / 255, THREE.SRGBColorSpace).r);

function countPoints() {
  pointCount = 0;
  for (const points of voxels.children) pointCount += points.geometry.getAttribute("position").count;
  document.body.dataset.voxels = String(voxels.children.length);
  document.body.dataset.points = String(pointCount);
}

// An object's voxels (ObjectDetail.voxels) as at most `budget` points, each in its voxel's mean colour (the
// class colour where the object has none); null when the budget is spent.
function pointsObject(detail, budget) {
  const { centers, colors, voxel_size_m } = detail.voxels;
  const n = Math.min(centers.length, POINTS_PER_OBJECT, budget);
  if (n <= 0) return null;
  const step = centers.length / n; // an even sample when the object has more voxels than it may draw
  const positions = new Float32Array(n * 3);
  const rgb = new Float32Array(n * 3);
  const flat = new THREE.Color(classColour(detail.label));
  for (let i = 0; i < n; i++) {
    const j = Math.floor(i * step);
    positions.set(centers[j], i * 3);
    if (colors) rgb.set([LINEAR[colors[j][0]], LINEAR[colors[j][1]], LINEAR[colors[j][2]]], i * 3);
    else rgb.set([flat.r, flat.g, flat.b], i * 3);
  }
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(positions, 3));
  geometry.setAttribute("color", new THREE.BufferAttribute(rgb, 3));
  return new THREE.Points(geometry, new THREE.PointsMaterial({ vertexColors: true, size: voxel_size_m * 0.8, sizeAttenuation: true }));
}

function syncVoxels() {
  const wanted = state.showVoxels ? [...state.objects.values()] : [];
  const wantedIds = new Set(wanted.map((o) => o.id));
  for (const [id, entry] of voxelState) {
    if (!wantedIds.has(id)) {
      if (entry.points) {
        voxels.remove(entry.points);
        disposeTree(entry.points);
      }
      voxelState.delete(id);
    }
  }
  countPoints();
  if (Date.now() < voxelPauseUntil) return;
  for (const o of wanted) {
    const entry = voxelState.get(o.id);
    if (voxelFetches >= VOXEL_FETCHES) break;
    if (entry && (entry.loading || entry.version === o.version)) continue; // in flight, drawn, or failed at this version
    if (pointCount >= MAX_POINTS && !entry?.points) continue; // no room left for another object's points
    loadVoxels(o);
  }
}

async function loadVoxels(o) {
  const previous = voxelState.get(o.id);
  voxelState.set(o.id, { ...previous, version: o.version, loading: true });
  voxelFetches += 1;
  try {
    const response = await fetch(`v1/maps/${encodeURIComponent(state.map)}/objects/${o.id}?voxels=true`, { cache: "no-store" });
    if (response.status === 429) {
      const wait_s = Number(response.headers.get("Retry-After")) || 1;
      voxelPauseUntil = Date.now() + wait_s * 1000;
      setTimeout(syncVoxels, wait_s * 1000);
      if (voxelState.has(o.id)) voxelState.set(o.id, { ...voxelState.get(o.id), loading: false, version: previous?.version }); // asked again after the pause
      return;
    }
    if (!response.ok) throw new Error(`voxels of object ${o.id}: HTTP ${response.status}`);
    const detail = await response.json();
    const entry = voxelState.get(o.id);
    if (!entry || !state.showVoxels) return;
    if (entry.points) {
      voxels.remove(entry.points);
      disposeTree(entry.points);
      countPoints();
    }
    const points = pointsObject(detail, MAX_POINTS - pointCount);
    if (points) voxels.add(points);
    voxelState.set(o.id, { version: detail.version, points });
    countPoints();
  } catch (error) {
    console.warn(error);
    if (voxelState.has(o.id)) voxelState.set(o.id, { ...voxelState.get(o.id), loading: false, failed: true }); // not asked again until it changes
  } finally {
    voxelFetches -= 1;
    requestRender();
  }
  syncVoxels(); // newer versions, or objects waiting for a free fetch
}

// --- the event stream ------------------------------------------------------------------------------------
class HttpError extends Error {
  constructor(status, detail) {
    super(detail);
    this.status = status;
  }
}

async function refusal(response) {
  let detail = `HTTP ${response.status}`;
  try {
    detail = (await response.json()).detail || detail;
  } catch {}
  return new HttpError(response.status, detail);
}

// A viewer session of the map: a ticket drawn with `key` (if typed), or `ticket`, traded for its cookie.
async function openSession(key, ticket) {
  const base = `v1/maps/${encodeURIComponent(state.map)}`;
  if (key) {
    const drawn = await fetch(`${base}/viewer-tickets`, { method: "POST", headers: { Authorization: `Bearer ${key}` }, cache: "no-store" });
    if (drawn.status === 404) return; // auth none: no ticket needed
    if (!drawn.ok) throw await refusal(drawn);
    ticket = (await drawn.json()).ticket;
  }
  if (!ticket) return; // a session's cookie from before, or auth none
  const traded = await fetch(`${base}/viewer-session`, {
    method: "POST",
    headers: { "Content-Type": "application/json" },
    body: JSON.stringify({ ticket }),
    cache: "no-store",
  });
  if (!traded.ok) throw await refusal(traded);
}

function setStatus(text, kind) {
  $("status").textContent = text;
  document.body.dataset.state = kind;
}

function handle(name, data) {
  if (name === "snapshot") {
    state.objects = new Map(data.objects.map((o) => [o.id, o]));
    state.devices = new Map(data.devices.map((d) => [d.device_id, d]));
    const m = data.world2gravity;
    world.quaternion.setFromRotationMatrix(new THREE.Matrix4().set(m[0], m[1], m[2], 0, m[3], m[4], m[5], 0, m[6], m[7], m[8], 0, 0, 0, 0, 1));
    redrawAll();
  } else if (name === "upsert") {
    state.objects.set(data.id, data);
    redrawObject(data);
  } else if (name === "removed") {
    state.objects.delete(data.id);
    state.labelVotes.delete(data.id);
    redrawObject({ id: data.id });
  } else if (name === "device") {
    state.devices.set(data.device_id, data);
    redrawDevices();
  } else if (name === "device_removed") {
    state.devices.delete(data.device_id);
    redrawDevices();
  } else if (name === "refused") {
    throw new HttpError(403, data.detail);
  } else return;
  refresh();
}

// Reads one stream until it ends; calls handle(name, data) for each event. Returns the server's retry (ms).
async function readStream(signal) {
  const url = `v1/maps/${encodeURIComponent(state.map)}/events?include=tentative`;
  const response = await fetch(url, { signal, cache: "no-store" });
  if (!response.ok) throw await refusal(response);
  setStatus(`Live: map ${state.map}`, "live");
  const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
  let buffer = "";
  let retry = RETRY_MS;
  for (;;) {
    const { value, done } = await reader.read();
    if (done) return retry;
    buffer += value;
    let end;
    while ((end = buffer.indexOf("\n\n")) >= 0) {
      const block = buffer.slice(0, end);
      buffer = buffer.slice(end + 2);
      let name = "message";
      const data = [];
      for (const raw of block.split("\n")) {
        const line = raw.endsWith("\r") ? raw.slice(0, -1) : raw;
        if (!line || line.startsWith(":")) continue; // a comment: keep-alive
        const colon = line.indexOf(":");
        const field = colon < 0 ? line : line.slice(0, colon);
        const text = colon < 0 ? "" : line.slice(colon + 1).replace(/^ /, "");
        if (field === "event") name = text;
        else if (field === "data") data.push(text);
        else if (field === "retry" && /^\d+$/.test(text)) retry = Number(text);
      }
      if (data.length) handle(name, JSON.parse(data.join("\n")));
    }
  }
}

async function connect() {
  state.connection?.abort();
  const controller = new AbortController();
  state.connection = controller;
  state.objects.clear();
  state.devices.clear();
  state.labelVotes.clear();
  redrawAll();
  refresh();
  while (!controller.signal.aborted) {
    let wait = RETRY_MS;
    setStatus(`Connecting to map ${state.map}…`, "connecting");
    try {
      wait = await readStream(controller.signal);
      setStatus("The stream ended; reconnecting…", "connecting");
    } catch (error) {
      if (controller.signal.aborted) return;
      if (error.status === 401 || error.status === 403) {
        refused(error);
        return;
      }
      if (error.status === 404) wait = MISSING_MAP_RETRY_MS;
      setStatus(`${error.message}; trying again in ${Math.round(wait / 1000)} s`, "error");
    }
    await new Promise((done) => setTimeout(done, wait));
  }
}

function refused(error) {
  setStatus(`Refused: ${error.message}. Enter a key that may read map ${state.map}, or open a new viewer link.`, "error");
}

// --- controls --------------------------------------------------------------------------------------------
function bindControls() {
  const minScore = $("min-score");
  minScore.addEventListener("input", () => {
    state.minScore = Number(minScore.value);
    $("min-score-value").textContent = state.minScore.toFixed(2);
    redrawAll();
    refresh();
  });
  for (const [id, key] of [["tentative", "showTentative"], ["labels", "showLabels"], ["voxels", "showVoxels"], ["cameras", "showCameras"]]) {
    const box = $(id);
    state[key] = box.checked;
    box.addEventListener("change", () => {
      state[key] = box.checked;
      redrawAll();
      refresh();
    });
  }
  $("details-close").addEventListener("click", () => select(null));
  $("fit").addEventListener("click", () => {
    state.userMoved = false;
    fitView();
    requestRender();
  });
  $("connect").addEventListener("submit", (event) => {
    event.preventDefault();
    openMap($("map").value.trim(), $("key").value.trim(), "");
  });
}

async function openMap(map, key, ticket) {
  state.connection?.abort();
  state.map = map;
  const url = new URL(window.location.href);
  url.search = map ? `?map=${encodeURIComponent(map)}` : "";
  url.hash = ""; // a used ticket is worth nothing, but leaves the address bar and history anyway
  history.replaceState(null, "", url);
  $("map").value = map;
  $("key").value = ""; // forgotten once it drew its ticket
  if (!map) return setStatus("Enter a map id.", "error");
  setStatus(`Opening map ${map}…`, "connecting");
  try {
    await openSession(key, ticket);
  } catch (error) {
    return refused(error);
  }
  connect();
}

bindControls();
resize();
window.arcloudViewer = { select }; // for tests and the console: the click's own code path
const params = new URLSearchParams(window.location.search);
openMap(params.get("map") || "", "", new URLSearchParams(window.location.hash.slice(1)).get("ticket") || "");
