// Validate a .glb / .gltf with the Khronos glTF validator; prints its JSON report.
// Usage: node tools/validate_gltf.js FILE   (needs `make gltf-validator`: .node/node_modules)
const fs = require("fs");
const path = require("path");
const validator = require(path.join(__dirname, "..", ".node", "node_modules", "gltf-validator"));

const file = process.argv[2];
validator.validateBytes(new Uint8Array(fs.readFileSync(file)), { maxIssues: 100 })
  .then((report) => { console.log(JSON.stringify(report, null, 1)); })
  .catch((error) => { console.error(`validation failed: ${error}`); process.exit(1); });
