//! Bounds-checked reading of glTF accessors into `f32`s (normalised integers scaled to
//! [0, 1] or [−1, 1], plain integers converted), including sparse accessors. Every offset is
//! checked against its buffer view and buffer before a byte is read, so a malformed file
//! gives an error naming the accessor, never an out-of-bounds index.

use std::borrow::Cow;

use gltf::accessor::{DataType, Dimensions};

use super::ImportError;

/// Most elements an accessor without a buffer view (all zeros, or sparse) may declare: such
/// counts are not bounded by any data in the file.
const MAX_VIEWLESS: usize = 1 << 22;

pub(crate) struct Buffers<'a> {
    pub file: &'a str,
    /// Each buffer's bytes; a GLB's binary chunk borrowed from the file.
    pub data: Vec<Cow<'a, [u8]>>,
}

impl Buffers<'_> {
    fn err(&self, accessor: usize, message: impl Into<String>) -> ImportError {
        ImportError::Accessor {
            file: self.file.to_owned(),
            accessor,
            message: message.into(),
        }
    }

    /// Bytes `[offset, offset + stride·(count−1) + elem)` of `view`, checked.
    fn slice(
        &self,
        accessor: usize,
        view: &gltf::buffer::View<'_>,
        offset: usize,
        count: usize,
        elem: usize,
        stride: usize,
    ) -> Result<&[u8], ImportError> {
        let buffer = self
            .data
            .get(view.buffer().index())
            .ok_or_else(|| self.err(accessor, "buffer not loaded"))?;
        let view_end = view
            .offset()
            .checked_add(view.length())
            .filter(|&e| e <= buffer.len())
            .ok_or_else(|| self.err(accessor, "buffer view runs past its buffer"))?;
        let view_bytes = &buffer[view.offset()..view_end];
        if count == 0 {
            return Ok(&[]);
        }
        let end = stride
            .checked_mul(count - 1)
            .and_then(|v| v.checked_add(elem))
            .and_then(|v| v.checked_add(offset))
            .filter(|&e| e <= view_bytes.len())
            .ok_or_else(|| {
                self.err(
                    accessor,
                    format!("{count} elements of {elem} bytes run past the buffer view"),
                )
            })?;
        Ok(&view_bytes[offset..end])
    }

    /// The accessor's components as `f32`, `count × dimensions` of them.
    pub fn read(&self, accessor: &gltf::Accessor<'_>) -> Result<Vec<f32>, ImportError> {
        let index = accessor.index();
        let dims = dims(accessor.dimensions());
        let ty = accessor.data_type();
        let size = ty.size();
        let elem = size * dims;
        let count = accessor.count();
        let normalized = accessor.normalized();
        let mut out = match accessor.view() {
            Some(view) => {
                let stride = view.stride().unwrap_or(elem);
                if stride < elem {
                    return Err(self.err(index, format!("byte stride {stride} < element {elem}")));
                }
                let bytes = self.slice(index, &view, accessor.offset(), count, elem, stride)?;
                if ty == DataType::F32 && stride == elem {
                    // Tightly packed floats, most of a mesh: one pass the compiler vectorises
                    // (the general loop below was a fifth of importing the built-in avatar).
                    bytes
                        .chunks_exact(4)
                        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                        .collect()
                } else {
                    let mut out = Vec::with_capacity(count * dims);
                    for i in 0..count {
                        let at = i * stride;
                        for c in 0..dims {
                            let p = at + c * size;
                            out.push(component(&bytes[p..p + size], ty, normalized));
                        }
                    }
                    out
                }
            }
            None => {
                if count > MAX_VIEWLESS {
                    return Err(self.err(index, format!("{count} elements without data")));
                }
                vec![0.0; count * dims]
            }
        };
        if let Some(sparse) = accessor.sparse() {
            let n = sparse.count();
            if n > count {
                return Err(self.err(index, format!("{n} sparse values for {count} elements")));
            }
            let idx = sparse.indices();
            let ity = match idx.index_type() {
                gltf::accessor::sparse::IndexType::U8 => DataType::U8,
                gltf::accessor::sparse::IndexType::U16 => DataType::U16,
                gltf::accessor::sparse::IndexType::U32 => DataType::U32,
            };
            let isize = ity.size();
            let ibytes = self.slice(index, &idx.view(), idx.offset(), n, isize, isize)?;
            let vals = sparse.values();
            let vbytes = self.slice(index, &vals.view(), vals.offset(), n, elem, elem)?;
            for k in 0..n {
                let target = component(&ibytes[k * isize..(k + 1) * isize], ity, false) as usize;
                if target >= count {
                    return Err(self.err(index, format!("sparse index {target} ≥ count {count}")));
                }
                for c in 0..dims {
                    let p = k * elem + c * size;
                    out[target * dims + c] = component(&vbytes[p..p + size], ty, normalized);
                }
            }
        }
        Ok(out)
    }

    /// A scalar unsigned-integer accessor read exactly (triangle indices).
    pub fn read_indices(&self, accessor: &gltf::Accessor<'_>) -> Result<Vec<u32>, ImportError> {
        let index = accessor.index();
        let ty = accessor.data_type();
        if accessor.dimensions() != Dimensions::Scalar
            || !matches!(ty, DataType::U8 | DataType::U16 | DataType::U32)
        {
            return Err(self.err(index, "indices must be unsigned integer scalars"));
        }
        let (Some(view), None) = (accessor.view(), accessor.sparse()) else {
            return Err(self.err(index, "indices without a plain buffer view"));
        };
        let size = ty.size();
        let stride = view.stride().unwrap_or(size);
        if stride < size {
            return Err(self.err(index, format!("byte stride {stride} < element {size}")));
        }
        let count = accessor.count();
        let bytes = self.slice(index, &view, accessor.offset(), count, size, stride)?;
        Ok((0..count)
            .map(|i| {
                let p = &bytes[i * stride..i * stride + size];
                match size {
                    1 => u32::from(p[0]),
                    2 => u32::from(u16::from_le_bytes([p[0], p[1]])),
                    _ => u32::from_le_bytes([p[0], p[1], p[2], p[3]]),
                }
            })
            .collect())
    }

    /// Reads an accessor that must have `expected` dimensions.
    pub fn read_as(
        &self,
        accessor: &gltf::Accessor<'_>,
        expected: Dimensions,
        what: &str,
    ) -> Result<Vec<f32>, ImportError> {
        if accessor.dimensions() != expected {
            return Err(self.err(
                accessor.index(),
                format!(
                    "{what} must be {expected:?}, is {:?}",
                    accessor.dimensions()
                ),
            ));
        }
        self.read(accessor)
    }
}

