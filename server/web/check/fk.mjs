// Checks the JavaScript client's forward kinematics and skinning matrices (server/sdk/fk.js)
// against vectors from posecast_proto::fk, written by tests/web/: `node fk.mjs FILE` with FILE
// a JSON list of {description, pose, worlds, skinning}. Prints {"cases", "max_error"} and
// exits 1 on a mismatch.

import { readFileSync } from "node:fs";
import { forwardKinematics, skinningMatrices } from "../../sdk/fk.js";

// f32 products over a chain of up to a dozen joints, placed up to 5 m away.
const TOLERANCE = 2e-4;

const cases = JSON.parse(readFileSync(process.argv[2], "utf8"));
let maxError = 0;
const failures = [];
/**
 * @param {string} what
 * @param {number} i
 * @param {string} id
 * @param {Float32Array} got
 * @param {number[]} want
 */
function compare(what, i, id, got, want) {
  if (got.length !== want.length) {
    failures.push(`case ${i} ${what}: ${got.length / 16} matrices, expected ${want.length / 16}`);
    return;
  }
  for (let k = 0; k < want.length; k++) {
    const e = Math.abs(got[k] - want[k]);
    maxError = Math.max(maxError, e);
    if (!(e <= TOLERANCE)) {
      failures.push(`case ${i} (${id}) ${what}, joint ${Math.floor(k / 16)} entry ${k % 16}: ${got[k]} vs ${want[k]}`);
      return;
    }
  }
}

cases.forEach((c, i) => {
  const worlds = forwardKinematics(c.description, c.pose);
  compare("world", i, c.description.id, worlds, c.worlds.flat());
  compare("skinning", i, c.description.id, skinningMatrices(c.description, worlds), c.skinning.flat());
});
console.log(JSON.stringify({ cases: cases.length, max_error: maxError, failures }));
process.exit(failures.length ? 1 : 0);
