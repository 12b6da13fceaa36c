/**
 * The mesh layer: a job's `mesh.glb` and its level-of-detail meshes (`mesh_lod1.glb` ...), or
 * the `mesh` URLs of the page, loaded on demand and drawn in the points' camera.
 *
 * Levels are ordered finest first. While the mesh is shown, the coarsest level loads first (so
 * something appears at once); then each frame picks the finest level whose triangle count stays
 * within TRIANGLES_PER_PIXEL times the pixel area of the mesh's projected bounding sphere (more
 * triangles than pixels add no detail), loads it if needed (one download at a time) and draws
 * the loaded level nearest to it. Triangle counts of levels not loaded yet are estimated from
 * their byte sizes when the artifact list gives them, else as a factor of 4 per level.
 *
 * A level that fails (HTTP error, GLB that does not parse, GPU out of memory) is marked failed
 * and reported by `onError` in one line; the other levels and the point view carry on.
 */

import { derivativePx, parseDerivative } from "./derivative";
import { type GlbMesh, parseGlb } from "./gltf";
import type { GpuMesh, Renderer } from "./renderer";

/**
 * Triangles a level may have per pixel of its bounding sphere's projected disc. A closed surface
 * shows about half its triangles, on at most that disc: below one visible triangle per two pixels.
 */
export const TRIANGLES_PER_PIXEL = 1;

const INDEX_BITS: Record<number, number> = { 5121: 8, 5123: 16, 5125: 32 };

export type LevelState = "unloaded" | "loading" | "loaded" | "failed";

export interface MeshLevel {
  url: string;
  /** Short name for messages and the UI (the file name). */
  name: string;
  /** File size when known beforehand (artifact list), else after download. */
  bytes: number | null;
  state: LevelState;
  triangles: number | null;
  gpu: GpuMesh | null;
  error: string | null;
}

export interface MeshView {
  /** Camera position, world. */
  eye: [number, number, number];
  focalPx: number;
}

export class MeshLayer {
  readonly levels: MeshLevel[];
  /** World bounds of the first loaded level (every level covers the same surface). */
  min: [number, number, number] | null = null;
  max: [number, number, number] | null = null;
  loading = 0;
  drawn: MeshLevel | null = null;
  wanted: MeshLevel | null = null;

  constructor(
    levels: { url: string; name?: string; bytes?: number | null }[],
    private headersFor: (url: string) => Record<string, string>,
    private renderer: Renderer,
    private onChange: () => void,
    private onError: (message: string) => void,
  ) {
    this.levels = levels.map((l) => ({
      url: l.url,
      name: l.name ?? (decodeURIComponent(new URL(l.url, document.baseURI).pathname.split("/").pop() || "") || l.url),
      bytes: l.bytes ?? null,
      state: "unloaded",
      triangles: null,
      gpu: null,
      error: null,
    }));
  }

  get failed(): MeshLevel[] {
    return this.levels.filter((l) => l.state === "failed");
  }

  /** Estimated triangles of a level: exact when loaded, else scaled from a loaded level. */
  estimate(level: MeshLevel): number {
    // A textured derivative's detail is its maps (Low, Medium and High have the same faces):
    // about a quarter of an atlas's texels face the camera, so a level is worth its texels / 4.
    const px = derivativePx(level.name);
    if (px !== null) return (px * px) / 4;
    if (level.triangles !== null) return level.triangles;
    const known = this.levels.find((l) => l.triangles !== null && l.bytes);
    if (known && level.bytes && known.bytes) return (known.triangles! * level.bytes) / known.bytes;
    const ref = known ?? null;
    const i = this.levels.indexOf(level);
    if (ref) return ref.triangles! * Math.pow(4, this.levels.indexOf(ref) - i);
    return level.bytes ? level.bytes / 20 : Math.pow(4, this.levels.length - i) * 1e3;
  }

