//! RGBA8 images: PNG files, and the comparison golden-image tests use (modelled on wgpu's
//! `tests/src/image.rs`: on failure, write `-actual.png` and `-difference.png` beside the
//! golden).

use super::error::RenderError;
use std::path::{Path, PathBuf};

/// Tightly packed 8-bit sRGB RGBA pixels, rows top to bottom.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RgbaImage {
    width: u32,
    height: u32,
    pixels: Vec<u8>,
}

impl RgbaImage {
    /// An image of `width × height` pixels from its packed RGBA bytes.
    ///
    /// # Panics
    /// If `pixels` is not `width × height × 4` bytes (a caller bug).
    #[must_use]
    pub fn new(width: u32, height: u32, pixels: Vec<u8>) -> Self {
        assert_eq!(
            pixels.len(),
            width as usize * height as usize * 4,
            "RGBA size"
        );
        Self {
            width,
            height,
            pixels,
        }
    }

    /// Width, pixels.
    #[must_use]
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height, pixels.
    #[must_use]
    pub fn height(&self) -> u32 {
        self.height
    }

    /// The packed pixels: 4 bytes (R, G, B, A) each, row by row from the top.
    #[must_use]
    pub fn pixels(&self) -> &[u8] {
        &self.pixels
    }

    /// RGBA of pixel (x, y), or `None` outside the image.
    #[must_use]
    pub fn pixel(&self, x: u32, y: u32) -> Option<[u8; 4]> {
        if x >= self.width || y >= self.height {
            return None;
        }
        let at = (y as usize * self.width as usize + x as usize) * 4;
        self.pixels.get(at..at + 4)?.try_into().ok()
    }

    /// Writes an 8-bit sRGB RGBA PNG.
    pub fn write_png(&self, path: &Path) -> Result<(), RenderError> {
        let failed = |reason: String| RenderError::ImageFile {
            path: path.display().to_string(),
            reason,
        };
        let file = std::fs::File::create(path).map_err(|e| failed(e.to_string()))?;
        let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), self.width, self.height);
        encoder.set_color(png::ColorType::Rgba);
        encoder.set_depth(png::BitDepth::Eight);
        encoder.set_source_srgb(png::SrgbRenderingIntent::Perceptual);
        let mut writer = encoder.write_header().map_err(|e| failed(e.to_string()))?;
        writer
            .write_image_data(&self.pixels)
            .map_err(|e| failed(e.to_string()))?;
        writer.finish().map_err(|e| failed(e.to_string()))
    }

    /// Reads an 8-bit RGBA or RGB PNG.
    pub fn read_png(path: &Path) -> Result<Self, RenderError> {
        let failed = |reason: String| RenderError::ImageFile {
            path: path.display().to_string(),
            reason,
        };
        let file = std::fs::File::open(path).map_err(|e| failed(e.to_string()))?;
        let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
        decoder.set_transformations(png::Transformations::EXPAND);
        let mut reader = decoder.read_info().map_err(|e| failed(e.to_string()))?;
        let mut buffer = vec![0; reader.output_buffer_size()];
        let info = reader
            .next_frame(&mut buffer)
            .map_err(|e| failed(e.to_string()))?;
        if info.bit_depth != png::BitDepth::Eight {
            return Err(failed(format!(
                "bit depth {:?}, expected 8",
                info.bit_depth
            )));
        }
        buffer.truncate(info.buffer_size());
        let pixels = match info.color_type {
            png::ColorType::Rgba => buffer,
            png::ColorType::Rgb => buffer
                .chunks_exact(3)
                .flat_map(|p| [p[0], p[1], p[2], 255])
                .collect(),
            other => return Err(failed(format!("colour type {other:?}, expected RGB(A)"))),
        };
        if pixels.len() != info.width as usize * info.height as usize * 4 {
            return Err(failed("pixel data does not match the size".into()));
        }
        Ok(Self::new(info.width, info.height, pixels))
    }

    /// Per-pixel comparison with `other` of the same size (RGB channels; alpha ignored).
    #[must_use]
    pub fn compare(&self, other: &Self, outlier_threshold: u8) -> Option<ImageDiff> {
        if (self.width, self.height) != (other.width, other.height) {
            return None;
        }
        let mut sum = 0u64;
        let mut max = 0u8;
        let mut outliers = 0usize;
        let mut difference = Vec::with_capacity(self.pixels.len());
        for (a, b) in self
            .pixels
            .chunks_exact(4)
            .zip(other.pixels.chunks_exact(4))
        {
            let d = [
                a[0].abs_diff(b[0]),
                a[1].abs_diff(b[1]),
                a[2].abs_diff(b[2]),
            ];
            let worst = d[0].max(d[1]).max(d[2]);
            sum += d.iter().map(|&v| u64::from(v)).sum::<u64>();
            max = max.max(worst);
            if worst > outlier_threshold {
                outliers += 1;
            }
            difference.extend([d[0], d[1], d[2], 255]);
        }
        let pixels = (self.width as usize * self.height as usize).max(1);
        Some(ImageDiff {
            mean: sum as f64 / (pixels * 3) as f64,
            max,
            outlier_fraction: outliers as f64 / pixels as f64,
            difference: Self::new(self.width, self.height, difference),
        })
    }

    /// Fraction of pixels differing from `background` by more than `threshold` in some channel:
    /// how much of the picture something covers.
    #[must_use]
    pub fn coverage(&self, background: [u8; 3], threshold: u8) -> f64 {
        let covered = self
            .pixels
            .chunks_exact(4)
            .filter(|p| (0..3).any(|c| p[c].abs_diff(background[c]) > threshold))
            .count();
        covered as f64 / (self.width as usize * self.height as usize).max(1) as f64
    }
}

