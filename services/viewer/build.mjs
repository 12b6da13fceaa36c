// Build the viewer's static assets into dist/: one bundled ES module, its CSS and the page.
import { build } from "esbuild";
import { copyFile, mkdir, rm } from "node:fs/promises";
import { dirname, join } from "node:path";
import { fileURLToPath } from "node:url";

const here = dirname(fileURLToPath(import.meta.url));
const dist = join(here, "dist");
const assets = join(dist, "assets");

await rm(dist, { recursive: true, force: true });
await mkdir(assets, { recursive: true });
await build({
  // The page's module and its decoder worker (loaded from beside it: assets/decoder.js).
  entryPoints: { viewer: join(here, "src", "main.ts"), decoder: join(here, "src", "decoder.worker.ts") },
  outdir: assets,
  bundle: true,
  format: "esm",
  // Dynamic imports (three's GLTFLoader for textured derivatives) become chunks loaded on demand.
  splitting: true,
  chunkNames: "chunks/[name]-[hash]",
  target: "es2020",
  minify: true,
  sourcemap: true,
  legalComments: "none",
  logLevel: "warning",
});
await copyFile(join(here, "src", "style.css"), join(assets, "viewer.css"));
// Google's Draco decoder (WebAssembly) from three's npm package, served beside the bundle: no CDN.
const draco = join(here, "node_modules", "three", "examples", "jsm", "libs", "draco");
await mkdir(join(assets, "draco"), { recursive: true });
for (const f of ["draco_decoder.wasm", "draco_wasm_wrapper.js"]) await copyFile(join(draco, f), join(assets, "draco", f));
await copyFile(join(here, "src", "index.html"), join(dist, "index.html"));
