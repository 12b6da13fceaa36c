/**
 * Graylight viewer page: wires tiles, level-of-detail selection, renderer, navigation and UI.
 *
 * Where the tiles come from: the `tiles` query parameter (any URL of a Potree 2.0 folder or its
 * metadata.json), else the URL the API injected for `/viewer/{job}` in the page's
 * `graylight-config` JSON. The API key for the job service is taken from the fragment
 * (`#key=...`, never sent to the server in the page request), the `key` query parameter or the
 * `graylight_key` cookie, and is sent as a Bearer header to same-origin tiles URLs only.
 *
 * Other parameters: budget (points), fov (degrees), sizing (seed|fixed), px (fixed splat
 * pixels), scale (splat diameter in sample sizes), edl (0|1), hq (0|1), grazing (1|0: widen
 * splats by 1 / cos of the scanner's incidence angle, from normals; on by default), scanner (x,y,z world, default
 * the origin), mode (fly|orbit), merged (1: a merged cloud, no scanner position: no grazing widening, the
 * camera frames it from view 0's side with `axis` (x,y,z, the turntable axis) up; a job whose artifacts
 * hold registration.json is merged without asking),
 * pos and look (x,y,z world), up (x,y,z or -y etc.), bg (hex colour), ui (0 hides the panel).
 * Mesh: `mesh` (a .glb URL; repeated for level-of-detail meshes, finest first), else a job's
 * `mesh.glb` / `mesh_lod*.glb` artifacts; showmesh (0|1: start with the mesh shown), meshpoints
 * (0|1: draw the points too, depth-tested with the mesh, instead of the mesh alone).
 * `window.graylight` exposes state, idle detection, settings and a capture for tests.
 */

import { glMatrix, mat4 } from "gl-matrix";
import { Camera, Controls, type NavMode, parseVector } from "./camera";
import { DecoderUnavailable } from "./decode";
import { selectNodes, type Selection, type ViewInfo } from "./lod";
import { derivativePx } from "./derivative";
import { MeshLayer, orderLevels } from "./mesh";
import { type TileNode, TileSource } from "./potree";
import { type DrawItem, type FrameSettings, type GpuNode, Renderer } from "./renderer";

// Camera and matrix maths in float64; matrices are converted to float32 only for upload.
glMatrix.setMatrixArrayType(Array);

interface Settings {
  budget: number;
  fov: number;
  sizing: "seed" | "fixed";
  fixedPx: number;
  splatScale: number;
  edl: boolean;
  edlStrength: number;
  edlRadius: number;
  hq: boolean;
  grazing: boolean;
  background: [number, number, number];
  /** Scanner position in world coordinates (Graylight clouds: the origin of the camera frame). */
  scanner: [number, number, number];
  /** Show the mesh (when there is one). */
  mesh: boolean;
  /** With the mesh shown, draw the points too (depth-tested with it) rather than the mesh alone. */
  meshPoints: boolean;
}

const MAX_CONCURRENT_LOADS = 6;
/** Field of view (degrees) a merged cloud opens with: a photographer's normal lens. */
const MERGED_FOV = 45;
const MIN_NODE_PX = 24;

function params(): URLSearchParams {
  const p = new URLSearchParams(location.search);
  const hash = location.hash.startsWith("#") ? location.hash.slice(1) : "";
  for (const [k, v] of new URLSearchParams(hash)) if (!p.has(k)) p.set(k, v);
  return p;
}

interface PageConfig {
  tiles?: string;
  job?: string;
  /** The job's artifact list (`GET /v1/jobs/{job}/artifacts`; its `name` titles the page). */
  artifacts?: string;
}

/** Title the page with a job's (or a folder's) name. */
function showName(name: string): void {
  const title = document.getElementById("title");
  if (title) title.textContent = `Graylight · ${name}`;
  document.title = `${name} · Graylight`;
}

function injectedConfig(): PageConfig {
  const el = document.getElementById("graylight-config");
  if (!el || !el.textContent) return {};
  try {
    return JSON.parse(el.textContent) as PageConfig;
  } catch {
    return {};
  }
}

function cookie(name: string): string | null {
  for (const part of document.cookie.split(";")) {
    const [k, ...v] = part.trim().split("=");
    if (k === name) return decodeURIComponent(v.join("="));
  }
  return null;
}

function parseColor(hex: string | null, fallback: [number, number, number]): [number, number, number] {
  if (!hex) return fallback;
  const m = /^#?([0-9a-f]{6})$/i.exec(hex.trim());
  if (!m) return fallback;
  const n = parseInt(m[1], 16);
  return [((n >> 16) & 255) / 255, ((n >> 8) & 255) / 255, (n & 255) / 255];
}

function num(p: URLSearchParams, key: string, fallback: number, lo: number, hi: number): number {
  const v = Number(p.get(key));
  if (!p.has(key) || !Number.isFinite(v)) return fallback;
  return Math.min(hi, Math.max(lo, v));
}

