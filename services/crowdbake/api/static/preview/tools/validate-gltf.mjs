// Validate glTF files with the Khronos glTF-Validator, their external files included; prints one JSON report
// per file (a JSON array).
// Usage: node tools/validate-gltf.mjs FILE.glb [...]; exits 1 when any file has an error.
import { readFileSync } from 'node:fs';
import { dirname, resolve } from 'node:path';
import { validateBytes } from 'gltf-validator';

const reports = [];
for (const path of process.argv.slice(2)) {
  // External files (the looks an export's LODs share) are read beside the .glb, so they are validated too.
  const externalResourceFunction = async (uri) => new Uint8Array(readFileSync(resolve(dirname(path), decodeURIComponent(uri))));
  const report = await validateBytes(new Uint8Array(readFileSync(path)), { maxIssues: 100, externalResourceFunction });
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
