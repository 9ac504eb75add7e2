//! A worked example of extending palpate from outside its own crates (see
//! docs/extending.md): a new encoder, [`adaptive_lif`], and a new sensor that is
//! not a grid, [`hex_fingertip`], registered with typetag exactly as the
//! built-in stages are, without touching `core/` or `stages/`.

pub mod adaptive_lif;
pub mod hex_fingertip;

/// Keeps this crate's registrations linked into a binary; returns the number of
/// registered stage types (built-in and plugin). Naming both configs here makes
/// the linker keep the object files that hold their registrations.
pub fn link() -> usize {
    let _ = std::hint::black_box((
        std::any::type_name::<adaptive_lif::AdaptiveLifConfig>(),
        std::any::type_name::<hex_fingertip::HexFingertipConfig>(),
    ));
    palpate::link()
}
