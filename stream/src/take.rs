//! A scene's *take*: everything it streamed, as one append-only file — the frames the server
//! already encoded for binary v1 subscribers (recording costs no second encode), the avatar
//! descriptions they refer to, and free-form events.
//!
//! This module is the format only: bytes appended to a `Vec<u8>` ([`write_start`],
//! [`write_avatars`], [`write_frame`], [`write_event`]), a scan of a whole take into its
//! index ([`TakeIndex::scan`]) and frames read back by index ([`TakeReader`]) through
//! positioned reads ([`ReadAt`]). Writing files and replaying them are the server's.
//!
//! # Layout
//!
//! All integers are little-endian.
//!
//! ```text
//! file     8 bytes  magic "PCTAKE01", then records
//! record   u32      payload length n (at most 64 MiB)
//!          u8       type
//!          n bytes  payload
//!          u32      CRC-32 (crc32fast) of the type byte and the payload
//! type 0   Header:  JSON of TakeHeader (the first record, and only there)
//! type 1   Avatars: JSON array of AvatarDescription, the scene's whole avatar list from here
//!                   on, in scene order
//! type 2   Frame:   u8 kind (1 key, 2 delta), u64 seq, u64 server time µs, u64 base seq,
//!                   u16 piece count; per piece: u32 avatar number, u32 chunk length, the v1
//!                   chunk as ChunkEncoder::encode wrote it, u16 weight count, u16 per weight
//!                   (round(w · 1023)). The scene number is not stored.
//! type 3   Event:   a JSON value (free-form), kept with the seq of the frame after it
//! other             skipped when their CRC holds (a later version's records)
//! ```
//!
//! # A crash leaves a readable take
//!
//! The file is only ever appended to, so a writer killed mid-write leaves at most its last
//! record damaged: cut short, or (after a power loss, when the file system grew the file but
//! the data never landed) holding zeros or stale bytes. The rule a scan follows:
//!
//! - A record is *bad* when its length is over the cap, the file ends inside it, or its CRC
//!   does not match.
//! - A bad record is the **torn tail** when no valid record (whole, length within the cap, CRC
//!   matching) starts anywhere after its first byte: the index ends before it
//!   ([`TakeIndex::valid_len`]) and the bytes from it to the end are [`TakeIndex::torn_tail`].
//!   This covers a record cut short, a last record whose CRC fails, and a zero-filled tail.
//! - A bad record with a valid record anywhere after it is **corruption** in the middle of the
//!   file, which an append-only writer cannot cause: [`TakeError::Corrupt`] with its offset.
//!   (A damaged length that points past the end of the file is caught this way too: the
//!   record after it is still there.)
//!
//! Looking for a valid record after a bad one reads on until one is found or the file ends,
//! holding at most one record's bytes (64 MiB) at a time; for a genuine torn tail that is the
//! tail's few bytes. A chance match of a CRC-32 in the bytes of a torn tail (odds 2⁻³² per
//! position whose length fits) would turn a torn tail into `Corrupt`.

use bytes::Bytes;
use posecast_proto::description::AvatarDescription;
use posecast_proto::frame::{
    AvatarPose, Frame, FrameDecoder, FrameError, FrameHeader, FrameKind, write_header,
};
use std::collections::HashMap;
use std::io::Read;
use std::sync::Arc;

/// The first 8 bytes of every take.
pub const MAGIC: &[u8; 8] = b"PCTAKE01";
/// The largest payload a record may have (64 MiB); a longer one is damage.
pub const MAX_PAYLOAD: u32 = 64 << 20;
/// Bytes a record adds to its payload: length, type and CRC.
pub const RECORD_OVERHEAD: usize = 9;

/// Record type: the take's [`TakeHeader`] (JSON).
pub const TYPE_HEADER: u8 = 0;
/// Record type: the scene's avatar list (JSON array of [`AvatarDescription`]).
pub const TYPE_AVATARS: u8 = 1;
/// Record type: one frame (binary).
pub const TYPE_FRAME: u8 = 2;
/// Record type: an event (JSON).
pub const TYPE_EVENT: u8 = 3;

/// Morph weights are stored as levels `round(w · 1023)`.
const WEIGHT_LEVELS: f32 = 1023.0;

/// What the take is: its first record.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TakeHeader {
    /// The take's name.
    pub take: String,
    /// The scene it recorded.
    pub scene: String,
    /// The scene's tick rate (Hz): seq differences over it are seconds.
    pub tick_rate: f32,
    /// When recording started, µs since the Unix epoch.
    pub started_us: u64,
}

/// Why a take cannot be read.
#[derive(Debug, Clone, thiserror::Error, PartialEq, Eq)]
pub enum TakeError {
    /// The file does not start with [`MAGIC`].
    #[error("not a take (bad magic)")]
    NotATake,
    /// The header record is missing (the file ends before it) or unreadable.
    #[error("take header: {0}")]
    Header(String),
    /// A damaged record that is not the torn tail (a valid record follows it), or a record
    /// whose CRC holds but whose contents are impossible.
    #[error("take corrupt at byte {at}: {why}")]
    Corrupt {
        /// Where the record starts.
        at: u64,
        /// What is wrong with it.
        why: &'static str,
    },
    /// Reading failed.
    #[error("reading the take: {0}")]
    Io(String),
    /// A frame record whose chunks do not decode.
    #[error("take frame at byte {at}: {error}")]
    Frame {
        /// Where the frame record starts.
        at: u64,
        /// The decoder's complaint.
        error: FrameError,
    },
    /// [`TakeReader::poses`] was asked for a frame the index does not have.
    #[error("no frame {index}: the take has {frames}")]
    NoSuchFrame {
        /// The index asked for.
        index: usize,
        /// How many frames the index has.
        frames: usize,
    },
}

impl From<std::io::Error> for TakeError {
    fn from(e: std::io::Error) -> Self {
        Self::Io(e.to_string())
    }
}

// ---------------------------------------------------------------------------------------------
// Writing
// ---------------------------------------------------------------------------------------------

/// Appends one record of type `kind` whose payload `body` appends (length and CRC around it).
fn record(kind: u8, out: &mut Vec<u8>, body: impl FnOnce(&mut Vec<u8>)) {
    let start = out.len();
    out.extend_from_slice(&[0; 4]);
    out.push(kind);
    body(out);
    let n = out.len() - start - 5;
    out[start..start + 4].copy_from_slice(&(n.min(u32::MAX as usize) as u32).to_le_bytes());
    let crc = crc32fast::hash(&out[start + 4..]);
    out.extend_from_slice(&crc.to_le_bytes());
}

/// Appends a JSON record of `value`. Serialising to memory fails only for values JSON cannot
/// hold (maps with non-string keys): the payload is then `null`, which a reader refuses as that
/// record's type, rather than a half-written value.
fn json_record<T: serde::Serialize + ?Sized>(kind: u8, value: &T, out: &mut Vec<u8>) {
    record(kind, out, |out| {
        let at = out.len();
        if serde_json::to_writer(&mut *out, value).is_err() {
            out.truncate(at);
            out.extend_from_slice(b"null");
        }
    });
}

/// Starts a take: appends [`MAGIC`] and the header record.
pub fn write_start(header: &TakeHeader, out: &mut Vec<u8>) {
    out.extend_from_slice(MAGIC);
    json_record(TYPE_HEADER, header, out);
}

