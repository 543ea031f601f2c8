// The Khronos glTF-Validator (npm `gltf-validator`) on files `gonio export --format gltf`
// wrote: a .glb or a folder's material.gltf with its external .bin and PNGs. Fails on any
// error; warnings and infos are printed, not counted.
//
// Usage: NODE_PATH=DIR/node_modules node gltf_validate.js FILE.glb|FILE.gltf ...
'use strict';
const fs = require('fs');
const path = require('path');
const validator = require('gltf-validator');

async function check(file) {
  const bytes = new Uint8Array(fs.readFileSync(file));
  const dir = path.dirname(file);
  const report = await validator.validateBytes(bytes, {
    uri: path.basename(file),
    externalResourceFunction: (uri) =>
      new Promise((resolve, reject) => {
        fs.readFile(path.join(dir, decodeURIComponent(uri)), (err, data) => (err ? reject(err.toString()) : resolve(new Uint8Array(data))));
      }),
  });
  const i = report.issues;
  console.log(`gltf-validator ${report.validatorVersion}: ${file}: ${i.numErrors} errors, ${i.numWarnings} warnings, ${i.numInfos} infos, ${i.numHints} hints`);
  for (const m of i.messages) {
    console.log(`  [${m.severity}] ${m.code} ${m.pointer || ''}: ${m.message}`);
  }
  return i.numErrors;
}

(async () => {
  let errors = 0;
  for (const f of process.argv.slice(2)) {
    errors += await check(f);
  }
  process.exit(errors === 0 ? 0 : 1);
})().catch((e) => {
  console.error(e);
  process.exit(1);
});
