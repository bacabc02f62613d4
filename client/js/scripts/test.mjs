// `npm test`: build dist/ (esbuild), type-check src/ and test/ and write dist/types/
// in one TypeScript pass (scripts/types.mjs), then run the unit tests:
// bundle each test/*.test.ts with esbuild (Node 20 runs no TypeScript by itself)
// into .test-build/, then `node --test` over them. Arguments pick test files by
// name and skip the typecheck and build. No nested npm: it runs with any node.
import { build } from "esbuild";
import { readdirSync, rmSync } from "node:fs";
import { spawnSync } from "node:child_process";
import { fileURLToPath } from "node:url";
import { dirname, join } from "node:path";
import { checkAndDeclare } from "./types.mjs";

const root = join(dirname(fileURLToPath(import.meta.url)), "..");
const out = join(root, ".test-build");
rmSync(out, { recursive: true, force: true });
const only = process.argv.slice(2);
if (!only.length) {
  const done = spawnSync(process.execPath, [join(root, "scripts/build.mjs"), "--no-types"], { stdio: "inherit", cwd: root });
  if (done.status !== 0) process.exit(done.status ?? 1);
  if (!checkAndDeclare(root)) process.exit(2);
}
const tests = readdirSync(join(root, "test"))
  .filter((f) => f.endsWith(".test.ts"))
  .filter((f) => !only.length || only.some((o) => f.includes(o)));
await build({
  entryPoints: tests.map((f) => join(root, "test", f)),
  bundle: true,
  format: "esm",
  platform: "node",
  target: "node20",
  outdir: out,
  outExtension: { ".js": ".mjs" },
  sourcemap: "inline",
  logLevel: "warning",
});
const files = tests.map((f) => join(out, f.replace(/\.ts$/, ".mjs")));
const run = spawnSync(process.execPath, ["--enable-source-maps", "--test", "--test-reporter=spec", ...files], { stdio: "inherit" });
process.exit(run.status ?? 1);
