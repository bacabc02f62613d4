// One TypeScript pass for `npm test`: type-check src/ and test/ (tsconfig.json) and
// write the declarations of src/ where `npm run build` writes them (dist/types/,
// tsconfig.build.json), instead of a `tsc --noEmit` run and the build's own tsc run
// that checked src/ a second time. Returns whether the check passed.
import ts from "typescript";
import { mkdirSync, writeFileSync } from "node:fs";
import { dirname, join, resolve, sep } from "node:path";

export function checkAndDeclare(root) {
  const config = (name) => {
    const path = join(root, name);
    const read = ts.readConfigFile(path, ts.sys.readFile);
    if (read.error) return { errors: [read.error] };
    return ts.parseJsonConfigFileContent(read.config, ts.sys, root, undefined, path);
  };
  const all = config("tsconfig.json");
  const build = config("tsconfig.build.json");
  const errors = [...all.errors, ...build.errors];
  if (!errors.length) {
    // The build's options over tsconfig.json's files (src/ and test/); rootDir would
    // refuse test/, so the outputs land under dist/types/src/ and are moved up below.
    const options = { ...build.options, rootDir: undefined };
    const program = ts.createProgram({ rootNames: all.fileNames, options });
    const types = join(root, "dist/types");
    const fromSrc = join(types, "src") + sep;
    const write = (file, text) => {
      const path = resolve(root, file);
      if (!path.startsWith(fromSrc)) return; // declarations of test/: not the build's
      const to = join(types, path.slice(fromSrc.length));
      mkdirSync(dirname(to), { recursive: true });
      writeFileSync(to, text);
    };
    const emitted = program.emit(undefined, write, undefined, true);
    errors.push(...ts.getPreEmitDiagnostics(program), ...emitted.diagnostics);
  }
  const failed = errors.filter((d) => d.category === ts.DiagnosticCategory.Error);
  if (errors.length) {
    const host = {
      getCanonicalFileName: (f) => f,
      getCurrentDirectory: () => root,
      getNewLine: () => "\n",
    };
    process.stderr.write(ts.formatDiagnostics(errors, host));
  }
  return failed.length === 0;
}
