//! Numeric arrays from NPY, NPZ and MATLAB v5 `.mat` files, and NPY writing.
//!
//! Every array is returned in C (row-major) order with its shape, as `f64`:
//! a NumPy file in Fortran order and every MATLAB array (column-major) are
//! transposed on reading, so `shape = [d0, d1, ...]` always means "index `d0`
//! varies slowest", and a MATLAB `data(i, j, k)` is element `[i-1, j-1, k-1]`.
//!
//! * NPY: any numeric dtype (`bool`, `i1..i8`, `u1..u8`, `f4`, `f8`, either
//!   byte order) converts to `f64`; structured (record) arrays whose fields are
//!   numeric scalars come back as named columns ([`NpyContent::Record`]), as
//!   neuromorphic event tools save events (`x`, `y`, `t`, `p` fields).
//! * NPZ: a zip of NPY files (`np.savez` stored, `np.savez_compressed`
//!   deflated), read in archive order (NumPy writes keyword arrays in call order).
//! * MAT: MATLAB v5/v7 files (`save -v7`, compressed or not) through the
//!   `matfile` crate; numeric real arrays only (char, cell and struct variables
//!   are skipped). v7.3 files are HDF5 and are rejected with a hint.

use std::io::{Cursor, Read};

/// A numeric array in C order.
#[derive(Clone, Debug, PartialEq)]
pub struct NdArray {
    /// Dimensions, slowest-varying first.
    pub shape: Vec<usize>,
    /// Elements in C order.
    pub data: Vec<f64>,
}

/// What an NPY file holds.
#[derive(Clone, Debug, PartialEq)]
pub enum NpyContent {
    /// A plain numeric array.
    Plain(NdArray),
    /// A 1-D structured array: `(field name, one value per record)`.
    Record(Vec<(String, Vec<f64>)>),
}

fn numeric(ts: &npyz::TypeStr, bytes: &[u8]) -> f64 {
    use npyz::{Endianness, TypeChar};
    let big = ts.endianness() == Endianness::Big;
    macro_rules! rd {
        ($t:ty, $n:expr) => {{
            let mut b = [0u8; $n];
            b.copy_from_slice(&bytes[..$n]);
            (if big {
                <$t>::from_be_bytes(b)
            } else {
                <$t>::from_le_bytes(b)
            }) as f64
        }};
    }
    match (ts.type_char(), ts.size_field()) {
        (TypeChar::Bool, 1) => f64::from(u8::from(bytes[0] != 0)),
        (TypeChar::Int, 1) => rd!(i8, 1),
        (TypeChar::Int, 2) => rd!(i16, 2),
        (TypeChar::Int, 4) => rd!(i32, 4),
        (TypeChar::Int, 8) => rd!(i64, 8),
        (TypeChar::Uint, 1) => rd!(u8, 1),
        (TypeChar::Uint, 2) => rd!(u16, 2),
        (TypeChar::Uint, 4) => rd!(u32, 4),
        (TypeChar::Uint, 8) => rd!(u64, 8),
        (TypeChar::Float, 4) => rd!(f32, 4),
        (TypeChar::Float, 8) => rd!(f64, 8),
        // Checked by `supported` before any element is read.
        _ => f64::NAN,
    }
}

fn supported(ts: &npyz::TypeStr) -> bool {
    use npyz::TypeChar;
    matches!(
        (ts.type_char(), ts.size_field()),
        (TypeChar::Bool, 1) | (TypeChar::Int | TypeChar::Uint, 1 | 2 | 4 | 8) | (TypeChar::Float, 4 | 8)
    )
}

/// Transposes a column-major (Fortran) buffer of `shape` into C order.
pub fn fortran_to_c(shape: &[usize], data: &[f64]) -> Vec<f64> {
    let n: usize = shape.iter().product();
    let mut out = vec![0.0; n];
    let nd = shape.len();
    let mut idx = vec![0usize; nd];
    // Walk C-order indices; compute the Fortran offset of each.
    for o in out.iter_mut() {
        let mut off = 0;
        let mut stride = 1;
        for d in 0..nd {
            off += idx[d] * stride;
            stride *= shape[d];
        }
        *o = data[off];
        for d in (0..nd).rev() {
            idx[d] += 1;
            if idx[d] < shape[d] {
                break;
            }
            idx[d] = 0;
        }
    }
    out
}