/// Appends an avatar list record: the scene's whole list of avatars from here on, in scene
/// order (written at the start and whenever it changes). A list whose JSON is over 64 MiB
/// (hundreds of thousands of joints) makes a record readers refuse.
pub fn write_avatars(avatars: &[&AvatarDescription], out: &mut Vec<u8>) {
    json_record(TYPE_AVATARS, avatars, out);
}

/// Appends an event record (free-form JSON; readers keep it with the seq of the next frame).
pub fn write_event(event: &serde_json::Value, out: &mut Vec<u8>) {
    json_record(TYPE_EVENT, event, out);
}

/// Appends one frame record: `header` (its scene number is not stored) and `pieces`, each an
/// avatar's number, its v1 chunk as [`posecast_proto::frame::ChunkEncoder::encode`] wrote it
/// for this frame, and its morph weights (stored as levels `round(w · 1023)`, clamped to
/// `[0, 1]`; NaN as 0). At most 65,535 pieces and 65,535 weights per piece are stored.
pub fn write_frame<'a>(
    header: &FrameHeader,
    pieces: impl Iterator<Item = (u32, &'a [u8], &'a [f32])>,
    out: &mut Vec<u8>,
) {
    record(TYPE_FRAME, out, |out| {
        out.push(match header.kind {
            FrameKind::Key => 1,
            FrameKind::Delta => 2,
        });
        out.extend_from_slice(&header.seq.to_le_bytes());
        out.extend_from_slice(&header.server_time_us.to_le_bytes());
        out.extend_from_slice(&header.base_seq.to_le_bytes());
        let count_at = out.len();
        out.extend_from_slice(&[0; 2]);
        let mut count = 0u16;
        for (num, chunk, weights) in pieces.take(usize::from(u16::MAX)) {
            count += 1;
            out.extend_from_slice(&num.to_le_bytes());
            out.extend_from_slice(&(chunk.len() as u32).to_le_bytes());
            out.extend_from_slice(chunk);
            let weights = &weights[..weights.len().min(usize::from(u16::MAX))];
            out.extend_from_slice(&(weights.len() as u16).to_le_bytes());
            out.reserve(2 * weights.len());
            for &w in weights {
                // NaN clamps to NaN and casts to 0.
                let level = (w.clamp(0.0, 1.0) * WEIGHT_LEVELS).round() as u16;
                out.extend_from_slice(&level.to_le_bytes());
            }
        }
        out[count_at..count_at + 2].copy_from_slice(&count.to_le_bytes());
    });
}

// ---------------------------------------------------------------------------------------------
// Frame payloads
// ---------------------------------------------------------------------------------------------

/// Bounds-checked reading of a payload (every failure is the payload's fault).
struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        let end = self.at.checked_add(n).filter(|&e| e <= self.bytes.len())?;
        let s = &self.bytes[self.at..end];
        self.at = end;
        Some(s)
    }

    fn array<const N: usize>(&mut self) -> Option<[u8; N]> {
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(N)?);
        Some(a)
    }

    fn u16(&mut self) -> Option<u16> {
        self.array().map(u16::from_le_bytes)
    }

    fn u32(&mut self) -> Option<u32> {
        self.array().map(u32::from_le_bytes)
    }

    fn u64(&mut self) -> Option<u64> {
        self.array().map(u64::from_le_bytes)
    }
}

/// One piece of a frame record, borrowed from its payload.
struct PieceRef<'a> {
    /// The avatar's number as the record names it.
    num: u32,
    /// The v1 chunk.
    chunk: &'a [u8],
    /// The weight levels, 2 bytes each (little-endian).
    levels: &'a [u8],
}

/// Reads a frame record's payload: its header (scene number 0) and piece count, calling
/// `piece` for each piece in order.
fn parse_frame<'a>(
    payload: &'a [u8],
    mut piece: impl FnMut(PieceRef<'a>),
) -> Result<(FrameHeader, u16), &'static str> {
    let mut r = Reader {
        bytes: payload,
        at: 0,
    };
    const SHORT: &str = "frame record cut short inside its payload";
    let kind = match r.array::<1>().ok_or(SHORT)?[0] {
        1 => FrameKind::Key,
        2 => FrameKind::Delta,
        _ => return Err("frame record of an unknown kind"),
    };
    let header = FrameHeader {
        kind,
        scene_num: 0,
        seq: r.u64().ok_or(SHORT)?,
        server_time_us: r.u64().ok_or(SHORT)?,
        base_seq: r.u64().ok_or(SHORT)?,
    };
    let count = r.u16().ok_or(SHORT)?;
    for _ in 0..count {
        let num = r.u32().ok_or(SHORT)?;
        let len = r.u32().ok_or(SHORT)? as usize;
        let chunk = r.take(len).ok_or(SHORT)?;
        let weights = usize::from(r.u16().ok_or(SHORT)?);
        let levels = r.take(2 * weights).ok_or(SHORT)?;
        piece(PieceRef { num, chunk, levels });
    }
    if r.at != payload.len() {
        return Err("bytes after a frame record's last piece");
    }
    Ok((header, count))
}

// ---------------------------------------------------------------------------------------------
// Scanning
// ---------------------------------------------------------------------------------------------

/// One frame record of a take, as the index knows it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameEntry {
    /// Where its record starts in the file.
    pub offset: u64,
    /// The whole record's length (payload plus [`RECORD_OVERHEAD`]).
    pub len: u32,
    /// The frame's tick number.
    pub seq: u64,
    /// Whether it is a keyframe.
    pub key: bool,
    /// The avatar list in effect (an index into [`TakeIndex::avatar_lists`]).
    pub avatars: usize,
}

/// The result of reading a take's records once (its chunks are not decoded): what a replay
/// needs to find frames and what they refer to.
#[derive(Debug, Clone, PartialEq)]
pub struct TakeIndex {
    /// The take's header.
    pub header: TakeHeader,
    /// Every avatar list, in the order written (a description unchanged from the list before
    /// shares its `Arc`).
    pub avatar_lists: Vec<Vec<Arc<AvatarDescription>>>,
    /// One entry per complete frame record, in file order.
    pub frames: Vec<FrameEntry>,
    /// Every event with the seq of the frame after it (after the last frame: that frame's seq
    /// + 1; with no frame at all: 0).
    pub events: Vec<(u64, serde_json::Value)>,
    /// Bytes up to the end of the last complete record (what a reader trusts).
    pub valid_len: u64,
    /// Bytes after it that belong to the torn tail (a writer killed mid-record); 0 for a whole
    /// file.
    pub torn_tail: u64,
}

/// The scanner's window on a stream: bytes from absolute offset `base` are in `buf[start..]`,
/// read on demand, so memory holds at most one record plus a read's worth.
struct Window<R> {
    input: R,
    buf: Vec<u8>,
    start: usize,
    /// Absolute offset of `buf[0]`.
    base: u64,
    eof: bool,
}

/// How much a refill asks the reader for at least.
const READ_SIZE: usize = 64 << 10;

impl<R: Read> Window<R> {
    /// The absolute offset of the window's first byte.
    fn pos(&self) -> u64 {
        self.base + self.start as u64
    }

    /// The bytes held from the window's start.
    fn held(&self) -> &[u8] {
        &self.buf[self.start..]
    }

