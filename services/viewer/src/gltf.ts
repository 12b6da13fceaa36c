/**
 * Binary glTF 2.0 (`.glb`) reader for the mesh layer: a 12-byte header, a JSON chunk and a BIN
 * chunk holding every buffer view (the layout `trimesh`, Blender and MeshLab write).
 *
 * The parse copies nothing: the result points into the BIN chunk with one vertex byte range and
 * one index byte range, so the renderer uploads each in a single buffer whatever the number of
 * primitives, and every primitive draws at its own offsets in them. Attributes keep their stored
 * component type (float, or normalised integers such as COLOR_0 as UNSIGNED_BYTE), which WebGL
 * converts in the vertex fetch. Indices are UNSIGNED_BYTE, _SHORT or _INT (32-bit in WebGL2).
 * Node transforms (`matrix`, or translation / rotation / scale) are applied per draw.
 *
 * Anything unsupported or inconsistent (bad magic or lengths, external or compressed buffers,
 * accessors reaching past their view, indices past the vertex count) raises `GlbError` with a
 * one-line reason.
 */

export class GlbError extends Error {}

/** One vertex attribute of a draw: a WebGL vertexAttribPointer call into the vertex range. */
export interface VertexAttribute {
  /** Shader location: 0 POSITION, 1 COLOR_0, 2 NORMAL. */
  location: number;
  size: number;
  /** WebGL component type (GL_FLOAT, GL_UNSIGNED_BYTE ...: glTF uses the same numbers). */
  type: number;
  normalized: boolean;
  /** Byte stride (0: tightly packed). */
  stride: number;
  /** Byte offset into `GlbMesh.vertexBytes`. */
  offset: number;
}

export interface MeshDraw {
  /** WebGL primitive: TRIANGLES (4), TRIANGLE_STRIP (5) or TRIANGLE_FAN (6). */
  mode: number;
  attributes: VertexAttribute[];
  /** Index type and byte offset into `GlbMesh.indexBytes`, or null for non-indexed draws. */
  indexType: number | null;
  indexOffset: number;
  /** Elements to draw (indices, or vertices when not indexed). */
  count: number;
  triangles: number;
  hasNormal: boolean;
  hasColor: boolean;
  /** Node-to-world transform, column-major 4x4. */
  matrix: Float64Array;
}

export interface GlbMesh {
  vertexBytes: Uint8Array;
  indexBytes: Uint8Array;
  draws: MeshDraw[];
  triangles: number;
  vertices: number;
  /** World-space bounding box of every draw (after node transforms). */
  min: [number, number, number];
  max: [number, number, number];
  /** Material maps of a textured derivative (derivative.ts; UVs at shader location 3). */
  maps?: { base?: TexImageSource; normal?: TexImageSource; occlusion?: TexImageSource };
}

const MAGIC = 0x46546c67; // "glTF"
const CHUNK_JSON = 0x4e4f534a;
const CHUNK_BIN = 0x004e4942;
const COMPONENT_BYTES: Record<number, number> = { 5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4 };
const TYPE_SIZE: Record<string, number> = { SCALAR: 1, VEC2: 2, VEC3: 3, VEC4: 4 };
const LOCATIONS: Record<string, number> = { POSITION: 0, COLOR_0: 1, NORMAL: 2 };
const TRIANGLE_MODES = new Set([4, 5, 6]);

interface Accessor {
  bufferView?: number;
  byteOffset?: number;
  componentType: number;
  normalized?: boolean;
  count: number;
  type: string;
  min?: number[];
  max?: number[];
  sparse?: unknown;
}
interface BufferView {
  buffer: number;
  byteOffset?: number;
  byteLength: number;
  byteStride?: number;
}
interface Primitive {
  attributes: Record<string, number>;
  indices?: number;
  mode?: number;
}
interface Node {
  mesh?: number;
  children?: number[];
  matrix?: number[];
  translation?: number[];
  rotation?: number[];
  scale?: number[];
}
interface Gltf {
  asset?: { version?: string };
  buffers?: { byteLength: number; uri?: string }[];
  bufferViews?: BufferView[];
  accessors?: Accessor[];
  meshes?: { primitives: Primitive[] }[];
  nodes?: Node[];
  scenes?: { nodes?: number[] }[];
  scene?: number;
  extensionsRequired?: string[];
}

