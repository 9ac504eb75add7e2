//! Reads the numeric variables of a MATLAB v5/v7 ("level 5") `.mat` file:
//! the format of `save`, `save -v6` and `save -v7` (and SciPy's `savemat`),
//! compressed or not. v7.3 files are HDF5 and read by [`super::arrays`].
//!
//! ## Format (MathWorks, "MAT-File Format")
//!
//! A 128-byte header (116 bytes of text, an 8-byte subsystem offset, a 2-byte
//! version, a 2-byte endian indicator: `IM` for a little-endian file, `MI`
//! for a big-endian one), then data elements to the end of the file. Each
//! element is an 8-byte tag (`u32` type, `u32` byte count, in the file's byte
//! order) and its data padded to a multiple of 8 bytes; or, when the upper 16
//! bits of the tag's first `u32` are non-zero, the small form: byte count =
//! those 16 bits (at most 4), type = the lower 16, the data in the tag's
//! second half. A `miCOMPRESSED` (15) element is a zlib stream, not padded,
//! that inflates to one element (normally a `miMATRIX`).
//!
//! A variable is a `miMATRIX` (14) element (byte count 0: an empty slot,
//! skipped) holding, in order: array flags (`miUINT32`, 8 bytes; the class is
//! the low byte of the first `u32`, bit `0x0800` marks complex data, `0x0200`
//! logical), dimensions (`miINT32`, at least 2), the name (`miINT8`), the real
//! part and, if complex, an imaginary part. Classes: cell 1, struct 2, object
//! 3, char 4, sparse 5, double 6, single 7, int8 8, uint8 9, int16 10, uint16
//! 11, int32 12, uint32 13, int64 14, uint64 15 (logical is uint8 with the
//! flag). The real part's storage type may be narrower than the class
//! (MATLAB stores a double array of small integers as `miUINT8`, say): values
//! are converted by the storage type (`miINT8` 1, `miUINT8` 2, `miINT16` 3,
//! `miUINT16` 4, `miINT32` 5, `miUINT32` 6, `miSINGLE` 7, `miDOUBLE` 9,
//! `miINT64` 12, `miUINT64` 13) to `f64` (exact, but for 64-bit integers past
//! 2^53, which round), and must hold exactly the product of the dimensions.
//!
//! ## What is returned
//!
//! Every variable of a numeric real class (6-15, logical included) as
//! `(name, array)` in file order. MATLAB stores arrays column-major; each
//! element is written straight to its C-order index while decoding (no
//! second copy), so `shape = dims` and MATLAB's `x(i, j, k)` is element
//! `[i-1, j-1, k-1]` ([`super::arrays`] module docs). Char, cell, struct and
//! object variables are skipped (by byte count, unread: their contents are
//! not walked), as are top-level elements that are not variables. A sparse
//! variable is an error asking for `full()`, a complex one an error (only
//! real data is supported).
//!
//! ## Errors
//!
//! Every error names the file and, where there is one, the variable: by name
//! once its name has been read, else by its 1-based position among the
//! file's top-level elements. A file that ends inside an element (or a
//! compressed variable whose stream ends before its declared size) is
//! "truncated": a variable cut short is an error, never dropped. (A file cut
//! exactly between two elements is a valid file with fewer variables: the
//! format has no count to check it against.)
//!
//! ## Hostile files (docs/resource-policy.md)
//!
//! Every size read from the file is checked arithmetic, and every element's
//! byte count must fit in its parent (the file, or the enclosing matrix's
//! byte count) before it is read. A compressed variable is inflated as a
//! stream (a `ZlibDecoder` over its bytes, read through `Read::take` of the
//! inner element's byte count), never into a buffer of its own; a skipped
//! compressed variable is not inflated at all. The output array is allocated
//! (exact size, `try_reserve_exact`) only after its dimensions are read and
//! checked: at most [`MAX_ELEMENTS`] elements, and the file's decoded output
//! in all (the sum over its variables of elements x 8 bytes) at most
//! [`mat73_read_cap`] of the file's length (8x the file, at least 1 GiB, at
//! most 16 GiB), so a 10 KB file cannot ask for more than 1 GiB however it
//! is crafted; the real part's byte count must match the dimensions and fit
//! in its matrix before anything is allocated (in an uncompressed file, the
//! data are thus in the file). Memory is the output plus fixed buffers
//! (8 KiB of data, a name of at most [`MAX_NAME_BYTES`], at most
//! [`MAX_DIMS`] dimensions).

use std::io::{ErrorKind, Read};

use super::arrays::{mat73_read_cap, NdArray, MAX_ELEMENTS};