    /// Makes `n` bytes from the window's start available; false when the stream ends first.
    fn ensure(&mut self, n: usize) -> Result<bool, TakeError> {
        while self.buf.len() - self.start < n {
            if self.eof {
                return Ok(false);
            }
            if self.start > 0 && self.start >= self.buf.len() / 2 {
                self.buf.drain(..self.start);
                self.base += self.start as u64;
                self.start = 0;
            }
            let have = self.buf.len();
            // At most a megabyte a read: a length past the end of the stream costs no more.
            let want = (n - (have - self.start)).clamp(READ_SIZE, 1 << 20);
            self.buf.resize(have + want, 0);
            let got = loop {
                match self.input.read(&mut self.buf[have..]) {
                    Ok(got) => break got,
                    Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                    Err(e) => {
                        self.buf.truncate(have);
                        return Err(e.into());
                    }
                }
            };
            self.buf.truncate(have + got);
            if got == 0 {
                self.eof = true;
            }
        }
        Ok(true)
    }

    /// Moves the window's start `n` bytes on (they must be held).
    fn consume(&mut self, n: usize) {
        self.start += n;
    }

    /// Reads to the end of the stream; the absolute offset of its end.
    fn end(&mut self) -> Result<u64, TakeError> {
        loop {
            // Keep nothing: only the count matters.
            self.base += self.buf.len() as u64;
            self.buf.clear();
            self.start = 0;
            if !self.ensure(1)? {
                return Ok(self.pos());
            }
        }
    }

    /// The record at the window's start, if it is valid: its type and payload length.
    fn valid_record(&mut self) -> Result<Option<(u8, usize)>, TakeError> {
        if !self.ensure(5)? {
            return Ok(None);
        }
        let h = self.held();
        let n = u32::from_le_bytes([h[0], h[1], h[2], h[3]]);
        if n > MAX_PAYLOAD {
            return Ok(None);
        }
        let n = n as usize;
        if !self.ensure(n + RECORD_OVERHEAD)? {
            return Ok(None);
        }
        let h = self.held();
        let body = &h[4..5 + n];
        let crc = u32::from_le_bytes([h[5 + n], h[6 + n], h[7 + n], h[8 + n]]);
        Ok((crc32fast::hash(body) == crc).then_some((h[4], n)))
    }

    /// After a bad record at the window's start: whether a valid record starts at any later
    /// byte. Moves the window on (the caller stops reading records either way).
    fn valid_record_follows(&mut self) -> Result<bool, TakeError> {
        loop {
            if !self.ensure(1)? {
                return Ok(false);
            }
            self.consume(1);
            if self.valid_record()?.is_some() {
                return Ok(true);
            }
            if self.eof && self.held().len() < RECORD_OVERHEAD {
                return Ok(false);
            }
        }
    }
}

/// Builds an index record by record (see [`TakeIndex::scan`]).
struct Indexer {
    header: Option<TakeHeader>,
    avatar_lists: Vec<Vec<Arc<AvatarDescription>>>,
    frames: Vec<FrameEntry>,
    events: Vec<(u64, serde_json::Value)>,
    /// Events read since the last frame (their seq is the next frame's).
    pending: Vec<serde_json::Value>,
}

impl Indexer {
    /// Takes in one valid record at `at`.
    fn record(&mut self, at: u64, kind: u8, payload: &[u8]) -> Result<(), TakeError> {
        let corrupt = |why| TakeError::Corrupt { at, why };
        if self.header.is_none() {
            if kind != TYPE_HEADER {
                return Err(TakeError::Header(
                    "the first record is not the header".into(),
                ));
            }
            let header: TakeHeader =
                serde_json::from_slice(payload).map_err(|e| TakeError::Header(e.to_string()))?;
            self.header = Some(header);
            return Ok(());
        }
        match kind {
            TYPE_HEADER => return Err(corrupt("a second header record")),
            TYPE_AVATARS => {
                let list: Vec<AvatarDescription> = serde_json::from_slice(payload)
                    .map_err(|_| corrupt("an avatar list that is not a JSON list of avatars"))?;
                // Descriptions unchanged since the list before share its Arcs.
                let before: HashMap<u32, &Arc<AvatarDescription>> = self
                    .avatar_lists
                    .last()
                    .map(|l| l.iter().map(|d| (d.num, d)).collect())
                    .unwrap_or_default();
                let list = list
                    .into_iter()
                    .map(|d| match before.get(&d.num) {
                        Some(&same) if **same == d => same.clone(),
                        _ => Arc::new(d),
                    })
                    .collect();
                self.avatar_lists.push(list);
            }
            TYPE_FRAME => {
                let (header, _) = parse_frame(payload, |_| ()).map_err(corrupt)?;
                let avatars = self
                    .avatar_lists
                    .len()
                    .checked_sub(1)
                    .ok_or(corrupt("a frame before any avatar list"))?;
                for event in self.pending.drain(..) {
                    self.events.push((header.seq, event));
                }
                self.frames.push(FrameEntry {
                    offset: at,
                    len: (payload.len() + RECORD_OVERHEAD) as u32,
                    seq: header.seq,
                    key: header.kind == FrameKind::Key,
                    avatars,
                });
            }
            TYPE_EVENT => {
                let event = serde_json::from_slice(payload)
                    .map_err(|_| corrupt("an event that is not JSON"))?;
                self.pending.push(event);
            }
            // A later version's record: skipped.
            _ => {}
        }
        Ok(())
    }
}

impl TakeIndex {
    /// Scans a whole take from its first byte: checks every record's CRC, reads the header,
    /// the avatar lists, the events and where every frame is (chunks are not decoded). Reads
    /// once, front to back, holding one record at a time besides the index.
    ///
    /// A torn tail (see the [module](self) documentation for the rule) ends the index before
    /// it; damage anywhere else is an error.
    ///
    /// # Errors
    /// [`TakeError::NotATake`] for a bad magic, [`TakeError::Header`] when the file ends before
    /// its header record or that record is not a readable header, [`TakeError::Corrupt`] for a
    /// damaged record with a valid one after it or a record whose contents are impossible
    /// (malformed frame, unreadable JSON, a second header, a frame before any avatar list),
    /// [`TakeError::Io`] when reading fails.
    pub fn scan(reader: impl Read) -> Result<TakeIndex, TakeError> {
        let mut w = Window {
            input: reader,
            buf: Vec::new(),
            start: 0,
            base: 0,
            eof: false,
        };
        let whole = w.ensure(MAGIC.len())?;
        let held = w.held();
        if held[..held.len().min(MAGIC.len())] != MAGIC[..held.len().min(MAGIC.len())] {
            return Err(TakeError::NotATake);
        }
        if !whole {
            return Err(TakeError::Header(
                "the file ends inside its magic, before its header record".into(),
            ));
        }
        w.consume(MAGIC.len());
        let mut ix = Indexer {
            header: None,
            avatar_lists: Vec::new(),
            frames: Vec::new(),
            events: Vec::new(),
            pending: Vec::new(),
        };
        let (valid_len, torn_tail) = loop {
            if !w.ensure(1)? {
                break (w.pos(), 0);
            }
            let at = w.pos();
            if let Some((kind, n)) = w.valid_record()? {
                ix.record(at, kind, &w.held()[5..5 + n])?;
                w.consume(n + RECORD_OVERHEAD);
                continue;
            }
            // A bad record: the torn tail unless a valid record follows it.
            let why = why_bad(&mut w)?;
            if w.valid_record_follows()? {
                return Err(TakeError::Corrupt { at, why });
            }
            let end = w.end()?;
            break (at, end - at);
        };
        let header = ix.header.ok_or_else(|| {
            TakeError::Header("the file ends before its header record is whole".into())
        })?;
        let next = ix.frames.last().map_or(0, |f| f.seq.saturating_add(1));
        let mut events = ix.events;
        events.extend(ix.pending.into_iter().map(|e| (next, e)));
        Ok(TakeIndex {
            header,
            avatar_lists: ix.avatar_lists,
            frames: ix.frames,
            events,
            valid_len,
            torn_tail,
        })
    }

