//! Graph loading (TOML parsing, stage configs, checks) on arbitrary text:
//! diagnostics or a graph, never a panic, a hang or unbounded memory.
//! Paths resolve in an empty folder; glob patterns that would walk the whole
//! file system (`**`) are skipped, since that time is the user's to spend.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if text.contains("**") {
        return;
    }
    palpate_stages::link();
    static DIR: std::sync::OnceLock<std::path::PathBuf> = std::sync::OnceLock::new();
    let dir = DIR.get_or_init(|| {
        let d = std::env::temp_dir().join(format!("palpate-fuzz-{}", std::process::id()));
        let _ = std::fs::create_dir_all(&d);
        d
    });
    let opts = palpate_core::LoadOptions {
        base_dir: Some(dir.clone()),
        out: Some(dir.join("out")),
        ..Default::default()
    };
    let _ = palpate_core::load_str(text, "fuzz.toml", "fuzz", &opts);
});
