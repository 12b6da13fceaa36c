/**
 * Decoding of octree.bin node bytes into GPU-ready arrays, on the main thread or in a worker.
 * Nodes come as Potree's plain records ("DEFAULT") or octree-coded ("GRAYLIGHT_OCTREE",
 * tilenode.ts); both give the same arrays.
 *
 * In: a node's bytes (numPoints records of `layout.stride` bytes, little-endian), the metadata's
 * scale and the offset of the integer grid relative to the viewer's local frame. Out: float32
 * local positions, 8-bit colours, world sizes and normals (each null when the tiles lack it).
 */

/** A node's points, decoded for the GPU. */
import { decodeOctreeNode, OCTREE_ENCODING } from "./tilenode";

export interface DecodedPoints {
  count: number;
  /** (count, 3) local-frame positions. */
  positions: Float32Array;
  /** (count, 3) 8-bit colours, or null when the tiles carry none. */
  colors: Uint8Array | null;
  /** (count,) per-point world sample size (scanner depth / focal length), or null. */
  sizes: Float32Array | null;
  /** (count, 3) unit normals, or null. */
  normals: Float32Array | null;
}

/** Byte offsets of the attributes the viewer uses within one point record (-1 or null: absent). */
export interface Layout {
  stride: number;
  position: number;
  color: { offset: number; type: string; shift: number } | null;
  size: { offset: number; type: string } | null;
  normal: number;
}

/** Everything a decoder needs besides the bytes (plain data, so it can be posted to a worker). */
export interface DecodeParams {
  layout: Layout;
  scale: number[];
  /** Position of integer 0 in the local frame (metadata offset minus the local origin). */
  gridOffset: number[];
  /** The metadata's node encoding: "DEFAULT" (absent: the same) or "GRAYLIGHT_OCTREE". */
  encoding?: string;
}

/** Decode a node in either encoding (octree-coded nodes inflate asynchronously). */
export function decodeNode(buffer: ArrayBuffer, count: number, params: DecodeParams): Promise<DecodedPoints> {
  if (params.encoding === OCTREE_ENCODING) return decodeOctreeNode(buffer, count, params);
  return Promise.resolve().then(() => decodePoints(buffer, count, params));
}

export function decodePoints(buffer: ArrayBuffer, count: number, params: DecodeParams): DecodedPoints {
  const { stride, position, color, size, normal } = params.layout;
  const view = new DataView(buffer);
  const [sx, sy, sz] = params.scale;
  const [ox, oy, oz] = params.gridOffset;
  const positions = new Float32Array(count * 3);
  for (let i = 0, at = position; i < count; i++, at += stride) {
    positions[3 * i] = view.getInt32(at, true) * sx + ox;
    positions[3 * i + 1] = view.getInt32(at + 4, true) * sy + oy;
    positions[3 * i + 2] = view.getInt32(at + 8, true) * sz + oz;
  }
  let colors: Uint8Array | null = null;
  if (color) {
    colors = new Uint8Array(count * 3);
    if (color.type === "uint16") {
      const shift = color.shift;
      for (let i = 0, at = color.offset; i < count; i++, at += stride) {
        colors[3 * i] = Math.min(255, view.getUint16(at, true) >> shift);
        colors[3 * i + 1] = Math.min(255, view.getUint16(at + 2, true) >> shift);
        colors[3 * i + 2] = Math.min(255, view.getUint16(at + 4, true) >> shift);
      }
    } else {
      for (let i = 0, at = color.offset; i < count; i++, at += stride) {
        colors[3 * i] = view.getUint8(at);
        colors[3 * i + 1] = view.getUint8(at + 1);
        colors[3 * i + 2] = view.getUint8(at + 2);
      }
    }
  }
  let sizes: Float32Array | null = null;
  if (size) {
    sizes = new Float32Array(count);
    const isFloat = size.type === "float";
    for (let i = 0, at = size.offset; i < count; i++, at += stride) {
      sizes[i] = isFloat ? view.getFloat32(at, true) : view.getFloat64(at, true);
    }
  }
  let normals: Float32Array | null = null;
  if (normal >= 0) {
    normals = new Float32Array(count * 3);
    for (let i = 0, at = normal; i < count; i++, at += stride) {
      normals[3 * i] = view.getFloat32(at, true);
      normals[3 * i + 1] = view.getFloat32(at + 4, true);
      normals[3 * i + 2] = view.getFloat32(at + 8, true);
    }
  }
  return { count, positions, colors, sizes, normals };
}

/** The typed arrays of a decoded node, for transferring them between threads without copies. */
export function transferables(points: DecodedPoints): ArrayBuffer[] {
  const out: ArrayBuffer[] = [points.positions.buffer as ArrayBuffer];
  for (const a of [points.colors, points.sizes, points.normals]) if (a) out.push(a.buffer as ArrayBuffer);
  return out;
}

/** Raised for jobs lost when the workers stopped; the caller may simply load the node again. */
export class DecoderUnavailable extends Error {}

interface Job {
  resolve: (points: DecodedPoints) => void;
  reject: (err: Error) => void;
}

/**
 * Decoder workers (`decoder.js` beside the viewer bundle), round robin. Falls back to decoding on
 * the main thread when workers cannot start.
 */
export class DecoderPool {
  private workers: Worker[] = [];
  private jobs = new Map<number, Job>();
  private nextId = 0;
  private turn = 0;

  constructor(scriptUrl: URL | null, size: number) {
    if (!scriptUrl || typeof Worker === "undefined") return;
    try {
      for (let i = 0; i < size; i++) {
        const worker = new Worker(scriptUrl, { type: "module" });
        worker.onmessage = (e: MessageEvent) => this.settle(e.data);
        worker.onerror = (e: ErrorEvent) => {
          e.preventDefault();
          this.fallBack(`decoder worker failed: ${e.message || "could not start"}`);
        };
        this.workers.push(worker);
      }
    } catch {
      this.workers = [];
    }
  }

  /** Decoder workers running (0: decoding on the main thread). */
  get size(): number {
    return this.workers.length;
  }

  private settle(data: { id: number; points?: DecodedPoints; error?: string }): void {
    const job = this.jobs.get(data.id);
    if (!job) return;
    this.jobs.delete(data.id);
    if (data.points) job.resolve(data.points);
    else job.reject(new Error(data.error ?? "decoder worker failed"));
  }

  /** Workers that cannot run (e.g. a script blocked by policy): decode pending jobs here instead. */
  private fallBack(reason: string): void {
    for (const w of this.workers) w.terminate();
    this.workers = [];
    for (const [id, job] of this.jobs) {
      job.reject(new DecoderUnavailable(reason));
      this.jobs.delete(id);
    }
  }

  decode(buffer: ArrayBuffer, count: number, params: DecodeParams): Promise<DecodedPoints> {
    if (this.workers.length === 0) return decodeNode(buffer, count, params);
    const id = this.nextId++;
    const worker = this.workers[this.turn++ % this.workers.length];
    return new Promise<DecodedPoints>((resolve, reject) => {
      this.jobs.set(id, { resolve, reject });
      worker.postMessage({ id, buffer, count, params }, [buffer]);
    });
  }
}