/// Reads an NPY file's bytes; `what` names the file for errors.
pub fn read_npy(bytes: &[u8], what: &str) -> Result<NpyContent, String> {
    let mut r = bytes;
    let header = npyz::NpyHeader::from_reader(&mut r)
        .map_err(|e| format!("{what}: not a readable NPY file ({e}); truncated or not NumPy's format?"))?;
    let npy = npyz::NpyFile::with_header(header, r);
    let shape: Vec<usize> = npy.shape().iter().map(|&d| d as usize).collect();
    let fortran = npy.order() == npyz::Order::Fortran;
    let n: usize = shape.iter().product();
    let data = r;
    match npy.dtype() {
        npyz::DType::Plain(ts) => {
            if !supported(&ts) {
                return Err(format!(
                    "{what}: dtype `{ts}` is not supported (use bool, integers, float32 or float64)"
                ));
            }
            let size = ts.size_field() as usize;
            let need = n * size;
            if data.len() < need {
                return Err(format!(
                    "{what}: truncated: shape {shape:?} needs {need} bytes of data, the file has {}",
                    data.len()
                ));
            }
            let mut v: Vec<f64> = data[..need].chunks_exact(size).map(|c| numeric(&ts, c)).collect();
            if fortran && shape.len() > 1 {
                v = fortran_to_c(&shape, &v);
            }
            Ok(NpyContent::Plain(NdArray { shape, data: v }))
        }
        npyz::DType::Record(fields) => {
            if shape.len() != 1 {
                return Err(format!(
                    "{what}: a structured array must be 1-D, got shape {shape:?}"
                ));
            }
            let mut layout = Vec::new();
            let mut off = 0usize;
            for f in &fields {
                match &f.dtype {
                    npyz::DType::Plain(ts) if supported(ts) => {
                        layout.push((f.name.clone(), ts.clone(), off));
                        off += ts.size_field() as usize;
                    }
                    other => {
                        return Err(format!(
                            "{what}: field `{}` has dtype `{}`; only numeric scalar fields are supported",
                            f.name,
                            other.descr()
                        ))
                    }
                }
            }
            let rec = off;
            let need = n * rec;
            if data.len() < need {
                return Err(format!(
                    "{what}: truncated: {n} records of {rec} bytes need {need} bytes, the file has {}",
                    data.len()
                ));
            }
            let cols = layout
                .into_iter()
                .map(|(name, ts, o)| {
                    let col = (0..n).map(|i| numeric(&ts, &data[i * rec + o..])).collect();
                    (name, col)
                })
                .collect();
            Ok(NpyContent::Record(cols))
        }
        other => Err(format!("{what}: dtype `{}` is not supported", other.descr())),
    }
}

/// Reads a plain numeric NPY array.
pub fn read_npy_plain(bytes: &[u8], what: &str) -> Result<NdArray, String> {
    match read_npy(bytes, what)? {
        NpyContent::Plain(a) => Ok(a),
        NpyContent::Record(_) => Err(format!(
            "{what}: expected a plain numeric array, found a structured one"
        )),
    }
}

/// Reads every array of an NPZ archive, in archive order: `(name, content)`.
pub fn read_npz(bytes: &[u8], what: &str) -> Result<Vec<(String, NpyContent)>, String> {
    let mut zip = zip::ZipArchive::new(Cursor::new(bytes))
        .map_err(|e| format!("{what}: not a readable NPZ (zip) file ({e}); truncated?"))?;
    let mut out = Vec::new();
    for i in 0..zip.len() {
        let mut f = zip
            .by_index(i)
            .map_err(|e| format!("{what}: cannot open archive member {i}: {e}"))?;
        let name = f.name().to_string();
        let Some(array) = name.strip_suffix(".npy") else {
            continue;
        };
        let array = array.to_string();
        let mut buf = Vec::new();
        f.read_to_end(&mut buf)
            .map_err(|e| format!("{what}: cannot read array `{array}` ({e}); truncated?"))?;
        let content = read_npy(&buf, &format!("{what}, array `{array}`"))?;
        out.push((array, content));
    }
    if out.is_empty() {
        return Err(format!("{what}: the archive holds no .npy array"));
    }
    Ok(out)
}

/// Reads every numeric variable of a MATLAB v5/v7 `.mat` file, in file order.
pub fn read_mat(bytes: &[u8], what: &str) -> Result<Vec<(String, NdArray)>, String> {
    if bytes.len() >= 128 && bytes.starts_with(b"MATLAB 7.3") {
        return Err(format!(
            "{what}: MATLAB v7.3 (HDF5) files are not supported; save with `save(..., '-v7')`"
        ));
    }
    if bytes.len() < 128 || !bytes.starts_with(b"MATLAB") {
        return Err(format!(
            "{what}: not a MATLAB .mat file (truncated, or no `MATLAB` header)"
        ));
    }
    check_mat_elements(bytes, what)?;
    let mat = matfile::MatFile::parse(bytes)
        .map_err(|e| format!("{what}: not a readable MAT v5/v7 file ({e}); truncated, or saved as v7.3?"))?;
    let mut out = Vec::new();
    for a in mat.arrays() {
        use matfile::NumericData as N;
        fn cv<T: Copy + Into<f64>>(v: &[T]) -> Vec<f64> {
            v.iter().map(|&x| x.into()).collect()
        }
        let (real, complex) = match a.data() {
            N::Double { real, imag } => (real.clone(), imag.is_some()),
            N::Single { real, imag } => (cv(real), imag.is_some()),
            N::Int8 { real, imag } => (cv(real), imag.is_some()),
            N::UInt8 { real, imag } => (cv(real), imag.is_some()),
            N::Int16 { real, imag } => (cv(real), imag.is_some()),
            N::UInt16 { real, imag } => (cv(real), imag.is_some()),
            N::Int32 { real, imag } => (cv(real), imag.is_some()),
            N::UInt32 { real, imag } => (cv(real), imag.is_some()),
            N::Int64 { real, imag } => (real.iter().map(|&x| x as f64).collect(), imag.is_some()),
            N::UInt64 { real, imag } => (real.iter().map(|&x| x as f64).collect(), imag.is_some()),
        };
        if complex {
            return Err(format!(
                "{what}: variable `{}` is complex; only real data is supported",
                a.name()
            ));
        }
        let shape = a.size().clone();
        if shape.iter().product::<usize>() != real.len() {
            return Err(format!("{what}: variable `{}` is truncated", a.name()));
        }
        let data = fortran_to_c(&shape, &real);
        out.push((a.name().to_string(), NdArray { shape, data }));
    }
    Ok(out)
}

