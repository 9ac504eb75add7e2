//! The `palpate` binary; see [`palpate::cli`].

fn main() -> std::process::ExitCode {
    palpate::cli::main()
}
