#!/usr/bin/env node
// Validates .glb/.gltf files with the Khronos glTF validator (the npm package `gltf-validator`,
// its `validateBytes` API) and prints one JSON summary line per file:
//   {"file", "validator", "errors", "warnings", "infos", "hints", "messages": [{code, severity, pointer, message}]}
// (severity: 0 error, 1 warning, 2 info, 3 hint). Exit status: 0 when no file has an error,
// 1 when one has, 2 when the validator is not installed or a file cannot be read.
//
// The package is looked up under $GLTF_VALIDATOR_PREFIX, by default target/npm of this
// repository (scripts/test installs it there: `npm install --prefix target/npm gltf-validator`).
//
//   node scripts/validate-gltf.mjs FILE.glb [FILE.gltf …]

import { createRequire } from "node:module";
import { readFile } from "node:fs/promises";
import path from "node:path";
import { fileURLToPath } from "node:url";

const root = path.resolve(path.dirname(fileURLToPath(import.meta.url)), "..");
const prefix = process.env.GLTF_VALIDATOR_PREFIX || path.join(root, "target", "npm");

let validator;
try {
  validator = createRequire(path.join(prefix, "package.json"))("gltf-validator");
} catch (error) {
  console.error(
    `gltf-validator is not installed under ${prefix} (npm install --prefix ${prefix} gltf-validator): ${error.message}`,
  );
  process.exit(2);
}

const files = process.argv.slice(2);
if (files.length === 0) {
  console.error("usage: node scripts/validate-gltf.mjs FILE.glb [FILE.gltf …]");
  process.exit(2);
}

let failed = false;
for (const file of files) {
  let bytes;
  try {
    bytes = new Uint8Array(await readFile(file));
  } catch (error) {
    console.error(`cannot read ${file}: ${error.message}`);
    process.exit(2);
  }
  const report = await validator.validateBytes(bytes, {
    uri: path.basename(file),
    maxIssues: 0, // every issue, not the first hundred
    writeTimestamp: false,
  });
  const issues = report.issues;
  failed ||= issues.numErrors > 0;
  console.log(
    JSON.stringify({
      file,
      validator: report.validatorVersion,
      errors: issues.numErrors,
      warnings: issues.numWarnings,
      infos: issues.numInfos,
      hints: issues.numHints,
      messages: issues.messages.map(({ code, severity, pointer, message }) => ({
        code,
        severity,
        pointer,
        message,
      })),
    }),
  );
}
// Not process.exit(): it can cut off stdout still draining into a pipe (a report of
// thousands of issues is longer than the pipe's buffer).
process.exitCode = failed ? 1 : 0;
