// The CAD model in WebGL (three.js, served from /vendor/three by `make web-vendor`): orbit with the
// mouse, click a surface point (raycast) to get its xyz in the canonical CAD frame (metres, +Y up,
// front +Z, unmirrored: a mirrored view maps hits back through the mirror), markers for clicked
// points, the symmetry axis. For tests: screenOf(xyz) gives the client pixel of a CAD point, pick(cx, cy) its hit.
import * as THREE from "three";
import {OrbitControls} from "three/addons/controls/OrbitControls.js";
import {GLTFLoader} from "three/addons/loaders/GLTFLoader.js";

export class Viewer {
  constructor(canvas, {onPick} = {}) {
    this.canvas = canvas; this.onPick = onPick; this.markers = []; this.mirrored = false; this.radius = 1;   // until the model loads (markers may come first)
    this.renderer = new THREE.WebGLRenderer({canvas, antialias: true, preserveDrawingBuffer: true});
    this.renderer.setPixelRatio(1);
    this.scene = new THREE.Scene(); this.scene.background = new THREE.Color(0xe9edf3);
    this.camera = new THREE.PerspectiveCamera(40, 1, 0.01, 100);
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x667080, 2.2));
    const sun = new THREE.DirectionalLight(0xffffff, 1.6); sun.position.set(2, 4, 3); this.scene.add(sun);
    this.group = new THREE.Group(); this.scene.add(this.group);   // the model frame (mirror = scale.x -1)
    this.controls = new OrbitControls(this.camera, canvas);
    this.controls.addEventListener("change", () => this.render());
    this.raycaster = new THREE.Raycaster();
    let down = null;
    canvas.addEventListener("pointerdown", (e) => (down = [e.clientX, e.clientY]));
    canvas.addEventListener("pointerup", (e) => {
      if (down && Math.hypot(e.clientX - down[0], e.clientY - down[1]) < 4) {
        const xyz = this.pick(e.clientX, e.clientY);
        if (xyz && this.onPick) this.onPick(xyz);
      }
      down = null;
    });
    new ResizeObserver(() => this.resize()).observe(canvas);
    this.resize();
  }
  resize() {
    const w = this.canvas.clientWidth, h = this.canvas.clientHeight;
    if (!w || !h) return;
    this.renderer.setSize(w, h, false); this.camera.aspect = w / h; this.camera.updateProjectionMatrix(); this.render();
  }
  async load(url, symmetry = 1) {
    const started = performance.now();
    const gltf = await new GLTFLoader().loadAsync(url);
    this.model = gltf.scene; this.group.add(this.model);
    this.model.traverse((o) => { if (o.isMesh) for (const m of [o.material].flat()) { m.side = THREE.DoubleSide; if ("metalness" in m) { m.metalness = 0; m.roughness = 0.85; } } });
    const box = new THREE.Box3().setFromObject(this.model), size = box.getSize(new THREE.Vector3()), c = box.getCenter(new THREE.Vector3());
    this.size = [size.x, size.y, size.z];   // the model's bounding-box size, CAD frame (x, y, z)
    this.radius = Math.max(size.x, size.y, size.z) / 2 || 1;
    // far enough that the model's bounding sphere fits the narrower of the view's two angles (a cube's
    // corners were cut off at 3.2 half-sides)
    const halfV = THREE.MathUtils.degToRad(this.camera.fov) / 2, halfH = Math.atan(Math.tan(halfV) * this.camera.aspect);
    const d = 1.05 * (size.length() / 2 || 1) / Math.sin(Math.min(halfV, halfH));
    this.camera.position.set(c.x + d * 0.55, c.y + d * 0.45, c.z + d * 0.75); this.camera.near = d / 100; this.camera.far = d * 10;
    this.camera.updateProjectionMatrix(); this.controls.target.copy(c); this.controls.update();
    // the symmetry axis: +Y through the model's centre (dashed when the model has no symmetry)
    const axis = new THREE.Line(new THREE.BufferGeometry().setFromPoints([new THREE.Vector3(c.x, box.min.y - size.y * 0.15, c.z), new THREE.Vector3(c.x, box.max.y + size.y * 0.15, c.z)]),
      symmetry > 1 ? new THREE.LineBasicMaterial({color: 0xd0308a}) : new THREE.LineDashedMaterial({color: 0x8090a0, dashSize: size.y / 20, gapSize: size.y / 20}));
    axis.computeLineDistances(); this.group.add(axis);
    let triangles = 0;
    this.model.traverse((o) => { if (o.isMesh) triangles += (o.geometry.index ? o.geometry.index.count : o.geometry.attributes.position.count) / 3; });
    this.triangles = triangles;
    this.render();
    this.loadMs = performance.now() - started;
    return this;
  }
  // Orbit the camera (keeping its distance) to look at the model's centre from world direction dir.
  viewDirection(dir) {
    const c = this.controls.target, d = new THREE.Vector3(...dir).normalize(), dist = this.camera.position.distanceTo(c);
    this.camera.position.copy(c).addScaledVector(d, dist); this.controls.update(); this.render();
  }
  setMirrored(on) { this.mirrored = on; this.group.scale.x = on ? -1 : 1; this.group.updateMatrixWorld(true); this.render(); }
  // The CAD-frame point under client pixel (cx, cy), or null.
  pick(cx, cy) {
    if (!this.model) return null;
    const r = this.canvas.getBoundingClientRect();
    const ndc = new THREE.Vector2(((cx - r.left) / r.width) * 2 - 1, -((cy - r.top) / r.height) * 2 + 1);
    this.raycaster.setFromCamera(ndc, this.camera);
    const hit = this.raycaster.intersectObject(this.model, true)[0];
    if (!hit) return null;
    const p = this.group.worldToLocal(hit.point.clone());
    return [p.x, p.y, p.z];
  }
  // Client pixel of a CAD-frame point (as displayed, mirror included).
  screenOf(xyz) {
    const v = this.group.localToWorld(new THREE.Vector3(...xyz)).project(this.camera), r = this.canvas.getBoundingClientRect();
    return [r.left + (v.x + 1) / 2 * r.width, r.top + (1 - v.y) / 2 * r.height];
  }
  setMarkers(points) {   // [{xyz, color, pending}]
    for (const m of this.markers) this.group.remove(m);
    this.markers = points.map((p) => {
      const m = new THREE.Mesh(new THREE.SphereGeometry(this.radius * 0.035, 16, 12), new THREE.MeshBasicMaterial({color: p.color, depthTest: false, transparent: true, opacity: p.pending ? 0.6 : 1}));
      m.renderOrder = 10; m.position.set(...p.xyz); this.group.add(m); return m;
    });
    this.render();
  }
  render() { this.renderer.render(this.scene, this.camera); }
}