class Viewer {
  readonly camera = new Camera();
  readonly renderer: Renderer;
  readonly settings: Settings;
  source: TileSource | null = null;
  error: string | null = null;
  /** The mesh and its levels of detail, when the job or the page has one. */
  mesh: MeshLayer | null = null;
  /**
   * Set for a merged cloud (a multi-view job: its artifacts hold `registration.json`; or
   * `merged=1`): it has no single scanner position, so the camera neither starts at the origin
   * (view 0's camera) nor widens splats by a scanner's incidence angle; `up` is the turntable
   * axis, signed to point up in view 0's image.
   */
  merged: { up: [number, number, number] } | null = null;
  /** The last non-fatal problem (a mesh that failed to load), shown in one line. */
  notice: string | null = null;
  private loaded = new Set<TileNode>();
  private loading = 0;
  private loadedPoints = 0;
  private frame = 0;
  private dirty = true;
  private lastSelection: Selection | null = null;
  private lastView: ViewInfo | null = null;
  /** Root node positions (local frame), kept from opening to frame the first view. */
  private framePoints: Float32Array | null = null;
  private lastTime = performance.now();
  private frameMs = 0;
  private statsEl: HTMLElement | null;
  private controls: Controls;
  /** Frames rendered since the last change (node loaded, camera moved, setting changed). */
  private quietFrames = 0;

  constructor(
    readonly canvas: HTMLCanvasElement,
    p: URLSearchParams,
  ) {
    this.renderer = new Renderer(canvas);
    this.settings = {
      budget: Math.round(num(p, "budget", 2_000_000, 1_000, 50_000_000)),
      fov: num(p, "fov", 60, 10, 140),
      sizing: p.get("sizing") === "fixed" ? "fixed" : "seed",
      fixedPx: num(p, "px", 1, 1, 64),
      splatScale: num(p, "scale", 1.5, 0.1, 8),
      edl: p.has("edl") ? p.get("edl") !== "0" : true,
      edlStrength: num(p, "edlstrength", 0.6, 0, 5),
      edlRadius: num(p, "edlradius", 1.4, 0.5, 4),
      hq: p.get("hq") === "1",
      grazing: p.get("grazing") !== "0",
      scanner: parseVector(p.get("scanner")) ?? [0, 0, 0],
      background: parseColor(p.get("bg"), [0.08, 0.09, 0.11]),
      mesh: p.get("showmesh") === "1",
      meshPoints: p.get("meshpoints") === "1",
    };
    this.camera.fovDeg = this.settings.fov;
    this.statsEl = document.getElementById("stats");
    this.controls = new Controls(this.camera, canvas, () => this.invalidate());
    new ResizeObserver(() => this.invalidate()).observe(canvas);
    canvas.addEventListener("webglcontextlost", (e) => {
      e.preventDefault();
      this.fail("the WebGL context was lost (GPU reset or out of memory): reload the page, perhaps with a lower point budget");
    });
  }

  invalidate(): void {
    this.dirty = true;
    this.quietFrames = 0;
  }

  async open(url: string, headers: Record<string, string>, p: URLSearchParams): Promise<void> {
    const source = new TileSource(url, headers, new URL("decoder.js", import.meta.url));
    await source.open();
    // The root node is a subsample of the whole cloud: load it first and frame its tight bounds
    // (the metadata's box is the octree cube, often much larger than the scan).
    const root = source.root;
    root.state = "loading";
    const points = await source.loadPoints(root);
    root.gpu = this.renderer.upload(points);
    root.state = "loaded";
    this.loaded.add(root);
    this.loadedPoints += points.count;
    if (points.count > 0) {
      const lo: [number, number, number] = [Infinity, Infinity, Infinity];
      const hi: [number, number, number] = [-Infinity, -Infinity, -Infinity];
      const pos = points.positions;
      for (let i = 0; i < pos.length; i += 3) {
        for (let k = 0; k < 3; k++) {
          const v = pos[i + k];
          if (v < lo[k]) lo[k] = v;
          if (v > hi[k]) hi[k] = v;
        }
      }
      source.tightMin = lo;
      source.tightMax = hi;
      this.framePoints = pos;
    }
    this.source = source;
    this.placeCamera(p);
    window.dispatchEvent(new Event("graylight-open"));
    this.invalidate();
  }

  /** Mark the cloud merged (see `merged`), with its turntable axis when known; re-frames an open cloud. */
  setMerged(axis: [number, number, number] | null, p: URLSearchParams): void {
    let up: [number, number, number] = axis && Math.hypot(...axis) > 0 ? axis : [0, -1, 0];
    const n = Math.hypot(...up);
    up = up.map((v) => v / n) as [number, number, number];
    if (up[1] > 0) up = up.map((v) => -v) as [number, number, number];
    this.merged = { up };
    // Grazing widening assumes the scanner at `scanner`: off unless asked for.
    if (!p.has("grazing")) this.settings.grazing = false;
    if (this.source) this.placeCamera(p);
    window.dispatchEvent(new Event("graylight-settings"));
    this.invalidate();
  }

