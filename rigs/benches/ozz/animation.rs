//! ozz's runtime `Animation` (`include/ozz/animation/runtime/animation.h`) and its key
//! formats (`src/animation/runtime/animation_keyframe.h`).
//!
//! Keys of all tracks live in one array per component (translation, rotation, scale), sorted
//! by the time they are first needed: the time of the previous key of the same track, then by
//! track. Each key stores an index into the shared `timepoints` (ratios `time / duration`, as
//! `u8` when there are at most 255 time points, else `u16`) and the offset back to the
//! previous key of its track.

/// A translation or scale key: three IEEE half floats.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Float3Key {
    pub values: [u16; 3],
}

/// A rotation key, 48 bits: the index of the largest component (2 bits), its sign (1 bit), and
/// the three others quantised on 15 bits each, pre-multiplied by √2 (they lie in
/// `[−√2/2, √2/2]`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct QuaternionKey {
    pub values: [u8; 6],
}

impl QuaternionKey {
    /// Bits per quantised component.
    pub const BITS: u32 = 15;
    /// `(1 << BITS) − 1`.
    pub const I_SCALE: i32 = (1 << Self::BITS) - 1;
    /// `I_SCALE` as a float.
    pub const F_SCALE: f32 = Self::I_SCALE as f32;
}

/// `pack`: endianness-independent store of a rotation key.
#[must_use]
pub fn pack(largest: i32, sign: i32, cpnt: [i32; 3]) -> QuaternionKey {
    let packed: u64 = (largest as u64 & 0x3)
        | ((sign as u64 & 0x1) << 2)
        | ((cpnt[0] as u64 & 0x7fff) << 3)
        | ((cpnt[1] as u64 & 0x7fff) << 18)
        | ((cpnt[2] as u64 & 0x7fff) << 33);
    let b = packed.to_le_bytes();
    QuaternionKey {
        values: [b[0], b[1], b[2], b[3], b[4], b[5]],
    }
}

/// `unpack`: (largest component index, sign of the largest, the three others quantised).
#[inline(always)]
#[must_use]
pub fn unpack(key: &QuaternionKey) -> (usize, i32, [i32; 3]) {
    let v = key.values;
    let packed = u64::from_le_bytes([v[0], v[1], v[2], v[3], v[4], v[5], 0, 0]);
    (
        (packed & 0x3) as usize,
        ((packed >> 2) & 0x1) as i32,
        [
            ((packed >> 3) & 0x7fff) as i32,
            ((packed >> 18) & 0x7fff) as i32,
            ((packed >> 33) & 0x7fff) as i32,
        ],
    )
}

/// `Animation::Component`: one component's keys.
#[derive(Clone, Debug, Default)]
pub struct Component<K> {
    /// Indices into `timepoints`, one per key: `u8` when `timepoints.len() <= 255`, else
    /// little-endian `u16` (the bytes ozz reinterprets).
    pub ratios: Vec<u8>,
    /// Per key, how many keys back the previous key of the same track is (0 for a first key).
    pub previouses: Vec<u16>,
    /// Key values.
    pub values: Vec<K>,
}

/// The runtime animation: every joint's tracks, sorted and compressed by the builder.
#[derive(Clone, Debug, Default)]
pub struct Animation {
    /// Duration, seconds.
    pub duration: f32,
    /// Joint tracks (the SoA arrays hold `num_soa_tracks() · 4`).
    pub num_tracks: usize,
    /// Every distinct key time as a ratio of the duration, increasing.
    pub timepoints: Vec<f32>,
    pub translations: Component<Float3Key>,
    pub rotations: Component<QuaternionKey>,
    pub scales: Component<Float3Key>,
}

impl Animation {
    /// SoA elements needed for `num_tracks`.
    #[must_use]
    pub fn num_soa_tracks(&self) -> usize {
        self.num_tracks.div_ceil(4)
    }

    /// Bytes of key data (ozz's `Animation::size()` without the name and header).
    #[must_use]
    pub fn size_bytes(&self) -> usize {
        fn c<K>(c: &Component<K>) -> usize {
            c.ratios.len() + 2 * c.previouses.len() + std::mem::size_of::<K>() * c.values.len()
        }
        4 * self.timepoints.len() + c(&self.translations) + c(&self.rotations) + c(&self.scales)
    }
}