const MI_INT8: u32 = 1;
const MI_UINT8: u32 = 2;
const MI_INT32: u32 = 5;
const MI_UINT32: u32 = 6;
const MI_MATRIX: u32 = 14;
const MI_COMPRESSED: u32 = 15;
const MI_UTF8: u32 = 16;

/// Most dimensions a variable may have (MATLAB drops trailing singleton
/// dimensions; real recordings have 2 or 3).
pub const MAX_DIMS: usize = 64;

/// Longest variable name read, in bytes (MATLAB's `namelengthmax` is 63).
pub const MAX_NAME_BYTES: usize = 1024;

/// Bytes of variable data decoded per read.
const CHUNK: usize = 8192;

/// Reads every numeric real variable of a MAT v5 file (module docs). The
/// caller has checked that `bytes` holds at least the 128-byte header.
pub fn read_mat5(bytes: &[u8], what: &str) -> Result<Vec<(String, NdArray)>, String> {
    let big = match bytes.get(126..128) {
        Some(b"IM") => false,
        Some(b"MI") => true,
        _ => return Err(format!("{what}: not a MAT v5 file (bad endian indicator)")),
    };
    let cap = mat73_read_cap(bytes.len()) as u64;
    let mut budget = Budget {
        left: cap,
        cap,
        file_len: bytes.len(),
    };
    let mut out = Vec::new();
    let mut pos = 128usize;
    let mut k = 0usize;
    while pos < bytes.len() {
        let rest = bytes.len() - pos;
        if rest < 8 {
            return Err(format!(
                "{what}: truncated: {rest} stray bytes after variable {k}"
            ));
        }
        k += 1;
        let ty = word(big, &bytes[pos..pos + 4]);
        if ty >> 16 != 0 {
            // A small element at the top level: no variable.
            pos += 8;
            continue;
        }
        let n = word(big, &bytes[pos + 4..pos + 8]) as usize;
        // miCOMPRESSED is not padded; every other element is padded to 8 bytes.
        let len = if ty == MI_COMPRESSED { n } else { pad8(n) };
        if len > rest - 8 {
            return Err(format!(
                "{what}: truncated: variable {k} needs {} bytes, the file ends after {rest}",
                len as u64 + 8
            ));
        }
        let body = &bytes[pos + 8..pos + 8 + n];
        let var = Var { what, k, name: None };
        let read = match ty {
            MI_MATRIX if n > 0 => {
                let mut src = Src {
                    r: body,
                    left: n as u64,
                    big,
                };
                matrix(&mut src, var, &mut budget)?
            }
            MI_COMPRESSED => compressed(body, big, var, &mut budget)?,
            _ => None,
        };
        out.extend(read);
        pos += 8 + len;
    }
    Ok(out)
}

/// What the file may still decode to (module docs).
struct Budget {
    left: u64,
    cap: u64,
    file_len: usize,
}

/// The variable being read, for error messages.
struct Var<'a> {
    what: &'a str,
    k: usize,
    name: Option<String>,
}

impl Var<'_> {
    /// `"{file}: variable {id}: {msg}"`.
    fn err(&self, msg: impl std::fmt::Display) -> String {
        format!("{}: variable {}: {msg}", self.what, self.id())
    }

    fn id(&self) -> String {
        match &self.name {
            Some(n) => format!("`{n}`"),
            None => self.k.to_string(),
        }
    }
}

fn word(big: bool, b: &[u8]) -> u32 {
    let a = [b[0], b[1], b[2], b[3]];
    if big {
        u32::from_be_bytes(a)
    } else {
        u32::from_le_bytes(a)
    }
}

/// `n` rounded up to a multiple of 8 (`n` < 2^32, so no overflow on 64 bits).
fn pad8(n: usize) -> usize {
    n.div_ceil(8).saturating_mul(8)
}

/// A data element's tag.
struct Tag {
    ty: u32,
    n: u32,
    /// The data of a small element (its first `n` bytes).
    small: Option<[u8; 4]>,
}

/// The bytes of one matrix: a slice of the file, or an inflating stream;
/// `left` is what its byte count leaves to read.
struct Src<R> {
    r: R,
    left: u64,
    big: bool,
}

impl<R: Read> Src<R> {
    /// Fills `buf` from the matrix; `part` names what is read, for errors.
    fn bytes(&mut self, buf: &mut [u8], part: &str) -> Result<(), String> {
        if buf.len() as u64 > self.left {
            return Err(format!(
                "corrupt: its {part} needs {} bytes, its matrix has {} left",
                buf.len(),
                self.left
            ));
        }
        self.r.read_exact(buf).map_err(|e| {
            if e.kind() == ErrorKind::UnexpectedEof {
                format!("truncated: its compressed data end inside its {part}")
            } else {
                format!("its compressed data do not inflate ({e}); truncated or corrupt?")
            }
        })?;
        self.left -= buf.len() as u64;
        Ok(())
    }

