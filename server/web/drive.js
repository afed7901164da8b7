// @ts-check
// The page as a live driver (the same `drive` and `pose` messages any driver sends): "Drive"
// takes the selected avatar and holds the pose it had; the joint sliders then set local
// rotations in that live pose instead of overriding joints. Poses go through the client's
// pacing (never over the drive's `max_rate_hz`) and are repeated well within the drive's
// `timeout`, so the drive lasts while the page is open and ends with it. "Release drive", a
// release by anyone else, or the connection's end stop it.

/** @typedef {import("../sdk/posecast.js").Client} Client */
/** @typedef {import("./protocol.js").Quat} Quat */

/** How many pose repeats fit in one drive timeout (2 s by default: one every 500 ms). */
const REPEATS_PER_TIMEOUT = 4;

export class PageDrive {
  /** @param {Client} conn */
  constructor(conn) {
    this.conn = conn;
    /** @type {string | null} The avatar this page drives. */
    this.avatar = null;
    /** @type {Record<string, Quat>} The live pose: local rotation by joint name. */
    this.rotations = {};
    /** @type {ReturnType<typeof setInterval> | undefined} */
    this.timer = undefined;
    /** Poses handed to the client (for the tests' `?debug` counters). */
    this.sent = 0;
  }

  /**
   * Takes `avatar` as its live driver, starting from `pose` (joint name → local rotation,
   * the avatar's streamed pose), which it then holds.
   * @param {string} avatar
   * @param {Record<string, Quat>} pose
   */
  async start(avatar, pose) {
    this.forget();
    const info = await this.conn.drive(avatar);
    const known = new Set(info.joints);
    this.avatar = avatar;
    this.rotations = Object.fromEntries(Object.entries(pose).filter(([joint]) => known.has(joint)));
    const timeoutMs = Number.isFinite(info.timeout) && info.timeout > 0 ? info.timeout * 1000 : 2000;
    this.timer = setInterval(() => this.send(), Math.max(50, timeoutMs / REPEATS_PER_TIMEOUT));
    this.send();
    return info;
  }

  /**
   * Sets one joint's local rotation in the live pose (sent at once, paced by the client).
   * @param {string} joint
   * @param {Quat} rotation
   */
  set(joint, rotation) {
    if (!this.avatar) return;
    this.rotations[joint] = rotation;
    this.send();
  }

  send() {
    if (!this.avatar) return;
    this.conn.sendPose(this.avatar, { rotations: this.rotations });
    this.sent += 1;
  }

  /** The drive ended (here, by someone else, or with the connection): stop sending. */
  forget() {
    if (this.timer !== undefined) clearInterval(this.timer);
    this.timer = undefined;
    if (this.avatar) this.conn.endPacing(this.avatar);
    this.avatar = null;
    this.rotations = {};
  }

  /** Ends the drive this page holds (`release_drive`): the avatar plays its clip again. */
  async release() {
    const avatar = this.avatar;
    this.forget();
    if (avatar) await this.conn.releaseDrive(avatar);
  }
}