  /** Initial view: from the URL, else framing the cloud as seen from the scanner's side (a
   * merged cloud: from view 0's side, level with its turntable axis up). */
  private placeCamera(p: URLSearchParams): void {
    const src = this.source!;
    const cam = this.camera;
    cam.setUp(parseVector(p.get("up")) ?? this.merged?.up ?? [0, -1, 0]);
    const o = src.origin;
    const center: [number, number, number] = [0, 1, 2].map((i) => o[i] + (src.tightMin[i] + src.tightMax[i]) / 2) as [
      number,
      number,
      number,
    ];
    const radius = 0.5 * Math.hypot(...[0, 1, 2].map((i) => src.tightMax[i] - src.tightMin[i])) || 1;
    cam.speed = radius * 0.5;
    const pos = parseVector(p.get("pos"));
    const look = parseVector(p.get("look"));
    if (pos) {
      cam.lookAt(pos, look ?? center);
    } else if (this.merged) {
      // No scanner: look across the axis from view 0's side (-z), 20 degrees above level, at the
      // distance where the bounding sphere fits the narrower of the two fields of view.
      if (!p.has("fov")) this.settings.fov = MERGED_FOV;
      cam.fovDeg = this.settings.fov;
      const up = cam.up.map((v) => v / Math.hypot(...cam.up));
      const along = -up[2];
      let h = [-up[0] * along, -up[1] * along, -1 - up[2] * along];
      if (Math.hypot(...h) < 1e-6) h = [1, 0, 0];
      h = h.map((v) => v / Math.hypot(...h));
      const el = (20 * Math.PI) / 180;
      const dir = [0, 1, 2].map((i) => Math.cos(el) * h[i] + Math.sin(el) * up[i]);
      const aspect = this.canvas.clientWidth / Math.max(1, this.canvas.clientHeight) || 1;
      const halfV = (this.settings.fov * Math.PI) / 360;
      const half = Math.min(halfV, Math.atan(Math.tan(halfV) * aspect));
      const dist = radius / Math.sin(half);
      cam.lookAt([0, 1, 2].map((i) => center[i] + dir[i] * dist) as [number, number, number], center);
    } else if (Math.hypot(...center) < 3 * radius && !src.tightMin.every((v, i) => v <= -o[i] && -o[i] <= src.tightMax[i])) {
      // A scan in its scanner's frame: start where the scanner stood, looking at the cloud, with a
      // field of view that frames it (unless one was asked for).
      cam.lookAt([0, 0, 0], center);
      if (!p.has("fov")) this.settings.fov = this.framingFov(cam);
    } else {
      // Otherwise view the cloud from the origin's side, framing its bounding sphere.
      let dir: [number, number, number] = [center[0], center[1], center[2]];
      if (Math.hypot(...dir) < 1e-9 * radius) dir = [0, 0, 1];
      const n = Math.hypot(...dir);
      dir = [dir[0] / n, dir[1] / n, dir[2] / n];
      const dist = radius / Math.sin((cam.fovDeg * Math.PI) / 360);
      cam.lookAt([center[0] - dir[0] * dist, center[1] - dir[1] * dist, center[2] - dir[2] * dist], center);
    }
    const mode = p.get("mode");
    cam.setMode(mode === "orbit" ? "orbit" : "fly");
    if (mode === "orbit" && !look) {
      cam.target = center;
      cam.distance = Math.hypot(cam.position[0] - center[0], cam.position[1] - center[1], cam.position[2] - center[2]);
    }
  }

  /** Vertical field of view (degrees) that shows the whole tight box from the camera's position. */
  private framingFov(cam: Camera): number {
    const src = this.source!;
    const f = cam.forward();
    const r = cam.right();
    const u = [r[1] * f[2] - r[2] * f[1], r[2] * f[0] - r[0] * f[2], r[0] * f[1] - r[1] * f[0]];
    const aspect = this.canvas.clientWidth / Math.max(1, this.canvas.clientHeight) || 1;
    // The root node's points (an even subsample of the cloud) decide, else the tight box's corners.
    const pts = this.framePoints;
    const count = pts ? pts.length / 3 : 8;
    const step = Math.max(1, Math.floor(count / 20_000));
    let tanV = 0;
    for (let i = 0; i < count; i += step) {
      const c = [0, 1, 2].map(
        (k) => src.origin[k] + (pts ? pts[3 * i + k] : i & (1 << k) ? src.tightMax[k] : src.tightMin[k]) - cam.position[k],
      );
      const depth = c[0] * f[0] + c[1] * f[1] + c[2] * f[2];
      if (depth <= 0) return this.settings.fov;
      const x = Math.abs(c[0] * r[0] + c[1] * r[1] + c[2] * r[2]) / depth;
      const y = Math.abs(c[0] * u[0] + c[1] * u[1] + c[2] * u[2]) / depth;
      tanV = Math.max(tanV, y, x / aspect);
    }
    const deg = (2 * Math.atan(tanV * 1.05) * 180) / Math.PI;
    return Math.min(100, Math.max(15, deg));
  }

