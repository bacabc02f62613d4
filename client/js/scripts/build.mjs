// Build the SDK: dist/posecast.js (one ES module with no dependencies, for browsers
// and Node), dist/posecast.min.js (minified), and the type declarations.
import { build } from "esbuild";
import { execFileSync } from "node:child_process";
import { fileURLToPath } from "node:url";
import { dirname, join } from "node:path";

const root = join(dirname(fileURLToPath(import.meta.url)), "..");
const common = {
  entryPoints: [join(root, "src/index.ts")],
  bundle: true,
  format: "esm",
  platform: "neutral",
  target: "es2022",
  logLevel: "warning",
};
await build({ ...common, outfile: join(root, "dist/posecast.js"), sourcemap: true });
await build({ ...common, outfile: join(root, "dist/posecast.min.js"), minify: true });
if (!process.argv.includes("--no-types")) {
  execFileSync(process.execPath, [join(root, "node_modules/typescript/bin/tsc"), "-p", join(root, "tsconfig.build.json")], {
    stdio: "inherit",
  });
}
