//! Numeric arrays from NPY, NPZ and MATLAB `.mat` (v5/v7 and v7.3) files, and NPY writing.
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
//! * MAT: MATLAB v5/v7 files (`save`, `save -v7`, SciPy's `savemat`;
//!   compressed or not, either byte order) through our own reader,
//!   [`super::mat5`]: numeric real arrays of every class (`double`, `single`,
//!   the integers, `logical`), whatever narrower type MATLAB stored them as;
//!   char, cell, struct and object variables are skipped; sparse and complex
//!   variables are errors.
//! * MAT v7.3 (`save -v7.3`, MATLAB's format for variables over 2 GB): HDF5
//!   behind a 512-byte user block, read by the pure-Rust `hdf5-reader`. Each
//!   root dataset is a variable whose `MATLAB_class` attribute names its
//!   class; MATLAB stores the dimensions reversed, so HDF5's C order over the
//!   reversed shape is MATLAB's column-major order and the array is then
//!   transposed as a v5 one is. Numeric real classes (`double`, `single`,
//!   the integers, `logical`) are read, whatever their chunking or deflate
//!   compression; `char`, `cell`, structs (groups), `#refs#`, and empty
//!   arrays (`MATLAB_empty`) are skipped; a complex array is an error, as in
//!   v5. HDF5 keeps no save order: variables come in the order the file lists
//!   them (by name, in the files MATLAB writes).
//!
//! ## Hostile files (docs/resource-policy.md)
//!
//! Sizes written in a file are checked against the file before anything is
//! allocated: an NPY header may not claim more bytes than the file has, its
//! Python-literal text may nest brackets at most [`MAX_NPY_NESTING`] deep (the
//! parser is exponential in the depth), every integer in it must be below
//! 2^63 and the shape's product (and every partial product) at most
//! [`MAX_ELEMENTS`]; the data must then hold exactly `product x item size`
//! bytes (fewer is a truncated file, more a header that describes another
//! array: both are errors naming the byte counts). So
//! reading an NPY file allocates at most 8 bytes per element of the file
//! (elements are at least 1 byte): memory is bounded by 8x the file (16x for
//! a Fortran-order array, transposed through a copy). An NPZ member is read
//! into a buffer of at most its declared size, itself capped by
//! [`MAX_NPZ_MEMBER_BYTES`] (deflate can expand 1000-fold). A v5 MAT file
//! checks every element's size against its parent, inflates compressed
//! variables as a stream, and allocates each array once, at its exact size,
//! after its dimensions are checked: a file's variables may decode to at most
//! [`mat73_read_cap`] bytes in all ([`super::mat5`] docs). A v7.3 variable
//! may decode to at most [`mat73_read_cap`] bytes (checked by the HDF5 reader
//! before it allocates), and a file's variables to at most that in all,
//! counting the `f64` output and, for other types, the decoded values held
//! while converting: a `f64` variable is decoded into its output and
//! transposed in place ([`fortran_to_c_in_place`]), any other converted
//! straight to its C-order index. The file reads no external file or link, and a panic
//! inside the HDF5 decoder on a malformed file becomes an error naming the
//! file (the decoder is a dependency; fuzz target `signal_mat` covers it).

use std::io::{Cursor, Read};

/// Deepest bracket nesting accepted in an NPY header (a structured dtype with
/// a nested record uses 3-4 levels). The header is a Python literal whose
/// parser backtracks: 20 nested brackets took 13.7 s, 24 over 100 s.
pub const MAX_NPY_NESTING: usize = 8;

/// Most elements (shape product) an array may declare: 2^31, 16 GiB as `f64`.
/// Any larger claim is an error before the data is touched; the data must also
/// actually be in the file.
pub const MAX_ELEMENTS: u64 = 1 << 31;