    fn tag(&mut self, part: &str) -> Result<Tag, String> {
        let mut b = [0u8; 8];
        self.bytes(&mut b, &format!("{part} tag"))?;
        let first = word(self.big, &b[..4]);
        if first >> 16 != 0 {
            let n = first >> 16;
            if n > 4 {
                return Err(format!(
                    "corrupt: its {part} is a small element of {n} bytes (at most 4)"
                ));
            }
            return Ok(Tag {
                ty: first & 0xffff,
                n,
                small: Some([b[4], b[5], b[6], b[7]]),
            });
        }
        Ok(Tag {
            ty: first,
            n: word(self.big, &b[4..]),
            small: None,
        })
    }

    /// The data of a short element (at most `max` bytes) and its padding.
    fn payload(&mut self, t: &Tag, max: usize, part: &str) -> Result<Vec<u8>, String> {
        let n = t.n as usize;
        if n > max {
            return Err(format!("corrupt: its {part} is {n} bytes long (at most {max})"));
        }
        if let Some(s) = t.small {
            return Ok(s[..n].to_vec());
        }
        let mut v = vec![0u8; pad8(n)];
        self.bytes(&mut v, part)?;
        v.truncate(n);
        Ok(v)
    }
}

/// One compressed top-level element: the variable it holds, if any.
fn compressed(
    body: &[u8],
    big: bool,
    var: Var,
    budget: &mut Budget,
) -> Result<Option<(String, NdArray)>, String> {
    let mut z = flate2::read::ZlibDecoder::new(body);
    let mut head = Src {
        r: &mut z,
        left: 8,
        big,
    };
    let t = head.tag("compressed element").map_err(|e| var.err(e))?;
    if t.small.is_some() || t.ty != MI_MATRIX || t.n == 0 {
        return Ok(None);
    }
    let n = u64::from(t.n);
    let mut src = Src {
        r: (&mut z).take(n),
        left: n,
        big,
    };
    matrix(&mut src, var, budget)
}

/// One miMATRIX's contents (after its tag): the variable, or `None` for a
/// class that is skipped.
fn matrix<R: Read>(
    src: &mut Src<R>,
    mut var: Var,
    budget: &mut Budget,
) -> Result<Option<(String, NdArray)>, String> {
    let big = src.big;
    // Array flags.
    let t = src.tag("array flags").map_err(|e| var.err(e))?;
    if t.small.is_some() || t.ty != MI_UINT32 || t.n != 8 {
        return Err(var.err(format!(
            "corrupt: its array flags are not an 8-byte miUINT32 element (type {}, {} bytes)",
            t.ty, t.n
        )));
    }
    let f = src.payload(&t, 8, "array flags").map_err(|e| var.err(e))?;
    let flags = word(big, &f[..4]);
    let class = flags & 0xff;
    let complex = flags & 0x0800 != 0;
    if (1..=4).contains(&class) {
        // Cell, struct, object, char: skipped.
        return Ok(None);
    }
    // Dimensions.
    let t = src.tag("dimensions").map_err(|e| var.err(e))?;
    if t.ty != MI_INT32 || t.n < 8 || !t.n.is_multiple_of(4) {
        return Err(var.err(format!(
            "corrupt: its dimensions are not a miINT32 element of at least 2 (type {}, {} bytes)",
            t.ty, t.n
        )));
    }
    let d = src
        .payload(&t, 4 * MAX_DIMS, "dimensions")
        .map_err(|e| var.err(e))?;
    let dims: Vec<i64> = d
        .chunks_exact(4)
        .map(|c| i64::from(word(big, c) as i32))
        .collect();
    // Name.
    let t = src.tag("name").map_err(|e| var.err(e))?;
    if ![MI_INT8, MI_UINT8, MI_UTF8].contains(&t.ty) {
        return Err(var.err(format!("corrupt: its name is of data type {}, not text", t.ty)));
    }
    let name = src.payload(&t, MAX_NAME_BYTES, "name").map_err(|e| var.err(e))?;
    var.name = Some(String::from_utf8_lossy(&name).into_owned());
    let name = var.id();
    match class {
        5 => {
            return Err(format!(
                "{}: variable {name} is sparse; only full arrays are read (in MATLAB, `x = full(x)` \
                 before saving it)",
                var.what
            ))
        }
        6..=15 => {}
        c => return Err(var.err(format!("corrupt: array class {c} is no MATLAB class"))),
    }
    if complex {
        return Err(format!(
            "{}: variable {name} is complex; only real data is supported",
            var.what
        ));
    }
    if let Some(d) = dims.iter().find(|&&d| d < 0) {
        return Err(var.err(format!("corrupt: dimensions {dims:?} include {d}")));
    }
    let mut count = 1u64;
    for &d in &dims {
        // Each factor < 2^31 and the product <= 2^31 before it: no overflow.
        count = count.saturating_mul(d as u64);
        if count > MAX_ELEMENTS {
            return Err(var.err(format!(
                "dimensions {dims:?} make more than {MAX_ELEMENTS} elements (the cap)"
            )));
        }
    }
    let want = count * 8;
    if want > budget.left {
        return Err(var.err(format!(
            "dimensions {dims:?} make {count} elements ({want} bytes as f64), past what this {}-byte file \
             may decode to ({} bytes in all, {} left: 8x the file, at least 1 GiB)",
            budget.file_len, budget.cap, budget.left
        )));
    }
    let shape: Vec<usize> = dims.iter().map(|&d| d as usize).collect();
    if count == 0 && src.left == 0 {
        // An empty array written without a real part.
        return Ok(Some((
            var.name.unwrap_or_default(),
            NdArray {
                shape,
                data: Vec::new(),
            },
        )));
    }
    // Real part.
    let t = src.tag("real part").map_err(|e| var.err(e))?;
    let Some(size) = storage_size(t.ty) else {
        return Err(var.err(format!(
            "corrupt: its real part is of data type {}, not numbers",
            t.ty
        )));
    };
    let n = u64::from(t.n);
    if !n.is_multiple_of(size as u64) || n / size as u64 != count {
        return Err(var.err(format!(
            "corrupt: its real part holds {n} bytes of {size}-byte values, its dimensions {dims:?} \
             make {count} elements"
        )));
    }
    if t.small.is_none() && n > src.left {
        return Err(var.err(format!(
            "corrupt: its real part needs {n} bytes, its matrix has {} left",
            src.left
        )));
    }
    let count = count as usize;
    let mut data = Vec::new();
    data.try_reserve_exact(count)
        .map_err(|e| var.err(format!("cannot allocate {count} elements ({e})")))?;
    data.resize(count, 0.0);
    let mut w = COrder::new(&shape, data);
    if let Some(s) = t.small {
        convert(t.ty, big, &s[..t.n as usize], &mut w);
    } else {
        let mut buf = [0u8; CHUNK];
        let mut rest = t.n as usize;
        while rest > 0 {
            let m = rest.min(CHUNK);
            src.bytes(&mut buf[..m], "real part").map_err(|e| var.err(e))?;
            convert(t.ty, big, &buf[..m], &mut w);
            rest -= m;
        }
    }
    budget.left -= want;
    let name = var.name.unwrap_or_default();
    Ok(Some((name, NdArray { shape, data: w.data })))
}