/// Walks the top-level data elements of a MAT v5 file and fails if the last
/// one runs past the end of the file: `matfile` silently drops a truncated
/// trailing variable, which would lose a trial without a word.
fn check_mat_elements(bytes: &[u8], what: &str) -> Result<(), String> {
    let big = match &bytes[126..128] {
        b"IM" => false,
        b"MI" => true,
        _ => return Err(format!("{what}: not a MAT v5 file (bad endian indicator)")),
    };
    let u32_at = |o: usize| {
        let b = [bytes[o], bytes[o + 1], bytes[o + 2], bytes[o + 3]];
        if big {
            u32::from_be_bytes(b)
        } else {
            u32::from_le_bytes(b)
        }
    };
    let mut pos = 128usize;
    let mut k = 0;
    while pos < bytes.len() {
        if bytes.len() - pos < 8 {
            return Err(format!(
                "{what}: truncated: {} stray bytes after variable {k}",
                bytes.len() - pos
            ));
        }
        let ty = u32_at(pos);
        let len = if ty >> 16 != 0 {
            // Small data element: 4 bytes of data inside the 8-byte tag.
            0
        } else {
            let n = u32_at(pos + 4) as usize;
            // miCOMPRESSED (15) is not padded; every other element is padded to 8 bytes.
            if ty == 15 {
                n
            } else {
                n.div_ceil(8) * 8
            }
        };
        let end = pos + 8 + len;
        if end > bytes.len() {
            return Err(format!(
                "{what}: truncated: variable {} needs {} bytes, the file ends after {}",
                k + 1,
                end - pos,
                bytes.len() - pos
            ));
        }
        pos = end;
        k += 1;
    }
    Ok(())
}

/// Encodes a C-order `f64` array as NPY bytes (`<f8`).
pub fn npy_bytes(shape: &[usize], data: &[f64]) -> std::io::Result<Vec<u8>> {
    debug_assert_eq!(shape.iter().product::<usize>(), data.len());
    let mut buf = Vec::new();
    let shape: Vec<u64> = shape.iter().map(|&d| d as u64).collect();
    use npyz::WriterBuilder;
    let mut w = npyz::WriteOptions::<f64>::new()
        .default_dtype()
        .shape(&shape)
        .writer(&mut buf)
        .begin_nd()?;
    w.extend(data.iter().copied())?;
    w.finish()?;
    Ok(buf)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fortran_transpose_matches_index_maths() {
        // 2x3 column-major [[1,2,3],[4,5,6]] is stored 1,4,2,5,3,6.
        assert_eq!(
            fortran_to_c(&[2, 3], &[1., 4., 2., 5., 3., 6.]),
            vec![1., 2., 3., 4., 5., 6.]
        );
        // 3-D: element (i,j,k) at i + 2*(j + 2*k) in Fortran order.
        let shape = [2, 2, 3];
        let f: Vec<f64> = (0..12).map(f64::from).collect();
        let c = fortran_to_c(&shape, &f);
        for i in 0..2 {
            for j in 0..2 {
                for k in 0..3 {
                    assert_eq!(c[(i * 2 + j) * 3 + k], (i + 2 * (j + 2 * k)) as f64);
                }
            }
        }
    }

    #[test]
    fn npy_round_trip_and_truncation() {
        let b = npy_bytes(&[2, 3], &[1., 2., 3., 4., 5., 6.5]).unwrap();
        let a = read_npy_plain(&b, "x.npy").unwrap();
        assert_eq!(a.shape, vec![2, 3]);
        assert_eq!(a.data, vec![1., 2., 3., 4., 5., 6.5]);
        let e = read_npy_plain(&b[..b.len() - 3], "x.npy").unwrap_err();
        assert!(e.contains("x.npy") && e.contains("truncated"), "{e}");
        let e = read_npy_plain(&b[..20], "x.npy").unwrap_err();
        assert!(e.contains("x.npy"), "{e}");
    }
}
