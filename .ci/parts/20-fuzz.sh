#!/usr/bin/env bash
# Short fuzz pass: every cargo-fuzz target of fuzz/ from its seed
# corpus, a fixed number of executions each, 2 GB memory cap, 10 s per input.
# Budget: under 2 minutes of fuzzing in all (11 targets x FUZZ_CI_RUNS); the
# build of the targets comes on top (a few minutes cold, seconds when
# target/fuzz is warm). Stable toolchain: RUSTC_BOOTSTRAP=1 (in scripts/fuzz.sh).
set -euo pipefail
cd "$(dirname "$0")/../.."
if ! command -v python3 >/dev/null; then
  echo "SKIPPED: python3 (for fuzz/make_seeds.py) is not installed and this part does not install system packages"
  exit 0
fi
if ! command -v c++ >/dev/null; then
  echo "SKIPPED: no C++ compiler for libFuzzer (libfuzzer-sys builds it from source)"
  exit 0
fi
# Unoptimized build (overflow checks and debug assertions on, as in the long
# run): the build is most of this part's time, and 3,000 executions per
# target run in under a minute in all even so.
FUZZ_DEV=1 scripts/fuzz.sh "${FUZZ_CI_RUNS:-3000}"
