/**
 * Potree 2.0 tiles reader: metadata.json, hierarchy.bin, octree.bin (DEFAULT encoding, or
 * Graylight's octree-coded nodes, "GRAYLIGHT_OCTREE": see tilenode.ts).
 *
 * hierarchy.bin holds 22-byte records (type u8: 0 normal, 1 leaf, 2 proxy; childMask u8;
 * numPoints u32; byteOffset i64; byteSize i64), breadth first per chunk; a proxy's offset
 * and size point at the chunk that continues below it. octree.bin holds every node's
 * points once (additive octree), each point laid out as the metadata "attributes" list.
 *
 * Coordinates: positions decode as int32 * scale + offset (world units). The viewer keeps
 * them relative to the octree cube's minimum corner ("local" frame) so float32 keeps its
 * precision for geo-referenced clouds; `origin` is that corner in world units.
 */

import { DecoderPool, type DecodedPoints, type DecodeParams, type Layout } from "./decode";
import { OCTREE_ATTRIBUTES, OCTREE_ENCODING } from "./tilenode";

export type { DecodedPoints } from "./decode";

export interface AttributeInfo {
  name: string;
  type: string;
  size: number;
  numElements: number;
  elementSize?: number;
  min?: number[];
  max?: number[];
}

export interface Metadata {
  version: string;
  name?: string;
  points: number;
  spacing: number;
  scale: number[];
  offset: number[];
  encoding?: string;
  boundingBox: { min: number[]; max: number[] };
  hierarchy: { firstChunkSize: number; stepSize: number; depth: number };
  attributes: AttributeInfo[];
}

export type NodeState = "unloaded" | "loading" | "loaded" | "failed";

/** One octree node. Bounds are in the local frame (world minus `TileSource.origin`). */
export class TileNode {
  name: string;
  level: number;
  min: [number, number, number];
  max: [number, number, number];
  spacing: number;
  parent: TileNode | null;
  children: (TileNode | null)[] = [null, null, null, null, null, null, null, null];
  nodeType = 2;
  numPoints = 0;
  byteOffset = 0;
  byteSize = 0;
  hierarchyByteOffset = 0;
  hierarchyByteSize = 0;
  state: NodeState = "unloaded";
  /** Renderer-owned GPU buffers while loaded. */
  gpu: unknown = null;
  /** Last frame the node was selected for drawing (for the least-recently-used cache). */
  lastVisibleFrame = -1;

  constructor(
    name: string,
    level: number,
    min: [number, number, number],
    max: [number, number, number],
    spacing: number,
    parent: TileNode | null,
  ) {
    this.name = name;
    this.level = level;
    this.min = min;
    this.max = max;
    this.spacing = spacing;
    this.parent = parent;
  }

  center(): [number, number, number] {
    return [(this.min[0] + this.max[0]) / 2, (this.min[1] + this.max[1]) / 2, (this.min[2] + this.max[2]) / 2];
  }

  radius(): number {
    const dx = this.max[0] - this.min[0];
    const dy = this.max[1] - this.min[1];
    const dz = this.max[2] - this.min[2];
    return 0.5 * Math.sqrt(dx * dx + dy * dy + dz * dz);
  }
}

const RECORD = 22;

function childBounds(node: TileNode, index: number): [[number, number, number], [number, number, number]] {
  const min: [number, number, number] = [node.min[0], node.min[1], node.min[2]];
  const max: [number, number, number] = [node.max[0], node.max[1], node.max[2]];
  // Child index bits: 4 -> x, 2 -> y, 1 -> z (upper half when set), as PotreeConverter writes them.
  const axes: [number, number][] = [[0, 4], [1, 2], [2, 1]];
  for (const [axis, bit] of axes) {
    const mid = (min[axis] + max[axis]) / 2;
    if (index & bit) min[axis] = mid;
    else max[axis] = mid;
  }
  return [min, max];
}

export class TileSource {
  readonly baseUrl: string;
  readonly headers: Record<string, string>;
  metadata!: Metadata;
  root!: TileNode;
  /** World coordinates of the local frame's origin (the octree cube's minimum corner). */
  origin: [number, number, number] = [0, 0, 0];
  /** Tight bounds of the points in the local frame (from the position attribute's min/max). */
  tightMin: [number, number, number] = [0, 0, 0];
  tightMax: [number, number, number] = [0, 0, 0];
  hasSize = false;
  hasColor = false;
  hasNormal = false;
  private layout!: Layout;
  /** Whole files kept when the server ignores Range requests (answers 200 with the whole body). */
  private whole = new Map<string, Promise<ArrayBuffer>>();

  readonly decoder: DecoderPool;

  /** `decoderUrl`: script of the decoder worker (null decodes on the main thread). */
  constructor(baseUrl: string, headers: Record<string, string> = {}, decoderUrl: URL | null = null) {
    this.decoder = new DecoderPool(decoderUrl, 2);
    let url = baseUrl;
    if (url.endsWith("metadata.json")) url = url.slice(0, -"metadata.json".length);
    if (!url.endsWith("/")) url += "/";
    this.baseUrl = url;
    this.headers = headers;
  }