/// How two images differ.
#[derive(Clone, Debug)]
pub struct ImageDiff {
    /// Mean absolute difference per channel, in 8-bit steps (0–255).
    pub mean: f64,
    /// Largest difference of any channel.
    pub max: u8,
    /// Fraction of pixels with some channel differing by more than the outlier threshold.
    pub outlier_fraction: f64,
    /// |a − b| per channel, as an image.
    pub difference: RgbaImage,
}

/// What a comparison tolerates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Tolerance {
    /// Largest allowed [`ImageDiff::mean`].
    pub mean: f64,
    /// A pixel is an outlier when some channel differs by more than this.
    pub outlier_threshold: u8,
    /// Largest allowed [`ImageDiff::outlier_fraction`].
    pub outlier_fraction: f64,
}

/// Compares `actual` with `expected`; on failure writes `<stem>-actual.png` and
/// `<stem>-difference.png` next to `reference` (the golden file's path, or where one would
/// be) and returns a description of the failure.
pub fn check_images(
    actual: &RgbaImage,
    expected: &RgbaImage,
    reference: &Path,
    tolerance: &Tolerance,
) -> Result<ImageDiff, String> {
    let Some(diff) = actual.compare(expected, tolerance.outlier_threshold) else {
        let written = write_failure(actual, None, reference);
        return Err(format!(
            "size {}×{} differs from the expected {}×{}{written}",
            actual.width, actual.height, expected.width, expected.height
        ));
    };
    if diff.mean <= tolerance.mean && diff.outlier_fraction <= tolerance.outlier_fraction {
        return Ok(diff);
    }
    let written = write_failure(actual, Some(&diff.difference), reference);
    Err(format!(
        "images differ: mean {:.3} (limit {}), {:.3}% of pixels off by more than {} (limit \
         {:.3}%), max {}{written}",
        diff.mean,
        tolerance.mean,
        diff.outlier_fraction * 100.0,
        tolerance.outlier_threshold,
        tolerance.outlier_fraction * 100.0,
        diff.max,
    ))
}

/// Compares `actual` with the PNG at `golden`. With `POSECAST_BLESS` set in the environment (to
/// anything but `0`), (re)writes the golden instead and passes.
pub fn check_golden(
    actual: &RgbaImage,
    golden: &Path,
    tolerance: &Tolerance,
) -> Result<(), String> {
    if std::env::var_os("POSECAST_BLESS").is_some_and(|v| v != "0") {
        return actual
            .write_png(golden)
            .map_err(|e| format!("blessing {}: {e}", golden.display()));
    }
    let expected = RgbaImage::read_png(golden).map_err(|e| {
        let written = write_failure(actual, None, golden);
        format!("{e}; run with POSECAST_BLESS=1 to create it{written}")
    })?;
    check_images(actual, &expected, golden, tolerance).map(drop)
}

fn sibling(reference: &Path, suffix: &str) -> PathBuf {
    let stem = reference
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "image".into());
    reference.with_file_name(format!("{stem}-{suffix}.png"))
}

fn write_failure(actual: &RgbaImage, difference: Option<&RgbaImage>, reference: &Path) -> String {
    let mut written = Vec::new();
    let mut save = |image: &RgbaImage, suffix| {
        let path = sibling(reference, suffix);
        match image.write_png(&path) {
            Ok(()) => written.push(path.display().to_string()),
            Err(e) => written.push(format!("(could not write: {e})")),
        }
    };
    save(actual, "actual");
    if let Some(d) = difference {
        save(d, "difference");
    }
    format!("; wrote {}", written.join(", "))
}