  private startLoads(sel: Selection): void {
    for (const node of sel.toLoad) {
      if (this.loading >= MAX_CONCURRENT_LOADS) break;
      if (node.state === "unloaded") this.startLoad(node);
    }
  }

  /** On each arrival, pick the next nodes for the last drawn view at once rather than a frame later. */
  private refillLoads(): void {
    if (!this.source || !this.lastView) return;
    const sel = selectNodes(this.source.root, this.lastView, this.settings.budget, MIN_NODE_PX);
    this.lastSelection = sel;
    this.startLoads(sel);
  }

  private startLoad(node: TileNode): void {
    const src = this.source!;
    node.state = "loading";
    this.loading++;
    src
      .loadPoints(node)
      .then((points) => {
        node.gpu = this.renderer.upload(points);
        node.state = "loaded";
        this.loaded.add(node);
        this.loadedPoints += points.count;
      })
      .catch((err: unknown) => {
        if (err instanceof DecoderUnavailable) {
          // The decoder workers stopped; later loads decode on the main thread.
          console.warn(`graylight viewer: ${err.message}`);
          node.state = "unloaded";
          return;
        }
        node.state = "failed";
        this.fail(`loading node ${node.name}: ${err instanceof Error ? err.message : String(err)}`);
      })
      .finally(() => {
        this.loading--;
        this.refillLoads();
        this.invalidate();
      });
  }

  /** Drop least recently drawn nodes when the GPU holds far more than the budget. */
  private evict(): void {
    const cap = Math.round(1.5 * this.settings.budget) + 500_000;
    if (this.loadedPoints <= cap) return;
    const candidates = [...this.loaded].filter((n) => n.lastVisibleFrame < this.frame).sort((a, b) => a.lastVisibleFrame - b.lastVisibleFrame);
    for (const node of candidates) {
      if (this.loadedPoints <= cap) break;
      this.renderer.release(node.gpu as GpuNode);
      node.gpu = null;
      node.state = "unloaded";
      this.loaded.delete(node);
      this.loadedPoints -= node.numPoints;
    }
  }

  /** Attach a mesh (levels finest first); `headersFor` gives each URL's request headers. */
  setMesh(levels: { url: string; name?: string; bytes?: number | null }[], headersFor: (url: string) => Record<string, string>): MeshLayer {
    this.mesh = new MeshLayer(levels, headersFor, this.renderer, () => this.invalidate(), (m) => this.warn(m));
    this.invalidate();
    return this.mesh;
  }

  /** A one-line message that leaves the point view running (unlike `fail`). */
  warn(message: string): void {
    this.notice = message;
    console.warn(`graylight viewer: ${message}`);
    const el = document.getElementById("notice");
    if (el) {
      el.textContent = message;
      el.hidden = false;
    }
  }

  fail(message: string): void {
    this.error = message;
    console.error(`graylight viewer: ${message}`);
    const el = document.getElementById("error");
    if (el) {
      el.textContent = message;
      el.hidden = false;
    }
  }

  private viewport(): { width: number; height: number } {
    const dpr = Math.min(window.devicePixelRatio || 1, 2);
    return {
      width: Math.max(1, Math.round(this.canvas.clientWidth * dpr)),
      height: Math.max(1, Math.round(this.canvas.clientHeight * dpr)),
    };
  }