  private url(file: string): string {
    return new URL(file, new URL(this.baseUrl, document.baseURI)).toString();
  }

  async open(): Promise<void> {
    const url = this.url("metadata.json");
    const response = await fetch(url, { headers: this.headers });
    if (!response.ok) {
      const hint: Record<number, string> = {
        401: " (the API key is missing or refused: open the page as /viewer/JOB#key=KEY)",
        403: " (the API key may not read this job)",
        404: " (no tiles here: has the job's tiles stage finished?)",
      };
      throw new Error(`${url}: HTTP ${response.status}${hint[response.status] ?? ""}`);
    }
    let md: Metadata;
    try {
      md = (await response.json()) as Metadata;
    } catch {
      throw new Error(`${url}: not valid JSON`);
    }
    this.validate(md, url);
    this.metadata = md;
    this.layout = this.makeLayout(md, url);
    const bbMin = md.boundingBox.min;
    const bbMax = md.boundingBox.max;
    this.origin = [bbMin[0], bbMin[1], bbMin[2]];
    const size: [number, number, number] = [bbMax[0] - bbMin[0], bbMax[1] - bbMin[1], bbMax[2] - bbMin[2]];
    const pos = md.attributes.find((a) => a.name === "position" || a.name === "POSITION_CARTESIAN");
    if (pos?.min && pos.max && pos.min.length === 3 && pos.max.length === 3) {
      this.tightMin = [pos.min[0] - bbMin[0], pos.min[1] - bbMin[1], pos.min[2] - bbMin[2]];
      this.tightMax = [pos.max[0] - bbMin[0], pos.max[1] - bbMin[1], pos.max[2] - bbMin[2]];
    } else {
      this.tightMin = [0, 0, 0];
      this.tightMax = size;
    }
    this.root = new TileNode("r", 0, [0, 0, 0], size, md.spacing, null);
    this.root.nodeType = 2;
    this.root.hierarchyByteOffset = 0;
    this.root.hierarchyByteSize = md.hierarchy.firstChunkSize;
    await this.loadHierarchy(this.root);
  }

  private validate(md: Metadata, url: string): void {
    const fail = (problem: string): never => {
      throw new Error(`${url}: ${problem}`);
    };
    if (typeof md !== "object" || md === null) fail("not a JSON object");
    if (!String(md.version ?? "").startsWith("2.")) fail(`Potree version ${md.version} is not 2.x`);
    if (md.encoding && md.encoding !== "DEFAULT" && md.encoding !== OCTREE_ENCODING) {
      fail(`encoding ${md.encoding} is not supported (use DEFAULT or ${OCTREE_ENCODING})`);
    }
    if (md.encoding === OCTREE_ENCODING && Array.isArray(md.attributes)) {
      for (const a of md.attributes) {
        if (!OCTREE_ATTRIBUTES.includes(a.name) || (a.name === "rgb" && a.type !== "uint16")) {
          fail(`attribute ${a.name} (${a.type}) cannot be octree-coded`);
        }
      }
    }
    for (const key of ["scale", "offset"] as const) {
      if (!Array.isArray(md[key]) || md[key].length !== 3) fail(`"${key}" must be 3 numbers`);
    }
    if (!md.boundingBox || md.boundingBox.min?.length !== 3 || md.boundingBox.max?.length !== 3) {
      fail('"boundingBox" must have 3-number min and max');
    }
    if (!md.hierarchy || !(md.hierarchy.firstChunkSize >= 0)) fail('"hierarchy.firstChunkSize" missing');
    if (!Array.isArray(md.attributes)) fail('"attributes" must be a list');
  }

  private makeLayout(md: Metadata, url: string): Layout {
    let offset = 0;
    let position = -1;
    let color: Layout["color"] = null;
    let size: Layout["size"] = null;
    let normal = -1;
    // Normals come either as one 3-float attribute or, as PotreeConverter and Graylight write
    // them, as NormalX, NormalY, NormalZ floats side by side: both are 12 contiguous bytes.
    const names = md.attributes.map((a) => a.name);
    for (const [i, a] of md.attributes.entries()) {
      if (a.name === "position" || a.name === "POSITION_CARTESIAN") {
        if (a.type !== "int32" || a.numElements !== 3) throw new Error(`${url}: position must be int32 x 3`);
        position = offset;
      } else if ((a.name === "rgb" || a.name === "rgba") && (a.type === "uint16" || a.type === "uint8")) {
        // 16-bit colours (PotreeConverter's convention) are brought to 8 bits when the data use the
        // upper byte; clouds whose values stay within 0..255 are taken as 8-bit already.
        const maxValue = a.max ? Math.max(...a.max) : 65535;
        const shift = a.type === "uint16" && maxValue > 255 ? 8 : 0;
        color = { offset, type: a.type, shift };
      } else if (a.name === "size" && a.numElements === 1 && (a.type === "float" || a.type === "double")) {
        size = { offset, type: a.type };
      } else if ((a.name === "normal" || a.name === "NORMAL") && a.type === "float" && a.numElements === 3) {
        normal = offset;
      } else if (
        a.name === "NormalX" && a.type === "float" && a.numElements === 1 &&
        names[i + 1] === "NormalY" && names[i + 2] === "NormalZ"
      ) {
        normal = offset;
      }
      offset += a.size;
    }
    if (position < 0) throw new Error(`${url}: no "position" attribute`);
    this.hasColor = color !== null;
    this.hasSize = size !== null;
    this.hasNormal = normal >= 0;
    return { stride: offset, position, color, size, normal };
  }

