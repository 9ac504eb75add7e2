//! A worked example of extending palpate from outside its own crates (see
//! docs/extending.md): a new encoder, [`adaptive_lif`], registered with typetag
//! exactly as the built-in stages are, without touching `core/` or `stages/`.

pub mod adaptive_lif;

/// Keeps this crate's registrations linked into a binary; returns the number of
/// registered stage types (built-in and plugin).
pub fn link() -> usize {
    palpate::link()
}