  /** Select nodes, queue loads and draw one frame. */
  renderFrame(): void {
    const src = this.source;
    const { width, height } = this.viewport();
    this.renderer.resize(width, height);
    const cam = this.camera;
    cam.fovDeg = this.settings.fov;
    const fovY = (cam.fovDeg * Math.PI) / 180;
    const focalPx = height / 2 / Math.tan(fovY / 2);
    const view = cam.viewMatrix();
    const origin = src ? src.origin : [0, 0, 0];
    const model = mat4.fromTranslation(mat4.create(), origin as [number, number, number]);
    const modelView = mat4.multiply(mat4.create(), view, model);
    // Near and far planes from the cloud's extent (and the mesh's), so depth precision follows the scene scale.
    let near = 0.01;
    let far = 1000;
    if (src) {
      const lo = [0, 1, 2].map((i) => origin[i] + src.tightMin[i]);
      const hi = [0, 1, 2].map((i) => origin[i] + src.tightMax[i]);
      if (this.mesh?.min && this.mesh.max && this.settings.mesh) {
        for (let i = 0; i < 3; i++) {
          lo[i] = Math.min(lo[i], this.mesh.min[i]);
          hi[i] = Math.max(hi[i], this.mesh.max[i]);
        }
      }
      const c = [0, 1, 2].map((i) => (lo[i] + hi[i]) / 2);
      const r = 0.5 * Math.hypot(...[0, 1, 2].map((i) => hi[i] - lo[i])) || 1;
      const d = Math.hypot(c[0] - cam.position[0], c[1] - cam.position[1], c[2] - cam.position[2]);
      far = d + r * 1.5 + 1e-6;
      near = Math.max(far * 1e-5, (d - r * 1.5) * 0.5);
    }
    const projection = mat4.perspective(mat4.create(), fovY, width / height, near, far);
    const meshes = this.mesh?.select(this.settings.mesh ? { eye: cam.position, focalPx } : null) ?? [];
    // The mesh stands in for the points unless both were asked for (points keep loading meanwhile).
    const drawPoints = meshes.length === 0 || this.settings.meshPoints;
    const items: DrawItem[] = [];
    let drawnPoints = 0;
    if (src) {
      const viewProj = mat4.multiply(mat4.create(), projection, modelView);
      const eyeLocal: [number, number, number] = [0, 1, 2].map((i) => cam.position[i] - origin[i]) as [number, number, number];
      const sel = selectNodes(src.root, { viewProj, eye: eyeLocal, focalPx }, this.settings.budget, MIN_NODE_PX);
      this.lastSelection = sel;
      for (const node of sel.visible) {
        // Marked in use even under the mesh, so the cache keeps them rather than evicting and reloading.
        node.lastVisibleFrame = this.frame;
        if (!drawPoints) continue;
        // Coarse nodes stand in for finer ones not drawn: size their splats from the node spacing.
        const fill = sel.coarse.has(node) || !src.hasSize ? node.spacing : 0;
        items.push({ gpu: node.gpu as GpuNode, fill });
        drawnPoints += node.numPoints;
      }
      this.lastView = { viewProj, eye: eyeLocal, focalPx };
      this.startLoads(sel);
      this.evict();
    }
    const s = this.settings;
    const frame: FrameSettings = {
      modelView: new Float32Array(modelView),
      projection: new Float32Array(projection),
      focalPx,
      sizing: s.sizing,
      fixedPx: s.fixedPx,
      splatScale: s.splatScale,
      edl: s.edl,
      edlStrength: s.edlStrength,
      edlRadius: s.edlRadius,
      hq: s.hq,
      blendDepth: 2,
      background: s.background,
      grazing: s.grazing,
      scanner: [0, 1, 2].map((i) => s.scanner[i] - origin[i]) as [number, number, number],
      view,
    };
    this.renderer.render(items, frame, meshes);
    this.frame++;
    this.drawnPoints = drawnPoints;
    this.drawnNodes = items.length;
  }

  drawnPoints = 0;
  drawnNodes = 0;

  tick(now: number): void {
    const dt = Math.min(0.1, (now - this.lastTime) / 1000);
    this.lastTime = now;
    if (this.camera.move(this.controls.keys, dt)) this.invalidate();
    const { width, height } = this.viewport();
    if (width !== this.canvas.width || height !== this.canvas.height) this.invalidate();
    if (this.dirty) {
      this.dirty = false;
      const t0 = performance.now();
      this.renderFrame();
      // Milliseconds of CPU time per drawn frame (GPU work is asynchronous and not included).
      this.frameMs = 0.8 * this.frameMs + 0.2 * (performance.now() - t0);
      this.updateStats();
      // Keep going while loads are pending: each arrival refines the cut.
      if (this.loading > 0) this.dirty = true;
    } else {
      this.quietFrames++;
    }
  }

  /** True once nothing is loading, nothing more is wanted for this view and that view was drawn. */
  idle(): boolean {
    if (this.error) return true;
    if (!this.source || this.loading > 0 || this.dirty) return false;
    if (this.mesh && this.settings.mesh && (this.mesh.loading > 0 || this.mesh.wanted?.state === "unloaded")) return false;
    const wanted = this.lastSelection?.toLoad.filter((n) => n.state === "unloaded").length ?? 0;
    return wanted === 0 && this.quietFrames > 0;
  }

  state(): Record<string, unknown> {
    return {
      error: this.error,
      frame: this.frame,
      totalPoints: this.source?.metadata.points ?? 0,
      drawnPoints: this.drawnPoints,
      drawnNodes: this.drawnNodes,
      loadedNodes: this.loaded.size,
      loadedPoints: this.loadedPoints,
      loading: this.loading,
      hasSize: this.source?.hasSize ?? false,
      hasColor: this.source?.hasColor ?? false,
      hasNormal: this.source?.hasNormal ?? false,
      decoderWorkers: this.source?.decoder.size ?? 0,
      camera: { position: this.camera.position, forward: this.camera.forward(), mode: this.camera.mode, fov: this.camera.fovDeg },
      settings: { ...this.settings },
      merged: this.merged,
      up: this.camera.up,
      maxPointPx: this.renderer.maxPointPx,
      notice: this.notice,
      mesh: this.mesh ? { shown: this.settings.mesh, ...this.mesh.state() } : null,
    };
  }

