// cubecloud share: one trained scene drawn by Spark on three.js, with anatomical cuts, a ruler in
// millimetres and the patient's axes. Everything the page needs is in the page: the scene as SPZ
// (base64) and what cubecloud knew of it (scene-info), so it opens from file:// with no network.
(async function () {
  "use strict";
  const state = { ready: false, error: null, frames: 0, distanceMm: null, picks: [], redraws: 0 };
  window.cubecloud = state; // what tests and a curious person at the console read
  const status = document.getElementById("status");
  try {
    await main(state, status);
  } catch (error) {
    state.error = String(error && error.stack ? error.stack : error);
    status.textContent = "This page could not draw the scene: " + error;
  }
})();

async function main(state, status) {
  const { THREE, OrbitControls, SparkRenderer, SplatMesh } = window.CubecloudVendor;
  const info = JSON.parse(document.getElementById("scene-info").textContent);
  if (new URLSearchParams(location.search).has("bare")) document.body.classList.add("bare"); // index.html?bare: the picture alone
  const canvas = document.getElementById("scene");
  const renderer = new THREE.WebGLRenderer({ canvas, antialias: false, preserveDrawingBuffer: true });
  renderer.setClearColor(0x000000, 1);
  const scene = new THREE.Scene();
  // A scene trained with Mip-Splatting's 2D filter is drawn with it (opacity-compensated blur);
  // a plain 3DGS scene with the reference's 0.3 px² dilation.
  scene.add(new SparkRenderer({ renderer, preBlurAmount: info.blur.dilation, blurAmount: info.blur.mip }));

  const camera = new THREE.PerspectiveCamera(info.camera.fovY, 1, 0.001, 100);
  camera.up.fromArray(info.camera.up); // before the controls, which orbit about it
  const controls = new OrbitControls(camera, canvas);
  const resetView = () => {
    camera.position.fromArray(info.camera.position);
    controls.target.fromArray(info.camera.target);
    camera.lookAt(controls.target);
    controls.update();
  };
  resetView();

  const bytes = base64Bytes(document.getElementById("scene-spz").textContent);
  const mesh = new SplatMesh({ fileBytes: bytes, fileType: "spz", splatEncoding: info.encoding });
  await mesh.initialized;
  scene.add(mesh);
  const splats = readSplats(mesh.packedSplats);

  const cut = setUpCut(info, splats, mesh);
  if (info.scalar) {
    const drawn = await readScalar(document.getElementById("scene-scalar").textContent, splats.count);
    const transfer = setUpTransfer(info.scalar, drawn, splats, cut, camera);
    // A chord-length scene's opacities follow the camera: drawn again once it has come to rest.
    let rest = null;
    if (info.scalar.chordLengths) controls.addEventListener("change", () => {
      clearTimeout(rest);
      rest = setTimeout(() => {
        transfer.lookFrom();
        state.redraws += 1;
      }, CAMERA_REST_MS);
    });
    Object.assign(state, { setTransfer: transfer.set, opacities: () => Array.from(splats.opacity) });
  }
  const ruler = setUpRuler(THREE, scene, camera, canvas, info, splats, cut, state);
  const labels = setUpAxisLabels(THREE, info);
  document.getElementById("reset").addEventListener("click", resetView);
  document.getElementById("summary").textContent =
    `${splats.count.toLocaleString("en")} Gaussians · ${info.antialiased ? "anti-aliased (Mip-Splatting filters)" : "plain 3DGS (0.3 px² dilation)"}` +
    (info.worldToScanner ? "" : " · no scanner frame: lengths in world units");
  status.textContent = "drag to turn · scroll to zoom · right-drag to pan";

  const resize = () => {
    const width = window.innerWidth, height = window.innerHeight;
    renderer.setSize(width, height, false);
    camera.aspect = width / Math.max(height, 1);
    camera.updateProjectionMatrix();
  };
  window.addEventListener("resize", resize);
  resize();
  Object.assign(state, {
    setCut: cut.set,
    pickAt: ruler.pickAt,
    resetView,
    moveCamera: (position) => {
      camera.position.fromArray(position);
      controls.update();
    },
    project: (point) => projectToPixels(THREE, camera, point),
  });
  renderer.setAnimationLoop(() => {
    controls.update();
    renderer.render(scene, camera);
    labels.update(camera);
    ruler.update();
    state.frames += 1;
    state.ready = true;
  });
}

function base64Bytes(text) {
  const binary = atob(text.trim());
  const bytes = new Uint8Array(binary.length);
  for (let i = 0; i < binary.length; i++) bytes[i] = binary.charCodeAt(i);
  return bytes;
}