    /// [`Self::scan`] of a take in memory.
    ///
    /// # Errors
    /// As [`Self::scan`].
    pub fn from_bytes(bytes: &[u8]) -> Result<TakeIndex, TakeError> {
        Self::scan(bytes)
    }

    /// The take's length in seconds: (last seq − first seq) / tick rate; 0 with fewer than two
    /// frames or a tick rate that is not positive.
    #[must_use]
    pub fn duration(&self) -> f64 {
        let rate = f64::from(self.header.tick_rate);
        match (self.frames.first(), self.frames.last()) {
            (Some(a), Some(b)) if rate > 0.0 && rate.is_finite() => {
                b.seq.saturating_sub(a.seq) as f64 / rate
            }
            _ => 0.0,
        }
    }

    /// The seq of the first frame.
    #[must_use]
    pub fn first_seq(&self) -> Option<u64> {
        self.frames.first().map(|f| f.seq)
    }

    /// The index of the last frame at or before take time `t` (seconds from the first frame;
    /// clamped to the take, NaN as 0). Frames are taken to be in increasing seq, as a scene's
    /// ticks are. `None` for a take without frames.
    #[must_use]
    pub fn frame_at(&self, t: f64) -> Option<usize> {
        let first = self.first_seq()?;
        let rate = f64::from(self.header.tick_rate);
        let t = if t.is_nan() { 0.0 } else { t };
        let ticks = if rate > 0.0 && rate.is_finite() {
            // A hair over, so a time computed as seq / rate lands on that seq.
            (t * rate + 1e-6).floor().max(0.0)
        } else {
            0.0
        };
        // Saturating float-to-int cast: an hour past the end is the end.
        let target = first.saturating_add(ticks as u64);
        Some(self.frames.partition_point(|f| f.seq <= target).max(1) - 1)
    }

    /// The index of the last keyframe at or before frame `i` (`None`: there is none, or `i` is
    /// past the last frame).
    #[must_use]
    pub fn key_before(&self, i: usize) -> Option<usize> {
        self.frames.get(..=i)?.iter().rposition(|f| f.key)
    }
}

/// Why the record at the window's start is bad (it is not valid).
fn why_bad<R: Read>(w: &mut Window<R>) -> Result<&'static str, TakeError> {
    if !w.ensure(5)? {
        return Ok("record cut short in its head");
    }
    let h = w.held();
    let n = u32::from_le_bytes([h[0], h[1], h[2], h[3]]);
    Ok(if n > MAX_PAYLOAD {
        "record length over 64 MiB"
    } else if !w.ensure(n as usize + RECORD_OVERHEAD)? {
        "record runs past the end of the file (its length is damaged)"
    } else {
        "record checksum mismatch"
    })
}

// ---------------------------------------------------------------------------------------------
// Reading frames
// ---------------------------------------------------------------------------------------------

/// Bytes that can be read at any offset without a cursor (so one open file can serve readers
/// on many threads).
pub trait ReadAt {
    /// Fills `buf` with the bytes from `offset`.
    ///
    /// # Errors
    /// Reading failed, or the source ends before `buf` is full (`UnexpectedEof`).
    fn read_at(&self, buf: &mut [u8], offset: u64) -> std::io::Result<()>;
}

impl ReadAt for [u8] {
    fn read_at(&self, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
        let src = usize::try_from(offset)
            .ok()
            .and_then(|at| self.get(at..at.checked_add(buf.len())?))
            .ok_or_else(|| {
                std::io::Error::new(
                    std::io::ErrorKind::UnexpectedEof,
                    "read past the end of the take",
                )
            })?;
        buf.copy_from_slice(src);
        Ok(())
    }
}

impl ReadAt for Vec<u8> {
    fn read_at(&self, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
        self.as_slice().read_at(buf, offset)
    }
}

impl ReadAt for Bytes {
    fn read_at(&self, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
        self.as_ref().read_at(buf, offset)
    }
}

impl<T: ReadAt + ?Sized> ReadAt for &T {
    fn read_at(&self, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
        (**self).read_at(buf, offset)
    }
}

impl<T: ReadAt + ?Sized> ReadAt for Arc<T> {
    fn read_at(&self, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
        (**self).read_at(buf, offset)
    }
}

#[cfg(unix)]
impl ReadAt for std::fs::File {
    fn read_at(&self, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
        std::os::unix::fs::FileExt::read_exact_at(self, buf, offset)
    }
}