// Whether points (n x 3) lie on one plane: the smallest singular value of the centred points below
// tol times the largest (as tasks.pose_checks / labels ingest decide, [pose] coplanar_tol).
export function coplanar(points, tol = 0.02) {
  if (points.length < 3) return false;
  const n = points.length, m = [0, 1, 2].map((k) => points.reduce((s, p) => s + p[k], 0) / n);
  const C = [[0, 0, 0], [0, 0, 0], [0, 0, 0]];
  for (const p of points) for (let i = 0; i < 3; i++) for (let j = 0; j < 3; j++) C[i][j] += (p[i] - m[i]) * (p[j] - m[j]);
  const e = symEig3(C).map((v) => Math.sqrt(Math.max(0, v)));
  return e[2] <= tol * e[0];
}
// The CAD axes ("x", "y", "z") along which points (n x 3) span less than minSpan of the model's
// size (x, y, z): the solver holds their scale to the other axes' (tasks.pose.checks.unobserved_axes,
// [pose] min_axis_span).
export function narrowAxes(points, size, minSpan = 0.2) {
  if (!points.length || !(minSpan > 0)) return [];
  return [0, 1, 2].filter((k) => {
    const v = points.map((p) => p[k]);
    return size[k] > 0 && Math.max(...v) - Math.min(...v) < minSpan * size[k];
  }).map((k) => "xyz"[k]);
}
function symEig3(A) {   // eigenvalues of a symmetric 3x3 matrix, descending (trigonometric method)
  const p1 = A[0][1] ** 2 + A[0][2] ** 2 + A[1][2] ** 2, q = (A[0][0] + A[1][1] + A[2][2]) / 3;
  if (p1 < 1e-30) return [A[0][0], A[1][1], A[2][2]].sort((a, b) => b - a);
  const p2 = (A[0][0] - q) ** 2 + (A[1][1] - q) ** 2 + (A[2][2] - q) ** 2 + 2 * p1, p = Math.sqrt(p2 / 6);
  const B = A.map((row, i) => row.map((v, j) => (v - (i === j ? q : 0)) / p));
  const det = B[0][0] * (B[1][1] * B[2][2] - B[1][2] * B[2][1]) - B[0][1] * (B[1][0] * B[2][2] - B[1][2] * B[2][0]) + B[0][2] * (B[1][0] * B[2][1] - B[1][1] * B[2][0]);
  const phi = Math.acos(Math.min(1, Math.max(-1, det / 2))) / 3;
  const e1 = q + 2 * p * Math.cos(phi), e3 = q + 2 * p * Math.cos(phi + (2 * Math.PI) / 3);
  return [e1, 3 * q - e1 - e3, e3];
}