const CAMERA_REST_MS = 300; // still this long after the last move: the drag has ended (view/camera_rest.py)

// Each Gaussian's centre, opacity, precision matrix (the inverse covariance, 6 terms) and mean log
// scale, as Spark decoded them: the ruler picks in these, the cut hides by the centres, a chord-length
// scene's opacities follow the camera by them.
function readSplats(packed) {
  const count = packed.numSplats;
  const centres = new Float32Array(3 * count), opacity = new Float32Array(count), precision = new Float32Array(6 * count);
  const meanLogScale = new Float32Array(count);
  packed.forEachSplat((i, centre, scales, q, alpha) => {
    meanLogScale[i] = (Math.log(scales.x) + Math.log(scales.y) + Math.log(scales.z)) / 3;
    centres.set([centre.x, centre.y, centre.z], 3 * i);
    opacity[i] = alpha;
    const { x, y, z, w } = q;
    const r = [ // the rotation matrix of the unit quaternion, row-major
      1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
      2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
      2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    ];
    const inverse = [scales.x, scales.y, scales.z].map((s) => 1 / Math.max(s * s, 1e-12));
    const term = (a, b) => r[3 * a] * r[3 * b] * inverse[0] + r[3 * a + 1] * r[3 * b + 1] * inverse[1] + r[3 * a + 2] * r[3 * b + 2] * inverse[2];
    precision.set([term(0, 0), term(0, 1), term(0, 2), term(1, 1), term(1, 2), term(2, 2)], 6 * i);
  });
  return { count, centres, opacity, precision, meanLogScale };
}

// log r of splat/chord.py: the Gaussian's chord along the ray from the camera against a round
// Gaussian's of the same volume, −½ log dᵀΣ⁻¹d − mean log s for the unit direction d; 0 where it is
// undefined, within ±12 (LOG_RATIO_LIMIT).
function chordLogRatio(splats, i, eye) {
  const c = splats.centres, p = splats.precision;
  const dx = c[3 * i] - eye.x, dy = c[3 * i + 1] - eye.y, dz = c[3 * i + 2] - eye.z;
  const squared = dx * dx + dy * dy + dz * dz;
  const o = 6 * i;
  const form = p[o] * dx * dx + p[o + 3] * dy * dy + p[o + 5] * dz * dz + 2 * (p[o + 1] * dx * dy + p[o + 2] * dx * dz + p[o + 4] * dy * dz);
  if (!(squared > 0 && form > 0 && Number.isFinite(form) && Number.isFinite(squared))) return 0;
  const value = -0.5 * Math.log(form / squared) - splats.meanLogScale[i];
  return Number.isFinite(value) ? Math.min(Math.max(value, -12), 12) : 0;
}

// The anatomical cut: Gaussians whose centre lies beyond the plane get opacity 0 in Spark's packed
// splats (the top byte of each splat's first word), the rest their own.
function setUpCut(info, splats, mesh) {
  const packed = mesh.packedSplats, words = packed.packedArray;
  const original = new Uint32Array(splats.count);
  for (let i = 0; i < splats.count; i++) original[i] = words[4 * i];
  const select = document.getElementById("cut-axis"), slider = document.getElementById("cut-position");
  const text = document.getElementById("cut-text");
  const current = { axis: -1, offset: 0 };
  const hidden = (i) => current.axis >= 0 && splats.centres[3 * i + current.axis] > current.offset;
  const apply = () => {
    for (let i = 0; i < splats.count; i++) words[4 * i] = hidden(i) ? original[i] & 0x00ffffff : original[i];
    packed.needsUpdate = true; // uploads the words again
    mesh.needsUpdate = true; // and makes Spark generate the splats from them again
    const name = select.value;
    text.textContent = current.axis < 0 ? "no cut" : `${name} plane at ${planeText(info, current.axis, current.offset)}; the ${info.axes[current.axis][1]} side hidden`;
  };
  const set = (name, offset) => {
    select.value = name;
    current.axis = name === "none" ? -1 : info.cutAxes[name];
    current.offset = Number.isFinite(offset) ? Math.min(Math.max(offset, -1), 1) : 0;
    slider.disabled = current.axis < 0;
    slider.value = String(current.offset);
    apply();
  };
  select.addEventListener("change", () => set(select.value, Number(slider.value)));
  slider.addEventListener("input", () => set(select.value, Number(slider.value)));
  // New colours and opacities for every Gaussian (a transfer function's), the cut kept on top.
  const recolour = (rgba) => {
    original.set(rgba);
    apply();
  };
  return { set, hidden, recolour };
}