  private updateStats(): void {
    if (!this.statsEl) return;
    const total = this.source?.metadata.points ?? 0;
    const drawnMesh = this.settings.mesh ? this.mesh?.drawn : null;
    const mesh = drawnMesh ? ` · mesh ${drawnMesh.name}: ${(drawnMesh.triangles ?? 0).toLocaleString()} triangles` : "";
    this.statsEl.textContent =
      `${this.drawnPoints.toLocaleString()} of ${total.toLocaleString()} points · ${this.drawnNodes} nodes` +
      ` · ${this.loading} loading · ${this.frameMs.toFixed(0)} ms a frame${mesh}`;
  }
}

function bindUi(viewer: Viewer, p: URLSearchParams): void {
  const panel = document.getElementById("panel");
  if (!panel) return;
  if (p.get("ui") === "0") {
    panel.hidden = true;
    return;
  }
  const s = viewer.settings;
  const $ = <T extends HTMLElement>(id: string) => document.getElementById(id) as T | null;
  const on = (id: string, fn: (el: HTMLInputElement) => void) => {
    const el = $<HTMLInputElement>(id);
    if (!el) return;
    el.addEventListener("input", () => {
      fn(el);
      viewer.invalidate();
    });
  };
  const label = (id: string, text: string) => {
    const el = $(id);
    if (el) el.textContent = text;
  };
  const budgetEl = $<HTMLInputElement>("budget");
  if (budgetEl) budgetEl.value = String(Math.log10(s.budget));
  label("budget-value", s.budget.toLocaleString());
  on("budget", (el) => {
    s.budget = Math.round(Math.pow(10, Number(el.value)));
    label("budget-value", s.budget.toLocaleString());
  });
  const fovEl = $<HTMLInputElement>("fov");
  if (fovEl) fovEl.value = String(s.fov);
  label("fov-value", `${s.fov.toFixed(0)}°`);
  on("fov", (el) => {
    s.fov = Number(el.value);
    label("fov-value", `${s.fov.toFixed(0)}°`);
  });
  const speedEl = $<HTMLInputElement>("speed");
  const showSpeed = () => label("speed-value", viewer.camera.speed.toPrecision(2));
  if (speedEl) speedEl.value = "0";
  let baseSpeed = 0;
  on("speed", (el) => {
    if (baseSpeed === 0) baseSpeed = viewer.camera.speed;
    viewer.camera.speed = baseSpeed * Math.pow(10, Number(el.value));
    showSpeed();
  });
  const scaleEl = $<HTMLInputElement>("scale");
  if (scaleEl) scaleEl.value = String(s.splatScale);
  label("scale-value", s.splatScale.toFixed(2));
  on("scale", (el) => {
    s.splatScale = Number(el.value);
    label("scale-value", s.splatScale.toFixed(2));
  });
  const checks: [string, "edl" | "hq" | "grazing"][] = [["edl", "edl"], ["hq", "hq"], ["grazing", "grazing"]];
  for (const [id, key] of checks) {
    const el = $<HTMLInputElement>(id);
    if (!el) continue;
    el.checked = s[key];
    el.addEventListener("change", () => {
      s[key] = el.checked;
      viewer.invalidate();
    });
    // A merged cloud turns grazing widening off after the panel is built (Viewer.setMerged).
    window.addEventListener("graylight-settings", () => {
      el.checked = s[key];
    });
  }
  const sizingEl = $<HTMLSelectElement>("sizing");
  if (sizingEl) {
    sizingEl.value = s.sizing;
    sizingEl.addEventListener("change", () => {
      s.sizing = sizingEl.value === "fixed" ? "fixed" : "seed";
      viewer.invalidate();
    });
  }
  const modeEl = $<HTMLSelectElement>("mode");
  if (modeEl) {
    modeEl.value = viewer.camera.mode;
    modeEl.addEventListener("change", () => {
      viewer.camera.setMode(modeEl.value as NavMode);
      viewer.invalidate();
    });
  }
  window.addEventListener("keydown", (e) => {
    const t = e.target as HTMLElement | null;
    if (t && (t.tagName === "INPUT" || t.tagName === "SELECT")) return;
    if (e.code === "KeyH") panel.hidden = !panel.hidden;
    if (e.code !== "KeyF" && e.code !== "KeyO") return;
    viewer.camera.setMode(e.code === "KeyF" ? "fly" : "orbit");
    if (modeEl) modeEl.value = viewer.camera.mode;
    viewer.invalidate();
  });
  // Keep the speed readout in step with mouse-wheel changes, and in step with the scene once open.
  viewer.canvas.addEventListener("wheel", showSpeed);
  window.addEventListener("graylight-open", () => {
    if (modeEl) modeEl.value = viewer.camera.mode;
    if (fovEl) fovEl.value = String(s.fov);
    label("fov-value", `${s.fov.toFixed(0)}°`);
    baseSpeed = viewer.camera.speed;
    if (speedEl) speedEl.value = "0";
    showSpeed();
  });
}

const MESH_ARTIFACT = /^mesh(_lod\d+)?\.glb$/;

/**
 * Find the mesh: the page's `mesh` URLs, else the job's `mesh.glb` / `mesh_lod*.glb` artifacts
 * (listed with the Bearer key). Nothing to find is not an error; a failed listing is a notice.
 */