  /**
   * The meshes to draw this frame (at most one level), starting any load the view needs.
   * `view` null means the mesh is hidden: nothing is drawn or loaded.
   */
  select(view: MeshView | null): GpuMesh[] {
    if (!view) return [];
    const usable = this.levels.filter((l) => l.state !== "failed");
    if (!usable.length) return [];
    const coarsest = usable[usable.length - 1];
    if (coarsest.state === "unloaded" && this.loading === 0) this.load(coarsest);
    let wanted = coarsest;
    if (this.min && this.max) {
      const c = [0, 1, 2].map((k) => (this.min![k] + this.max![k]) / 2);
      const r = 0.5 * Math.hypot(...[0, 1, 2].map((k) => this.max![k] - this.min![k])) || 1;
      const d = Math.hypot(c[0] - view.eye[0], c[1] - view.eye[1], c[2] - view.eye[2]);
      // Inside or very near the sphere the projection blows up: any detail may be seen.
      const rPx = d > r * 1.01 ? (view.focalPx * r) / Math.sqrt(d * d - r * r) : Infinity;
      const pixels = Math.PI * rPx * rPx;
      wanted = usable.find((l) => this.estimate(l) <= TRIANGLES_PER_PIXEL * pixels) ?? coarsest;
    }
    this.wanted = wanted;
    if (wanted.state === "unloaded" && this.loading === 0) this.load(wanted);
    // Draw the loaded level nearest the wanted one (finer first on a tie: it was wanted before).
    const at = usable.indexOf(wanted);
    let best: MeshLevel | null = null;
    for (const l of usable) {
      if (l.state !== "loaded") continue;
      if (!best || Math.abs(usable.indexOf(l) - at) < Math.abs(usable.indexOf(best) - at)) best = l;
    }
    if (best !== this.drawn && best) {
      // Free the GPU memory of levels finer than the one drawn (unless wanted); coarser ones
      // stay, all of them together holding about a third of the drawn one's triangles.
      for (const l of usable) {
        if (usable.indexOf(l) < usable.indexOf(best) && l !== wanted && l.state === "loaded") this.unload(l);
      }
    }
    this.drawn = best;
    return best ? [best.gpu!] : [];
  }

  private unload(level: MeshLevel): void {
    if (level.gpu) this.renderer.releaseMesh(level.gpu);
    level.gpu = null;
    level.state = "unloaded";
  }

  private load(level: MeshLevel): void {
    level.state = "loading";
    this.loading++;
    this.fetchLevel(level)
      .then((mesh) => {
        level.gpu = this.renderer.uploadMesh(mesh);
        level.triangles = mesh.triangles;
        level.state = "loaded";
        if (!this.min) {
          this.min = mesh.min;
          this.max = mesh.max;
        }
      })
      .catch((err: unknown) => {
        level.state = "failed";
        level.error = err instanceof Error ? err.message : String(err);
        this.onError(`mesh ${level.name}: ${level.error}`);
      })
      .finally(() => {
        this.loading--;
        this.onChange();
      });
  }

  private async fetchLevel(level: MeshLevel): Promise<GlbMesh> {
    const response = await fetch(level.url, { headers: this.headersFor(level.url) });
    if (!response.ok) throw new Error(`HTTP ${response.status} ${response.statusText}`.trim());
    const buffer = await response.arrayBuffer();
    level.bytes = buffer.byteLength;
    return derivativePx(level.name) !== null ? parseDerivative(buffer) : parseGlb(buffer);
  }

  state(): Record<string, unknown> {
    const gpu = this.drawn?.gpu ?? null;
    return {
      levels: this.levels.map((l) => ({ name: l.name, url: l.url, state: l.state, triangles: l.triangles, bytes: l.bytes, error: l.error })),
      drawn: this.drawn?.name ?? null,
      drawnTriangles: this.drawn?.triangles ?? 0,
      // GL buffers of the drawn level (one vertex, one index) and the index widths it draws with.
      drawnBuffers: gpu ? 1 + (gpu.indexBuffer ? 1 : 0) : 0,
      drawnIndexBits: gpu ? [...new Set(gpu.draws.map((d) => INDEX_BITS[d.draw.indexType ?? 0] ?? 0))] : [],
      wanted: this.wanted?.name ?? null,
      loading: this.loading,
      min: this.min,
      max: this.max,
    };
  }
}

/** Order mesh artifacts finest first: `mesh.glb`, then `mesh_lod1.glb`, `mesh_lod2.glb` ... */
export function orderLevels<T extends { name: string }>(levels: T[]): T[] {
  const rank = (name: string) => {
    const px = derivativePx(name);
    if (px !== null) return -Math.log2(px); // derivatives: finest maps first
    const m = /(?:^|\/)mesh(?:_lod(\d+))?\.glb$/.exec(name);
    return m ? (m[1] ? Number(m[1]) : 0) : Infinity;
  };
  return [...levels].sort((a, b) => rank(a.name) - rank(b.name));
}
