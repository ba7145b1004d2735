// Validate glTF 2.0 files with the Khronos glTF-Validator; one JSON report per file on stdout.
// Usage: node validate-gltf.mjs FILE.glb [...]
import { readFile } from "node:fs/promises";
import validator from "gltf-validator";

for (const path of process.argv.slice(2)) {
  const bytes = new Uint8Array(await readFile(path));
  const report = await validator.validateBytes(bytes, { uri: path, maxIssues: 100 });
  console.log(JSON.stringify({ path, issues: report.issues, info: report.info }));
}
