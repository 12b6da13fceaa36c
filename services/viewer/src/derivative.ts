/**
 * Textured derivatives (`mesh_low.glb`, `mesh_medium.glb` ... of the `derivatives` stage): glTF
 * 2.0 with `KHR_draco_mesh_compression` geometry and JPEG base-colour, normal and occlusion maps,
 * decoded by three.js's GLTFLoader with Google's Draco decoder (DRACOLoader; the WebAssembly
 * decoder from three's npm package, copied to `assets/draco/` by build.mjs: no CDN), then handed
 * to the viewer's own renderer as a `GlbMesh` with its maps.
 *
 * Why GLTFLoader rather than growing gltf.ts: these files use Draco, embedded JPEG textures and
 * three material maps; three's loader is the Khronos-tested reference for all of them (the
 * derivatives' own test loads every level with it), while gltf.ts would need a Draco binding,
 * image decoding and material parsing of its own, each to be tested on Khronos samples. It is
 * loaded on demand (separate chunks), so a page without derivatives pays nothing: measured, the
 * viewer's module grew by about 3 kB (83 kB minified) and the derivative chunks are 413 kB minified
 * (three's core 358 kB, GLTFLoader 47 kB, DRACOLoader 8 kB), plus the Draco decoder's 286 kB wasm
 * and 59 kB wrapper, fetched once, on the first derivative.
 * Load time, headless Chromium on SwiftShader, the 12-view bunny's page (417 k points) to idle with
 * the mesh drawn: 3.9-4.2 s with the textured Low level (150 k faces, Draco, three 1024 px JPEG
 * maps, chunks and wasm included) against 3.9-4.2 s with the untextured mesh_lod2.glb (76 k faces,
 * gltf.ts): the loader costs no visible time.
 */

import type { GlbMesh, MeshDraw } from "./gltf";

// three.js objects, untyped (src/three.d.ts): the members read below are checked where they matter.
// biome-ignore lint/suspicious/noExplicitAny: three ships no declarations
type Three = any;

/** Voyager's quality levels as the derivatives stage names them, coarse to fine, with the nominal map size (px). */
export const DERIVATIVE_LEVELS: Record<string, number> = { thumb: 512, low: 1024, medium: 2048, high: 4096, highest: 8192 };
export const DERIVATIVE_NAME = /(?:^|\/)mesh_(thumb|low|medium|high|highest)\.glb$/;

/** Nominal map size (px) of a derivative level by its file name, or null for another mesh. */
export function derivativePx(name: string): number | null {
  const m = DERIVATIVE_NAME.exec(name);
  return m ? DERIVATIVE_LEVELS[m[1]] : null;
}

type Loader = { parseAsync(data: ArrayBuffer, path: string): Promise<{ scene: Three }> };
let loader: Promise<Loader> | null = null;

function gltfLoader(): Promise<Loader> {
  loader ??= (async () => {
    const [{ GLTFLoader }, { DRACOLoader }] = await Promise.all([
      import("three/examples/jsm/loaders/GLTFLoader.js"),
      import("three/examples/jsm/loaders/DRACOLoader.js"),
    ]);
    const draco = new DRACOLoader();
    draco.setDecoderPath(new URL("draco/", import.meta.url).toString());
    draco.setDecoderConfig({ type: "wasm" });
    return new GLTFLoader().setDRACOLoader(draco) as unknown as Loader;
  })();
  return loader;
}

/** Decode a derivative GLB into the renderer's mesh form (positions, normals, UVs, 32-bit indices, maps). */
export async function parseDerivative(buffer: ArrayBuffer): Promise<GlbMesh> {
  const gltf = await (await gltfLoader()).parseAsync(buffer, "");
  gltf.scene.updateMatrixWorld(true);
  let found: Three | null = null;
  gltf.scene.traverse((o: Three) => {
    if (!found && (o as Three).isMesh) found = o as Three;
  });
  if (!found) throw new Error("no mesh in the derivative");
  const mesh = found as Three;
  const geo = mesh.geometry;
  const pos = geo.getAttribute("position");
  const nor = geo.getAttribute("normal");
  const uv = geo.getAttribute("uv");
  const n = pos.count;
  const floats = new Float32Array(n * 8);
  for (let i = 0; i < n; i++) {
    floats[3 * i] = pos.getX(i);
    floats[3 * i + 1] = pos.getY(i);
    floats[3 * i + 2] = pos.getZ(i);
    if (nor) {
      floats[3 * n + 3 * i] = nor.getX(i);
      floats[3 * n + 3 * i + 1] = nor.getY(i);
      floats[3 * n + 3 * i + 2] = nor.getZ(i);
    }
    if (uv) {
      floats[6 * n + 2 * i] = uv.getX(i);
      floats[6 * n + 2 * i + 1] = uv.getY(i);
    }
  }
  const index = geo.getIndex();
  const indices = index ? Uint32Array.from(index.array as ArrayLike<number>) : Uint32Array.from({ length: n - (n % 3) }, (_, i) => i);
  const attributes: MeshDraw["attributes"] = [
    { location: 0, size: 3, type: 5126, normalized: false, stride: 0, offset: 0 },
    ...(nor ? [{ location: 2, size: 3, type: 5126, normalized: false, stride: 0, offset: 12 * n }] : []),
    ...(uv ? [{ location: 3, size: 2, type: 5126, normalized: false, stride: 0, offset: 24 * n }] : []),
  ];
  const matrix = Float64Array.from(mesh.matrixWorld.elements);
  geo.computeBoundingBox();
  const box = geo.boundingBox!.clone().applyMatrix4(mesh.matrixWorld);
  const material = mesh.material as Three;
  const image = (t: Three | null | undefined) => (t?.image as TexImageSource | undefined) ?? undefined;
  return {
    vertexBytes: new Uint8Array(floats.buffer),
    indexBytes: new Uint8Array(indices.buffer),
    draws: [{ mode: 4, attributes, indexType: 5125, indexOffset: 0, count: indices.length, triangles: indices.length / 3,
              hasNormal: !!nor, hasColor: false, matrix }],
    triangles: indices.length / 3,
    vertices: n,
    min: [box.min.x, box.min.y, box.min.z],
    max: [box.max.x, box.max.y, box.max.z],
    maps: uv ? { base: image(material.map), normal: image(material.normalMap), occlusion: image(material.aoMap) } : undefined,
  };
}
