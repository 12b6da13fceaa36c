/**
 * Virtual camera and navigation: fly-through (mouse look, WASD, speed) and orbit.
 *
 * The camera lives in world coordinates (the cloud's own units and frame). Heading is kept
 * as yaw and pitch about a world "up" axis; Graylight clouds are in the scanner camera's
 * frame (x right, y down, z forward), so up defaults to -y and the first view looks along +z.
 */

import { mat4, vec3 } from "gl-matrix";

export type NavMode = "fly" | "orbit";
type V3 = [number, number, number];

function norm(v: V3): V3 {
  const n = Math.hypot(v[0], v[1], v[2]) || 1;
  return [v[0] / n, v[1] / n, v[2] / n];
}
function cross(a: V3, b: V3): V3 {
  return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
}
function dot(a: V3, b: V3): number {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}
function add(a: V3, b: V3, s = 1): V3 {
  return [a[0] + s * b[0], a[1] + s * b[1], a[2] + s * b[2]];
}

/** Parse "x,y,z" or an axis name like "-y" into a vector. */
export function parseVector(text: string | null): V3 | null {
  if (!text) return null;
  const axes: Record<string, V3> = { x: [1, 0, 0], y: [0, 1, 0], z: [0, 0, 1] };
  const t = text.trim().toLowerCase();
  const m = /^([+-]?)([xyz])$/.exec(t);
  if (m) {
    const s = m[1] === "-" ? -1 : 1;
    const a = axes[m[2]];
    return [s * a[0], s * a[1], s * a[2]];
  }
  const parts = t.split(",").map(Number);
  if (parts.length !== 3 || parts.some((p) => !Number.isFinite(p))) return null;
  return [parts[0], parts[1], parts[2]];
}

export class Camera {
  up: V3 = [0, -1, 0];
  private f0: V3 = [0, 0, 1];
  private r0: V3 = [1, 0, 0];
  position: V3 = [0, 0, 0];
  yaw = 0;
  pitch = 0;
  mode: NavMode = "fly";
  /** Orbit centre and distance (orbit mode). */
  target: V3 = [0, 0, 1];
  distance = 1;
  fovDeg = 60;
  /** Fly speed in world units per second. */
  speed = 1;

  setUp(up: V3): void {
    this.up = norm(up);
    // A horizontal reference direction: the world axis least aligned with up, made orthogonal.
    const candidates: V3[] = [[0, 0, 1], [0, 1, 0], [1, 0, 0]];
    let best = candidates[0];
    for (const c of candidates) if (Math.abs(dot(c, this.up)) < Math.abs(dot(best, this.up))) best = c;
    this.f0 = norm(add(best, this.up, -dot(best, this.up)));
    this.r0 = norm(cross(this.f0, this.up));
  }

  forward(): V3 {
    const cp = Math.cos(this.pitch);
    const h = add([0, 0, 0], this.f0, cp * Math.cos(this.yaw));
    return norm(add(add(h, this.r0, cp * Math.sin(this.yaw)), this.up, Math.sin(this.pitch)));
  }

  right(): V3 {
    return norm(cross(this.forward(), this.up));
  }

  /** Place the camera at `pos` looking at `look` (world coordinates). */
  lookAt(pos: V3, look: V3): void {
    const f = norm(add(look, pos, -1));
    this.position = [...pos];
    this.pitch = Math.asin(Math.max(-1, Math.min(1, dot(f, this.up))));
    const h = add(f, this.up, -dot(f, this.up));
    this.yaw = Math.atan2(dot(h, this.r0), dot(h, this.f0));
    this.target = [...look];
    this.distance = Math.max(1e-9, Math.hypot(look[0] - pos[0], look[1] - pos[1], look[2] - pos[2]));
  }

  setMode(mode: NavMode): void {
    if (mode === this.mode) return;
    if (mode === "orbit") this.target = add(this.position, this.forward(), this.distance);
    this.mode = mode;
  }

  /** Orbit mode keeps the eye on a sphere about the target. */
  private syncOrbit(): void {
    if (this.mode === "orbit") this.position = add(this.target, this.forward(), -this.distance);
  }

  /** World-to-view matrix (float64 arrays, as gl-matrix is configured in main). */
  viewMatrix(): mat4 {
    const eye = vec3.fromValues(...this.position);
    const center = vec3.fromValues(...add(this.position, this.forward()));
    return mat4.lookAt(mat4.create(), eye, center, vec3.fromValues(...this.up));
  }

