// The report page's views: the relit normal map (a 2D canvas) and the surface (three.js).
// Reads #report-data; sets window.cnnpsReport (cnnps/io/report/page.py says what it holds).
const data = JSON.parse(document.getElementById("report-data").textContent);
const hook = (window.cnnpsReport = { ready: false, light: null, glossy: false, relitFrames: 0,
                                     renderedLight: null, mesh: null, problems: [] });
const listeners = [];  // called with the light when it moves

function bytesOf(b64) {
  const text = atob(b64);
  const out = new Uint8Array(text.length);
  for (let i = 0; i < text.length; i++) out[i] = text.charCodeAt(i);
  return out;
}

async function inflate(b64, format) {
  const stream = new Blob([bytesOf(b64)]).stream().pipeThrough(new DecompressionStream(format));
  return new Uint8Array(await new Response(stream).arrayBuffer());
}

function undelta(bytes, k) {
  for (let i = k; i < bytes.length; i++) bytes[i] = (bytes[i] + bytes[i - k]) & 255;
  return bytes;
}

// A point of an element -> a unit light: the element's inscribed circle is the hemisphere
// seen from the camera (centre: l = +z, rim: l in the image plane).
function lightAt(element, clientX, clientY) {
  const r = element.getBoundingClientRect();
  const radius = Math.min(r.width, r.height) / 2;
  let u = (clientX - (r.left + r.width / 2)) / radius;
  let v = ((r.top + r.height / 2) - clientY) / radius;
  const r2 = u * u + v * v;
  if (r2 > 1) { const s = 1 / Math.sqrt(r2); u *= s; v *= s; }
  return [u, v, Math.sqrt(Math.max(0, 1 - u * u - v * v))];
}

function draggable(element, onLight) {
  let active = false;
  element.addEventListener("pointerdown", (e) => {
    active = true; element.setPointerCapture(e.pointerId); onLight(lightAt(element, e.clientX, e.clientY));
  });
  element.addEventListener("pointermove", (e) => { if (active) onLight(lightAt(element, e.clientX, e.clientY)); });
  const stop = (e) => { active = false; if (element.hasPointerCapture(e.pointerId)) element.releasePointerCapture(e.pointerId); };
  element.addEventListener("pointerup", stop);
  element.addEventListener("pointercancel", stop);
}

function decodeNormals(cells, count) {
  const n = new Float64Array(count * 3);
  const inside = new Uint8Array(count);
  for (let p = 0; p < count; p++) {
    if (!cells[4 * p + 3]) continue;
    const x = cells[4 * p] / 127.5 - 1, y = cells[4 * p + 1] / 127.5 - 1, z = cells[4 * p + 2] / 127.5 - 1;
    const len = Math.hypot(x, y, z);
    if (len === 0) continue;
    n[3 * p] = x / len; n[3 * p + 1] = y / len; n[3 * p + 2] = z / len; inside[p] = 1;
  }
  return { n, inside };
}

// The shade of one unit normal: max(0, n.l), or with gloss (1 - w) max(0, n.l) + w max(0, n.h)^s
// (h: the half vector of l and the view +z; no highlight where n.l <= 0).
function shader(light, glossy, gloss) {
  const [lx, ly, lz] = light;
  let hx = lx, hy = ly, hz = lz + 1;
  const hl = Math.hypot(hx, hy, hz) || 1;
  hx /= hl; hy /= hl; hz /= hl;
  const w = gloss.weight, s = gloss.shininess;
  return (nx, ny, nz) => {
    const d = nx * lx + ny * ly + nz * lz;
    const diffuse = Math.max(0, d);
    if (!glossy) return diffuse;
    const spec = d > 0 ? Math.pow(Math.max(0, nx * hx + ny * hy + nz * hz), s) : 0;
    return (1 - w) * diffuse + w * spec;
  };
}

