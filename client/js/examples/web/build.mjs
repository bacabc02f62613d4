// Build the page: dist/app.js, one ES module holding the app, three.js, the posecast
// SDK (bundled from ../../src, TypeScript) and IWER (used only with ?emulate=quest3).
import { build } from "esbuild";
import { fileURLToPath } from "node:url";
import { dirname, join } from "node:path";

const root = dirname(fileURLToPath(import.meta.url));
await build({
  entryPoints: [join(root, "src/main.js")],
  bundle: true,
  format: "esm",
  platform: "browser",
  target: "es2022",
  minify: process.argv.includes("--minify"),
  sourcemap: true,
  outfile: join(root, "dist/app.js"),
  logLevel: "warning",
});