fn dims(d: Dimensions) -> usize {
    match d {
        Dimensions::Scalar => 1,
        Dimensions::Vec2 => 2,
        Dimensions::Vec3 => 3,
        Dimensions::Vec4 | Dimensions::Mat2 => 4,
        Dimensions::Mat3 => 9,
        Dimensions::Mat4 => 16,
    }
}

/// One little-endian component; `bytes` has exactly the type's size.
fn component(bytes: &[u8], ty: DataType, normalized: bool) -> f32 {
    let b = |i: usize| bytes.get(i).copied().unwrap_or(0);
    match ty {
        DataType::I8 => {
            let v = f32::from(b(0) as i8);
            if normalized { (v / 127.0).max(-1.0) } else { v }
        }
        DataType::U8 => {
            let v = f32::from(b(0));
            if normalized { v / 255.0 } else { v }
        }
        DataType::I16 => {
            let v = f32::from(i16::from_le_bytes([b(0), b(1)]));
            if normalized {
                (v / 32767.0).max(-1.0)
            } else {
                v
            }
        }
        DataType::U16 => {
            let v = f32::from(u16::from_le_bytes([b(0), b(1)]));
            if normalized { v / 65535.0 } else { v }
        }
        DataType::U32 => {
            let v = u32::from_le_bytes([b(0), b(1), b(2), b(3)]) as f32;
            if normalized { v / u32::MAX as f32 } else { v }
        }
        DataType::F32 => f32::from_le_bytes([b(0), b(1), b(2), b(3)]),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The same two points read packed and interleaved with a normal (byte stride 24, the
    /// normals at offset 12): the packed floats take a path of their own.
    #[test]
    fn packed_and_interleaved_floats_read_the_same() {
        let floats: [f32; 18] = [
            1.0, 2.0, 3.0, 4.0, 5.0, 6.0, // packed points
            1.0, 2.0, 3.0, 7.0, 8.0, 9.0, // point 0, normal 0
            4.0, 5.0, 6.0, 10.0, 11.0, 12.0, // point 1, normal 1
        ];
        let bytes: Vec<u8> = floats.iter().flat_map(|f| f.to_le_bytes()).collect();
        let json = serde_json::json!({
            "asset": {"version": "2.0"},
            "buffers": [{"byteLength": 72}],
            "bufferViews": [
                {"buffer": 0, "byteOffset": 0, "byteLength": 24},
                {"buffer": 0, "byteOffset": 24, "byteLength": 48, "byteStride": 24}
            ],
            "accessors": [
                {"bufferView": 0, "componentType": 5126, "count": 2, "type": "VEC3"},
                {"bufferView": 1, "componentType": 5126, "count": 2, "type": "VEC3"},
                {"bufferView": 1, "byteOffset": 12, "componentType": 5126, "count": 2,
                 "type": "VEC3"}
            ]
        });
        let gltf =
            gltf::Gltf::from_slice_without_validation(json.to_string().as_bytes()).expect("parses");
        let buffers = Buffers {
            file: "test.gltf",
            data: vec![Cow::Owned(bytes)],
        };
        let read: Vec<Vec<f32>> = gltf
            .accessors()
            .map(|a| {
                buffers
                    .read_as(&a, Dimensions::Vec3, "test")
                    .expect("reads")
            })
            .collect();
        assert_eq!(read[0], [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
        assert_eq!(read[1], read[0]);
        assert_eq!(read[2], [7.0, 8.0, 9.0, 10.0, 11.0, 12.0]);
    }
}
