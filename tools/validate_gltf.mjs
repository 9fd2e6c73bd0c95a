#!/usr/bin/env node
// Validate a .glb / .gltf file with the Khronos glTF validator and print the JSON report on stdout.
// Usage: node tools/validate_gltf.mjs FILE [--max-issues N]
// Exit status: 0 when the report has no errors, 1 when it has errors, 2 on bad input or a validator crash.
// External resources (.bin, images beside a .gltf) are resolved relative to FILE.
import fs from "node:fs";
import path from "node:path";
import { createRequire } from "node:module";

const require = createRequire(import.meta.url);
const validator = require("gltf-validator");

const args = process.argv.slice(2);
if (args.length < 1) {
  console.error("usage: node tools/validate_gltf.mjs FILE [--max-issues N]");
  process.exit(2);
}
const file = path.resolve(args[0]);
const mi = args.indexOf("--max-issues");
const maxIssues = mi >= 0 ? parseInt(args[mi + 1], 10) : 100;

let bytes;
try {
  bytes = fs.readFileSync(file);
} catch (err) {
  console.error(`cannot read ${file}: ${err}`);
  process.exit(2);
}

validator
  .validateBytes(new Uint8Array(bytes), {
    uri: path.basename(file),
    maxIssues,
    externalResourceFunction: (uri) =>
      new Promise((resolve, reject) => {
        const p = path.resolve(path.dirname(file), decodeURIComponent(uri));
        fs.readFile(p, (err, data) => (err ? reject(err.toString()) : resolve(new Uint8Array(data))));
      }),
  })
  .then(
    (report) => {
      process.stdout.write(JSON.stringify(report, null, 2) + "\n");
      process.exit(report.issues.numErrors > 0 ? 1 : 0);
    },
    (err) => {
      console.error(`validator could not read ${file}: ${err}`);
      process.exit(2);
    },
  );
