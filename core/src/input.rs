//! Reading users' files with a documented size cap, so that no file (a
//! device such as `/dev/zero`, a named pipe that never ends, or a file far
//! larger than memory) can hang a run or exhaust memory: a read stops one
//! byte past the cap and fails with an error naming the cap.
//!
//! Two caps: [`MAX_TEXT_FILE_BYTES`] for configuration and label files
//! (graphs, scenes, label files, sweep manifests), whose largest real use is
//! a label file of a few hundred thousand trials; [`MAX_DATA_FILE_BYTES`]
//! for one recording file (CSV, NPY, NPZ, MAT, raw DAQ, spike events), well
//! past any single recording (16 taxels at 1 kHz in f64 fill it in more
//! than three days) and below the memory of the machines palpate runs on.

use std::io::Read;
use std::path::Path;

/// Largest configuration or label file read, bytes (64 MiB).
pub const MAX_TEXT_FILE_BYTES: u64 = 64 << 20;

/// Largest single data file read, bytes (4 GiB).
pub const MAX_DATA_FILE_BYTES: u64 = 4 << 30;

/// The bytes of `path`, or an error when it cannot be read or holds more
/// than `cap` bytes.
pub fn read_capped(path: &Path, cap: u64) -> std::io::Result<Vec<u8>> {
    let file = std::fs::File::open(path)?;
    // A regular file's length sizes the buffer once; a device or pipe has
    // none, and the cap bounds it.
    let hint = file.metadata().map(|m| m.len().min(cap)).unwrap_or(0);
    let mut bytes = Vec::with_capacity(usize::try_from(hint).unwrap_or(0));
    file.take(cap.saturating_add(1)).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > cap {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("the file is larger than the cap of {cap} bytes (or never ends)"),
        ));
    }
    Ok(bytes)
}

/// The text of a configuration or label file: [`read_capped`] at
/// [`MAX_TEXT_FILE_BYTES`], then UTF-8.
pub fn read_text(path: &Path) -> std::io::Result<String> {
    let bytes = read_capped(path, MAX_TEXT_FILE_BYTES)?;
    String::from_utf8(bytes).map_err(|_| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            "stream did not contain valid UTF-8",
        )
    })
}

/// The bytes of one data file: [`read_capped`] at [`MAX_DATA_FILE_BYTES`].
pub fn read_data(path: &Path) -> std::io::Result<Vec<u8>> {
    read_capped(path, MAX_DATA_FILE_BYTES)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_file_past_the_cap_or_an_endless_device_is_an_error() {
        let d = std::env::temp_dir().join(format!("palpate-input-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        let p = d.join("f.txt");
        std::fs::write(&p, "0123456789").unwrap();
        assert_eq!(read_capped(&p, 10).unwrap(), b"0123456789");
        let e = read_capped(&p, 9).unwrap_err();
        assert!(e.to_string().contains("cap of 9 bytes"), "{e}");
        std::fs::write(&p, [0xff, 0xfe]).unwrap();
        assert!(read_text(&p).unwrap_err().to_string().contains("UTF-8"));
        #[cfg(unix)]
        {
            let e = read_capped(Path::new("/dev/zero"), 1 << 16).unwrap_err();
            assert!(e.to_string().contains("cap of 65536 bytes"), "{e}");
        }
        std::fs::remove_dir_all(&d).unwrap();
    }
}
