// @ts-check
// The SDK's one error type: a refused or failed command, a refused hello, a malformed frame.

/** @typedef {import("./posecast.js").ErrorCode} ErrorCode */
/** @typedef {import("./protocol").ErrorDetails} ErrorDetails */

/**
 * A refusal or failure with the protocol's error code (`unauthorized`, `forbidden`,
 * `unknown_avatar`, …; proto/PROTOCOL.md) or the SDK's own (`offline`, `timeout`).
 */
export class PosecastError extends Error {
  /**
   * @param {ErrorCode} code
   * @param {string} message
   * @param {{id?: number, retryAfterMs?: number, details?: ErrorDetails}} [options]
   */
  constructor(code, message, options = {}) {
    super(message);
    this.name = "PosecastError";
    /** @type {ErrorCode} */
    this.code = code;
    /** @type {number | undefined} The command's id, when the error answered one. */
    this.id = options.id;
    /** @type {number | undefined} With `rate_limited`: when to try again. */
    this.retryAfterMs = options.retryAfterMs;
    /** @type {ErrorDetails | undefined} What the error is about, as fields (the scene, avatar,
     * rig, clip, joint, expression or take not found; the quota that refused). */
    this.details = options.details;
  }
}