function multiply(a: Float64Array, b: Float64Array): Float64Array {
  const out = new Float64Array(16);
  for (let c = 0; c < 4; c++)
    for (let r = 0; r < 4; r++) {
      let s = 0;
      for (let k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k];
      out[c * 4 + r] = s;
    }
  return out;
}

/** A node's local transform: its matrix, or T * R * S. */
function nodeMatrix(node: Node): Float64Array {
  if (node.matrix) {
    if (node.matrix.length !== 16 || !node.matrix.every(Number.isFinite)) throw new GlbError("a node matrix is not 16 numbers");
    return Float64Array.from(node.matrix);
  }
  const [tx, ty, tz] = node.translation ?? [0, 0, 0];
  const [x, y, z, w] = node.rotation ?? [0, 0, 0, 1];
  const [sx, sy, sz] = node.scale ?? [1, 1, 1];
  // Column-major rotation of the unit quaternion, columns scaled.
  return Float64Array.from([
    (1 - 2 * (y * y + z * z)) * sx, 2 * (x * y + z * w) * sx, 2 * (x * z - y * w) * sx, 0,
    2 * (x * y - z * w) * sy, (1 - 2 * (x * x + z * z)) * sy, 2 * (y * z + x * w) * sy, 0,
    2 * (x * z + y * w) * sz, 2 * (y * z - x * w) * sz, (1 - 2 * (x * x + y * y)) * sz, 0,
    tx, ty, tz, 1,
  ]); // prettier-ignore
}

const IDENTITY = Float64Array.from([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]);