async function attachMesh(viewer: Viewer, p: URLSearchParams, config: PageConfig, tilesUrl: URL, key: string | null): Promise<void> {
  const headersFor = (url: string): Record<string, string> =>
    key && new URL(url, document.baseURI).origin === location.origin ? { Authorization: `Bearer ${key}` } : {};
  const urls = p.getAll("mesh").filter((u) => u.trim());
  if (p.get("merged") === "1") viewer.setMerged(parseVector(p.get("axis")), p);
  let levels: { url: string; name?: string; bytes?: number | null }[] = [];
  if (urls.length) {
    levels = urls.map((u) => ({ url: new URL(u, document.baseURI).toString() }));
  } else if (config.job) {
    // The artifact list sits beside the tiles folder: .../artifacts/tiles/ -> .../artifacts.
    const listUrl = new URL(config.artifacts ?? new URL("..", tilesUrl).toString().replace(/\/$/, ""), document.baseURI);
    const response = await fetch(listUrl, { headers: headersFor(listUrl.toString()) });
    if (!response.ok) throw new Error(`listing the job's artifacts: HTTP ${response.status} from ${listUrl.pathname}`);
    const list = (await response.json()) as { name?: string; artifacts?: { name: string; stage?: string; size?: number }[] };
    if (list.name && !p.get("name")) showName(list.name);
    const arts = list.artifacts ?? [];
    // A multi-view job (its merge published registration.json): merged, axis up.
    const reg = arts.find((a) => a.name === "registration.json") ?? arts.find((a) => /^[^/]+\/registration\.json$/.test(a.name));
    if (reg) await markMerged(viewer, p, new URL(`${listUrl.toString().replace(/\/$/, "")}/${reg.name}`), headersFor);
    // mesh.glb by its short (published) name, else as STAGE/mesh.glb; the levels of detail from
    // the same stage, by short name if published, else STAGE/mesh_lodN.glb.
    const file = (name: string) => name.slice(name.lastIndexOf("/") + 1);
    const isLevel = (name: string) => MESH_ARTIFACT.test(file(name)) && name.split("/").length <= 2;
    const main = arts.find((a) => a.name === "mesh.glb") ?? arts.find((a) => isLevel(a.name) && file(a.name) === "mesh.glb");
    const stage = main?.stage ?? (main && main.name.includes("/") ? main.name.split("/")[0] : undefined);
    const chosen = new Map<string, { name: string; size?: number }>();
    for (const a of arts) {
      if (!isLevel(a.name)) continue;
      const inStage = a.name.includes("/") ? a.name.split("/")[0] === stage : a.stage === undefined || a.stage === stage;
      if (main && !inStage) continue;
      if (!a.name.includes("/") || !chosen.has(file(a.name))) chosen.set(file(a.name), a);
    }
    const base = listUrl.toString().replace(/\/$/, "");
    // Textured derivatives (the derivatives stage's published names) win over the untextured
    // master and its LODs; Thumb (a catalogue thumbnail) only when there is nothing finer.
    const derived = arts.filter((a) => !a.name.includes("/") && derivativePx(a.name) !== null);
    const shown = derived.length > 1 ? derived.filter((a) => a.name !== "mesh_thumb.glb") : derived;
    if (shown.length) {
      chosen.clear();
      for (const a of shown) chosen.set(a.name, a);
      // The object itself is what a merged job opens on; the points are one toggle (M) away.
      if (!p.has("showmesh")) viewer.settings.mesh = true;
    }
    levels = orderLevels([...chosen.entries()].map(([f, a]) => ({ name: f, path: a.name, size: a.size }))).map((a) => ({
      url: `${base}/${a.path.split("/").map(encodeURIComponent).join("/")}`,
      name: a.name,
      bytes: a.size ?? null,
    }));
  }
  if (!levels.length) return;
  viewer.setMesh(levels, headersFor);
  bindMeshUi(viewer, levels[0].url, headersFor(levels[0].url));
}

/**
 * Mark the viewer's cloud merged, with the turntable axis of the merge's registration.json when
 * it has one (a merge without a turntable: view 0's up). A registration that cannot be read
 * still marks it merged (the cloud has no scanner either way) and says so in one line.
 */
async function markMerged(viewer: Viewer, p: URLSearchParams, url: URL, headersFor: (url: string) => Record<string, string>): Promise<void> {
  let axis: [number, number, number] | null = null;
  try {
    const r = await fetch(url, { headers: headersFor(url.toString()) });
    if (!r.ok) throw new Error(`HTTP ${r.status}`);
    const doc = (await r.json()) as { turntable_axis?: { direction?: unknown } | null };
    const d = doc.turntable_axis?.direction;
    if (Array.isArray(d) && d.length === 3 && d.every((v) => typeof v === "number" && Number.isFinite(v))) {
      axis = d as [number, number, number];
    }
  } catch (err) {
    viewer.warn(`registration.json not read (${err instanceof Error ? err.message : String(err)}): the view keeps view 0's up`);
  }
  viewer.setMerged(axis, p);
}

