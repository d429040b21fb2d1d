// Validates glTF files with Khronos's glTF-Validator (npm gltf-validator, pinned in package.json) and prints its
// report as JSON, one line per file: node tools/validate_gltf.mjs FILE.glb [FILE.glb ...]
import { readFile } from "node:fs/promises";
import validator from "gltf-validator";

for (const path of process.argv.slice(2)) {
  const report = await validator.validateBytes(new Uint8Array(await readFile(path)), { maxIssues: 100 });
  console.log(JSON.stringify({ path, issues: report.issues, info: report.info }));
}
