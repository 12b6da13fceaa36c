/**
 * Decoder of octree-coded tile nodes (metadata "encoding": "GRAYLIGHT_OCTREE"), written by
 * shared/compress/tilenode.py; the layout is documented there. Runs in the decoder worker.
 *
 * In: a node's bytes ("GTN1", u32 numPoints, u32 inflated payload bytes, u32 zlib bytes, u32 CRC-32
 * of the raw planes, the zlib
 * stream the browser inflates natively with DecompressionStream("deflate"), then the byte planes
 * stored raw). Out: the same DecodedPoints
 * the plain decoder gives for the same node (float32 local positions = int32 * scale + grid
 * offset, 8-bit colours, sizes, normals), its points in octree order.
 */

import type { DecodedPoints, DecodeParams } from "./decode";

/** The metadata.json encoding of tiles whose nodes are octree-coded. */
export const OCTREE_ENCODING = "GRAYLIGHT_OCTREE";
/** Attributes an octree-coded node may carry (the codec's record). */
export const OCTREE_ATTRIBUTES = ["position", "rgb", "NormalX", "NormalY", "NormalZ", "size"];

const MAGIC = 0x314e5447; // "GTN1" read as a little-endian u32
const HEAD = 20;
const PAYLOAD_HEAD = 32;
const FLAG_RGB = 1;
const FLAG_RGB8 = 2;
const FLAG_NORMAL = 4;
const FLAG_SIZE = 8;

const POPCOUNT = new Uint8Array(256);
for (let b = 0; b < 256; b++) POPCOUNT[b] = (b & 1) + POPCOUNT[b >> 1];
/** The occupied children of every occupancy byte, in order: CHILDREN[CHILD_START[b] ...]. */
const CHILD_START = new Uint16Array(257);
const CHILDREN = new Uint8Array(1024);
for (let b = 0, w = 0; b < 256; b++) {
  CHILD_START[b] = w;
  for (let j = 0; j < 8; j++) if (b & (1 << j)) CHILDREN[w++] = j;
  CHILD_START[b + 1] = w;
}

const CRC_TABLE = new Int32Array(256);
for (let n = 0; n < 256; n++) {
  let c = n;
  for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1;
  CRC_TABLE[n] = c;
}

/** CRC-32 (zlib's) of bytes, as an unsigned 32-bit number. */
function crc32(bytes: Uint8Array): number {
  let c = -1;
  for (let i = 0; i < bytes.length; i++) c = CRC_TABLE[(c ^ bytes[i]) & 0xff] ^ (c >>> 8);
  return (c ^ -1) >>> 0;
}

/**
 * Inflate a zlib stream of known length with the browser's own decompressor, written straight
 * into the stream (a Blob in between would cost the worker several times the inflate itself).
 */
async function inflate(buffer: ArrayBuffer, offset: number, length: number, expected: number): Promise<Uint8Array> {
  const ds = new DecompressionStream("deflate");
  const writer = ds.writable.getWriter();
  // Their failures (a corrupt stream) surface through the reader below.
  writer.write(new Uint8Array(buffer, offset, length)).catch(() => undefined);
  writer.close().catch(() => undefined);
  const reader = ds.readable.getReader();
  const out = new Uint8Array(expected);
  let at = 0;
  try {
    for (;;) {
      const { done, value } = await reader.read();
      if (done) break;
      if (at + value.length > expected) throw new Error(`inflates to more than the ${expected} bytes its head says`);
      out.set(value, at);
      at += value.length;
    }
  } catch (err) {
    reader.cancel().catch(() => undefined);
    throw new Error(`octree-coded node is corrupt: ${err instanceof Error ? err.message : String(err)}`);
  }
  if (at !== expected) throw new Error(`octree-coded node inflates to ${at} bytes, its head says ${expected}`);
  return out;
}