// A scalar scene's per-Gaussian value, optical length and 3D-filter factor (share/page.py's
// scalar_block: three little-endian arrays, gzip-compressed).
async function readScalar(text, count) {
  const stream = new Blob([base64Bytes(text)]).stream().pipeThrough(new DecompressionStream("gzip"));
  const raw = new DataView(await new Response(stream).arrayBuffer());
  if (raw.byteLength !== 6 * count) throw new Error(`the scalar values hold ${raw.byteLength} bytes for ${count} Gaussians`);
  const values = new Float32Array(count), logLengths = new Float32Array(count), attenuation = new Float32Array(count);
  for (let i = 0; i < count; i++) {
    values[i] = raw.getUint16(2 * i, true) / 65535;
    logLengths[i] = raw.getInt16(2 * count + 2 * i, true) / 2048;
    attenuation[i] = raw.getUint16(4 * count + 2 * i, true) / 65535;
  }
  return { values, logLengths, attenuation };
}

// σ(v) of cubecloud's TransferFunction: a linear rise from low to high, for a band a fall from
// fall_low to fall_high, times the density (ramp widths at least 1e-6, as MIN_RAMP_WIDTH).
function extinction(tf, v) {
  const clamp = (x) => Math.min(Math.max(x, 0), 1);
  let ramp = clamp((v - tf.low) / Math.max(tf.high - tf.low, 1e-6));
  if (tf.fall_low !== null && tf.fall_low !== undefined) ramp *= 1 - clamp((v - tf.fall_low) / Math.max(tf.fall_high - tf.fall_low, 1e-6));
  return tf.density * ramp;
}

function withWindow(tf, low, high) {
  if (tf.fall_low === null || tf.fall_low === undefined || tf.fall_low >= high) return { ...tf, low, high };
  return { ...tf, low, high, fall_low: high, fall_high: Math.max(tf.fall_high, high) };
}

function mapColour(anchors, v) {
  const x = Math.min(Math.max(Number.isFinite(v) ? v : 0, 0), 1) * (anchors.length - 1);
  const i = Math.min(Math.floor(x), anchors.length - 2), f = x - i;
  return [0, 1, 2].map((k) => anchors[i][k] * (1 - f) + anchors[i + 1][k] * f);
}

// The page's transfer-function controls: each Gaussian's opacity is α = (1 − exp(−σ(v) ℓ)) times
// its 3D filter's factor and its colour the value (or the colour map's), as `cubecloud view`
// recolours a scalar scene; a chord-length scene's ℓ is scaled by r seen from the camera.
function setUpTransfer(scalar, drawn, splats, cut, camera) {
  document.getElementById("transfer").hidden = false;
  const preset = document.getElementById("tf-preset"), colours = document.getElementById("tf-colours");
  const low = document.getElementById("tf-low"), high = document.getElementById("tf-high");
  const opacity = document.getElementById("tf-opacity");
  opacity.max = String(scalar.maxOpacityScale);
  for (const name of [...Object.keys(scalar.presets), "custom"]) preset.add(new Option(name, name));
  for (const name of Object.keys(scalar.colourMaps)) colours.add(new Option(name, name));
  const chosen = { tf: Object.values(scalar.presets)[0], scale: 1, map: "grey" };
  const rgba = new Uint32Array(splats.count);
  // ℓ as drawn: times r seen from the camera in a chord-length scene, within ±10 in log (as
  // LOG_LENGTH_LIMIT); computed when the camera rests, not at each change of a control.
  const seen = new Float32Array(splats.count);
  const seeLengths = () => {
    const eye = camera.position;
    for (let i = 0; i < splats.count; i++) {
      const ratio = scalar.chordLengths ? chordLogRatio(splats, i, eye) : 0;
      seen[i] = Math.exp(Math.min(Math.max(drawn.logLengths[i] + ratio, -10), 10));
    }
  };
  const byte = (x) => Math.min(Math.max(Math.round(x * 255), 0), 255);
  const draw = () => {
    const tf = { ...chosen.tf, density: Math.min(chosen.tf.density * chosen.scale, 999999) };
    const anchors = scalar.colourMaps[chosen.map];
    for (let i = 0; i < splats.count; i++) {
      const v = drawn.values[i];
      const alpha = Math.min(Math.max(-Math.expm1(-extinction(tf, v) * seen[i]) * drawn.attenuation[i], 0), 1);
      const [r, g, b] = chosen.map === "grey" ? [v, v, v] : mapColour(anchors, v);
      rgba[i] = (byte(r) | (byte(g) << 8) | (byte(b) << 16) | (byte(alpha) << 24)) >>> 0;
      splats.opacity[i] = alpha; // the ruler picks in what is shown
    }
    cut.recolour(rgba);
    low.value = String(chosen.tf.low);
    high.value = String(chosen.tf.high);
    const reading = (v) => (scalar.huWindow ? `${Math.round(scalar.huWindow[0] + v * (scalar.huWindow[1] - scalar.huWindow[0]))} HU` : v.toFixed(3));
    document.getElementById("tf-low-text").textContent = reading(chosen.tf.low);
    document.getElementById("tf-high-text").textContent = reading(chosen.tf.high);
    document.getElementById("tf-opacity-text").textContent = `× ${chosen.scale.toFixed(1)}`;
  };
  const set = ({ preset: name, low: lo, high: hi, opacity: scale, colourMap } = {}) => {
    if (name !== undefined && name !== "custom") {
      if (!(name in scalar.presets)) throw new Error(`no transfer preset ${name}`);
      chosen.tf = scalar.presets[name];
      preset.value = name;
    }
    if (lo !== undefined || hi !== undefined) {
      const newLow = Math.min(Math.max(Number(lo ?? chosen.tf.low) || 0, 0), 1);
      const newHigh = Math.min(Math.max(Number(hi ?? chosen.tf.high) || 0, newLow), 1);
      chosen.tf = withWindow(chosen.tf, newLow, newHigh);
      preset.value = "custom";
    }
    if (scale !== undefined) chosen.scale = Math.min(Math.max(Number(scale) || 0, 0), scalar.maxOpacityScale);
    if (colourMap !== undefined && colourMap in scalar.colourMaps) chosen.map = colourMap;
    draw();
  };
  preset.addEventListener("change", () => preset.value !== "custom" && set({ preset: preset.value }));
  low.addEventListener("input", () => set({ low: Number(low.value) }));
  high.addEventListener("input", () => set({ high: Number(high.value) }));
  opacity.addEventListener("input", () => set({ opacity: Number(opacity.value) }));
  colours.addEventListener("change", () => set({ colourMap: colours.value }));
  seeLengths();
  set({ preset: Object.keys(scalar.presets)[0] });
  const lookFrom = () => {
    seeLengths();
    draw();
  };
  return { set, lookFrom };
}

