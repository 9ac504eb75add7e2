pub use palpate_core;