/// Bytes per value of a numeric storage type.
fn storage_size(ty: u32) -> Option<usize> {
    match ty {
        1 | 2 => Some(1),
        3 | 4 => Some(2),
        5..=7 => Some(4),
        9 | 12 | 13 => Some(8),
        _ => None,
    }
}

/// Converts whole values of storage type `ty` (checked by [`storage_size`];
/// `chunk` holds a multiple of its size) into `w`.
fn convert(ty: u32, big: bool, chunk: &[u8], w: &mut COrder) {
    macro_rules! each {
        ($t:ty, $n:expr) => {
            for c in chunk.chunks_exact($n) {
                let mut a = [0u8; $n];
                a.copy_from_slice(c);
                let v = if big {
                    <$t>::from_be_bytes(a)
                } else {
                    <$t>::from_le_bytes(a)
                };
                w.push(v as f64);
            }
        };
    }
    match ty {
        1 => each!(i8, 1),
        2 => each!(u8, 1),
        3 => each!(i16, 2),
        4 => each!(u16, 2),
        5 => each!(i32, 4),
        6 => each!(u32, 4),
        7 => each!(f32, 4),
        9 => each!(f64, 8),
        12 => each!(i64, 8),
        13 => each!(u64, 8),
        _ => {}
    }
}

/// Writes values given in column-major order to their C-order index (also
/// used by the v7.3 reader in [`super::arrays`]).
pub(super) struct COrder {
    data: Vec<f64>,
    dims: Vec<usize>,
    /// C-order stride of each dimension.
    stride: Vec<usize>,
    /// The column-major index of the next value, first dimension fastest.
    idx: Vec<usize>,
    /// Its C-order offset.
    off: usize,
}

impl COrder {
    /// `data` holds the product of `dims` elements.
    pub(super) fn new(dims: &[usize], data: Vec<f64>) -> Self {
        let mut stride = vec![1usize; dims.len()];
        for d in (0..dims.len().saturating_sub(1)).rev() {
            stride[d] = stride[d + 1].saturating_mul(dims[d + 1]);
        }
        COrder {
            data,
            dims: dims.to_vec(),
            stride,
            idx: vec![0; dims.len()],
            off: 0,
        }
    }