/** Parse a `.glb` file held in `buffer`. */
export function parseGlb(buffer: ArrayBuffer): GlbMesh {
  if (buffer.byteLength < 20) throw new GlbError(`not a binary glTF file (${buffer.byteLength} bytes)`);
  const dv = new DataView(buffer);
  if (dv.getUint32(0, true) !== MAGIC) throw new GlbError("not a binary glTF file (no 'glTF' magic)");
  const version = dv.getUint32(4, true);
  if (version !== 2) throw new GlbError(`glTF version ${version} is not supported (only 2)`);
  const length = dv.getUint32(8, true);
  if (length > buffer.byteLength) throw new GlbError(`the file is truncated (${buffer.byteLength} of ${length} bytes)`);
  let json: Gltf | null = null;
  let bin: Uint8Array | null = null;
  for (let at = 12; at + 8 <= length; ) {
    const chunkLength = dv.getUint32(at, true);
    const chunkType = dv.getUint32(at + 4, true);
    const start = at + 8;
    if (start + chunkLength > length) throw new GlbError("a chunk runs past the end of the file");
    if (chunkType === CHUNK_JSON && json === null) {
      try {
        json = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, start, chunkLength))) as Gltf;
      } catch (err) {
        throw new GlbError(`the JSON chunk does not parse (${err instanceof Error ? err.message : String(err)})`);
      }
    } else if (chunkType === CHUNK_BIN && bin === null) {
      bin = new Uint8Array(buffer, start, chunkLength);
    }
    at = start + ((chunkLength + 3) & ~3);
  }
  if (json === null || typeof json !== "object") throw new GlbError("no JSON chunk");
  const required = (json.extensionsRequired ?? []).filter((e) => e !== "KHR_mesh_quantization");
  if (required.length) throw new GlbError(`needs unsupported glTF extension ${required.join(", ")}`);
  const gltf = json;
  const binary = bin ?? new Uint8Array(0);

  const accessor = (index: number, what: string): { acc: Accessor; begin: number; stride: number; end: number } => {
    const acc = gltf.accessors?.[index];
    if (!acc) throw new GlbError(`${what}: accessor ${index} does not exist`);
    if (acc.sparse) throw new GlbError(`${what}: sparse accessors are not supported`);
    const bytes = COMPONENT_BYTES[acc.componentType];
    const size = TYPE_SIZE[acc.type];
    if (!bytes || !size) throw new GlbError(`${what}: accessor ${index} has component type ${acc.componentType} / type ${acc.type}`);
    if (acc.bufferView === undefined) throw new GlbError(`${what}: accessor ${index} has no buffer view`);
    const view = gltf.bufferViews?.[acc.bufferView];
    if (!view) throw new GlbError(`${what}: buffer view ${acc.bufferView} does not exist`);
    if (view.buffer !== 0 || gltf.buffers?.[0]?.uri !== undefined) {
      throw new GlbError(`${what}: data outside the GLB's BIN chunk (external buffers) is not supported`);
    }
    const viewStart = view.byteOffset ?? 0;
    if (viewStart + view.byteLength > binary.byteLength) {
      throw new GlbError(`${what}: buffer view ${acc.bufferView} runs past the BIN chunk (${binary.byteLength} bytes)`);
    }
    const element = bytes * size;
    const stride = view.byteStride ?? 0;
    const begin = viewStart + (acc.byteOffset ?? 0);
    const end = acc.count > 0 ? begin + (acc.count - 1) * (stride || element) + element : begin;
    if (!Number.isInteger(acc.count) || acc.count < 0 || end > viewStart + view.byteLength) {
      throw new GlbError(`${what}: accessor ${index} (${acc.count} x ${acc.type}) runs past its buffer view`);
    }
    if ((binary.byteOffset + begin) % bytes !== 0 || stride % bytes !== 0) {
      throw new GlbError(`${what}: accessor ${index} is not aligned to its component size`);
    }
    return { acc, begin, stride, end };
  };

  // Which meshes to draw, with which transforms: the scene's node tree, else every mesh as is.
  const instances: { mesh: number; matrix: Float64Array }[] = [];
  const sceneIndex = gltf.scene ?? 0;
  const roots = gltf.scenes?.[sceneIndex]?.nodes;
  if (roots && gltf.nodes) {
    const visit = (index: number, parent: Float64Array, depth: number) => {
      const node = gltf.nodes![index];
      if (!node || depth > 64) throw new GlbError(`node ${index} does not exist (or the node tree has a cycle)`);
      const matrix = multiply(parent, nodeMatrix(node));
      if (node.mesh !== undefined) instances.push({ mesh: node.mesh, matrix });
      for (const child of node.children ?? []) visit(child, matrix, depth + 1);
    };
    for (const r of roots) visit(r, IDENTITY, 0);
  } else {
    (gltf.meshes ?? []).forEach((_, i) => instances.push({ mesh: i, matrix: IDENTITY }));
  }

  // First pass: the draws with absolute byte offsets into the BIN chunk.
  const draws: MeshDraw[] = [];
  let vLo = Infinity;
  let vHi = 0;
  let iLo = Infinity;
  let iHi = 0;
  const min: [number, number, number] = [Infinity, Infinity, Infinity];
  const max: [number, number, number] = [-Infinity, -Infinity, -Infinity];
  let vertices = 0;
  let triangles = 0;
  const checkedIndices = new Set<number>();
  for (const { mesh: meshIndex, matrix } of instances) {
    const mesh = gltf.meshes?.[meshIndex];
    if (!mesh) throw new GlbError(`mesh ${meshIndex} does not exist`);
    mesh.primitives.forEach((prim, p) => {
      const what = `mesh ${meshIndex} primitive ${p}`;
      const mode = prim.mode ?? 4;
      if (!TRIANGLE_MODES.has(mode)) return; // points and lines are not surfaces
      if (prim.attributes?.POSITION === undefined) throw new GlbError(`${what} has no POSITION`);
      const attributes: VertexAttribute[] = [];
      let vertexCount = 0;
      for (const [name, location] of Object.entries(LOCATIONS)) {
        const index = prim.attributes[name];
        if (index === undefined) continue;
        const { acc, begin, stride, end } = accessor(index, `${what} ${name}`);
        const size = TYPE_SIZE[acc.type];
        if ((name === "COLOR_0" && size < 3) || (name !== "COLOR_0" && size !== 3)) {
          throw new GlbError(`${what} ${name} is ${acc.type}`);
        }
        if (name === "POSITION") {
          vertexCount = acc.count;
          const lo = acc.min;
          const hi = acc.max;
          if (!lo || !hi || lo.length !== 3 || hi.length !== 3) throw new GlbError(`${what} POSITION lacks min / max`);
          for (let corner = 0; corner < 8; corner++) {
            const x = corner & 1 ? hi[0] : lo[0];
            const y = corner & 2 ? hi[1] : lo[1];
            const z = corner & 4 ? hi[2] : lo[2];
            for (let k = 0; k < 3; k++) {
              const v = matrix[k] * x + matrix[4 + k] * y + matrix[8 + k] * z + matrix[12 + k];
              if (v < min[k]) min[k] = v;
              if (v > max[k]) max[k] = v;
            }
          }
        } else if (acc.count < vertexCount) {
          throw new GlbError(`${what} ${name} has ${acc.count} values for ${vertexCount} vertices`);
        }
        // Integer colours and normals are normalised by the glTF rules; positions only if flagged.
        const normalized = acc.componentType !== 5126 && (name !== "POSITION" || acc.normalized === true);
        attributes.push({ location, size: Math.min(size, 4), type: acc.componentType, normalized, stride, offset: begin });
        vLo = Math.min(vLo, begin);
        vHi = Math.max(vHi, end);
      }
      let indexType: number | null = null;
      let indexOffset = 0;
      let count = vertexCount;
      if (prim.indices !== undefined) {
        const { acc, begin, stride } = accessor(prim.indices, `${what} indices`);
        if (acc.type !== "SCALAR" || ![5121, 5123, 5125].includes(acc.componentType) || stride !== 0) {
          throw new GlbError(`${what} indices are not tightly packed unsigned integers`);
        }
        indexType = acc.componentType;
        indexOffset = begin;
        count = acc.count;
        const key = prim.indices * 4294967296 + vertexCount;
        if (!checkedIndices.has(key)) {
          // WebGL refuses a draw whose indices reach past the buffers: say so at load time.
          const at = binary.byteOffset + begin;
          const data =
            indexType === 5125
              ? new Uint32Array(binary.buffer, at, count)
              : indexType === 5123
                ? new Uint16Array(binary.buffer, at, count)
                : new Uint8Array(binary.buffer, at, count);
          let top = 0;
          for (let i = 0; i < data.length; i++) if (data[i] > top) top = data[i];
          if (count > 0 && top >= vertexCount) throw new GlbError(`${what} has index ${top} for ${vertexCount} vertices`);
          checkedIndices.add(key);
        }
        iLo = Math.min(iLo, begin);
        iHi = Math.max(iHi, begin + count * COMPONENT_BYTES[indexType]);
      }
      const tris = mode === 4 ? Math.floor(count / 3) : Math.max(0, count - 2);
      triangles += tris;
      vertices += vertexCount;
      draws.push({
        mode,
        attributes,
        indexType,
        indexOffset,
        count,
        triangles: tris,
        hasNormal: prim.attributes.NORMAL !== undefined,
        hasColor: prim.attributes.COLOR_0 !== undefined,
        matrix,
      });
    });
  }
  if (draws.length === 0 || triangles === 0) throw new GlbError("the file holds no triangles");
  // One vertex range and one index range, starting 4-byte aligned so every offset keeps its alignment.
  vLo -= (binary.byteOffset + vLo) % 4;
  const indexBytes = iHi > 0 ? ((iLo -= (binary.byteOffset + iLo) % 4), binary.subarray(iLo, iHi)) : new Uint8Array(0);
  for (const d of draws) {
    for (const a of d.attributes) a.offset -= vLo;
    if (d.indexType !== null) d.indexOffset -= iLo;
  }
  return { vertexBytes: binary.subarray(vLo, vHi), indexBytes, draws, triangles, vertices, min, max };
}