async function relitView() {
  const cfg = data.relit;
  const count = cfg.w * cfg.h;
  const { n, inside } = decodeNormals(undelta(await inflate(cfg.normals, "deflate"), 4), count);
  const canvas = document.getElementById("relit-canvas");
  const ball = document.getElementById("light-ball");
  const glossBox = document.getElementById("glossy");
  const shininess = document.getElementById("shininess");
  const readout = document.getElementById("light-readout");
  const ctx = canvas.getContext("2d", { willReadFrequently: true });
  const image = ctx.createImageData(cfg.w, cfg.h);
  const px = image.data;
  const [br, bg, bb] = cfg.background;
  let pending = false;

  function draw() {
    pending = false;
    const light = hook.light.slice();
    const gloss = { weight: cfg.gloss.weight, shininess: Number(shininess.value) };
    const shade = shader(light, hook.glossy, gloss);
    for (let p = 0; p < count; p++) {
      const o = 4 * p;
      if (inside[p]) {
        const v = Math.round(255 * Math.min(1, shade(n[3 * p], n[3 * p + 1], n[3 * p + 2])));
        px[o] = v; px[o + 1] = v; px[o + 2] = v;
      } else { px[o] = br; px[o + 1] = bg; px[o + 2] = bb; }
      px[o + 3] = 255;
    }
    ctx.putImageData(image, 0, 0);
    drawBall(ball, light, shade);
    readout.textContent = `l = (${light.map((c) => c.toFixed(3)).join(", ")})`;
    hook.renderedLight = light;
    hook.relitFrames += 1;
  }
  const redraw = () => { if (!pending) { pending = true; requestAnimationFrame(draw); } };
  const setLight = (l) => { hook.light = l; redraw(); listeners.forEach((f) => f(l)); };
  hook.light = cfg.light.slice();
  hook.glossy = glossBox.checked;
  glossBox.addEventListener("change", () => { hook.glossy = glossBox.checked; redraw(); });
  shininess.addEventListener("input", redraw);
  draggable(canvas, setLight);
  draggable(ball, setLight);
  hook.setLight = setLight;
  draw();
}

function drawBall(ball, light, shade) {
  const ctx = ball.getContext("2d");
  const size = ball.width, r = size / 2 - 2;
  const image = ctx.createImageData(size, size);
  for (let y = 0; y < size; y++) {
    for (let x = 0; x < size; x++) {
      const u = (x + 0.5 - size / 2) / r, v = (size / 2 - y - 0.5) / r, q = u * u + v * v;
      const o = 4 * (y * size + x);
      if (q > 1) { image.data[o + 3] = 0; continue; }
      const value = Math.round(255 * Math.min(1, shade(u, v, Math.sqrt(1 - q))));
      image.data[o] = value; image.data[o + 1] = value; image.data[o + 2] = value; image.data[o + 3] = 255;
    }
  }
  ctx.putImageData(image, 0, 0);
  ctx.beginPath();
  ctx.arc(size / 2 + light[0] * r, size / 2 - light[1] * r, 5, 0, 2 * Math.PI);
  ctx.fillStyle = "#ffb000"; ctx.strokeStyle = "#000"; ctx.fill(); ctx.stroke();
}

async function scriptText(id) {
  return new TextDecoder().decode(await inflate(document.getElementById(id).textContent.trim(), "gzip"));
}

const moduleUrl = (text) => URL.createObjectURL(new Blob([text], { type: "text/javascript" }));

async function loadThree() {
  const core = moduleUrl(await scriptText("three-core"));
  const main = moduleUrl((await scriptText("three-module")).split("'./three.core.js'").join(JSON.stringify(core)));
  const orbit = moduleUrl((await scriptText("three-orbit")).split("from 'three'").join(`from ${JSON.stringify(main)}`));
  const THREE = await import(main);
  const { OrbitControls } = await import(orbit);
  return { THREE, OrbitControls };
}