    pub(super) fn push(&mut self, v: f64) {
        if let Some(s) = self.data.get_mut(self.off) {
            *s = v;
        }
        for d in 0..self.dims.len() {
            self.idx[d] += 1;
            self.off += self.stride[d];
            if self.idx[d] < self.dims[d] {
                return;
            }
            self.off -= self.stride[d] * self.dims[d];
            self.idx[d] = 0;
        }
    }

    pub(super) fn into_data(self) -> Vec<f64> {
        self.data
    }
}

#[cfg(test)]
mod tests {
    use super::super::arrays::read_mat;
    use super::*;
    use proptest::prelude::*;

    /// One element in `big` or little byte order: tag, data, padding.
    fn element(big: bool, ty: u32, payload: &[u8]) -> Vec<u8> {
        let u = |x: u32| if big { x.to_be_bytes() } else { x.to_le_bytes() };
        let mut b = u(ty).to_vec();
        b.extend(u(payload.len() as u32));
        b.extend(payload);
        b.resize(pad8(b.len()), 0);
        b
    }

    /// A small element: at most 4 bytes of data inside the tag.
    fn small(big: bool, ty: u32, payload: &[u8]) -> Vec<u8> {
        assert!(payload.len() <= 4);
        let first = ((payload.len() as u32) << 16) | ty;
        let mut b = if big {
            first.to_be_bytes()
        } else {
            first.to_le_bytes()
        }
        .to_vec();
        b.extend(payload);
        b.resize(8, 0);
        b
    }

    /// The contents of a miMATRIX element: flags, dimensions, name (small
    /// when it fits), and `real` (an element already built, if any).
    fn matrix(big: bool, flags: u32, dims: &[i32], name: &str, real: Option<Vec<u8>>) -> Vec<u8> {
        let u = |x: u32| if big { x.to_be_bytes() } else { x.to_le_bytes() };
        let mut f = u(flags).to_vec();
        f.extend([0u8; 4]);
        let mut m = element(big, MI_UINT32, &f);
        let d: Vec<u8> = dims.iter().flat_map(|&x| u(x as u32)).collect();
        m.extend(element(big, MI_INT32, &d));
        if name.len() <= 4 {
            m.extend(small(big, MI_INT8, name.as_bytes()));
        } else {
            m.extend(element(big, MI_INT8, name.as_bytes()));
        }
        m.extend(real.unwrap_or_default());
        m
    }

    fn file(big: bool, elements: &[Vec<u8>]) -> Vec<u8> {
        let mut b = b"MATLAB 5.0 MAT-file, palpate tests".to_vec();
        b.resize(124, b' ');
        b.extend(if big { [0x01, 0x00] } else { [0x00, 0x01] });
        b.extend(if big { b"MI" } else { b"IM" });
        for e in elements {
            b.extend(e);
        }
        b
    }

