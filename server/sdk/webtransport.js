// @ts-check
// The protocol over WebTransport (proto/PROTOCOL.md "WebTransport"; Rust: posecast-proto
// `quic.rs` and posecast-client `transport.rs`), behind the part of the WebSocket interface the
// client uses, so the connection code is the same for both: one bidirectional stream carries
// every message framed as a kind (1 text, 2 binary, 3 ping, 4 pong, 5 close), a little-endian
// u32 length and the payload; frames come as datagrams. This socket answers the server's pings
// itself (a browser's WebSocket does) and sends the client's acknowledgements: of wire v1
// keyframes (`ackKey`, protocol versions 1 to 7), and of every wire v2 frame decoded
// (`ackFrame`, protocol version 8), so the server codes deltas only against frames the client
// holds and a lost datagram costs its own tick.

import { httpBase } from "./tokens.js";

const TEXT = 1;
const BINARY = 2;
const PING = 3;
const PONG = 4;
const CLOSE = 5;
const KEY_ACK = 0x4b; // "K"
const FRAME_ACK = 0x41; // "A"
/** Most avatars one acknowledgement names (more: the whole frame is acknowledged). */
const MAX_ACKED_AVATARS = 256;
/** The largest message the server's stream may carry (a websocket library's default bound). */
const MAX_MESSAGE_BYTES = 64 << 20;

/**
 * What `GET /api/quic` of the server behind a websocket URL offers: the WebTransport URL (the
 * websocket's host, the endpoint's UDP port) and, for a self-signed certificate, its SHA-256
 * to trust; `null` when the server offers none (or predates the endpoint).
 * @param {string} wsUrl
 * @param {number} timeoutMs
 * @returns {Promise<{url: string, certSha256: Uint8Array | null} | null>}
 */
export async function discoverWebTransport(wsUrl, timeoutMs) {
  const controller = new AbortController();
  const timer = setTimeout(() => controller.abort(), timeoutMs);
  try {
    const response = await fetch(httpBase(wsUrl) + "/api/quic", { signal: controller.signal });
    if (!response.ok) return null;
    const info = await response.json();
    if (!info || info.available !== true || typeof info.port !== "number") return null;
    let certSha256 = null;
    if (info.self_signed === true) {
      const hex = String(info.cert_sha256 ?? "");
      if (!/^[0-9a-fA-F]{64}$/.test(hex)) return null;
      certSha256 = new Uint8Array(32);
      for (let i = 0; i < 32; i++) certSha256[i] = parseInt(hex.slice(2 * i, 2 * i + 2), 16);
    }
    const host = new URL(wsUrl).hostname;
    const bracketed = host.includes(":") && !host.startsWith("[") ? `[${host}]` : host;
    return { url: `https://${bracketed}:${info.port}/`, certSha256 };
  } finally {
    clearTimeout(timer);
  }
}

/**
 * A WebTransport session shaped as the WebSocket the client uses: `send`, `close`,
 * `readyState`, and `onopen`, `onmessage`, `onclose` (`{code, reason}`), `onerror`.
 */
export class WebTransportSocket {
  /**
   * Opens a session and its stream; resolves once both are ready, rejects when either fails
   * or `timeoutMs` passes (UDP blocked on the way looks like a handshake that never ends).
   * @param {string} url
   * @param {Uint8Array | null} certSha256
   * @param {number} timeoutMs
   * @returns {Promise<WebTransportSocket>}
   */
  static async open(url, certSha256, timeoutMs) {
    /** @type {WebTransportOptions} */
    const options = certSha256 ? { serverCertificateHashes: [{ algorithm: "sha-256", value: certSha256 }] } : {};
    const transport = new WebTransport(url, options);
    /** @type {ReturnType<typeof setTimeout> | undefined} */
    let timer;
    const late = new Promise((_, reject) => {
      timer = setTimeout(() => reject(new Error(`no QUIC handshake with ${url} within ${timeoutMs / 1000} s (UDP blocked?)`)), timeoutMs);
    });
    try {
      await Promise.race([transport.ready, late]);
      const stream = await Promise.race([transport.createBidirectionalStream(), late]);
      return new WebTransportSocket(transport, /** @type {WebTransportBidirectionalStream} */ (stream));
    } catch (e) {
      transport.close();
      throw e;
    } finally {
      clearTimeout(timer);
    }
  }

  /**
   * @param {WebTransport} transport
   * @param {WebTransportBidirectionalStream} stream
   */
  constructor(transport, stream) {
    this.transport = transport;
    this.writer = stream.writable.getWriter();
    this.datagrams = transport.datagrams.writable.getWriter();
    this.readyState = 1; // WebSocket.OPEN
    this.binaryType = "arraybuffer";
    /** @type {(() => void) | null} */
    this.onopen = null;
    /** @type {((e: {data: string | ArrayBuffer}) => void) | null} */
    this.onmessage = null;
    /** @type {((e: {code: number, reason: string}) => void) | null} */
    this.onclose = null;
    /** @type {(() => void) | null} */
    this.onerror = null;
    this.closed = false;
    this.readStream(stream.readable.getReader());
    this.readDatagrams(transport.datagrams.readable.getReader());
    transport.closed.then(
      () => this.ended(1000, "the session closed"),
      (e) => this.ended(1006, String(e?.message ?? e)),
    );
  }