  rotate(dxPx: number, dyPx: number, heightPx: number): void {
    const perPx = ((this.fovDeg * Math.PI) / 180) / Math.max(1, heightPx);
    const sign = this.mode === "orbit" ? -1 : 1;
    this.yaw += sign * dxPx * perPx;
    this.pitch = Math.max(-1.55, Math.min(1.55, this.pitch - dyPx * perPx));
    this.syncOrbit();
  }

  pan(dxPx: number, dyPx: number, heightPx: number): void {
    const perPx = (2 * this.distance * Math.tan((this.fovDeg * Math.PI) / 360)) / Math.max(1, heightPx);
    const r = this.right();
    const u = norm(cross(r, this.forward()));
    const move = add(add([0, 0, 0], r, -dxPx * perPx), u, dyPx * perPx);
    this.target = add(this.target, move);
    this.position = add(this.position, move);
  }

  /** Mouse wheel: dolly in orbit mode, change speed in fly mode. */
  wheel(steps: number): void {
    const factor = Math.pow(1.15, steps);
    if (this.mode === "orbit") {
      this.distance = Math.max(1e-6, this.distance * factor);
      this.syncOrbit();
    } else {
      this.speed = Math.max(1e-6, this.speed / factor);
    }
  }

  /** Move by held keys for `dt` seconds; returns whether the camera moved. */
  move(keys: Set<string>, dt: number): boolean {
    let fwd = 0;
    let side = 0;
    let lift = 0;
    if (keys.has("KeyW") || keys.has("ArrowUp")) fwd += 1;
    if (keys.has("KeyS") || keys.has("ArrowDown")) fwd -= 1;
    if (keys.has("KeyD") || keys.has("ArrowRight")) side += 1;
    if (keys.has("KeyA") || keys.has("ArrowLeft")) side -= 1;
    if (keys.has("KeyE") || keys.has("Space")) lift += 1;
    if (keys.has("KeyQ") || keys.has("KeyC")) lift -= 1;
    if (fwd === 0 && side === 0 && lift === 0) return false;
    const boost = keys.has("ShiftLeft") || keys.has("ShiftRight") ? 4 : 1;
    const step = this.speed * boost * dt;
    if (this.mode === "orbit") {
      // In orbit mode W/S dolly towards the target and A/D/Q/E circle about it.
      this.distance = Math.max(1e-6, this.distance * Math.exp(-fwd * dt * 1.5 * boost));
      this.yaw -= side * dt * 1.2 * boost;
      this.pitch = Math.max(-1.55, Math.min(1.55, this.pitch + lift * dt * 1.2 * boost));
      this.syncOrbit();
      return true;
    }
    let p = add(this.position, this.forward(), fwd * step);
    p = add(p, this.right(), side * step);
    p = add(p, this.up, lift * step);
    this.position = p;
    return true;
  }
}

/** Mouse and keyboard bindings; calls `changed` whenever the view moves. */
export class Controls {
  keys = new Set<string>();
  private dragging: number | null = null;
  private last: [number, number] = [0, 0];

  constructor(
    private camera: Camera,
    private canvas: HTMLCanvasElement,
    private changed: () => void,
  ) {
    canvas.addEventListener("contextmenu", (e) => e.preventDefault());
    canvas.addEventListener("pointerdown", (e) => {
      this.dragging = e.button;
      this.last = [e.clientX, e.clientY];
      canvas.setPointerCapture(e.pointerId);
      canvas.focus();
    });
    canvas.addEventListener("pointerup", (e) => {
      this.dragging = null;
      canvas.releasePointerCapture(e.pointerId);
    });
    canvas.addEventListener("pointermove", (e) => {
      if (this.dragging === null) return;
      const dx = e.clientX - this.last[0];
      const dy = e.clientY - this.last[1];
      this.last = [e.clientX, e.clientY];
      const h = canvas.clientHeight;
      if (this.dragging === 0 && !e.shiftKey) this.camera.rotate(dx, dy, h);
      else this.camera.pan(dx, dy, h);
      this.changed();
    });
    canvas.addEventListener(
      "wheel",
      (e) => {
        e.preventDefault();
        this.camera.wheel(Math.sign(e.deltaY));
        this.changed();
      },
      { passive: false },
    );
    window.addEventListener("keydown", (e) => {
      const t = e.target as HTMLElement | null;
      if (t && (t.tagName === "INPUT" || t.tagName === "SELECT")) return;
      this.keys.add(e.code);
    });
    window.addEventListener("keyup", (e) => this.keys.delete(e.code));
    window.addEventListener("blur", () => this.keys.clear());
  }
}