/// Most bytes one NPZ member may decompress to (1 GiB).
pub const MAX_NPZ_MEMBER_BYTES: u64 = 1 << 30;

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
///
/// `data` must hold the product of `shape` elements (an internal invariant:
/// callers check it); a shortfall is an error rather than a panic.
pub fn fortran_to_c(shape: &[usize], data: &[f64]) -> Vec<f64> {
    let n = shape
        .iter()
        .try_fold(1usize, |a, &d| a.checked_mul(d))
        .filter(|&n| n <= data.len())
        .unwrap_or(0);
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

/// Checks an NPY file's preamble and header text before `npyz` sees them:
/// `npyz` allocates the header length the file claims (up to 4 GiB), parses
/// nested brackets in exponential time and multiplies the shape without
/// overflow checks. Returns nothing; errors name the file.
fn check_npy_header(bytes: &[u8], what: &str) -> Result<(), String> {
    let bad = |m: &str| Err(format!("{what}: not a readable NPY file ({m})"));
    if bytes.len() < 10 || !bytes.starts_with(b"\x93NUMPY") {
        return bad("no NPY magic, or truncated");
    }
    let (start, len) = match bytes[6] {
        1 => (10usize, usize::from(u16::from_le_bytes([bytes[8], bytes[9]]))),
        2 | 3 if bytes.len() >= 12 => (
            12,
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
        ),
        2 | 3 => return bad("truncated preamble"),
        v => return bad(&format!("unknown NPY version {v}")),
    };
    if len > bytes.len() - start {
        return Err(format!(
            "{what}: truncated: the NPY header claims {len} bytes, the file has {} after the preamble",
            bytes.len() - start
        ));
    }
    let text = &bytes[start..start + len];
    // Bracket depth and integer literals, outside quoted strings.
    let (mut depth, mut quote, mut escaped) = (0usize, None::<u8>, false);
    let mut product: u64 = 1;
    let mut i = 0;
    while i < text.len() {
        let c = text[i];
        if let Some(q) = quote {
            if escaped {
                escaped = false;
            } else if c == b'\\' {
                escaped = true;
            } else if c == q {
                quote = None;
            }
            i += 1;
            continue;
        }
        match c {
            b'\'' | b'"' => quote = Some(c),
            b'(' | b'[' | b'{' => {
                depth += 1;
                if depth > MAX_NPY_NESTING {
                    return Err(format!(
                        "{what}: NPY header nests brackets deeper than {MAX_NPY_NESTING} levels"
                    ));
                }
            }
            b')' | b']' | b'}' => depth = depth.saturating_sub(1),
            b'0'..=b'9' => {
                // A number literal runs over letters, digits and `_` (0x1F, 1_000).
                let s = i;
                while i < text.len() && (text[i].is_ascii_alphanumeric() || text[i] == b'_') {
                    i += 1;
                }
                let tok: String = String::from_utf8_lossy(&text[s..i]).replace('_', "");
                let v = match tok.get(..2) {
                    Some("0x" | "0X") => u64::from_str_radix(&tok[2..], 16),
                    Some("0o" | "0O") => u64::from_str_radix(&tok[2..], 8),
                    Some("0b" | "0B") => u64::from_str_radix(&tok[2..], 2),
                    _ => tok.parse::<u64>(),
                }
                .map_err(|_| format!("{what}: NPY header holds `{tok}`, not a size"))?;
                if v != 0 {
                    product = product.saturating_mul(v);
                }
                if v >= 1 << 63 || product > MAX_ELEMENTS {
                    return Err(format!(
                        "{what}: the NPY header declares more than {MAX_ELEMENTS} elements (the cap)"
                    ));
                }
                continue;
            }
            _ => {}
        }
        i += 1;
    }
    Ok(())
}

/// Reads an NPY file's bytes; `what` names the file for errors.
pub fn read_npy(bytes: &[u8], what: &str) -> Result<NpyContent, String> {
    check_npy_header(bytes, what)?;
    let mut r = bytes;
    let header = npyz::NpyHeader::from_reader(&mut r)
        .map_err(|e| format!("{what}: not a readable NPY file ({e}); truncated or not NumPy's format?"))?;
    let npy = npyz::NpyFile::with_header(header, r);
    // Dimensions fit: `check_npy_header` bounded every integer of the header.
    let shape: Vec<usize> = npy
        .shape()
        .iter()
        .map(|&d| usize::try_from(d).map_err(|_| format!("{what}: dimension {d} is too large")))
        .collect::<Result<_, _>>()?;
    let fortran = npy.order() == npyz::Order::Fortran;
    let n: usize = shape
        .iter()
        .try_fold(1usize, |a, &d| a.checked_mul(d))
        .filter(|&n| n as u64 <= MAX_ELEMENTS)
        .ok_or_else(|| format!("{what}: shape {shape:?} has more than {MAX_ELEMENTS} elements (the cap)"))?;
    let data = r;
    match npy.dtype() {
        npyz::DType::Plain(ts) => {
            if !supported(&ts) {
                return Err(format!(
                    "{what}: dtype `{ts}` is not supported (use bool, integers, float32 or float64)"
                ));
            }
            let size = ts.size_field() as usize;
            // n <= 2^31 and size <= 8: no overflow.
            let need = n * size;
            if data.len() < need {
                return Err(format!(
                    "{what}: truncated: shape {shape:?} needs {need} bytes of data, the file has {}",
                    data.len()
                ));
            }
            check_no_trailing(what, data.len(), need, &format!("shape {shape:?}"))?;
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
                    // (field count is bounded by the header, itself by the file)
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
            let need = n.saturating_mul(rec);
            if data.len() < need {
                return Err(format!(
                    "{what}: truncated: {n} records of {rec} bytes need {need} bytes, the file has {}",
                    data.len()
                ));
            }
            check_no_trailing(what, data.len(), need, &format!("{n} records of {rec} bytes"))?;
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

/// An error when an NPY file's data (`have` bytes after the header) runs
/// past the `need` bytes its header declares (`declared` says how): the
/// header then describes another array than the one written (a shape edited
/// by hand, two arrays appended), and the extra bytes would be dropped
/// without a word.
fn check_no_trailing(what: &str, have: usize, need: usize, declared: &str) -> Result<(), String> {
    if have > need {
        return Err(format!(
            "{what}: {} bytes after the data: the header declares {declared}, {need} bytes of \
             data, but the file holds {have} (a wrong shape in the header, or two arrays in one file?)",
            have - need
        ));
    }
    Ok(())
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
        // The declared size may lie: read at most it (capped), and one byte more
        // to notice a member longer than declared. Growing to the exact size
        // avoids `read_to_end`'s doubling (a 1 GiB array took ~7 GiB to read).
        let declared = f.size();
        if declared > MAX_NPZ_MEMBER_BYTES {
            return Err(format!(
                "{what}: array `{array}` is {declared} bytes uncompressed, over the cap of {MAX_NPZ_MEMBER_BYTES}"
            ));
        }
        let mut buf = Vec::with_capacity(declared as usize);
        (&mut f)
            .take(declared + 1)
            .read_to_end(&mut buf)
            .map_err(|e| format!("{what}: cannot read array `{array}` ({e}); truncated?"))?;
        if buf.len() as u64 != declared {
            return Err(format!(
                "{what}: array `{array}` holds {} bytes but the archive declares {declared}",
                buf.len()
            ));
        }
        let content = read_npy(&buf, &format!("{what}, array `{array}`"))?;
        out.push((array, content));
    }
    if out.is_empty() {
        return Err(format!("{what}: the archive holds no .npy array"));
    }
    Ok(out)
}

/// Reads every numeric variable of a MATLAB `.mat` file, in file order: v5/v7
/// by [`super::mat5`], v7.3 (HDF5) by `hdf5-reader` (module docs).
pub fn read_mat(bytes: &[u8], what: &str) -> Result<Vec<(String, NdArray)>, String> {
    if bytes.starts_with(b"MATLAB 7.3") {
        return read_mat73(bytes, what);
    }
    if bytes.len() < 128 || !bytes.starts_with(b"MATLAB") {
        return Err(format!(
            "{what}: not a MATLAB .mat file (truncated, or no `MATLAB` header)"
        ));
    }
    super::mat5::read_mat5(bytes, what)
}

/// Reads every numeric variable of a MATLAB v7.3 (HDF5) `.mat` file (module
/// docs), in the order the file lists them.
fn read_mat73(bytes: &[u8], what: &str) -> Result<Vec<(String, NdArray)>, String> {
    let bad = |e: hdf5_reader::error::Error| {
        format!("{what}: not a readable MAT v7.3 (HDF5) file ({e}); truncated?")
    };
    // The decoder is a dependency: a panic it raises on a malformed file is
    // this file's error, not the run's end.
    let read = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        let cap = mat73_read_cap(bytes.len());
        let opts = hdf5_reader::OpenOptions::default()
            .with_max_read_bytes(cap)
            .with_max_chunk_bytes(cap.min(MAX_NPZ_MEMBER_BYTES as usize));
        let file = hdf5_reader::Hdf5File::from_bytes_with_options(bytes, opts).map_err(bad)?;
        // The superblock's end of file is absolute (libhdf5 checks it the
        // same way): a file cut short may still decode the objects before
        // the cut, and would lose the rest without a word.
        let eof = file.superblock().eof_address;
        if eof > bytes.len() as u64 {
            return Err(format!(
                "{what}: truncated: the file is {} bytes, its HDF5 superblock says {eof}",
                bytes.len()
            ));
        }
        let (_, datasets) = file.root_group().and_then(|g| g.members()).map_err(bad)?;
        let mut out = Vec::new();
        // The file's decoded output in all, as for v5 (io::mat5).
        let mut left = cap as u64;
        for d in datasets {
            let name = d.name().to_string();
            let read = mat73_variable(&d, &mut left, bytes.len());
            if let Some(array) = read.map_err(|e| format!("{what}: variable `{name}`: {e}"))? {
                out.push((name, array));
            }
        }
        Ok(out)
    }));
    read.unwrap_or_else(|_| Err(format!("{what}: not a readable MAT v7.3 (HDF5) file (malformed)")))
}