#[cfg(windows)]
impl ReadAt for std::fs::File {
    fn read_at(&self, mut buf: &mut [u8], mut offset: u64) -> std::io::Result<()> {
        use std::os::windows::fs::FileExt;
        while !buf.is_empty() {
            match self.seek_read(buf, offset) {
                Ok(0) => return Err(std::io::ErrorKind::UnexpectedEof.into()),
                Ok(n) => {
                    buf = &mut buf[n..];
                    offset += n as u64;
                }
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
        Ok(())
    }
}

/// One avatar's pose in a replayed frame.
#[derive(Debug, Clone, PartialEq)]
pub struct TakePose {
    /// The avatar, from the avatar list in effect at the frame.
    pub description: Arc<AvatarDescription>,
    /// Its pose (weights as the stored levels / 1023).
    pub pose: AvatarPose,
}

/// Reads a take's frames by index, decoding their v1 chunks through one [`FrameDecoder`].
///
/// A delta decodes against its keyframe, which the decoder must have decoded; a delta does not
/// change the decoder. So a frame costs one record when the decoder holds its keyframe
/// (sequential reading, or a jump within the same keyframe's deltas) and two otherwise (the
/// keyframe [`TakeIndex::key_before`] it, then the frame).
#[derive(Debug)]
pub struct TakeReader<R> {
    source: R,
    index: Arc<TakeIndex>,
    decoder: FrameDecoder,
    /// The keyframe the decoder holds (index into the frames).
    key: Option<usize>,
    /// The frame whose poses `poses` holds.
    current: Option<usize>,
    poses: Vec<TakePose>,
    /// The record being read.
    record: Vec<u8>,
    /// The v1 frame rebuilt from it.
    v1: Vec<u8>,
    /// The weight levels of the frame decoded last, every piece's in turn.
    levels: Vec<u16>,
    /// Each piece of the frame decoded last: its avatar number and its range of `levels`.
    pieces: Vec<(u32, std::ops::Range<usize>)>,
    /// The avatar list `by_num` indexes, and its descriptions by avatar number.
    list: Option<usize>,
    by_num: HashMap<u32, Arc<AvatarDescription>>,
}

impl<R: ReadAt> TakeReader<R> {
    /// A reader of the take in `source`, which `index` was scanned from.
    pub fn new(source: R, index: Arc<TakeIndex>) -> Self {
        Self {
            source,
            index,
            decoder: FrameDecoder::new(),
            key: None,
            current: None,
            poses: Vec::new(),
            record: Vec::new(),
            v1: Vec::new(),
            levels: Vec::new(),
            pieces: Vec::new(),
            list: None,
            by_num: HashMap::new(),
        }
    }

    /// The take's index.
    #[must_use]
    pub fn index(&self) -> &TakeIndex {
        &self.index
    }

    /// The poses of frame `i`, one per piece in scene order, each with its description (looked
    /// up by avatar number in the avatar list in effect at the frame). Reading `i` after `i − 1`
    /// decodes one record; a jump to another keyframe's deltas decodes that keyframe first.
    ///
    /// # Errors
    /// [`TakeError::NoSuchFrame`] past the index; [`TakeError::Io`] when reading fails;
    /// [`TakeError::Corrupt`] for a record that changed since the scan or names an avatar the
    /// list in effect does not have; [`TakeError::Frame`] for a chunk that does not decode (a
    /// delta without its keyframe among them).
    pub fn poses(&mut self, i: usize) -> Result<&[TakePose], TakeError> {
        let frames = self.index.frames.len();
        let entry = *self
            .index
            .frames
            .get(i)
            .ok_or(TakeError::NoSuchFrame { index: i, frames })?;
        if self.current == Some(i) {
            return Ok(&self.poses);
        }
        self.current = None;
        if !entry.key
            && let Some(k) = self.index.key_before(i)
            && self.key != Some(k)
        {
            self.decode(k)?;
            self.key = Some(k);
        }
        let frame = self.decode(i)?;
        if entry.key {
            self.key = Some(i);
        }
        self.attach(entry, frame)?;
        self.current = Some(i);
        Ok(&self.poses)
    }

    /// Reads frame record `i`, rebuilds its v1 frame and decodes it (leaving each piece's
    /// avatar number and weight levels in `pieces` and `levels`).
    fn decode(&mut self, i: usize) -> Result<Frame, TakeError> {
        let entry = self.index.frames[i];
        let at = entry.offset;
        let corrupt = |why| TakeError::Corrupt { at, why };
        let len = entry.len as usize;
        if len < RECORD_OVERHEAD {
            return Err(corrupt("frame record shorter than a record"));
        }
        self.record.resize(len, 0);
        self.source.read_at(&mut self.record, at)?;
        let r = &self.record;
        let n = u32::from_le_bytes([r[0], r[1], r[2], r[3]]) as usize;
        let crc = u32::from_le_bytes([r[len - 4], r[len - 3], r[len - 2], r[len - 1]]);
        if n + RECORD_OVERHEAD != len || r[4] != TYPE_FRAME || crc32fast::hash(&r[4..5 + n]) != crc
        {
            return Err(corrupt("frame record changed since the take was scanned"));
        }
        self.v1.clear();
        self.levels.clear();
        self.pieces.clear();
        let (v1, levels, pieces) = (&mut self.v1, &mut self.levels, &mut self.pieces);
        let (header, count) = parse_frame(&r[5..5 + n], |p| {
            v1.extend_from_slice(p.chunk);
            let from = levels.len();
            levels.extend(
                p.levels
                    .chunks_exact(2)
                    .map(|l| u16::from_le_bytes([l[0], l[1]])),
            );
            pieces.push((p.num, from..levels.len()));
        })
        .map_err(corrupt)?;
        // The header goes in front of the chunks: appended, then rotated into place.
        let chunks = self.v1.len();
        write_header(&header, count, &mut self.v1);
        let head = self.v1.len() - chunks;
        self.v1.rotate_right(head);
        self.decoder
            .decode(&self.v1)
            .map_err(|error| TakeError::Frame { at, error })
    }

    /// Turns a decoded frame into `poses`: weights from the levels, descriptions by number.
    fn attach(&mut self, entry: FrameEntry, frame: Frame) -> Result<(), TakeError> {
        let corrupt = |why| TakeError::Corrupt {
            at: entry.offset,
            why,
        };
        if self.list != Some(entry.avatars) {
            let list = self
                .index
                .avatar_lists
                .get(entry.avatars)
                .ok_or(corrupt("a frame whose avatar list is not in the index"))?;
            self.by_num = list.iter().map(|d| (d.num, d.clone())).collect();
            self.list = Some(entry.avatars);
        }
        self.poses.clear();
        for (mut pose, (num, range)) in frame.avatars.into_iter().zip(self.pieces.drain(..)) {
            if pose.avatar_num != num {
                return Err(corrupt("a piece whose avatar number is not its chunk's"));
            }
            let description = self
                .by_num
                .get(&num)
                .ok_or(corrupt(
                    "a chunk of an avatar the avatar list does not have",
                ))?
                .clone();
            pose.weights = self.levels[range]
                .iter()
                .map(|&l| f32::from(l) / WEIGHT_LEVELS)
                .collect();
            self.poses.push(TakePose { description, pose });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use posecast_proto::frame::ChunkEncoder;
    use posecast_proto::msg::AvatarId;
    use posecast_rigs::rig::Rig;
    use posecast_sim::avatar::Avatar;
    use posecast_sim::avatar::playback::Layer;
    use serde_json::json;

    /// A small xorshift generator (no dependency, the same numbers everywhere).
    struct Rng(u64);

    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            self.0
        }

        fn below(&mut self, n: usize) -> usize {
            (self.next() % n.max(1) as u64) as usize
        }
    }

    fn header() -> TakeHeader {
        TakeHeader {
            take: "t1".into(),
            scene: "lobby".into(),
            tick_rate: 60.0,
            started_us: 1_700_000_000_000_000,
        }
    }

    fn walker(rig: &Arc<Rig>, num: u32, start: f32) -> Avatar {
        let mut a = Avatar::new(AvatarId(format!("a{num}")), num, rig.clone());
        let walk = rig
            .clip("walk")
            .cloned()
            .expect("the built-in avatar walks");
        a.play(Layer::new(walk, None, start, 1.0, true), 0.0);
        a
    }

    /// A recorded take and what a v1 client decodes from the same frames.
    struct Recorded {
        bytes: Vec<u8>,
        /// Per frame: the poses a `FrameDecoder` fed the v1 frames gives, with the weights and
        /// descriptions attached.
        expected: Vec<Vec<TakePose>>,
    }

    /// `frames` ticks at 60 Hz from seq 1000 of avatars 1 and 2 walking (2 with morph weights),
    /// avatar 3 joining at frame `join` (a new avatar list and a keyframe); a keyframe every 10
    /// frames; an event before frame 5 and a record of an unknown type before frame 7.
    fn recorded(frames: usize, join: usize) -> Recorded {
        let rig = Arc::new(posecast_rigs::builtin::rig().unwrap());
        let mut avatars = vec![walker(&rig, 1, 0.0), walker(&rig, 2, 0.4)];
        let mut encoders = vec![ChunkEncoder::new(), ChunkEncoder::new()];
        let descriptions = |avatars: &[Avatar]| {
            avatars
                .iter()
                .map(|a| a.description.clone())
                .collect::<Vec<_>>()
        };
        let mut bytes = Vec::new();
        write_start(&header(), &mut bytes);
        let list = descriptions(&avatars);
        write_avatars(&list.iter().map(|d| &**d).collect::<Vec<_>>(), &mut bytes);
        let mut client = FrameDecoder::new();
        let mut expected = Vec::new();
        let mut base = 0;
        for f in 0..frames {
            let seq = 1000 + f as u64;
            let mut key = f.is_multiple_of(10);
            if f == join {
                avatars.push(walker(&rig, 3, 1.1));
                encoders.push(ChunkEncoder::new());
                let list = descriptions(&avatars);
                write_avatars(&list.iter().map(|d| &**d).collect::<Vec<_>>(), &mut bytes);
                key = true;
            }
            if f == 5 {
                write_event(&json!({"driver": "alice"}), &mut bytes);
            }
            if f == 7 {
                record(42, &mut bytes, |o| o.extend_from_slice(b"from the future"));
            }
            let kind = if key {
                FrameKind::Key
            } else {
                FrameKind::Delta
            };
            if key {
                base = seq;
            }
            let header = FrameHeader {
                kind,
                scene_num: 9,
                seq,
                server_time_us: 1_700_000_000_000_000 + seq * 16_667,
                base_seq: base,
            };
            let mut chunks = Vec::new();
            let mut weights = Vec::new();
            for (a, enc) in avatars.iter_mut().zip(&mut encoders) {
                a.tick(f as f64 / 60.0);
                let mut pose = a.pose().clone();
                if a.num() == 2 {
                    pose.weights = (0..4)
                        .map(|k| ((f * 37 + k * 300) % 1024) as f32 / 1023.0)
                        .collect();
                }
                let mut chunk = Vec::new();
                enc.encode(&pose, kind, &mut chunk);
                chunks.push(chunk);
                weights.push(pose.weights);
            }
            // The frame as a v1 subscriber gets it, through a client's decoder.
            let mut v1 = Vec::new();
            write_header(&header, chunks.len() as u16, &mut v1);
            chunks.iter().for_each(|c| v1.extend_from_slice(c));
            let decoded = client.decode(&v1).unwrap();
            expected.push(
                decoded
                    .avatars
                    .into_iter()
                    .zip(&weights)
                    .zip(&avatars)
                    .map(|((mut pose, w), a)| {
                        pose.weights.clone_from(w);
                        TakePose {
                            description: a.description.clone(),
                            pose,
                        }
                    })
                    .collect(),
            );
            let pieces = avatars
                .iter()
                .zip(&chunks)
                .zip(&weights)
                .map(|((a, c), w)| (a.num(), c.as_slice(), w.as_slice()));
            write_frame(&header, pieces, &mut bytes);
        }
        Recorded { bytes, expected }
    }

    /// Every record of a whole take: (offset, type, whole length).
    fn records(bytes: &[u8]) -> Vec<(u64, u8, usize)> {
        let mut at = MAGIC.len();
        let mut out = Vec::new();
        while at < bytes.len() {
            let n = u32::from_le_bytes(bytes[at..at + 4].try_into().unwrap()) as usize;
            out.push((at as u64, bytes[at + 4], n + RECORD_OVERHEAD));
            at += n + RECORD_OVERHEAD;
        }
        assert_eq!(at, bytes.len());
        out
    }

    /// A reader that hands out at most 7 bytes a call (the scan must not care).
    struct Trickle<'a>(&'a [u8]);

    impl Read for Trickle<'_> {
        fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
            let n = buf.len().min(7).min(self.0.len());
            buf[..n].copy_from_slice(&self.0[..n]);
            self.0 = &self.0[n..];
            Ok(n)
        }
    }

    fn temp_file(name: &str, bytes: &[u8]) -> std::path::PathBuf {
        let path =
            std::env::temp_dir().join(format!("posecast-take-{}-{name}.take", std::process::id()));
        std::fs::write(&path, bytes).unwrap();
        path
    }

    /// A take reads back as exactly what a v1 client decodes from the same frames, weights and
    /// descriptions attached, read in order, by jumps both ways, from memory and from a file.
    #[test]
    fn a_take_reads_back_as_a_client_decodes_its_frames() {
        let rec = recorded(40, 25);
        let index = TakeIndex::from_bytes(&rec.bytes).unwrap();
        assert_eq!(index.header, header());
        assert_eq!(index.frames.len(), 40);
        assert_eq!(
            (index.valid_len, index.torn_tail),
            (rec.bytes.len() as u64, 0)
        );
        let lists = &index.avatar_lists;
        assert_eq!(lists.iter().map(Vec::len).collect::<Vec<_>>(), vec![2, 3]);
        assert!(
            Arc::ptr_eq(&lists[0][1], &lists[1][1]),
            "an unchanged description is shared"
        );
        assert_eq!(lists[1][2].num, 3);
        assert_eq!(index.events, vec![(1005, json!({"driver": "alice"}))]);
        for (f, e) in index.frames.iter().enumerate() {
            assert_eq!(e.seq, 1000 + f as u64);
            assert_eq!(e.key, f.is_multiple_of(10) || f == 25, "frame {f}");
            assert_eq!(e.avatars, usize::from(f >= 25));
        }
        // The streaming scan sees the same, however the bytes arrive.
        assert_eq!(TakeIndex::scan(Trickle(&rec.bytes)).unwrap(), index);
        let index = Arc::new(index);

        let mut reader = TakeReader::new(rec.bytes.clone(), index.clone());
        for (i, expected) in rec.expected.iter().enumerate() {
            assert_eq!(reader.poses(i).unwrap(), &expected[..], "frame {i}");
        }
        let weighted = &reader.poses(13).unwrap()[1].pose.weights;
        assert!(weighted.len() == 4 && weighted.iter().any(|&w| w > 0.0));
        assert_eq!(
            reader.poses(40).unwrap_err(),
            TakeError::NoSuchFrame {
                index: 40,
                frames: 40
            }
        );

        let path = temp_file("roundtrip", &rec.bytes);
        let file = std::fs::File::open(&path).unwrap();
        assert_eq!(TakeIndex::scan(&file).unwrap(), *index);
        let mut reader = TakeReader::new(file, index.clone());
        let mut order = vec![39, 3, 27, 12, 11, 10, 9, 35, 0, 25, 24, 26, 26, 19, 20, 21];
        let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
        order.extend((0..100).map(|_| rng.below(40)));
        for i in order {
            assert_eq!(
                reader.poses(i).unwrap(),
                &rec.expected[i][..],
                "jump to {i}"
            );
        }
        let _ = std::fs::remove_file(path);
        let shared: Arc<[u8]> = rec.bytes.clone().into();
        let mut reader = TakeReader::new(Bytes::from(rec.bytes.clone()), index.clone());
        assert_eq!(reader.poses(33).unwrap(), &rec.expected[33][..]);
        let mut reader = TakeReader::new(shared, index.clone());
        assert_eq!(reader.poses(8).unwrap(), &rec.expected[8][..]);
        let mut reader = TakeReader::new(&rec.bytes[..], index);
        assert_eq!(reader.poses(17).unwrap(), &rec.expected[17][..]);
    }

    /// Every cut of a take (a writer killed at any byte) scans to its last whole record, and
    /// every frame of it reads back.
    #[test]
    fn every_cut_reads_up_to_its_last_whole_record() {
        let rec = recorded(24, 15);
        let bytes = &rec.bytes;
        let all = records(bytes);
        let ends: Vec<u64> = all.iter().map(|&(at, _, len)| at + len as u64).collect();
        let header_end = ends[0] as usize;
        for cut in 0..header_end {
            assert!(
                matches!(
                    TakeIndex::from_bytes(&bytes[..cut]),
                    Err(TakeError::Header(_))
                ),
                "cut at {cut}"
            );
        }
        let mut frames_before = 0;
        for cut in header_end..=bytes.len() {
            let index =
                TakeIndex::from_bytes(&bytes[..cut]).unwrap_or_else(|e| panic!("cut {cut}: {e}"));
            let valid = ends
                .iter()
                .copied()
                .filter(|&e| e <= cut as u64)
                .max()
                .unwrap();
            assert_eq!(index.valid_len, valid, "cut {cut}");
            assert_eq!(index.torn_tail, cut as u64 - valid, "cut {cut}");
            let whole_frames = all
                .iter()
                .filter(|&&(at, kind, len)| kind == TYPE_FRAME && at + len as u64 <= cut as u64)
                .count();
            assert_eq!(index.frames.len(), whole_frames, "cut {cut}");
            assert!(index.frames.len() >= frames_before);
            let n = index.frames.len();
            if n != frames_before || cut == bytes.len() {
                let mut reader = TakeReader::new(&bytes[..cut], Arc::new(index));
                for i in 0..n {
                    assert_eq!(
                        reader.poses(i).unwrap(),
                        &rec.expected[i][..],
                        "cut {cut}, frame {i}"
                    );
                }
            }
            frames_before = n;
        }
        assert_eq!(frames_before, 24);
    }

    /// A damaged record with whole records after it is corruption, reported at its offset;
    /// damage at the very end is a torn tail; a bad magic is not a take.
    #[test]
    fn damage_in_the_middle_is_corruption_and_at_the_end_a_torn_tail() {
        let rec = recorded(24, 15);
        let bytes = &rec.bytes;
        let all = records(bytes);
        let middle: Vec<_> = all
            .iter()
            .filter(|&&(_, kind, _)| kind != TYPE_HEADER)
            .filter(|&&(at, kind, _)| {
                kind == TYPE_EVENT || kind == 42 || (kind == TYPE_AVATARS && at > all[1].0)
            })
            .chain(all.iter().filter(|r| r.1 == TYPE_FRAME).nth(12))
            .copied()
            .collect();
        assert_eq!(
            middle.len(),
            4,
            "the event, the unknown record, the second list, a frame"
        );
        for (at, kind, len) in middle {
            let at_us = at as usize;
            // Every byte of small records; the head and tail of a long one.
            let positions: Vec<usize> = if len < 2000 {
                (at_us..at_us + len).collect()
            } else {
                (at_us..at_us + 16)
                    .chain(at_us + len - 8..at_us + len)
                    .collect()
            };
            for p in positions {
                for flip in [0x01u8, 0x80] {
                    let mut damaged = bytes.clone();
                    damaged[p] ^= flip;
                    match TakeIndex::from_bytes(&damaged) {
                        Err(TakeError::Corrupt { at: got, .. }) => {
                            assert_eq!(got, at, "record of type {kind}, byte {p}")
                        }
                        other => panic!("record of type {kind}, byte {p} ^ {flip}: {other:?}"),
                    }
                }
            }
        }
        // A length past the cap in the middle.
        let frame = all.iter().find(|r| r.1 == TYPE_FRAME).unwrap().0 as usize;
        let mut damaged = bytes.clone();
        damaged[frame..frame + 4].copy_from_slice(&u32::MAX.to_le_bytes());
        assert_eq!(
            TakeIndex::from_bytes(&damaged),
            Err(TakeError::Corrupt {
                at: frame as u64,
                why: "record length over 64 MiB"
            })
        );
        // The last record's checksum failing: a torn tail (it could be the last write).
        let &(last, _, last_len) = all.last().unwrap();
        let mut damaged = bytes.clone();
        damaged[last as usize + 20] ^= 0x10;
        let index = TakeIndex::from_bytes(&damaged).unwrap();
        assert_eq!((index.valid_len, index.torn_tail), (last, last_len as u64));
        assert_eq!(index.frames.len(), 23);
        // A zero-filled tail (a file system that grew the file before the data landed).
        let mut zeros = bytes.clone();
        zeros.resize(bytes.len() + 4096, 0);
        let index = TakeIndex::from_bytes(&zeros).unwrap();
        assert_eq!(
            (index.valid_len, index.torn_tail),
            (bytes.len() as u64, 4096)
        );
        assert_eq!(index.frames.len(), 24);
        // Not a take.
        let mut magic = bytes.clone();
        magic[3] ^= 1;
        assert_eq!(TakeIndex::from_bytes(&magic), Err(TakeError::NotATake));
        assert_eq!(TakeIndex::from_bytes(b"PCTAKE02"), Err(TakeError::NotATake));
        assert_eq!(TakeIndex::from_bytes(b"{}"), Err(TakeError::NotATake));
        // A record changed after the scan: the reader notices.
        let index = Arc::new(TakeIndex::from_bytes(bytes).unwrap());
        let mut changed = bytes.clone();
        changed[index.frames[3].offset as usize + 30] ^= 4;
        let mut reader = TakeReader::new(changed, index.clone());
        assert_eq!(
            reader.poses(3).unwrap_err(),
            TakeError::Corrupt {
                at: index.frames[3].offset,
                why: "frame record changed since the take was scanned"
            }
        );
    }

    /// The header must come first, and once; frames need an avatar list; chunks must decode and
    /// name avatars of the list.
    #[test]
    fn impossible_contents_are_refused() {
        let mut no_header = MAGIC.to_vec();
        write_avatars(&[], &mut no_header);
        assert!(matches!(
            TakeIndex::from_bytes(&no_header),
            Err(TakeError::Header(_))
        ));
        let mut bad_header = MAGIC.to_vec();
        json_record(TYPE_HEADER, &json!({"take": 1}), &mut bad_header);
        assert!(matches!(
            TakeIndex::from_bytes(&bad_header),
            Err(TakeError::Header(_))
        ));

        let mut start = Vec::new();
        write_start(&header(), &mut start);
        let two = start.len() as u64;
        let mut twice = start.clone();
        json_record(TYPE_HEADER, &header(), &mut twice);
        assert_eq!(
            TakeIndex::from_bytes(&twice),
            Err(TakeError::Corrupt {
                at: two,
                why: "a second header record"
            })
        );

        let rig = Arc::new(posecast_rigs::builtin::rig().unwrap());
        let mut a = walker(&rig, 7, 0.0);
        a.tick(0.1);
        let frame = |kind, seq, out: &mut Vec<u8>| {
            let mut chunk = Vec::new();
            ChunkEncoder::new().encode(a.pose(), kind, &mut chunk);
            let h = FrameHeader {
                kind,
                scene_num: 1,
                seq,
                server_time_us: 0,
                base_seq: 1,
            };
            write_frame(&h, std::iter::once((7, &chunk[..], &[][..])), out);
        };
        let mut orphan = start.clone();
        frame(FrameKind::Key, 1, &mut orphan);
        assert_eq!(
            TakeIndex::from_bytes(&orphan),
            Err(TakeError::Corrupt {
                at: two,
                why: "a frame before any avatar list"
            })
        );

        // A delta without its keyframe: indexed, but it does not decode.
        let mut keyless = start.clone();
        write_avatars(&[&a.description], &mut keyless);
        let at = keyless.len() as u64;
        frame(FrameKind::Delta, 2, &mut keyless);
        let index = Arc::new(TakeIndex::from_bytes(&keyless).unwrap());
        assert_eq!(index.key_before(0), None);
        let mut reader = TakeReader::new(keyless, index);
        assert_eq!(
            reader.poses(0).unwrap_err(),
            TakeError::Frame {
                at,
                error: FrameError::MissingKeyframe {
                    avatar: 7,
                    base_seq: 1
                }
            }
        );

        // A chunk of avatar 7 in a take whose list only has avatar 8.
        let stranger = walker(&rig, 8, 0.0);
        let mut unknown = start;
        write_avatars(&[&stranger.description], &mut unknown);
        let at = unknown.len() as u64;
        frame(FrameKind::Key, 1, &mut unknown);
        let index = Arc::new(TakeIndex::from_bytes(&unknown).unwrap());
        let mut reader = TakeReader::new(unknown, index);
        assert_eq!(
            reader.poses(0).unwrap_err(),
            TakeError::Corrupt {
                at,
                why: "a chunk of an avatar the avatar list does not have"
            }
        );
    }

    /// Random bytes — alone, after the magic, after a valid start or a whole take, or
    /// sprinkled over a whole take — never make the scan or the reader panic.
    #[test]
    fn garbage_never_panics() {
        let rec = recorded(12, 6);
        let start_len = records(&rec.bytes)[1].0 as usize + records(&rec.bytes)[1].2;
        let mut ok = 0;
        for seed in 1..=300u64 {
            let mut rng = Rng(seed.wrapping_mul(0x2545_f491_4f6c_dd1d) | 1);
            let len = rng.below(2000);
            let noise: Vec<u8> = (0..len).map(|_| rng.next() as u8).collect();
            let mut sprinkled = rec.bytes.clone();
            for _ in 0..1 + rng.below(4) {
                let p = rng.below(sprinkled.len());
                sprinkled[p] = rng.next() as u8;
            }
            let candidates = [
                noise.clone(),
                [&MAGIC[..], &noise].concat(),
                [&rec.bytes[..start_len], &noise].concat(),
                [&rec.bytes[..], &noise].concat(),
                sprinkled,
            ];
            for bytes in candidates {
                if let Ok(index) = TakeIndex::from_bytes(&bytes) {
                    ok += 1;
                    let n = index.frames.len();
                    let mut reader = TakeReader::new(bytes, Arc::new(index));
                    for i in (0..n).rev().chain(0..n) {
                        let _ = reader.poses(i);
                    }
                }
            }
        }
        // The valid starts and the whole takes with noise after them scan (as torn tails).
        assert!(ok >= 600, "{ok} scanned");
    }

    /// Times, frames and keyframes of a hand-made take (10 Hz): seqs 100 (key), 101, 102,
    /// 104, 105 (key), 106, 110 (key), 111.
    #[test]
    fn frame_at_key_before_and_duration() {
        let mut bytes = Vec::new();
        write_start(
            &TakeHeader {
                tick_rate: 10.0,
                ..header()
            },
            &mut bytes,
        );
        write_avatars(&[], &mut bytes);
        for (seq, key) in [
            (100, true),
            (101, false),
            (102, false),
            (104, false),
            (105, true),
            (106, false),
            (110, true),
            (111, false),
        ] {
            let h = FrameHeader {
                kind: if key {
                    FrameKind::Key
                } else {
                    FrameKind::Delta
                },
                scene_num: 0,
                seq,
                server_time_us: seq,
                base_seq: seq,
            };
            write_frame(&h, std::iter::empty(), &mut bytes);
        }
        write_event(&json!("the end"), &mut bytes);
        let index = TakeIndex::from_bytes(&bytes).unwrap();
        assert_eq!(index.first_seq(), Some(100));
        assert!(
            (index.duration() - 1.1).abs() < 1e-9,
            "{}",
            index.duration()
        );
        for (t, i) in [
            (0.0, 0),
            (0.1, 1),
            (0.2, 2),
            (0.3, 2),
            (0.39, 2),
            (0.4, 3),
            (0.55, 4),
            (0.6, 5),
            (0.9, 5),
            (1.0, 6),
            (1.1, 7),
            (5.0, 7),
            (-3.0, 0),
            (f64::NAN, 0),
            (f64::INFINITY, 7),
        ] {
            assert_eq!(index.frame_at(t), Some(i), "t = {t}");
        }
        for (i, k) in [
            (0, Some(0)),
            (3, Some(0)),
            (4, Some(4)),
            (5, Some(4)),
            (6, Some(6)),
            (7, Some(6)),
            (8, None),
        ] {
            assert_eq!(index.key_before(i), k, "frame {i}");
        }
        assert_eq!(index.events, vec![(112, json!("the end"))]);
        // A single frame lasts nothing; no frame has no time.
        let mut one = Vec::new();
        write_start(&header(), &mut one);
        let empty = TakeIndex::from_bytes(&one).unwrap();
        assert_eq!(
            (empty.frame_at(1.0), empty.first_seq(), empty.duration()),
            (None, None, 0.0)
        );
        write_avatars(&[], &mut one);
        let h = FrameHeader {
            kind: FrameKind::Delta,
            scene_num: 0,
            seq: 7,
            server_time_us: 0,
            base_seq: 3,
        };
        write_frame(&h, std::iter::empty(), &mut one);
        let single = TakeIndex::from_bytes(&one).unwrap();
        assert_eq!(
            (
                single.duration(),
                single.frame_at(9.0),
                single.key_before(0)
            ),
            (0.0, Some(0), None)
        );
    }

    /// Weights are stored as levels of 1/1023, clamped, NaN as 0.
    #[test]
    fn weights_are_stored_as_levels() {
        let mut bytes = Vec::new();
        let h = FrameHeader {
            kind: FrameKind::Key,
            scene_num: 3,
            seq: 1,
            server_time_us: 2,
            base_seq: 1,
        };
        let weights = [0.0, 1.0, 0.5, 2.0, -1.0, f32::NAN, 100.0 / 1023.0];
        write_frame(
            &h,
            std::iter::once((5, &b"chunk"[..], &weights[..])),
            &mut bytes,
        );
        let mut levels = Vec::new();
        let (read, count) = parse_frame(&bytes[5..bytes.len() - 4], |p| {
            assert_eq!((p.num, p.chunk), (5, &b"chunk"[..]));
            levels.extend(
                p.levels
                    .chunks_exact(2)
                    .map(|l| u16::from_le_bytes([l[0], l[1]])),
            );
        })
        .unwrap();
        assert_eq!((read, count), (FrameHeader { scene_num: 0, ..h }, 1));
        assert_eq!(levels, vec![0, 1023, 512, 1023, 0, 0, 100]);
    }
}