export async function decodeOctreeNode(buffer: ArrayBuffer, count: number, params: DecodeParams): Promise<DecodedPoints> {
  const fail = (problem: string): never => {
    throw new Error(`octree-coded node: ${problem}`);
  };
  if (count === 0 && buffer.byteLength === 0) {
    // An empty node (an ancestor kept for the hierarchy) has no bytes at all, as in plain tiles.
    const none = params.layout;
    return { count: 0, positions: new Float32Array(0), colors: none.color ? new Uint8Array(0) : null,
             sizes: none.size ? new Float32Array(0) : null, normals: none.normal >= 0 ? new Float32Array(0) : null };
  }
  if (buffer.byteLength < HEAD) fail(`${buffer.byteLength} bytes is truncated`);
  const head = new DataView(buffer);
  if (head.getUint32(0, true) !== MAGIC) fail("wrong magic (not an octree-coded node)");
  const n = head.getUint32(4, true);
  if (n !== count) fail(`holds ${n} points, the hierarchy says ${count}`);
  const zlen = head.getUint32(12, true);
  if (HEAD + zlen > buffer.byteLength) fail(`${buffer.byteLength} bytes is truncated (its zlib stream has ${zlen})`);
  const payload = await inflate(buffer, HEAD, zlen, head.getUint32(8, true));
  if (payload.length < PAYLOAD_HEAD) fail("payload is truncated");
  const view = new DataView(payload.buffer, payload.byteOffset, payload.byteLength);
  const origin = [view.getInt32(0, true), view.getInt32(4, true), view.getInt32(8, true)];
  const depth = view.getUint8(12);
  const k = view.getUint8(13);
  const flags = view.getUint8(14);
  const nocc = view.getUint32(16, true);
  const ncells = view.getUint32(20, true);
  const ncount = view.getUint32(24, true);
  const mask = view.getUint32(28, true);
  const { color, size, normal } = params.layout;
  const hasRgb = (flags & FLAG_RGB) !== 0;
  const hasNormal = (flags & FLAG_NORMAL) !== 0;
  const hasSize = (flags & FLAG_SIZE) !== 0;
  if (hasRgb !== (color !== null) || hasNormal !== normal >= 0 || hasSize !== (size !== null)) {
    fail("its attributes do not match the tiles' attribute list");
  }
  const eight = (flags & FLAG_RGB8) !== 0;
  const nb = (k + 7) >> 3;
  if (k > 32) fail(`cell bits ${k} out of range`);
  const nplanes = n ? 3 * nb + (hasNormal ? 12 : 0) + (hasSize ? 4 : 0) : 0;
  let nraw = 0;
  for (let b = 0; b < 32; b++) if ((mask >>> b) & 1) nraw++;
  const ncolour = hasRgb ? (eight ? 3 : 6) * n : 0;
  if ((nplanes < 32 && mask >>> nplanes !== 0) || PAYLOAD_HEAD + nocc + ncount + ncolour + (nplanes - nraw) * n !== payload.length) {
    fail("its streams do not add up to its payload");
  }
  if (HEAD + zlen + nraw * n !== buffer.byteLength) fail(`has ${buffer.byteLength} bytes, its streams ${HEAD + zlen + nraw * n}`);
  // Where every optional plane (offsets, normals, size) lies: in the payload, or raw after the zlib stream.
  const raw = new Uint8Array(buffer, HEAD + zlen);
  if (crc32(raw) !== head.getUint32(16, true)) fail("corrupt (its raw planes fail their CRC-32)");
  const planeSrc: Uint8Array[] = [];
  const planeAt: number[] = [];
  {
    let inPayload = PAYLOAD_HEAD + nocc + ncount;
    let inRaw = 0;
    for (let i = 0; i < nplanes; i++) {
      if (i === 3 * nb) inPayload += ncolour; // the colour planes sit between offsets and floats
      if ((mask >>> i) & 1) {
        planeSrc.push(raw);
        planeAt.push(inRaw);
        inRaw += n;
      } else {
        planeSrc.push(payload);
        planeAt.push(inPayload);
        inPayload += n;
      }
    }
  }
  const colourAt = PAYLOAD_HEAD + nocc + ncount + (n ? planeSrc.slice(0, 3 * nb).filter((a) => a === payload).length * n : 0);

  // Occupancy, breadth first: the cells of every level in Morton order (child bits 4 x, 2 y, 1 z).
  let at = PAYLOAD_HEAD;
  let cx = new Uint32Array(1);
  let cy = new Uint32Array(1);
  let cz = new Uint32Array(1);
  for (let level = 0; level < depth; level++) {
    const m = cx.length;
    if (at + m > PAYLOAD_HEAD + nocc) fail("occupancy stream is short");
    let next = 0;
    for (let i = 0; i < m; i++) next += POPCOUNT[payload[at + i]];
    const nx = new Uint32Array(next);
    const ny = new Uint32Array(next);
    const nz = new Uint32Array(next);
    let w = 0;
    for (let i = 0; i < m; i++) {
      const b = payload[at + i];
      if (b === 0) fail("an occupied cell has no children");
      const x2 = 2 * cx[i];
      const y2 = 2 * cy[i];
      const z2 = 2 * cz[i];
      for (let t = CHILD_START[b], end = CHILD_START[b + 1]; t < end; t++, w++) {
        const j = CHILDREN[t];
        nx[w] = x2 + ((j >> 2) & 1);
        ny[w] = y2 + ((j >> 1) & 1);
        nz[w] = z2 + (j & 1);
      }
    }
    at += m;
    cx = nx;
    cy = ny;
    cz = nz;
  }
  if (at !== PAYLOAD_HEAD + nocc || cx.length !== ncells) fail("occupancy stream does not match the cell count");

  // Counts and offsets in cells: integer positions, then the local float32 frame as the plain decoder.
  const [sx, sy, sz] = params.scale;
  const [gx, gy, gz] = params.gridOffset;
  const positions = new Float32Array(n * 3);
  const cell = 2 ** k;
  let c = PAYLOAD_HEAD + nocc;
  const countEnd = c + ncount;
  let p = 0;
  for (let ci = 0; ci < ncells; ci++) {
    let v = 0;
    let shift = 0;
    for (;;) {
      if (c >= countEnd || shift > 28) fail("count stream is short or malformed");
      const byte = payload[c++];
      v += (byte & 0x7f) * 2 ** shift;
      shift += 7;
      if (byte < 0x80) break;
    }
    const m = v + 1;
    if (p + m > n) fail("cells hold more points than the node");
    const bx = origin[0] + cx[ci] * cell;
    const by = origin[1] + cy[ci] * cell;
    const bz = origin[2] + cz[ci] * cell;
    for (let e = p + m; p < e; p++) {
      let rx = 0;
      let ry = 0;
      let rz = 0;
      for (let j = 0, mul = 1; j < nb; j++, mul *= 256) {
        rx += planeSrc[j][planeAt[j] + p] * mul;
        ry += planeSrc[nb + j][planeAt[nb + j] + p] * mul;
        rz += planeSrc[2 * nb + j][planeAt[2 * nb + j] + p] * mul;
      }
      if (rx >= cell || ry >= cell || rz >= cell) fail("a point's offset lies outside its cell");
      positions[3 * p] = (bx + rx) * sx + gx;
      positions[3 * p + 1] = (by + ry) * sy + gy;
      positions[3 * p + 2] = (bz + rz) * sz + gz;
    }
  }
  if (p !== n || c !== countEnd) fail("cells hold fewer points than the node");
  at = colourAt;

  let colors: Uint8Array | null = null;
  if (color) {
    colors = new Uint8Array(n * 3);
    const shift = color.shift;
    const mask = eight ? 0xff : 0xffff;
    const scale = eight ? 257 : 1;
    let g = 0;
    let r = 0;
    let b = 0;
    for (let i = 0; i < n; i++) {
      let dg: number;
      let dr: number;
      let db: number;
      if (eight) {
        dg = payload[at + i];
        dr = payload[at + n + i];
        db = payload[at + 2 * n + i];
      } else {
        dg = payload[at + i] | (payload[at + n + i] << 8);
        dr = payload[at + 2 * n + i] | (payload[at + 3 * n + i] << 8);
        db = payload[at + 4 * n + i] | (payload[at + 5 * n + i] << 8);
      }
      g = (g + dg) & mask;
      r = (r + dr) & mask;
      b = (b + db) & mask;
      colors[3 * i] = Math.min(255, (((r + g) & mask) * scale) >> shift);
      colors[3 * i + 1] = Math.min(255, (g * scale) >> shift);
      colors[3 * i + 2] = Math.min(255, (((b + g) & mask) * scale) >> shift);
    }
    at += (eight ? 3 : 6) * n;
  }

  /** Float bit patterns: zig-zagged differences from the previous point, four byte planes a column. */
  let plane = 3 * nb;
  const floats = (bits: Int32Array, columns: number): void => {
    for (let col = 0; col < columns; col++, plane += 4) {
      const [s0, s1, s2, s3] = planeSrc.slice(plane, plane + 4);
      const [a0, a1, a2, a3] = planeAt.slice(plane, plane + 4);
      let prev = 0;
      for (let i = 0; i < n; i++) {
        const zz = s0[a0 + i] | (s1[a1 + i] << 8) | (s2[a2 + i] << 16) | (s3[a3 + i] << 24);
        prev = (prev + ((zz >>> 1) ^ -(zz & 1))) | 0;
        bits[columns * i + col] = prev;
      }
    }
  };
  let normals: Float32Array | null = null;
  if (hasNormal) {
    normals = new Float32Array(n * 3);
    floats(new Int32Array(normals.buffer), 3);
  }
  let sizes: Float32Array | null = null;
  if (size) {
    sizes = new Float32Array(n);
    floats(new Int32Array(sizes.buffer), 1);
  }
  return { count: n, positions, colors, sizes, normals };
}