/// Most bytes one v7.3 variable of a `file_len`-byte file may decode to: 8x
/// the file (MATLAB deflates its chunks; real signals shrink by far less),
/// at least [`MAX_NPZ_MEMBER_BYTES`], at most [`MAX_ELEMENTS`] doubles, so
/// a small file cannot claim gigabytes while a large uncompressed recording
/// (v7.3 is what MATLAB needs for variables over 2 GB) still reads.
pub fn mat73_read_cap(file_len: usize) -> usize {
    let floor = MAX_NPZ_MEMBER_BYTES as usize;
    let ceil = usize::try_from(MAX_ELEMENTS * 8).unwrap_or(usize::MAX);
    file_len.saturating_mul(8).clamp(floor, ceil)
}

/// One v7.3 variable as a C-order array of its MATLAB shape, or `None` for
/// a variable that holds no numeric data (module docs).
fn mat73_variable(
    d: &hdf5_reader::Dataset,
    left: &mut u64,
    file_len: usize,
) -> Result<Option<NdArray>, String> {
    use hdf5_reader::Datatype as T;
    if d.name().starts_with('#') {
        return Ok(None);
    }
    let attr = |key: &str| d.attribute(key).ok();
    let class = attr("MATLAB_class").and_then(|a| a.read_string().ok());
    let numeric = [
        "double", "single", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64",
        "logical",
    ];
    match class.as_deref() {
        // No class: a plain HDF5 dataset (from h5py, say) is read by its type.
        None => {}
        Some(c) if numeric.contains(&c) => {}
        Some(_) => return Ok(None),
    }
    let empty = attr("MATLAB_empty").and_then(|a| a.read_as_f64().ok());
    if empty.is_some_and(|e| e != 0.0) {
        return Ok(None);
    }
    // MATLAB's shape is HDF5's reversed; a scalar or 1-D dataset (written by
    // other tools) is a column, as MATLAB would load it.
    let mut shape: Vec<usize> = d.shape().iter().rev().map(|&n| n as usize).collect();
    match shape.len() {
        0 => shape = vec![1, 1],
        1 => shape.push(1),
        _ => {}
    }
    let n = d
        .shape()
        .iter()
        .try_fold(1u64, |p, &k| p.checked_mul(k).filter(|&p| p <= MAX_ELEMENTS));
    let Some(n) = n else {
        return Err(format!(
            "shape {shape:?} makes more than {MAX_ELEMENTS} elements (the cap)"
        ));
    };
    // The decoded values (`item` bytes each) and the `f64` output are both
    // held while converting (a `f64` dataset is decoded into the output and
    // transposed in place): both count against what the file may decode to.
    let item = d.raw_element_size().unwrap_or(8) as u64;
    let is_f64 = matches!(d.dtype(), T::FloatingPoint { size: 8, .. });
    let held = n * 8 + if is_f64 { 0 } else { n * item };
    if held > *left {
        return Err(format!(
            "shape {shape:?} makes {n} elements ({held} bytes decoded and as f64), past what this \
             {file_len}-byte file may decode to ({} bytes in all, {} left: 8x the file, at least 1 GiB)",
            mat73_read_cap(file_len),
            *left
        ));
    }
    let n = n as usize;
    fn alloc<V: Clone + Default>(n: usize) -> Result<Vec<V>, String> {
        let mut v = Vec::new();
        v.try_reserve_exact(n)
            .map_err(|e| format!("cannot allocate {n} elements ({e})"))?;
        v.resize(n, V::default());
        Ok(v)
    }
    // Every element of `d` as `V`, written straight to its C-order index as
    // `f64` (exact up to 2^53).
    fn widen<V: hdf5_reader::H5Type + Copy + Default>(
        d: &hdf5_reader::Dataset,
        shape: &[usize],
        n: usize,
        f: fn(V) -> f64,
    ) -> Result<Vec<f64>, String> {
        let mut raw = alloc::<V>(n)?;
        d.read_into(&mut raw).map_err(|e| e.to_string())?;
        let mut w = super::mat5::COrder::new(shape, alloc(n)?);
        raw.iter().for_each(|&v| w.push(f(v)));
        Ok(w.into_data())
    }
    let data = match d.dtype() {
        T::FloatingPoint { size: 8, .. } => {
            let mut v = alloc::<f64>(n)?;
            d.read_into(&mut v).map_err(|e| e.to_string())?;
            fortran_to_c_in_place(&shape, &mut v);
            v
        }
        T::FloatingPoint { size: 4, .. } => widen::<f32>(d, &shape, n, f64::from)?,
        T::FixedPoint { size, signed, .. } => match (size, signed) {
            (1, true) => widen::<i8>(d, &shape, n, f64::from)?,
            (1, false) => widen::<u8>(d, &shape, n, f64::from)?,
            (2, true) => widen::<i16>(d, &shape, n, f64::from)?,
            (2, false) => widen::<u16>(d, &shape, n, f64::from)?,
            (4, true) => widen::<i32>(d, &shape, n, f64::from)?,
            (4, false) => widen::<u32>(d, &shape, n, f64::from)?,
            (8, true) => widen::<i64>(d, &shape, n, |v| v as f64)?,
            (8, false) => widen::<u64>(d, &shape, n, |v| v as f64)?,
            _ => return Err(format!("{size}-byte integers are not a MATLAB class")),
        },
        T::Compound { fields, .. } if fields.iter().any(|f| f.name == "imag") => {
            return Err("is complex; only real data is supported".into())
        }
        other if class.is_some() => return Err(format!("holds {other:?}, not numbers")),
        // An unclassed dataset of another type (strings, say) is no variable.
        _ => return Ok(None),
    };
    *left -= n as u64 * 8;
    Ok(Some(NdArray { shape, data }))
}