function planeText(info, axis, offset) {
  if (!info.worldToScanner) return `${offset.toFixed(3)} world units`;
  const point = [0, 0, 0];
  point[axis] = offset;
  const mm = toScanner(info, point);
  const component = info.scannerComponent[axis];
  return `${"RAS"[component]} ${mm[component].toFixed(1)} mm`;
}

function toScanner(info, p) {
  const m = info.worldToScanner;
  if (!m) return p;
  return [0, 1, 2].map((r) => m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3]);
}

// Where a ray meets the scene: the first depth at which its transmittance through the Gaussians
// falls to ½. Each Gaussian stops the ray by its opacity times its peak response along the ray,
// exp(−½ m²), m the Mahalanobis distance of the ray's closest approach; it acts at that approach.
function pickAlongRay(splats, origin, direction, hidden) {
  const hits = [];
  const { centres, precision, opacity } = splats;
  for (let i = 0; i < splats.count; i++) {
    if (opacity[i] < 1 / 255 || hidden(i)) continue;
    const p = precision.subarray(6 * i, 6 * i + 6);
    const v = [centres[3 * i] - origin[0], centres[3 * i + 1] - origin[1], centres[3 * i + 2] - origin[2]];
    const pd = [p[0] * direction[0] + p[1] * direction[1] + p[2] * direction[2],
                p[1] * direction[0] + p[3] * direction[1] + p[4] * direction[2],
                p[2] * direction[0] + p[4] * direction[1] + p[5] * direction[2]];
    const a = pd[0] * direction[0] + pd[1] * direction[1] + pd[2] * direction[2];
    if (!(a > 0)) continue;
    const b = pd[0] * v[0] + pd[1] * v[1] + pd[2] * v[2];
    const vPv = v[0] * (p[0] * v[0] + p[1] * v[1] + p[2] * v[2]) + v[1] * (p[1] * v[0] + p[3] * v[1] + p[4] * v[2]) +
      v[2] * (p[2] * v[0] + p[4] * v[1] + p[5] * v[2]);
    const t = b / a, m2 = Math.max(vPv - (b * b) / a, 0);
    if (t <= 0 || m2 > 18) continue; // beyond 6σ a Gaussian stops under 1e-8 of the ray
    hits.push([t, opacity[i] * Math.exp(-0.5 * m2)]);
  }
  hits.sort((x, y) => x[0] - y[0]);
  let transmittance = 1;
  for (const [t, alpha] of hits) {
    transmittance *= 1 - Math.min(alpha, 0.99);
    if (transmittance <= 0.5) return [0, 1, 2].map((k) => origin[k] + t * direction[k]);
  }
  return null;
}

