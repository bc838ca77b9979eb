// Validate glTF files with the Khronos glTF-Validator; prints one JSON report per file (a JSON array).
// Usage: node tools/validate-gltf.mjs FILE.glb [...]; exits 1 when any file has an error.
import { readFileSync } from 'node:fs';
import { validateBytes } from 'gltf-validator';

const reports = [];
for (const path of process.argv.slice(2)) {
  const report = await validateBytes(new Uint8Array(readFileSync(path)), { maxIssues: 100 });
  reports.push({
    path,
    validator: report.validatorVersion,
    errors: report.issues.numErrors,
    warnings: report.issues.numWarnings,
    infos: report.issues.numInfos,
    messages: report.issues.messages,
  });
}
console.log(JSON.stringify(reports, null, 2));
process.exitCode = reports.some((r) => r.errors > 0) ? 1 : 0;