    /// `contents` (one element) behind a miCOMPRESSED tag.
    fn compressed_element(big: bool, contents: &[u8]) -> Vec<u8> {
        use std::io::Write;
        let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::default());
        z.write_all(contents).unwrap();
        let comp = z.finish().unwrap();
        let u = |x: u32| if big { x.to_be_bytes() } else { x.to_le_bytes() };
        let mut b = u(MI_COMPRESSED).to_vec();
        b.extend(u(comp.len() as u32));
        b.extend(comp);
        b
    }

    /// A real double matrix `name` of `dims`, values column-major as f64.
    fn double_var(big: bool, name: &str, dims: &[i32], col_major: &[f64]) -> Vec<u8> {
        let r: Vec<u8> = col_major
            .iter()
            .flat_map(|x| if big { x.to_be_bytes() } else { x.to_le_bytes() })
            .collect();
        element(
            big,
            MI_MATRIX,
            &matrix(big, 6, dims, name, Some(element(big, 9, &r))),
        )
    }

    fn data_path(f: &str) -> std::path::PathBuf {
        std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/data")
            .join(f)
    }

    /// SciPy's files (tests/data/make_mat5.py): int32 variables (an int32
    /// scalar stored as a small element, a 2x16 array) read with their
    /// values, compressed or not; a logical row; char, cell and struct
    /// variables skipped. `matfile` read no int32 variable.
    #[test]
    fn scipy_int32_logical_and_skipped_variables() {
        for f in ["mat5_int32.mat", "mat5_int32_z.mat"] {
            let b = std::fs::read(data_path(f)).unwrap();
            let vars = read_mat(&b, f).unwrap();
            let names: Vec<&str> = vars.iter().map(|(n, _)| n.as_str()).collect();
            assert_eq!(names, ["fs", "data", "touching"], "{f}");
            assert_eq!(
                vars[0].1,
                NdArray {
                    shape: vec![1, 1],
                    data: vec![1000.0]
                }
            );
            let want: Vec<f64> = (0..32).map(|v| if v % 2 == 1 { -v } else { v } as f64).collect();
            assert_eq!(
                vars[1].1,
                NdArray {
                    shape: vec![2, 16],
                    data: want
                },
                "{f}"
            );
            assert_eq!(
                vars[2].1,
                NdArray {
                    shape: vec![1, 3],
                    data: vec![1.0, 0.0, 1.0]
                },
                "{f}"
            );
        }
    }

    #[test]
    fn sparse_and_complex_variables_are_errors_naming_them() {
        let b = std::fs::read(data_path("mat5_sparse.mat")).unwrap();
        let e = read_mat(&b, "s.mat").unwrap_err();
        assert!(
            e.starts_with("s.mat: variable `s` is sparse") && e.contains("full("),
            "{e}"
        );
        let b = std::fs::read(data_path("mat5_complex.mat")).unwrap();
        let e = read_mat(&b, "z.mat").unwrap_err();
        assert_eq!(e, "z.mat: variable `z` is complex; only real data is supported");
    }

    /// A 2x3x2 array, written column-major, comes back in C order with
    /// MATLAB's subscripts, in either byte order, compressed or not.
    #[test]
    fn column_major_to_c_order_in_both_byte_orders() {
        let dims = [2, 3, 2];
        // MATLAB x(i, j, k) = 100 i + 10 j + k (1-based), stored i fastest.
        let mut col = Vec::new();
        for k in 1..=2 {
            for j in 1..=3 {
                for i in 1..=2 {
                    col.push(f64::from(100 * i + 10 * j + k));
                }
            }
        }
        for big in [false, true] {
            let var = double_var(big, "cube", &dims, &col);
            let z = compressed_element(big, &var);
            for b in [file(big, std::slice::from_ref(&var)), file(big, &[z])] {
                let v = read_mat(&b, "c.mat").unwrap();
                assert_eq!(v.len(), 1);
                let a = &v[0].1;
                assert_eq!(a.shape, vec![2, 3, 2]);
                for i in 0..2 {
                    for j in 0..3 {
                        for k in 0..2 {
                            let want = 100 * (i + 1) + 10 * (j + 1) + (k + 1);
                            assert_eq!(a.data[(i * 3 + j) * 2 + k], want as f64, "big {big}");
                        }
                    }
                }
            }
        }
    }

    /// A double array stored as every numeric type (MATLAB narrows small
    /// integers) converts by the storage type, in either byte order; a
    /// value that fits in 4 bytes may be a small element.
    #[test]
    fn every_storage_type_of_a_double_class() {
        let vals = [-3.0f64, 0.0, 7.0, 100.0];
        for big in [false, true] {
            // `src` as `$t`, in the file's byte order (unsigned types take
            // the absolute values).
            macro_rules! bytes {
                ($src:expr, $t:ty) => {
                    $src.iter()
                        .map(|&v| v as $t)
                        .flat_map(|v| {
                            if big {
                                v.to_be_bytes()
                            } else {
                                v.to_le_bytes()
                            }
                        })
                        .collect::<Vec<u8>>()
                };
            }
            let abs: Vec<f64> = vals.iter().map(|v| v.abs()).collect();
            let cases: Vec<(u32, Vec<u8>, &[f64])> = vec![
                (1, bytes!(vals, i8), &vals),
                (2, bytes!(abs, u8), &abs),
                (3, bytes!(vals, i16), &vals),
                (4, bytes!(abs, u16), &abs),
                (5, bytes!(vals, i32), &vals),
                (6, bytes!(abs, u32), &abs),
                (7, bytes!(vals, f32), &vals),
                (9, bytes!(vals, f64), &vals),
                (12, bytes!(vals, i64), &vals),
                (13, bytes!(abs, u64), &abs),
            ];
            for (ty, raw, want) in cases {
                let m = matrix(big, 6, &[1, 4], "x", Some(element(big, ty, &raw)));
                let b = file(big, &[element(big, MI_MATRIX, &m)]);
                let v = read_mat(&b, "t.mat").unwrap_or_else(|e| panic!("type {ty}: {e}"));
                assert_eq!(v[0].1.data, want, "type {ty}, big {big}");
            }
            // Small elements: a scalar double stored as one miUINT8 byte and
            // as one miINT32; the name `fs` in the tag too.
            for (ty, raw) in [
                (2, vec![200u8]),
                (
                    5,
                    if big {
                        200i32.to_be_bytes()
                    } else {
                        200i32.to_le_bytes()
                    }
                    .to_vec(),
                ),
            ] {
                let m = matrix(big, 6, &[1, 1], "fs", Some(small(big, ty, &raw)));
                let b = file(big, &[element(big, MI_MATRIX, &m)]);
                let v = read_mat(&b, "t.mat").unwrap();
                assert_eq!(
                    v,
                    vec![(
                        "fs".to_string(),
                        NdArray {
                            shape: vec![1, 1],
                            data: vec![200.0]
                        }
                    )]
                );
            }
        }
    }

    /// A storage type holding another count than the dimensions make is
    /// refused; so is a real part that is not numbers.
    #[test]
    fn storage_count_must_match_the_dimensions() {
        let m = matrix(false, 6, &[2, 3], "x", Some(element(false, 9, &[0u8; 40])));
        let e = read_mat(&file(false, &[element(false, MI_MATRIX, &m)]), "t.mat").unwrap_err();
        assert!(
            e.starts_with("t.mat: variable `x`: corrupt") && e.contains("make 6 elements"),
            "{e}"
        );
        let m = matrix(false, 6, &[1, 1], "x", Some(element(false, MI_MATRIX, &[0u8; 8])));
        let e = read_mat(&file(false, &[element(false, MI_MATRIX, &m)]), "t.mat").unwrap_err();
        assert!(e.contains("`x`") && e.contains("not numbers"), "{e}");
    }

    /// Empty arrays (with or without a real part) read as empty; a zero
    /// byte count miMATRIX is an empty slot, skipped.
    #[test]
    fn empty_arrays_and_slots() {
        let with = matrix(false, 6, &[0, 0], "e", Some(element(false, 9, &[])));
        let without = matrix(false, 6, &[0, 3], "f", None);
        let b = file(
            false,
            &[
                element(false, MI_MATRIX, &with),
                element(false, MI_MATRIX, &[]),
                element(false, MI_MATRIX, &without),
            ],
        );
        let v = read_mat(&b, "e.mat").unwrap();
        assert_eq!(v.len(), 2);
        assert_eq!(
            v[0],
            (
                "e".into(),
                NdArray {
                    shape: vec![0, 0],
                    data: vec![]
                }
            )
        );
        assert_eq!(
            v[1],
            (
                "f".into(),
                NdArray {
                    shape: vec![0, 3],
                    data: vec![]
                }
            )
        );
    }

    /// A compressed variable declaring more elements than a small file may
    /// decode to is refused from its dimensions, before anything is
    /// allocated or inflated past them; past `MAX_ELEMENTS` too.
    #[test]
    fn a_compressed_variable_over_the_budget_is_refused_before_allocating() {
        // 2^30 x 2 doubles = 16 GiB claimed, 8 bytes of data.
        for (dims, needle) in [
            (vec![1 << 30, 2], "past what this"),
            (vec![1 << 16, 1 << 16], "the cap"),
            (vec![i32::MAX, i32::MAX, i32::MAX], "the cap"),
        ] {
            let m = matrix(false, 6, &dims, "big", Some(element(false, 9, &[0u8; 8])));
            let b = file(
                false,
                &[compressed_element(false, &element(false, MI_MATRIX, &m))],
            );
            assert!(b.len() < 400);
            let e = read_mat(&b, "big.mat").unwrap_err();
            assert!(
                e.starts_with("big.mat: variable `big`: dimensions") && e.contains(needle),
                "{e}"
            );
        }
    }

    /// The budget is the file's total: a variable that fits alone is
    /// refused once earlier ones have used it, naming what is left.
    #[test]
    fn the_budget_counts_every_variable_of_the_file() {
        let mut budget = Budget {
            left: 100,
            cap: 100,
            file_len: 10,
        };
        let m = matrix(false, 6, &[10, 1], "a", Some(element(false, 9, &[0u8; 80])));
        let var = |k| Var {
            what: "t.mat",
            k,
            name: None,
        };
        let mut src = Src {
            r: &m[..],
            left: m.len() as u64,
            big: false,
        };
        assert_eq!(
            super::matrix(&mut src, var(1), &mut budget)
                .unwrap()
                .unwrap()
                .1
                .data,
            vec![0.0; 10]
        );
        assert_eq!(budget.left, 20);
        let mut src = Src {
            r: &m[..],
            left: m.len() as u64,
            big: false,
        };
        let e = super::matrix(&mut src, var(2), &mut budget).unwrap_err();
        assert!(
            e.starts_with("t.mat: variable `a`: dimensions") && e.contains("20 left"),
            "{e}"
        );
    }

    /// Cut at every byte, a file (two variables, compressed or not, a
    /// small-element name and data) is an error naming the file, but at the
    /// boundaries between elements, where it is a valid shorter file.
    #[test]
    fn a_file_cut_anywhere_is_an_error_naming_it() {
        for z in [false, true] {
            let mut vars = vec![
                double_var(false, "data", &[3, 2], &[1., 2., 3., 4., 5., 6.]),
                element(
                    false,
                    MI_MATRIX,
                    &matrix(false, 6, &[1, 1], "fs", Some(small(false, 2, &[9]))),
                ),
            ];
            if z {
                vars = vars.iter().map(|v| compressed_element(false, v)).collect();
            }
            let b = file(false, &vars);
            let bounds = [128, 128 + vars[0].len(), b.len()];
            assert_eq!(read_mat(&b, "cut.mat").unwrap().len(), 2);
            for cut in 0..b.len() {
                match read_mat(&b[..cut], "cut.mat") {
                    Ok(v) => assert!(bounds.contains(&cut), "cut at {cut} read {} variables", v.len()),
                    Err(e) => {
                        assert!(!bounds.contains(&cut), "cut at {cut}: {e}");
                        assert!(e.starts_with("cut.mat: "), "{e}");
                        if cut > 128 {
                            assert!(e.contains("truncated"), "cut at {cut}: {e}");
                        }
                    }
                }
            }
        }
    }

    /// A compressed variable whose stream ends before its declared size is
    /// truncated; a corrupt stream is named as one.
    #[test]
    fn compressed_streams_short_or_corrupt() {
        let v = double_var(false, "data", &[3, 2], &[1., 2., 3., 4., 5., 6.]);
        let b = file(false, &[compressed_element(false, &v[..v.len() - 8])]);
        let e = read_mat(&b, "z.mat").unwrap_err();
        assert!(e.starts_with("z.mat: variable `data`: truncated"), "{e}");
        let mut b = file(false, &[compressed_element(false, &v)]);
        let n = b.len();
        b[140..n - 4].iter_mut().for_each(|x| *x ^= 0x5a);
        let e = read_mat(&b, "z.mat").unwrap_err();
        assert!(
            e.starts_with("z.mat: variable 1: ") && e.contains("inflate"),
            "{e}"
        );
    }

    /// An element inside a matrix claiming more bytes than the matrix has
    /// is corrupt (checked before reading), naming the variable's position.
    #[test]
    fn inner_lengths_are_checked_against_their_matrix() {
        let mut m = matrix(
            false,
            6,
            &[1, 1],
            "x",
            Some(element(false, 9, &1f64.to_le_bytes())),
        );
        // The dimensions' byte count (bytes 20..24 of the contents).
        m[20..24].copy_from_slice(&0xffff_fff8u32.to_le_bytes());
        let e = read_mat(&file(false, &[element(false, MI_MATRIX, &m)]), "t.mat").unwrap_err();
        assert!(e.starts_with("t.mat: variable 1: corrupt"), "{e}");
    }

    /// Char, cell and struct variables are passed over by byte count
    /// (their contents unread, here not even valid), in either byte order.
    #[test]
    fn char_cell_struct_are_skipped_in_both_byte_orders() {
        for big in [false, true] {
            let text = element(big, MI_MATRIX, &matrix(big, 4, &[1, 2], "s", None));
            let flags = if big {
                [0, 0, 0, 1, 0, 0, 0, 0]
            } else {
                [1, 0, 0, 0, 0, 0, 0, 0]
            };
            let cell = element(
                big,
                MI_MATRIX,
                &[element(big, MI_UINT32, &flags), vec![0xee; 40]].concat(),
            );
            let st = element(
                big,
                MI_MATRIX,
                &matrix(big, 2, &[1, 1], "st", Some(vec![0xab; 24])),
            );
            let x = double_var(big, "x", &[1, 1], &[2.5]);
            let v = read_mat(&file(big, &[text, cell, st, x]), "s.mat").unwrap();
            assert_eq!(
                v,
                vec![(
                    "x".into(),
                    NdArray {
                        shape: vec![1, 1],
                        data: vec![2.5]
                    }
                )],
                "big {big}"
            );
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(512))]
        /// Arbitrary bytes after a valid header, raw or behind a
        /// miCOMPRESSED tag: an error or variables, never a panic.
        #[test]
        fn arbitrary_bytes_after_a_header_do_not_panic(
            body in proptest::collection::vec(any::<u8>(), 0..600),
            big in any::<bool>(),
            seed in proptest::collection::vec(any::<u8>(), 0..64),
        ) {
            let b = file(big, std::slice::from_ref(&body));
            let _ = read_mat(&b, "p.mat");
            // Structured prefixes reach deeper: a matrix tag and flags.
            let mut m = matrix(big, 6, &[2, 2], "p", None);
            m.extend(&seed);
            m.extend(&body);
            let _ = read_mat(&file(big, &[element(big, MI_MATRIX, &m)]), "p.mat");
            let _ = read_mat(&file(big, &[compressed_element(big, &m)]), "p.mat");
        }
    }
}