function setUpRuler(THREE, scene, camera, canvas, info, splats, cut, state) {
  const toggle = document.getElementById("measure"), readout = document.getElementById("distance");
  const label = document.getElementById("distance-label");
  const material = new THREE.LineBasicMaterial({ color: 0x66ccff, depthTest: false });
  const line = new THREE.Line(new THREE.BufferGeometry(), material);
  line.renderOrder = 10;
  scene.add(line);
  const markers = [];
  const pickAt = (x, y) => {
    const rect = canvas.getBoundingClientRect();
    const ndc = new THREE.Vector2(((x - rect.left) / rect.width) * 2 - 1, -((y - rect.top) / rect.height) * 2 + 1);
    const raycaster = new THREE.Raycaster();
    raycaster.setFromCamera(ndc, camera);
    const point = pickAlongRay(splats, raycaster.ray.origin.toArray(), raycaster.ray.direction.toArray(), cut.hidden);
    if (point) add(point);
    else readout.textContent = "nothing under the pointer: click on the scene";
    return point;
  };
  const add = (point) => {
    if (state.picks.length === 2) clear();
    state.picks.push(point);
    const marker = new THREE.Mesh(new THREE.SphereGeometry(0.008, 12, 8), new THREE.MeshBasicMaterial({ color: 0x66ccff, depthTest: false }));
    marker.position.fromArray(point);
    marker.renderOrder = 11;
    markers.push(marker);
    scene.add(marker);
    if (state.picks.length === 2) {
      const [a, b] = state.picks.map((p) => toScanner(info, p));
      state.distanceMm = Math.hypot(a[0] - b[0], a[1] - b[1], a[2] - b[2]);
      line.geometry.setFromPoints(state.picks.map((p) => new THREE.Vector3(...p)));
      readout.textContent = `${state.distanceMm.toFixed(1)} ${info.worldToScanner ? "mm" : "world units"}`;
    } else {
      readout.textContent = "first point set: click the second";
    }
  };
  const clear = () => {
    state.picks = [];
    state.distanceMm = null;
    markers.splice(0).forEach((m) => scene.remove(m));
    line.geometry.setFromPoints([]);
    readout.textContent = "\u00a0";
  };
  document.getElementById("clear").addEventListener("click", clear);
  let down = null; // a click is a press and release within 4 px; a drag turns the view
  canvas.addEventListener("pointerdown", (e) => { down = [e.clientX, e.clientY]; });
  canvas.addEventListener("pointerup", (e) => {
    if (toggle.checked && down && Math.hypot(e.clientX - down[0], e.clientY - down[1]) < 4) pickAt(e.clientX, e.clientY);
    down = null;
  });
  const update = () => {
    if (state.picks.length !== 2) { label.style.display = "none"; return; }
    const middle = state.picks[0].map((v, k) => (v + state.picks[1][k]) / 2);
    const [x, y, visible] = projectToPixels(THREE, camera, middle);
    label.style.display = visible ? "block" : "none";
    label.style.left = `${x}px`;
    label.style.top = `${y}px`;
    label.textContent = readout.textContent;
  };
  return { pickAt, update };
}

function projectToPixels(THREE, camera, point) {
  const v = new THREE.Vector3(...point).project(camera);
  return [(v.x + 1) / 2 * window.innerWidth, (1 - v.y) / 2 * window.innerHeight, v.z > -1 && v.z < 1];
}

// The patient's directions (R/L, A/P, S/I) at the ends of the cube's axes.
function setUpAxisLabels(THREE, info) {
  const labels = [];
  info.axes.forEach((ends, axis) => {
    ends.forEach((letter, side) => {
      const element = document.createElement("div");
      element.className = "axis";
      element.textContent = letter;
      document.body.appendChild(element);
      const point = [0, 0, 0];
      point[axis] = side ? 1.15 : -1.15;
      labels.push([element, point]);
    });
  });
  const forward = new THREE.Vector3();
  return {
    update(camera) {
      camera.getWorldDirection(forward);
      for (const [element, point] of labels) {
        const [x, y, visible] = projectToPixels(THREE, camera, point);
        // An axis seen end-on puts both its letters on the middle of the scene: they say nothing there.
        const endOn = Math.abs(forward.dot(new THREE.Vector3(...point).normalize())) > 0.95;
        element.style.display = visible && !endOn ? "block" : "none";
        element.style.left = `${x}px`;
        element.style.top = `${y}px`;
      }
    },
  };
}
