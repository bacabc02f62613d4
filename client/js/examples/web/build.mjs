// Build the pages into dist/:
// - app.js: the example page (index.html): the app, three.js, the posecast SDK (bundled
//   from ../../src, TypeScript) and IWER (used only with ?emulate=quest3);
// - minimal.js: the README's "Connect your app" page (minimal.html, src/minimal.js), which
//   imports the SDK as the package "posecast", as an app that installed it would;
// - emulate.js: IWER as a Meta Quest 3, a classic script (no module) that replaces the
//   browser's WebXR when it runs before a page's own scripts (the browser tests inject it).
import { build } from "esbuild";
import { fileURLToPath } from "node:url";
import { dirname, join } from "node:path";

const root = dirname(fileURLToPath(import.meta.url));
const common = {
  bundle: true,
  platform: "browser",
  target: "es2022",
  minify: process.argv.includes("--minify"),
  sourcemap: true,
  logLevel: "warning",
  alias: { posecast: join(root, "../../src/index.ts") },
};
await build({
  ...common,
  entryPoints: { app: join(root, "src/main.js"), minimal: join(root, "src/minimal.js") },
  format: "esm",
  outdir: join(root, "dist"),
});
await build({
  ...common,
  entryPoints: { emulate: join(root, "src/emulate.js") },
  format: "iife",
  outdir: join(root, "dist"),
});