/// Transposes a column-major buffer of `shape` into C order in place, by
/// following the permutation's cycles (a bit per element marks those
/// placed). `data` holds the product of `shape` elements (else unchanged).
pub fn fortran_to_c_in_place(shape: &[usize], data: &mut [f64]) {
    let n = data.len();
    if shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d)) != Some(n)
        || shape.iter().filter(|&&d| d > 1).count() < 2
    {
        // At most one dimension over 1: both orders are the same.
        return;
    }
    // C-order stride of each dimension.
    let mut stride = vec![1usize; shape.len()];
    for d in (0..shape.len() - 1).rev() {
        stride[d] = stride[d + 1] * shape[d + 1];
    }
    let c_of = |mut f: usize| {
        let mut c = 0;
        for (d, &k) in shape.iter().enumerate() {
            c += (f % k) * stride[d];
            f /= k;
        }
        c
    };
    let mut done = vec![0u64; n.div_ceil(64)];
    for start in 0..n {
        if done[start / 64] >> (start % 64) & 1 == 1 {
            continue;
        }
        // Move the value at `cur` (held in `carry`) to its C index, taking
        // the value found there along, until the cycle closes.
        let mut cur = start;
        let mut carry = data[start];
        loop {
            let to = c_of(cur);
            std::mem::swap(&mut carry, &mut data[to]);
            done[to / 64] |= 1 << (to % 64);
            cur = to;
            if to == start {
                break;
            }
        }
    }
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
    fn a_v73_variable_may_decode_to_eight_times_its_file_within_bounds() {
        let gib = 1usize << 30;
        assert_eq!(mat73_read_cap(10_856), gib);
        assert_eq!(mat73_read_cap(gib), 8 * gib);
        assert_eq!(mat73_read_cap(usize::MAX), 16 * gib);
    }

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

    /// A v7.3 variable is refused from its shape, before it is decoded,
    /// when it would pass what is left of the file's budget (the fuzz
    /// target's out-of-memory file: 16775449 x 4 x 2 doubles, 1 GiB).
    #[test]
    fn a_v73_file_may_decode_to_its_budget_in_all() {
        let b = include_bytes!("../../tests/data/fuzz_oom_v73.mat");
        let file = hdf5_reader::Hdf5File::from_bytes(b).unwrap();
        let (_, datasets) = file.root_group().and_then(|g| g.members()).unwrap();
        let d = datasets.iter().find(|d| d.name() == "data").unwrap();
        // 16775449 x 4 x 2 x 8 = 1073628736 bytes: 512 MiB left refuses it.
        let mut left = 1 << 29;
        let e = match mat73_variable(d, &mut left, b.len()) {
            Ok(a) => panic!("read {:?}", a.map(|a| a.shape)),
            Err(e) => e,
        };
        assert!(
            e.contains("[16775449, 4, 2]")
                && e.contains("past what this 10856-byte file")
                && e.contains("536870912 left"),
            "{e}"
        );
        assert_eq!(left, 1 << 29);
    }

    /// The in-place transposition equals the copying one, for shapes of 1
    /// to 4 dimensions (some of length 1 or 0).
    #[test]
    fn in_place_transpose_matches_the_copy() {
        for shape in [
            vec![7],
            vec![1, 5],
            vec![5, 1],
            vec![3, 4],
            vec![4, 3, 2],
            vec![2, 1, 3],
            vec![3, 2, 2, 5],
            vec![0, 4],
            vec![64, 3],
        ] {
            let n: usize = shape.iter().product();
            let f: Vec<f64> = (0..n).map(|v| v as f64).collect();
            let mut g = f.clone();
            fortran_to_c_in_place(&shape, &mut g);
            assert_eq!(g, fortran_to_c(&shape, &f), "{shape:?}");
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

    /// Bytes after the data the header declares are refused, naming the
    /// file and both counts, for plain and structured arrays.
    #[test]
    fn npy_bytes_after_the_data_are_an_error() {
        let mut b = npy_bytes(&[2, 3], &[1., 2., 3., 4., 5., 6.5]).unwrap();
        b.extend_from_slice(&[0u8; 8]);
        let e = read_npy_plain(&b, "x.npy").unwrap_err();
        assert!(
            e.contains("x.npy")
                && e.contains("8 bytes after the data")
                && e.contains("48 bytes")
                && e.contains("56"),
            "{e}"
        );
        // A structured array (x, y as u2): 2 records of 4 bytes, 3 bytes extra.
        let header = "{'descr': [('x', '<u2'), ('y', '<u2')], 'fortran_order': False, 'shape': (2,), }";
        let mut h = header.to_string();
        while !(10 + h.len() + 1).is_multiple_of(64) {
            h.push(' ');
        }
        h.push('\n');
        let mut r = b"\x93NUMPY\x01\x00".to_vec();
        r.extend_from_slice(&(h.len() as u16).to_le_bytes());
        r.extend_from_slice(h.as_bytes());
        r.extend_from_slice(&[1, 0, 2, 0, 3, 0, 4, 0]);
        assert!(matches!(read_npy(&r, "ev.npy"), Ok(NpyContent::Record(_))));
        r.extend_from_slice(&[9, 9, 9]);
        let e = read_npy(&r, "ev.npy").unwrap_err();
        assert!(
            e.contains("ev.npy") && e.contains("3 bytes after the data"),
            "{e}"
        );
    }
}
