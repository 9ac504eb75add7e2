//! `palpate-plugin`: the palpate command line with this plugin's stages linked.
//! `palpate-plugin stages` lists `adaptive_lif` and `hex_fingertip` beside the
//! built-in stages.

fn main() -> std::process::ExitCode {
    palpate_plugin_example::link();
    palpate::cli::main()
}