function meshGeometry(THREE, cfg, xyz) {
  const { w, h } = cfg;
  const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
  for (let i = 0; i < w * h; i++) {
    if (Number.isNaN(xyz[3 * i])) continue;
    for (let k = 0; k < 3; k++) { lo[k] = Math.min(lo[k], xyz[3 * i + k]); hi[k] = Math.max(hi[k], xyz[3 * i + k]); }
  }
  const centre = lo.map((v, k) => (v + hi[k]) / 2);
  const index = [];
  const ok = (i) => !Number.isNaN(xyz[3 * i]);
  for (let r = 0; r + 1 < h; r++) {
    for (let c = 0; c + 1 < w; c++) {
      const a = r * w + c, b = a + 1, d = a + w, e = d + 1;  // a b / d e, counter-clockwise seen from +z
      if (ok(a) && ok(b) && ok(d) && ok(e)) index.push(a, d, b, b, d, e);
    }
  }
  for (let i = 0; i < w * h; i++) {  // unused vertices: at the centre, so the bounds stay finite
    if (!ok(i)) { xyz[3 * i] = centre[0]; xyz[3 * i + 1] = centre[1]; xyz[3 * i + 2] = centre[2]; }
  }
  if (index.length === 0) throw new Error("no 2 x 2 block of the depth map is complete: no surface to draw");
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(xyz, 3));
  geometry.setIndex(index);
  geometry.computeVertexNormals();
  const radius = Math.max(1e-9, Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) / 2);
  return { geometry, centre: new THREE.Vector3(...centre), radius, triangles: index.length / 3 };
}

async function surfaceView() {
  const cfg = data.mesh;
  const canvas = document.getElementById("mesh-canvas");
  const { THREE, OrbitControls } = await loadThree();
  const bytes = await inflate(cfg.positions, "deflate");
  const { geometry, centre, radius } = meshGeometry(THREE, cfg, new Float32Array(bytes.buffer));
  const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(window.devicePixelRatio || 1);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0x202329);
  const material = new THREE.MeshStandardMaterial({ color: 0xd0d0d0, roughness: 0.6, metalness: 0,
                                                    side: THREE.DoubleSide });
  scene.add(new THREE.Mesh(geometry, material));
  scene.add(new THREE.HemisphereLight(0xffffff, 0x303030, 0.6));
  const sun = new THREE.DirectionalLight(0xffffff, 2.2);
  scene.add(sun, sun.target);
  sun.target.position.copy(centre);
  const camera = new THREE.PerspectiveCamera(35, 1, radius / 100, radius * 100);
  const view = new THREE.Vector3(-0.3, 0.45, 0.84).normalize().multiplyScalar(radius * 4);  // from the upper left
  camera.position.copy(centre).add(view);
  const controls = new OrbitControls(camera, canvas);
  controls.target.copy(centre);
  hook.mesh = { calls: 0, triangles: 0, frames: 0 };
  function render() {
    const width = canvas.clientWidth || 640, height = canvas.clientHeight || 480;
    renderer.setSize(width, height, false);
    camera.aspect = width / height;
    camera.updateProjectionMatrix();
    renderer.render(scene, camera);
    hook.mesh = { calls: renderer.info.render.calls, triangles: renderer.info.render.triangles,
                  frames: hook.mesh.frames + 1 };
  }
  const follow = (l) => { sun.position.set(centre.x + l[0] * radius * 4, centre.y + l[1] * radius * 4,
                                           centre.z + l[2] * radius * 4); render(); };
  controls.addEventListener("change", render);
  window.addEventListener("resize", render);
  listeners.push(follow);
  controls.update();
  follow(hook.light || data.relit.light);
}

async function main() {
  for (const [name, view] of [["relit", relitView], ["surface", data.mesh ? surfaceView : null]]) {
    if (!view) continue;
    try {
      await view();
    } catch (err) {
      hook.problems.push(`${name}: ${err && err.message ? err.message : err}`);
      const note = document.createElement("p");
      note.className = "absent";
      note.textContent = `This view could not be drawn in this browser (${err && err.message ? err.message : err}).`;
      document.getElementById(name).appendChild(note);
    }
  }
  hook.ready = true;
}

main();