  /** Fetch bytes [first, first + size) of a tiles file, with a Range request when the server honours it. */
  private async fetchRange(file: string, first: number, size: number): Promise<ArrayBuffer> {
    if (size === 0) return new ArrayBuffer(0);
    const url = this.url(file);
    const cached = this.whole.get(file);
    if (cached) return (await cached).slice(first, first + size);
    const response = await fetch(url, {
      headers: { ...this.headers, Range: `bytes=${first}-${first + size - 1}` },
    });
    if (!response.ok) throw new Error(`${url}: HTTP ${response.status}`);
    if (response.status === 206) {
      const buffer = await response.arrayBuffer();
      if (buffer.byteLength !== size) throw new Error(`${url}: range answer has ${buffer.byteLength} bytes, expected ${size}`);
      return buffer;
    }
    // A 200 answer carries the whole file: keep it so later nodes do not download it again.
    const whole = response.arrayBuffer();
    this.whole.set(file, whole);
    const buffer = await whole;
    if (buffer.byteLength < first + size) {
      throw new Error(`${url}: file has ${buffer.byteLength} bytes, a node needs bytes up to ${first + size}`);
    }
    return buffer.slice(first, first + size);
  }

  /** Read the hierarchy chunk below a proxy node and create its descendants. */
  async loadHierarchy(node: TileNode): Promise<void> {
    if (node.nodeType !== 2) return;
    const buffer = await this.fetchRange("hierarchy.bin", node.hierarchyByteOffset, node.hierarchyByteSize);
    this.parseHierarchy(node, buffer);
  }

  parseHierarchy(chunkRoot: TileNode, buffer: ArrayBuffer): void {
    if (buffer.byteLength % RECORD !== 0) {
      throw new Error(`hierarchy.bin: chunk of ${buffer.byteLength} bytes is not a multiple of ${RECORD}`);
    }
    const view = new DataView(buffer);
    const count = buffer.byteLength / RECORD;
    const nodes: TileNode[] = [chunkRoot];
    for (let i = 0; i < count; i++) {
      const current = nodes[i];
      if (!current) throw new Error(`hierarchy.bin: chunk of ${chunkRoot.name} has more records than nodes`);
      const at = i * RECORD;
      const type = view.getUint8(at);
      const childMask = view.getUint8(at + 1);
      const numPoints = view.getUint32(at + 2, true);
      const byteOffset = Number(view.getBigInt64(at + 6, true));
      const byteSize = Number(view.getBigInt64(at + 14, true));
      if (current.nodeType === 2 && i === 0) {
        current.byteOffset = byteOffset;
        current.byteSize = byteSize;
        current.numPoints = numPoints;
      } else if (type === 2) {
        current.hierarchyByteOffset = byteOffset;
        current.hierarchyByteSize = byteSize;
        current.numPoints = numPoints;
      } else {
        current.byteOffset = byteOffset;
        current.byteSize = byteSize;
        current.numPoints = numPoints;
      }
      // Some PotreeConverter versions report points for inner nodes that carry no bytes.
      if (type !== 2 && current.byteSize === 0) current.numPoints = 0;
      current.nodeType = type;
      if (type === 2) continue;
      for (let c = 0; c < 8; c++) {
        if (!(childMask & (1 << c))) continue;
        const [min, max] = childBounds(current, c);
        const child = new TileNode(current.name + c, current.level + 1, min, max, current.spacing / 2, current);
        current.children[c] = child;
        nodes.push(child);
      }
    }
  }

  /** Fetch and decode a node's points (loading its hierarchy chunk first when it is a proxy). */
  async loadPoints(node: TileNode): Promise<DecodedPoints> {
    if (node.nodeType === 2) await this.loadHierarchy(node);
    const { stride } = this.layout;
    const encoding = this.metadata.encoding ?? "DEFAULT";
    if (encoding === "DEFAULT" && node.byteSize !== node.numPoints * stride) {
      throw new Error(`octree.bin: node ${node.name} has ${node.byteSize} bytes for ${node.numPoints} points of ${stride} bytes`);
    }
    const buffer = await this.fetchRange("octree.bin", node.byteOffset, node.byteSize);
    const md = this.metadata;
    const params: DecodeParams = {
      layout: this.layout,
      scale: md.scale,
      // Offsets of the integer grid relative to the local frame, in float64 before the float32 store.
      gridOffset: [0, 1, 2].map((k) => md.offset[k] - this.origin[k]),
      encoding,
    };
    return this.decoder.decode(buffer, node.numPoints, params);
  }

}
