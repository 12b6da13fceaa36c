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
  target: "es2020",
  minify: true,
  sourcemap: true,
  legalComments: "none",
  logLevel: "warning",
});
await copyFile(join(here, "src", "style.css"), join(assets, "viewer.css"));
await copyFile(join(here, "src", "index.html"), join(dist, "index.html"));