/** The mesh section of the panel: the toggle, points-with-mesh, and a download of the finest level. */
function bindMeshUi(viewer: Viewer, downloadUrl: string, headers: Record<string, string>): void {
  const section = document.getElementById("mesh-controls");
  if (!section) return;
  section.hidden = false;
  const s = viewer.settings;
  const boxes = [["mesh", "mesh"], ["mesh-points", "meshPoints"]] as const;
  const sync = () => {
    for (const [id, key] of boxes) {
      const el = document.getElementById(id) as HTMLInputElement | null;
      if (el) el.checked = s[key];
    }
  };
  for (const [id, key] of boxes) {
    const el = document.getElementById(id) as HTMLInputElement | null;
    if (!el) continue;
    el.addEventListener("change", () => {
      s[key] = el.checked;
      viewer.invalidate();
    });
  }
  sync();
  // Settings changed elsewhere (window.graylight.set, the M key) show in the boxes.
  window.addEventListener("graylight-settings", sync);
  window.addEventListener("keydown", (e) => {
    const t = e.target as HTMLElement | null;
    if (e.code !== "KeyM" || (t && (t.tagName === "INPUT" || t.tagName === "SELECT"))) return;
    s.mesh = !s.mesh;
    sync();
    viewer.invalidate();
  });
  const link = document.getElementById("mesh-download") as HTMLAnchorElement | null;
  if (!link) return;
  const layer = viewer.mesh!;
  const finest = layer.levels[0];
  link.href = downloadUrl;
  link.download = finest.name;
  link.textContent = `Download ${finest.name}` + (finest.bytes ? ` (${(finest.bytes / 1e6).toFixed(1)} MB)` : "");
  if (!headers.Authorization) return;
  // A plain link cannot carry the Bearer key: fetch the file with it and save the blob.
  link.addEventListener("click", (e) => {
    e.preventDefault();
    fetch(downloadUrl, { headers })
      .then((r) => {
        if (!r.ok) throw new Error(`HTTP ${r.status}`);
        return r.blob();
      })
      .then((blob) => {
        const a = document.createElement("a");
        a.href = URL.createObjectURL(blob);
        a.download = finest.name;
        document.body.appendChild(a);
        a.click();
        a.remove();
        setTimeout(() => URL.revokeObjectURL(a.href), 60_000);
      })
      .catch((err: unknown) => viewer.warn(`downloading ${finest.name}: ${err instanceof Error ? err.message : String(err)}`));
  });
}

function start(): void {
  const p = params();
  const canvas = document.getElementById("view") as HTMLCanvasElement;
  const config = injectedConfig();
  const tiles = p.get("tiles") ?? config.tiles ?? null;
  let viewer: Viewer;
  try {
    viewer = new Viewer(canvas, p);
  } catch (err) {
    const message = err instanceof Error ? err.message : String(err);
    console.error(`graylight viewer: ${message}`);
    const el = document.getElementById("error");
    if (el) {
      el.textContent = message;
      el.hidden = false;
    }
    return;
  }
  const api = {
    viewer,
    state: () => viewer.state(),
    idle: () => viewer.idle(),
    /** Apply settings (same names as the Settings record) and redraw. */
    set: (changes: Partial<Settings>) => {
      Object.assign(viewer.settings, changes);
      window.dispatchEvent(new Event("graylight-settings"));
      viewer.invalidate();
    },
    /** Place the camera (world coordinates) and redraw. */
    lookAt: (pos: [number, number, number], look: [number, number, number]) => {
      viewer.camera.lookAt(pos, look);
      viewer.invalidate();
    },
    /** Draw a frame now and return the canvas as a PNG data URL. */
    capture: (): string => {
      viewer.renderFrame();
      return canvas.toDataURL("image/png");
    },
  };
  (window as unknown as { graylight: typeof api }).graylight = api;
  bindUi(viewer, p);
  const loop = (now: number) => {
    viewer.tick(now);
    requestAnimationFrame(loop);
  };
  requestAnimationFrame(loop);
  if (!tiles) {
    viewer.fail("no tiles to show: open /viewer/{job} or give ?tiles=URL of a Potree 2.0 folder");
    return;
  }
  const headers: Record<string, string> = {};
  const key = p.get("key") ?? cookie("graylight_key");
  const tilesUrl = new URL(tiles, document.baseURI);
  // The key is for the job service only: never send it to another origin.
  if (key && tilesUrl.origin === location.origin) headers.Authorization = `Bearer ${key}`;
  // The title is ?name=, or the job's name once its artifact list (read with the key) names it.
  const named = p.get("name") ?? config.job;
  if (named) showName(named);
  viewer.open(tilesUrl.toString(), headers, p).catch((err: unknown) => {
    viewer.fail(err instanceof Error ? err.message : String(err));
  });
  attachMesh(viewer, p, config, tilesUrl, key).catch((err: unknown) => {
    viewer.warn(err instanceof Error ? err.message : String(err));
  });
}

start();