  /**
   * Messages of the stream, framed: they may span reads, and a read may hold several.
   * @param {ReadableStreamDefaultReader<Uint8Array>} reader
   */
  async readStream(reader) {
    let buffered = new Uint8Array(0);
    try {
      for (;;) {
        const { value, done } = await reader.read();
        if (done) break;
        const joined = new Uint8Array(buffered.length + value.length);
        joined.set(buffered);
        joined.set(value, buffered.length);
        buffered = joined;
        while (buffered.length >= 5) {
          const view = new DataView(buffered.buffer, buffered.byteOffset, buffered.length);
          const kind = view.getUint8(0);
          const len = view.getUint32(1, true);
          if (len > MAX_MESSAGE_BYTES) throw new Error(`a message of ${len} bytes`);
          if (buffered.length < 5 + len) break;
          const payload = buffered.slice(5, 5 + len);
          buffered = buffered.slice(5 + len);
          this.onStreamMessage(kind, payload);
          if (this.closed) return;
        }
      }
      this.ended(1000, "the stream ended");
    } catch (e) {
      this.ended(1006, String(/** @type {Error} */ (e)?.message ?? e));
    }
  }

  /**
   * @param {number} kind
   * @param {Uint8Array} payload
   */
  onStreamMessage(kind, payload) {
    switch (kind) {
      case TEXT:
        this.onmessage?.({ data: new TextDecoder().decode(payload) });
        break;
      case BINARY:
        this.onmessage?.({ data: payload.buffer.slice(payload.byteOffset, payload.byteOffset + payload.length) });
        break;
      case PING:
        this.write(PONG, payload);
        break;
      case PONG:
        break;
      case CLOSE: {
        const code = payload.length >= 2 ? payload[0] | (payload[1] << 8) : 1005;
        this.ended(code, new TextDecoder().decode(payload.slice(2)));
        break;
      }
      default:
        this.ended(1002, `a message of unknown kind ${kind}`);
    }
  }

  /**
   * The server's datagrams: frames, as binary messages.
   * @param {ReadableStreamDefaultReader<Uint8Array>} reader
   */
  async readDatagrams(reader) {
    try {
      for (;;) {
        const { value, done } = await reader.read();
        if (done || this.closed) return;
        this.onmessage?.({ data: value.buffer.slice(value.byteOffset, value.byteOffset + value.length) });
      }
    } catch {
      // The session's end says why.
    }
  }

  /**
   * @param {number} kind
   * @param {Uint8Array} payload
   */
  write(kind, payload) {
    if (this.closed) return;
    const message = new Uint8Array(5 + payload.length);
    const view = new DataView(message.buffer);
    view.setUint8(0, kind);
    view.setUint32(1, payload.length, true);
    message.set(payload, 5);
    this.writer.write(message).catch(() => {});
  }

  /** @param {string | ArrayBuffer} data */
  send(data) {
    if (typeof data === "string") this.write(TEXT, new TextEncoder().encode(data));
    else this.write(BINARY, new Uint8Array(data));
  }

  /**
   * Acknowledges the chunks of `avatars` in the keyframe of tick `seq` of scene number
   * `sceneNum` (a keyframe too large for a datagram comes cut by avatar, and any part may be
   * lost): a datagram of "K", the scene number as u32, the tick as u64 and each avatar number
   * as u32, little-endian (none: the whole keyframe).
   * @param {number} sceneNum
   * @param {number} seq
   * @param {number[]} avatars
   */
  ackKey(sceneNum, seq, avatars) {
    // A lost acknowledgement is made up for by the next keyframe's.
    this.acknowledge(KEY_ACK, sceneNum, seq, avatars);
  }

  /**
   * Acknowledges the chunks of `avatars` in the wire v2 frame (protocol version 8: a keyframe
   * or a delta) of tick `seq` of scene number `sceneNum`, as the client decoded them (a frame
   * too large for a datagram comes cut by avatar, and any part may be lost): a datagram laid
   * out as {@link ackKey}'s, of first byte "A". The server's deltas name only frames
   * acknowledged for every avatar they were sent with.
   * @param {number} sceneNum
   * @param {number} seq
   * @param {number[]} avatars
   */
  ackFrame(sceneNum, seq, avatars) {
    // A lost acknowledgement costs the frame its use as a reference; the next one's makes up.
    this.acknowledge(FRAME_ACK, sceneNum, seq, avatars);
  }

  /**
   * An acknowledgement datagram: `kind`, the scene number as u32, the tick as u64 and each
   * avatar number as u32, little-endian (none, or more than 256: the whole frame).
   * @param {number} kind
   * @param {number} sceneNum
   * @param {number} seq
   * @param {number[]} avatars
   */
  acknowledge(kind, sceneNum, seq, avatars) {
    if (this.closed) return;
    const named = avatars.length <= MAX_ACKED_AVATARS ? avatars : [];
    const ack = new Uint8Array(13 + 4 * named.length);
    const view = new DataView(ack.buffer);
    view.setUint8(0, kind);
    view.setUint32(1, sceneNum, true);
    view.setBigUint64(5, BigInt(seq), true);
    named.forEach((num, i) => view.setUint32(13 + 4 * i, num, true));
    this.datagrams.write(ack).catch(() => {});
  }

  close() {
    if (this.closed) return;
    this.closed = true;
    this.readyState = 3; // WebSocket.CLOSED
    try {
      this.transport.close();
    } catch {
      // Already closed.
    }
  }

  /**
   * @param {number} code
   * @param {string} reason
   */
  ended(code, reason) {
    if (this.closed) return;
    this.close();
    this.onclose?.({ code, reason });
  }
}
