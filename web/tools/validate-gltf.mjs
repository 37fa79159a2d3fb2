// The Khronos glTF validator on one .glb (tests/test_human.py): prints its report's summary as
// JSON ({errors, warnings, infos, messages}) and exits 1 when it found errors.
import { readFileSync } from "node:fs";
import validator from "gltf-validator";

const path = process.argv[2];
const report = await validator.validateBytes(new Uint8Array(readFileSync(path)), { maxIssues: 50 });
const issues = report.issues;
console.log(JSON.stringify({
  errors: issues.numErrors, warnings: issues.numWarnings, infos: issues.numInfos,
  messages: issues.messages.map((m) => `${m.severity} ${m.code} ${m.pointer || ""}: ${m.message}`),
}));
process.exit(issues.numErrors > 0 ? 1 : 0);
